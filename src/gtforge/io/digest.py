"""Content hashes of the input files a scene is built from (``meta.json``'s ``input_blake3``).

BLAKE3 (the ``blake3`` package, the algorithm's authors' Rust implementation): a cryptographic hash like SHA-256, so
a recorded digest still identifies the exact bytes a scene was built from (``b3sum FILE`` prints the same hex), at
4.5x SHA-256's speed here on one thread (2.0 against 9.0 ms for a scene's 18 MB of inputs, with the CPU's SHA
instructions; benchmarks/RESULTS.md). One thread: a build already runs one worker per core.
"""
from __future__ import annotations

from pathlib import Path

import blake3

CHUNK_BYTES = 1 << 20


def blake3_hex(data: bytes | memoryview) -> str:
    """BLAKE3 of ``data``, as lower-case hex (64 characters)."""
    return blake3.blake3(data).hexdigest()


def blake3_file(path: str | Path) -> str:
    """BLAKE3 of a file's contents, read in 1 MiB chunks; the same as ``blake3_hex(path.read_bytes())``."""
    h = blake3.blake3()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(CHUNK_BYTES), b""):
            h.update(chunk)
    return h.hexdigest()
