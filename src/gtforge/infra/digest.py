"""Content hashes of files: the inputs a scene is built from (``meta.json``'s ``input_blake3``) and the calibration
file (``calibration_sha256``).

BLAKE3 (the ``blake3`` package, the algorithm's authors' Rust implementation): a cryptographic hash like SHA-256, so
a recorded digest still identifies the exact bytes a scene was built from (``b3sum FILE`` prints the same hex),
and faster on one thread, even against a CPU's SHA instructions: it is built for SIMD (benchmarks/RESULTS.md,
"Figures from code comments"). One thread: a build already runs one worker per core.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import blake3

CHUNK_BYTES = 1 << 20


def blake3_hex(data: bytes | memoryview) -> str:
    """BLAKE3 of ``data``, as lower-case hex (64 characters)."""
    return blake3.blake3(data).hexdigest()


def blake3_file(path: str | Path) -> str:
    """BLAKE3 of a file's contents; the same as ``blake3_hex(path.read_bytes())``."""
    return _file_hexdigest(path, blake3.blake3())


def sha256_file(path: str | Path) -> str:
    """SHA-256 of a file's contents (the calibration file's identity in meta.json and the manifest)."""
    return _file_hexdigest(path, hashlib.sha256())


def _file_hexdigest(path: str | Path, h) -> str:
    """``h`` (a hashlib-style object) updated with the file's contents, read in 1 MiB chunks, as hex."""
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(CHUNK_BYTES), b""):
            h.update(chunk)
    return h.hexdigest()
