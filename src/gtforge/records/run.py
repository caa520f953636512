"""What ``gtforge run`` writes beside the stages' own files: ``run_state.json`` (``RunState``), each stage's inputs'
hashes, options, outputs and verdict as of its last run, from which the next run knows what to redo and why."""
from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import Field

from gtforge.core.schema import GTModel, VersionedFile

STAGES = ("calibrate", "align-depth", "validate", "calibrate-scale", "refine", "build-dataset", "verify")


class FileHash(GTModel):
    """A file's BLAKE3 and its size + mtime when hashed (a later run trusts the hash without reading the file when both
    are unchanged and the file was not modified within ``dataset.layout.STAMP_MARGIN_NS`` of hashing)."""
    blake3: str
    size_bytes: int
    mtime_ns: int
    hashed_at_ns: int


class StageRecord(GTModel):
    stage: str
    status: Literal["done", "not applicable"]
    reason: str = ""  # not applicable: why
    options: dict[str, Any] = Field(default_factory=dict)
    inputs: dict[str, str] = Field(default_factory=dict)  # "session/<relative path>" or "out/<relative path>" -> BLAKE3
    outputs: dict[str, str] = Field(default_factory=dict)  # "out/<relative path>" -> BLAKE3 ("" : must exist only)
    verdict: Literal["PASS", "WARN", "FAIL"] | None = None
    verdict_reasons: list[str] = Field(default_factory=list)
    detail: dict[str, Any] = Field(default_factory=dict)  # per stage: e.g. build-dataset's scene ids
    time_s: float = 0.0


class RunState(VersionedFile):
    KIND: ClassVar[str] = "run state (run_state.json from gtforge run)"
    gtforge_version: str
    session_dir: str
    stages: dict[str, StageRecord] = Field(default_factory=dict)
    hashes: dict[str, FileHash] = Field(default_factory=dict)  # cache: absolute path -> hash
