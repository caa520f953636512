"""Scene folders while they are written: one writer per scene (an advisory lock file), and stale temporary folders of
writers that died removed before a build lands its views."""
from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

try:
    import fcntl  # scene writer locks (POSIX); without it stale folders are removed unconditionally
except ImportError:  # pragma: no cover
    fcntl = None


def remove_stale_entries(out: Path, locks: bool = True) -> None:
    """Temporary scene folders of a run that was killed or interrupted: never scenes, always removed.
    A replaced scene (``.old-<id>-<token>``) whose replacement never landed is put back. Folders whose writer
    still runs (its ``.lock-<id>-<token>`` is held: a Dask task cancelled by Ctrl-C, which runs to its end) are
    left alone: removing files under a live writer could let it rename a partial folder into place. ``locks``: also
    delete the lock files no writer holds (a finished scene's, ``unlock_writer``)."""
    scenes = out / "scenes"
    for stale in scenes.glob(".tmp-*"):
        if not writer_alive(scenes, stale.name):
            shutil.rmtree(stale, ignore_errors=True)
    for old in scenes.glob(".old-*"):
        if writer_alive(scenes, old.name):
            continue
        sid = old.name[len(".old-"):].rsplit("-", 1)[0]
        if not (scenes / sid).exists():
            os.replace(old, scenes / sid)
        else:
            shutil.rmtree(old, ignore_errors=True)
    for lock in scenes.glob(".lock-*") if locks else ():
        if not writer_alive(scenes, lock.name):
            lock.unlink(missing_ok=True)
    for stale in out.glob(".views-*"):  # a views/ tree being built or swapped when the run stopped
        shutil.rmtree(stale, ignore_errors=True)



def lock_writer(scenes: Path, sid: str, token: str) -> int | None:
    """Take ``scenes/.lock-<sid>-<token>`` (flock; released by the kernel if this process dies)."""
    if fcntl is None:
        return None
    scenes.mkdir(parents=True, exist_ok=True)
    path = scenes / f".lock-{sid}-{token}"
    fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
    except OSError:  # a filesystem without locks: write unlocked, as without fcntl
        os.close(fd)
        path.unlink(missing_ok=True)
        return None
    return fd



def unlock_writer(scenes: Path, sid: str, token: str, fd: int | None) -> None:
    """Release the lock. Its file stays until the run's end (``remove_stale_entries`` removes unheld locks): a file
    deleted
    per scene would make ext4 without a journal skip it, for a minute, each time it allocates an inode in that folder
    (``recently_deleted``), a search paid in every scene and again for each of the split views' links
    (benchmarks/RESULTS.md, "Figures from code comments")."""
    if fd is not None:
        os.close(fd)



def writer_alive(scenes: Path, name: str) -> bool:
    """Whether the process writing hidden entry ``name`` (``.tmp-``/``.old-``/``.lock-<sid>-<token>``) holds its
    lock."""
    if fcntl is None:
        return False
    try:
        fd = os.open(scenes / (".lock-" + name.split("-", 1)[1]), os.O_RDWR)
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:  # a filesystem without locks: cannot tell, treat as stale (as without fcntl)
        return False
    finally:
        os.close(fd)
    return False


@contextmanager
def scene_writer(scenes: Path, sid: str) -> Iterator[Path]:
    """A new scene's folder while it is written: ``scenes/.tmp-<sid>-<token>``, under this writer's lock. When the
    block ends it is renamed into ``scenes/<sid>`` whole (an older build of the scene is swapped out, then removed);
    when the block raises (Ctrl-C included) it is removed, and an older build stays as it was."""
    token = uuid.uuid4().hex[:12]  # unique across processes and machines (Dask workers share the folder)
    tmp = scenes / f".tmp-{sid}-{token}"
    lock = lock_writer(scenes, sid, token)  # held until the scene is in place (see remove_stale_entries)
    try:
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        yield tmp
        final = scenes / sid
        old = scenes / f".old-{sid}-{token}"
        if final.exists():
            os.replace(final, old)
        os.replace(tmp, final)
        if old.exists():
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # (its writes have ended: the block waited for them)
        raise
    finally:
        unlock_writer(scenes, sid, token, lock)
