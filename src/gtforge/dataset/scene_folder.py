"""Scene folders while they are written: one writer per scene (an advisory lock file), and stale temporary folders of
writers that died removed before a build lands its views."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

try:
    import fcntl  # scene writer locks (POSIX); without it stale folders are removed unconditionally
except ImportError:  # pragma: no cover
    fcntl = None


def _remove_stale(out: Path, locks: bool = True) -> None:
    """Temporary scene folders of a run that was killed or interrupted: never scenes, always removed.
    A replaced scene (``.old-<id>-<token>``) whose replacement never landed is put back. Folders whose writer
    still runs (its ``.lock-<id>-<token>`` is held: a Dask task cancelled by Ctrl-C, which runs to its end) are
    left alone: removing files under a live writer could let it rename a partial folder into place. ``locks``: also
    delete the lock files no writer holds (a finished scene's, ``_unlock_writer``)."""
    scenes = out / "scenes"
    for stale in scenes.glob(".tmp-*"):
        if not _writer_alive(scenes, stale.name):
            shutil.rmtree(stale, ignore_errors=True)
    for old in scenes.glob(".old-*"):
        if _writer_alive(scenes, old.name):
            continue
        sid = old.name[len(".old-"):].rsplit("-", 1)[0]
        if not (scenes / sid).exists():
            os.replace(old, scenes / sid)
        else:
            shutil.rmtree(old, ignore_errors=True)
    for lock in scenes.glob(".lock-*") if locks else ():
        if not _writer_alive(scenes, lock.name):
            lock.unlink(missing_ok=True)
    for stale in out.glob(".views-*"):  # a views/ tree being built or swapped when the run stopped
        shutil.rmtree(stale, ignore_errors=True)



def _lock_writer(scenes: Path, sid: str, token: str) -> int | None:
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



def _unlock_writer(scenes: Path, sid: str, token: str, fd: int | None) -> None:
    """Release the lock. Its file stays until the run's end (``_remove_stale`` removes unheld locks): a file deleted
    per scene would make ext4 without a journal skip it, for a minute, each time it allocates an inode in that folder
    (``recently_deleted``), a search paid in every scene and again for each of the split views' links
    (benchmarks/RESULTS.md, "Figures from code comments")."""
    if fd is not None:
        os.close(fd)



def _writer_alive(scenes: Path, name: str) -> bool:
    """Whether the process writing hidden entry ``name`` (``.tmp-``/``.old-``/``.lock-<sid>-<token>``) holds its lock."""
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
