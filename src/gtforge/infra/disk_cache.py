"""Arrays kept on disk between commands: results that take long to compute, depend only on a small, hashable
description, and are the same every time (the depth camera's ray grid: ``camera.PinholeCamera.ray_grid``).

Where: ``$GTFORGE_CACHE_DIR`` if set (empty: no disk cache), else ``$XDG_CACHE_HOME/gtforge`` (``~/.cache/gtforge``),
the place the XDG base-directory convention gives data a program can always recompute. Not the output folder: a ray
grid belongs to a camera model, not to a dataset (every dataset built with one calibration shares it, it survives
``--overwrite`` and a new output folder), and a dataset folder holds the dataset's own files only.

A file is ``<kind>/<key>-<blake3 of the array's bytes>.npy``, written atomically (a temporary file, then a rename);
a file whose bytes no longer match its digest, or that cannot be read, is deleted and the caller recomputes: a
cached array is bit-identical to a computed one, or it is not used. At most ``KEEP_FILES`` files of a kind are kept
(the least recently used go). Nothing here raises: a cache that cannot be read or written costs the computation,
nothing else."""
from __future__ import annotations

import contextlib
import logging
import os
import time
from pathlib import Path

import numpy as np

from gtforge.infra.atomic import atomic_path
from gtforge.infra.digest import blake3_hex

CACHE_ENV = "GTFORGE_CACHE_DIR"
# files of one kind kept (a full-resolution ray grid is 37 MB: 1920 x 1200 x 2 float64)
KEEP_FILES = 4
# a temporary file older than this is a dead writer's (a ray grid is written in well under a second)
STALE_TEMP_S = 3600.0

log = logging.getLogger("gtforge.disk_cache")


def cache_dir() -> Path | None:
    """The cache's folder, or None where ``$GTFORGE_CACHE_DIR`` is set empty (no disk cache)."""
    v = os.environ.get(CACHE_ENV)
    if v is not None:
        return Path(v) if v else None
    # a relative XDG_CACHE_HOME is invalid (the XDG specification: ignore it); without a home folder ("~" unexpanded)
    # there is no cache rather than a "~" folder in the working directory, which may be an input folder
    base = os.environ.get("XDG_CACHE_HOME", "")
    if not os.path.isabs(base):
        base = os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "gtforge" if os.path.isabs(base) else None


def _files(kind: str, key: str) -> list[Path]:
    root = cache_dir()
    if root is None:
        return []
    with contextlib.suppress(OSError):
        return sorted((root / kind).glob(f"{key}-*.npy"))
    return []


def load_array(kind: str, key: str) -> np.ndarray | None:
    """The array stored under ``kind``/``key``, read-only, or None (none stored, unreadable or corrupted)."""
    for path in _files(kind, key):
        digest = path.stem.rsplit("-", 1)[1]
        try:
            # mapped, not read: the file's pages in the page cache are the array (a fork server's workers share them),
            # where reading it into new memory cost a fresh process 0.08-0.1 s of page faults for a full-resolution
            # ray grid, on the first scene's critical path (benchmarks/RESULTS.md, round 23). The file is never
            # written in place (``store_array`` renames a new one over it), so the mapped bytes stay those checked
            arr = np.asarray(np.load(path, mmap_mode="r", allow_pickle=False))
            ok = arr.flags.c_contiguous and blake3_hex(memoryview(arr).cast("B")) == digest
        except (OSError, ValueError, EOFError) as exc:
            log.debug("cache file %s unreadable (%s): recomputed", path, exc)
            ok = False
        if not ok:
            with contextlib.suppress(OSError):
                path.unlink()
            continue
        with contextlib.suppress(OSError):
            os.utime(path)  # its last use: what the least-recently-used clean-up goes by
        arr.setflags(write=False)
        return arr
    return None


def store_array(kind: str, key: str, arr: np.ndarray) -> None:
    """Keep ``arr`` (C-contiguous after conversion) under ``kind``/``key``; drop the least recently used files of
    ``kind`` beyond ``KEEP_FILES``. Failures are logged at debug level and otherwise ignored."""
    root = cache_dir()
    if root is None:
        return
    arr = np.ascontiguousarray(arr)
    folder = root / kind
    path = folder / f"{key}-{blake3_hex(memoryview(arr).cast('B'))}.npy"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_path(path, private=False) as tmp, open(tmp, "wb") as f:
            np.save(f, arr, allow_pickle=False)
        files = sorted(folder.glob("*.npy"), key=lambda p: p.stat().st_mtime, reverse=True)
        # and what a process killed while it wrote left (an unused fork server is killed at exit): a hidden
        # temporary file no writer has touched for STALE_TEMP_S
        stale = [t for t in folder.glob(".*.tmp.npy") if time.time() - t.stat().st_mtime > STALE_TEMP_S]
        for old in files[KEEP_FILES:] + stale:
            with contextlib.suppress(OSError):
                old.unlink()
    except OSError as exc:
        log.debug("could not keep %s in the disk cache (%s)", path, exc)
