"""Output files written past the page cache (``O_DIRECT``), and from a background thread.

Why: a buffered write costs the writing process CPU for every byte (the kernel copies the data into page-cache
pages, which a VM's guest must first get from the host, and writes them back later); an ``O_DIRECT`` write costs it
almost none: the device reads the process's own buffer (benchmarks/RESULTS.md, "Writes past the page cache"). A
build writes about 56 MB a full-resolution scene.

``O_DIRECT`` wants the buffer's address, the file offset and the length to be multiples of the device's block size:
the bytes are put in an ``AlignedBuffer`` (``BLOCK_BYTES``-aligned, its length padded to a whole block), written
whole, and the file is cut to its real length. Where the filesystem refuses ``O_DIRECT`` (tmpfs, some network
filesystems), the platform has none, or a write ends off a block boundary, the rest is written the ordinary way:
the file's bytes are the same either way. Files under ``MIN_DIRECT_BYTES`` are written the ordinary way (their
page-cache cost is small; a direct write waits for the device).

A direct write returns only once the device has the data: ``background_writes`` lets the calling thread go on
(encoding the next file) while this process's writer thread waits for the device.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np

BLOCK_BYTES = 4096  # a multiple of every Linux block device's logical block size in use (512 or 4096)
MIN_DIRECT_BYTES = 256 * 1024
_O_DIRECT = getattr(os, "O_DIRECT", 0)  # 0: not on this platform (macOS, Windows)


@dataclass(frozen=True)
class AlignedBuffer:
    """``n_bytes`` of file content at the start of ``padded``, a uint8 array whose data starts on a ``BLOCK_BYTES``
    boundary and whose length is ``n_bytes`` rounded up to a whole block (the padding is not written to the file)."""

    padded: np.ndarray
    n_bytes: int

    @property
    def data(self) -> np.ndarray:
        """The file's bytes (a view: fill it in place)."""
        return self.padded[:self.n_bytes]


def aligned_buffer(n_bytes: int) -> AlignedBuffer:
    """An uninitialised ``AlignedBuffer`` for ``n_bytes`` bytes (from numpy's allocator, so freed ones are reused)."""
    n_padded = -(-n_bytes // BLOCK_BYTES) * BLOCK_BYTES
    raw = np.empty(n_padded + BLOCK_BYTES, np.uint8)
    start = -raw.ctypes.data % BLOCK_BYTES
    return AlignedBuffer(raw[start:start + n_padded], n_bytes)


def buffer_of(data: bytes | bytearray | memoryview) -> AlignedBuffer:
    """``data`` copied into an ``AlignedBuffer``."""
    view = memoryview(data).cast("B")
    buf = aligned_buffer(view.nbytes)
    buf.data[:] = np.frombuffer(view, np.uint8)
    return buf


def write_file(path: str | os.PathLike, buf: AlignedBuffer) -> None:
    """Create (or truncate) ``path`` and write ``buf``'s bytes to it, past the page cache where the filesystem allows
    (module docstring). The file's mode is a normal ``open(path, "w")``'s (0666 minus the umask)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0)
    direct = bool(_O_DIRECT) and buf.n_bytes >= MIN_DIRECT_BYTES
    try:
        fd = os.open(path, flags | (_O_DIRECT if direct else 0), 0o666)
    except OSError as exc:
        if not direct or exc.errno != errno.EINVAL:  # EINVAL: this filesystem has no O_DIRECT
            raise
        direct, fd = False, os.open(path, flags, 0o666)
    try:
        view = memoryview(buf.padded if direct else buf.data)
        done = 0
        while done < len(view):
            try:
                n = os.write(fd, view[done:])
            except OSError as exc:
                if not direct or exc.errno != errno.EINVAL:
                    raise
                direct = _stop_direct(fd)  # refused after all (alignment the device wants is larger): buffered
                continue
            done += n
            if direct and done % BLOCK_BYTES:  # a short write off a block boundary: the rest buffered
                direct = _stop_direct(fd)
        if len(view) != buf.n_bytes:
            os.ftruncate(fd, buf.n_bytes)  # the padding goes
    finally:
        os.close(fd)


def _stop_direct(fd: int) -> bool:
    fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~_O_DIRECT)
    return False


# ---- background writes -------------------------------------------------------------------------------------
_JOBS: ContextVar[list[Future] | None] = ContextVar("gtforge_background_writes", default=None)
_WRITER: tuple[int, ThreadPoolExecutor] | None = None  # (pid, executor): a forked child starts its own
_WRITER_LOCK = threading.Lock()


def _writer() -> ThreadPoolExecutor:
    global _WRITER
    with _WRITER_LOCK:
        if _WRITER is None or _WRITER[0] != os.getpid():
            _WRITER = (os.getpid(), ThreadPoolExecutor(1, thread_name_prefix="gtforge-writer"))
        return _WRITER[1]


def run_or_queue(job: Callable[[], object]) -> None:
    """Run ``job`` (a file write) now, or, inside ``background_writes``, queue it to this process's writer thread
    (jobs run one at a time, in the order queued)."""
    jobs = _JOBS.get()
    if jobs is None:
        job()
    else:
        jobs.append(_writer().submit(job))


@contextlib.contextmanager
def background_writes() -> Iterator[None]:
    """Within this context, the writes of ``run_or_queue`` (every atomic writer's large files, ``io.atomic``) go to
    this process's writer thread while the caller goes on; leaving it waits for all of them and raises the first
    write's error, if any (the caller's own exception, if there is one, takes precedence). A file is therefore
    complete, and at its final name, once the context has exited, and not before: read none of them inside it."""
    jobs: list[Future] = []
    token = _JOBS.set(jobs)
    failed = True
    try:
        yield
        failed = False
    finally:
        _JOBS.reset(token)
        errors = [e for e in (f.exception() for f in jobs) if e is not None]  # waits for every job
        if errors and not failed:
            raise errors[0]
