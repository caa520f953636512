"""What build-dataset writes about a dataset: ``BuildParams`` (its settings), each scene's ``meta.json``
(``SceneMeta``) and the dataset's ``manifest.json`` (``Manifest``). Read by verify, evaluate, the reports and the
training loaders."""
from __future__ import annotations

import hashlib
import json
from typing import ClassVar, Literal

from pydantic import Field

from gtforge.core.ground_truth.reproject import ReprojectParams
from gtforge.core.ground_truth.uncertainty import SigmaStats, UncertaintyParams
from gtforge.core.schema import GTModel, VersionedFile
from gtforge.infra import defaults
from gtforge.records.verification import MotionParams, SceneVerification, VerifyParams


class BuildParams(GTModel):
    mode: Literal["mesh", "splat"] = "mesh"
    max_slant_deg: float = Field(defaults.MAX_SLANT_DEG, gt=0, lt=90)
    abs_tol_mm: float = Field(0.5, ge=0)
    occlusion_rel_tol: float = 0.01
    fruit_height_mm: float = Field(10.0, gt=0)  # points this far above the table plane are foreground
    plane_threshold_mm: float = Field(3.0, gt=0)
    min_component_frac: float = 0.2  # keep foreground components at least this share of the largest
    erosion_px: int = Field(defaults.EROSION_PX, ge=1)  # fruit centre = fruit eroded by this; edge = the rest
    lambda_edge: float = 1.4
    lambda_center: float = 1.0
    lambda_bg: float = 0.8
    split_train: float = defaults.SPLIT_TRAIN
    split_val: float = defaults.SPLIT_VAL
    split_seed: int = defaults.SPLIT_SEED
    kitti: bool = True
    eth3d: bool = True
    crop_wh: tuple[int, int] | None = None
    ply: bool = False
    max_disp_px: float = 192.0  # statistics: share of pixels above this (many training repos drop them)
    verification: bool = True  # per-scene checks of the GT against its own images (gtforge.verify)
    sigma: bool = True  # disp0GT_sigma.pfm: per-pixel 1-sigma GT uncertainty (gtforge.core.ground_truth.uncertainty)
    right_gt: bool = True  # disp1GT.pfm + mask1nocc.png (+ KITTI disp_occ_1/disp_noc_1): the right view's GT
    uncertainty: UncertaintyParams = Field(default_factory=UncertaintyParams)
    verify: VerifyParams = Field(default_factory=VerifyParams)
    quarantine: bool = False  # leave flagged scenes out of the split lists (they stay in scenes/)
    motion: MotionParams = Field(default_factory=MotionParams)  # a scene whose fruit moved: compensation (issue 37)

    def reproject_params(self) -> ReprojectParams:
        return ReprojectParams(self.mode, self.max_slant_deg, self.abs_tol_mm)

    def output_hash(self, with_motion: bool = True) -> str:
        """Hash of the parameters that change a scene's files (not the split lists). ``with_motion=False``: without
        the motion compensation's, which change only the files of a scene whose fruit verification suspects moved."""
        d = self.model_dump(exclude={"split_train", "split_val", "split_seed", "quarantine"})
        if not with_motion or self.motion == MotionParams():  # the default: the hash of the builds before motion
            del d["motion"]  # compensation existed (a scene it changes says so in its meta.json)
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]



class SceneStats(GTModel):
    valid_pct: float
    nonoccluded_pct: float
    fruit_pct: float
    disp_min_px: float | None
    disp_max_px: float | None
    over_max_disp_pct: float



class InputStamp(GTModel):
    """An input file's size and modification time when its BLAKE3 was taken (meta.json)."""

    size_bytes: int
    mtime_ns: int
    hashed_at_ns: int



class SceneMeta(VersionedFile):

    # 2: the inputs' BLAKE3 (input_blake3) instead of their SHA-256; 3: verification.motion_compensation (issue 37)
    SCHEMA_VERSION: ClassVar[int] = 3
    KIND: ClassVar[str] = "scene meta.json (from gtforge build-dataset)"
    schema_version: int = 3
    scene: str
    fruit_id: str | None = None
    gtforge_version: str
    calibration_sha256: str
    params_hash: str
    input_blake3: dict[str, str]  # the input files' BLAKE3 (io.digest), by name
    input_stamps: dict[str, InputStamp] = Field(default_factory=dict)  # resume fast path (inputs_unchanged)
    stats: SceneStats
    crop_xywh: list[int] | None = None
    fruit_mask_source: Literal["geometry", "user"] = "geometry"
    time_s: float = 0.0
    time_read_s: float = 0.0
    time_compute_s: float = 0.0
    time_write_s: float = 0.0
    verification: SceneVerification | None = None
    sigma: dict[str, SigmaStats] | None = None  # GT uncertainty per region: all, fruit, fruit_centre, ...
    sigma_extrinsic_included: bool = False  # False: the calibration file had no covariance (older gtforge)



class Manifest(VersionedFile):

    SCHEMA_VERSION: ClassVar[int] = 3  # 2: scene metas of schema 2; 3: of schema 3, compensated (issue 37)
    KIND: ClassVar[str] = "dataset manifest.json (from gtforge build-dataset)"
    schema_version: int = 3
    gtforge_version: str
    calibration_path: str
    calibration_sha256: str
    session_dir: str
    params: BuildParams
    scenes: dict[str, SceneMeta]
    failures: dict[str, str] = Field(default_factory=dict)
    splits: dict[str, list[str]] = Field(default_factory=dict)
    flagged: dict[str, list[str]] = Field(default_factory=dict)  # scene -> why verification flagged it
    quarantined: list[str] = Field(default_factory=list)  # flagged scenes left out of the split lists
    # scenes whose fruit moved between the exposures and whose ground truth was rebuilt with the fruit moved (issue 37)
    compensated: list[str] = Field(default_factory=list)

    # what differs between two builds of the same labels: where the build ran from and when, and how long it took
    VOLATILE: ClassVar[tuple[str, ...]] = ("calibration_path", "session_dir", "input_stamps", "time_s", "time_read_s",
                                           "time_compute_s", "time_write_s")

    def content_sha256(self) -> str:
        """SHA-256 of the manifest without its ``VOLATILE`` fields (at any depth): the same for two builds of the
        same labels (a rebuild, a copy, the same session built on a Dask cluster), which the file's own hash is not."""
        def strip(x):
            if isinstance(x, dict):
                return {k: strip(v) for k, v in x.items() if k not in self.VOLATILE}
            return [strip(v) for v in x] if isinstance(x, list) else x

        text = json.dumps(strip(self.model_dump(mode="json")), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()
