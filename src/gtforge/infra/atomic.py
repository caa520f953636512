"""Atomic writes: a temporary file in the destination folder, then ``os.replace``; straight to the final name in a
``private_folder`` (a folder renamed into place whole once complete, which is the atomic step then). Large files are
written past the page cache, and inside ``unbuffered.background_writes`` from a writer thread (``io.unbuffered``)."""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterator

from gtforge.infra.unbuffered import (
    MIN_DIRECT_BYTES,
    AlignedBuffer,
    aligned_buffer,
    buffer_of,
    run_or_queue,
    write_file,
)


def _umask() -> int:
    """The process umask (read without changing it for longer than one call)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """The mode a normal ``open(path, "w")`` would give a new file: 0666 minus the umask."""
    return 0o666 & ~_umask()


# folders being filled by ``private_folder`` (absolute or as given; unique names: a lock-free set is enough)
_PRIVATE_FOLDERS: set[str] = set()


@contextlib.contextmanager
def private_folder(folder: str | Path) -> Iterator[Path]:
    """Within this context, the atomic writers write files directly in ``folder`` (not in its subfolders) under their
    final names: ``folder`` is one that nobody reads until the caller renames it into place, complete, and deletes it
    whole otherwise (a scene's hidden temporary folder), so a temporary file and a rename per file would add work and
    no safety."""
    key = os.fspath(folder)
    _PRIVATE_FOLDERS.add(key)
    try:
        yield Path(folder)
    finally:
        _PRIVATE_FOLDERS.discard(key)


def _in_private_folder(path: Path) -> bool:
    return os.fspath(path.parent) in _PRIVATE_FOLDERS


@contextlib.contextmanager
def atomic_path(path: str | Path, private: bool | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix); renamed onto ``path`` on success. In a
    ``private_folder`` (``private``: whether it is, decided by the caller): ``path`` itself."""
    path = Path(path)
    if _in_private_folder(path) if private is None else private:
        yield path
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.fchmod(fd, file_mode())  # mkstemp makes 0600; outputs are shared like any normal file (umask)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    if len(data) >= MIN_DIRECT_BYTES:
        return atomic_write_buffer(path, buffer_of(data))
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_buffer(path: str | Path, buf: AlignedBuffer) -> Path:
    """Write ``buf``'s bytes to ``path`` atomically, past the page cache (``unbuffered.write_file``); inside
    ``unbuffered.background_writes``, from the writer thread (do not change ``buf`` afterwards)."""
    path = Path(path)
    private = _in_private_folder(path)  # decided now: the folder's context may have ended when the job runs

    def job():
        with atomic_path(path, private) as tmp:
            write_file(tmp, buf)

    run_or_queue(job)
    return path


def atomic_copy_file(src: str | Path, dst: str | Path) -> Path:
    """A copy of the file ``src`` at ``dst``, written atomically and past the page cache (``atomic_write_buffer``;
    ``shutil.copyfile`` sends it through the page cache)."""
    with open(src, "rb", buffering=0) as f:
        size = os.fstat(f.fileno()).st_size
        buf = aligned_buffer(size)
        n = f.readinto(buf.padded)  # (one byte more than the size fits, if the file grew)
        while n < len(buf.padded) and (k := f.readinto(buf.padded[n:])):
            n += k
        if n != size or f.read(1):  # the file changed size while being read: copied as it is now
            with atomic_path(dst) as tmp:
                shutil.copyfile(src, tmp)
            return Path(dst)
    return atomic_write_buffer(dst, buf)


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_with(path: str | Path, writer: Callable[[Path], None]) -> Path:
    """Call ``writer(tmp_path)`` and move the result onto ``path``."""
    with atomic_path(path) as tmp:
        writer(tmp)
    return Path(path)
