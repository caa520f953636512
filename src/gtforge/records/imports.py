"""What ``gtforge import`` writes beside the session's captures: ``ImportParams`` (pairing thresholds) and
``import.json`` (``ImportRecord``: the sources with their hashes, the topics, every pair kept with its timestamps and
skew, the pairs dropped and why). One ``ImportRun`` per import into the session (``--add`` appends one)."""
from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import ConfigDict, Field

from gtforge.core.schema import GTModel, VersionedFile
from gtforge.core.targets.models import BoardModel


class ImportParams(GTModel):
    """How frames become captures (docs/capture-layout.md, "From recordings")."""

    # every figure finite: --max-skew-ms inf was written into import.json as Infinity (no JSON) and paired any frames
    model_config = ConfigDict(allow_inf_nan=False)

    max_skew_ms: float = Field(20.0, gt=0)  # |t_a - t_b| of two frames paired (after the clock offset)
    # a frame is still when its mean |grey difference| to both neighbours (images reduced to <= 160 px wide) is below
    # this (grey levels 0-255: above 255 every frame would be still)
    still_threshold: float = Field(2.0, gt=0, le=255)
    # the stereo camera's clock minus the depth camera's (ms); None: 0 where the clocks overlap, else estimated from
    # the motion events both recordings saw
    clock_offset_ms: float | None = Field(None, allow_inf_nan=False)
    estimate_clock_offset: bool = False  # estimate it from motion events even where the clocks overlap
    every: int = Field(1, ge=1)  # keep every N-th still capture
    max_captures: int | None = Field(None, ge=1)
    board: BoardModel | None = None  # the target board captures show (None: the default 12x9 checkerboard)
    classify: bool = True  # False: every capture is a scene


class SourceFile(GTModel):
    path: str
    size_bytes: int
    blake3: str


class PairRecord(GTModel):
    capture: str  # relative to the session (its board_dir, scenes_dir), e.g. board/000
    t_depth_ns: int
    t_texture_ns: int
    t_left_ns: int | None = None  # the stereo camera's own clock
    t_right_ns: int | None = None
    skew_ms: float  # the largest |difference| between the capture's frames, after the clock offset


class ImportRun(GTModel):
    sources: list[SourceFile]
    depth_recording: str
    stereo_recording: str | None
    streams: dict[str, str]  # role -> topic or track
    notes: list[str] = Field(default_factory=list)
    # role (depth, stereo) -> the device's serial number where the recording names it (RealSense, Azure Kinect, ZED
    # .svo2); --add refuses recordings of another device
    serials: dict[str, str] = Field(default_factory=dict)
    params: ImportParams
    clock_offset_ms: float
    clock_offset_source: Literal["given", "overlap", "motion events", "one clock"]
    pairs: list[PairRecord]
    dropped: dict[str, int]  # reason (skew, motion, no image, every/max) -> pairs


class ImportRecord(VersionedFile):
    KIND: ClassVar[str] = "import record (import.json)"

    runs: list[ImportRun]
