"""Files written past the page cache (``io.unbuffered``): the same bytes and mode as an ordinary write, whichever way
the filesystem takes them, and background writes that are complete when their context exits."""
import errno
import fcntl
import multiprocessing
import os

import numpy as np
import pytest
import tifffile

from gtforge.infra import unbuffered
from gtforge.infra.atomic import atomic_copy_file, atomic_write_buffer, atomic_write_bytes, file_mode, private_folder
from gtforge.infra.unbuffered import (
    BLOCK_BYTES,
    MIN_DIRECT_BYTES,
    aligned_buffer,
    background_writes,
    buffer_of,
    write_file,
)
from gtforge.io.formats import read_pfm, write_pfm, write_tiff_float

SIZES = [0, 1, BLOCK_BYTES - 1, BLOCK_BYTES, MIN_DIRECT_BYTES - 1, MIN_DIRECT_BYTES, MIN_DIRECT_BYTES + 1,
         MIN_DIRECT_BYTES + BLOCK_BYTES, 3 * 1024 * 1024 + 5]


def _data(n, seed=0):
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


@pytest.fixture
def open_flags(monkeypatch):
    """The flags of every ``os.open`` in io.unbuffered."""
    seen = []
    real_open = os.open

    def spy(path, flags, *a):
        seen.append(flags)
        return real_open(path, flags, *a)

    monkeypatch.setattr(unbuffered.os, "open", spy)
    return seen


def test_aligned_buffer_is_aligned_and_padded_to_whole_blocks():
    for n in SIZES[1:]:  # (an empty buffer has no data to align)
        buf = aligned_buffer(n)
        assert buf.padded.ctypes.data % BLOCK_BYTES == 0
        assert len(buf.padded) == -(-n // BLOCK_BYTES) * BLOCK_BYTES and len(buf.data) == n
        assert buf.data.ctypes.data == buf.padded.ctypes.data  # a view: filling data fills the file's bytes


@pytest.mark.parametrize("n", SIZES)
def test_write_file_writes_exactly_the_bytes_with_a_normal_files_mode(tmp_path, n, open_flags):
    old = os.umask(0o027)
    try:
        data = _data(n, n)
        p = tmp_path / "f.bin"
        p.write_bytes(b"x" * (2 * n + 10))  # an existing, longer file: truncated
        write_file(p, buffer_of(data))
        assert p.read_bytes() == data
        assert p.stat().st_mode & 0o777 == 0o640
    finally:
        os.umask(old)
    direct = bool(open_flags[-1] & unbuffered._O_DIRECT)
    assert direct == (n >= MIN_DIRECT_BYTES and bool(unbuffered._O_DIRECT))  # small files: the ordinary way


def test_write_file_falls_back_where_o_direct_is_refused(tmp_path, monkeypatch):
    if not unbuffered._O_DIRECT:
        pytest.skip("no O_DIRECT on this platform")
    data = _data(MIN_DIRECT_BYTES + 77)
    real_open, real_write = os.open, os.write

    def no_direct_open(path, flags, *a):  # tmpfs: open refuses O_DIRECT
        if flags & unbuffered._O_DIRECT:
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_open(path, flags, *a)

    monkeypatch.setattr(unbuffered.os, "open", no_direct_open)
    write_file(tmp_path / "a.bin", buffer_of(data))
    monkeypatch.setattr(unbuffered.os, "open", real_open)
    assert (tmp_path / "a.bin").read_bytes() == data

    calls = []

    def refusing_write(fd, view):  # open accepts O_DIRECT, writes refuse it (an alignment larger than BLOCK_BYTES)
        calls.append(len(view))
        if fcntl.fcntl(fd, fcntl.F_GETFL) & unbuffered._O_DIRECT:
            raise OSError(errno.EINVAL, "Invalid argument")
        return real_write(fd, view)

    monkeypatch.setattr(unbuffered.os, "write", refusing_write)
    write_file(tmp_path / "b.bin", buffer_of(data))
    assert (tmp_path / "b.bin").read_bytes() == data and len(calls) >= 2

    def short_write(fd, view):  # the first write stops off a block boundary (as a buffered one may): the rest buffered
        calls.append(len(view))
        if len(calls) > 1:
            return real_write(fd, view)
        flags = fcntl.fcntl(fd, fcntl.F_GETFL)
        fcntl.fcntl(fd, fcntl.F_SETFL, flags & ~unbuffered._O_DIRECT)
        n = real_write(fd, view[:1000])
        fcntl.fcntl(fd, fcntl.F_SETFL, flags)
        return n

    calls.clear()
    monkeypatch.setattr(unbuffered.os, "write", short_write)
    write_file(tmp_path / "c.bin", buffer_of(data))
    assert (tmp_path / "c.bin").read_bytes() == data and len(calls) == 2

    def failing_write(fd, view):  # any other error is the caller's
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(unbuffered.os, "write", failing_write)
    with pytest.raises(OSError, match="No space"):
        write_file(tmp_path / "d.bin", buffer_of(data))


def test_atomic_writers_leave_no_temporary_file_and_copy_exactly(tmp_path):
    data = _data(MIN_DIRECT_BYTES * 2 + 3)
    src = tmp_path / "src.png"
    src.write_bytes(data)
    atomic_write_bytes(tmp_path / "a.bin", data)
    atomic_copy_file(src, tmp_path / "copy.png")
    for n in (0, 5, BLOCK_BYTES, MIN_DIRECT_BYTES + 1):  # every size, block boundaries included
        small = tmp_path / f"s{n}"
        small.write_bytes(data[:n])
        atomic_copy_file(small, tmp_path / f"c{n}")
        assert (tmp_path / f"c{n}").read_bytes() == data[:n]
    assert (tmp_path / "a.bin").read_bytes() == data and (tmp_path / "copy.png").read_bytes() == data
    assert (tmp_path / "copy.png").stat().st_mode & 0o777 == file_mode()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_background_writes_are_complete_when_the_context_exits(tmp_path):
    blobs = {f"f{i}.bin": _data(MIN_DIRECT_BYTES + 1000 * i, i) for i in range(6)}
    folder = tmp_path / ".tmp-scene"
    folder.mkdir()
    with private_folder(folder), background_writes():
        for name, b in blobs.items():
            atomic_write_bytes(folder / name, b)
        atomic_write_bytes(tmp_path / "outside.bin", blobs["f0.bin"])  # outside the private folder: tmp + rename
    assert {n: (folder / n).read_bytes() for n in blobs} == blobs
    assert (tmp_path / "outside.bin").read_bytes() == blobs["f0.bin"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".tmp-scene", "outside.bin"]  # no temporary file left


def test_a_failed_background_write_is_raised_at_the_exit_after_the_others(tmp_path):
    buf = buffer_of(_data(MIN_DIRECT_BYTES))
    (tmp_path / "b.bin").mkdir()  # a folder where the file should go: its rename fails, in the writer thread
    with pytest.raises(IsADirectoryError):
        with background_writes():
            atomic_write_buffer(tmp_path / "a.bin", buf)
            atomic_write_buffer(tmp_path / "b.bin", buf)
            atomic_write_buffer(tmp_path / "c.bin", buf)
    assert (tmp_path / "a.bin").read_bytes() == (tmp_path / "c.bin").read_bytes() == buf.data.tobytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.bin", "c.bin"]  # the failed one's temporary: gone

    with pytest.raises(KeyboardInterrupt):  # the caller's own exception wins; queued writes still end first
        with background_writes():
            atomic_write_buffer(tmp_path / "d.bin", buf)
            raise KeyboardInterrupt
    assert (tmp_path / "d.bin").read_bytes() == buf.data.tobytes()


def _child_writes(path):
    with background_writes():
        atomic_write_bytes(path, _data(MIN_DIRECT_BYTES, 3))


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="no fork")
def test_a_forked_child_gets_its_own_writer_thread(tmp_path):
    with background_writes():  # the parent's writer thread exists when it forks
        atomic_write_bytes(tmp_path / "parent.bin", _data(MIN_DIRECT_BYTES, 3))
    p = multiprocessing.get_context("fork").Process(target=_child_writes, args=(tmp_path / "child.bin",))
    p.start()
    p.join(60)
    assert p.exitcode == 0
    assert (tmp_path / "child.bin").read_bytes() == (tmp_path / "parent.bin").read_bytes()


@pytest.mark.parametrize("shape", [(1, 1), (3, 5), (37, 129), (300, 401)])
def test_tiff_and_pfm_files_are_the_reference_writers_bytes(tmp_path, shape):
    a = np.random.default_rng(1).normal(500, 100, shape).astype(np.float32)
    a.flat[::7] = np.nan
    a.flat[3::11] = -np.inf
    write_tiff_float(tmp_path / "a.tiff", a)
    tifffile.imwrite(tmp_path / "ref.tiff", a)
    assert (tmp_path / "a.tiff").read_bytes() == (tmp_path / "ref.tiff").read_bytes()
    write_pfm(tmp_path / "a.pfm", a)
    body = np.where(np.isfinite(a), a, np.inf)[::-1].astype("<f4").tobytes()
    assert (tmp_path / "a.pfm").read_bytes() == f"Pf\n{shape[1]} {shape[0]}\n-1.0\n".encode() + body
    np.testing.assert_array_equal(read_pfm(tmp_path / "a.pfm"), np.where(np.isfinite(a), a, np.nan))
