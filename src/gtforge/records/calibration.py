"""What calibrate, refine and calibrate-scale write: the calibration file (``CalibrationFile``: the rig every later
stage uses, its covariance, and every correction with where it came from) and its parts; and how a stage opens a
session with a calibration is ``gtforge.io.calibrated_session``. Pure data: nothing here opens a session."""
from __future__ import annotations

from pathlib import Path
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, PrivateAttr, model_serializer

from gtforge.core.camera import Rig
from gtforge.core.targets.coverage import CoverageResult
from gtforge.core.zed.rectification import RectificationQuality
from gtforge.core.schema import GTModel, VersionedFile
from gtforge.core.zed.selfcal import SelfRectifyParams, ZedRightCorrection, ZedSelfRectification
from gtforge.core.targets.models import BoardModel
from gtforge.infra import defaults
from gtforge.io.zed_rectification import ZedConfChoice
from gtforge.records.depth_alignment import DepthAlignment
from gtforge.records.verification import VerifyParams


class CalibrateParams(GTModel):
    board: BoardModel = Field(default_factory=BoardModel)
    use_depth: bool = False
    huber_px: float = 1.0
    outlier_k: float = 4.0  # median + k * 1.4826 * MAD rule on the per-pose extrinsic estimates
    outlier_floor_deg: float = 0.1
    outlier_floor_mm: float = 1.0
    blur_sharpness_px: float = 4.0  # flag poses whose edge width exceeds this
    min_poses: int = 3
    leave_one_out: bool = True
    # the board's squares measured in the depth must match square_size_mm within this (%); 0 switches it off
    square_check_pct: float = Field(3.0, ge=0)
    # ... and within this (%) for a PASS: a board declared 2.5 % off moved the extrinsic 45 sigma under a PASS
    square_warn_pct: float = Field(1.0, ge=0)
    # --use-depth: the two methods may differ by at most max(these floors, 5 sigma) before the verdict is FAIL
    methods_agree_deg: float = 0.1
    methods_agree_mm: float = 1.0
    # the ZED right camera's residual rotation from left-right matches over the captures (gtforge.core.zed.selfcal)
    self_rectify: bool = True
    self_rectification: SelfRectifyParams = Field(default_factory=SelfRectifyParams)



class PoseResult(GTModel):
    capture: str
    status: Literal["used", "skipped", "outlier"]
    reason: str = ""
    rms_mech_px: float | None = None
    rms_zed_px: float | None = None
    max_px: float | None = None
    sharpness_mech_px: float | None = None
    sharpness_zed_px: float | None = None
    blurred: bool = False
    init_rot_dev_deg: float | None = None
    init_trans_dev_mm: float | None = None
    loo_transfer_mean_px: float | None = None
    loo_transfer_max_px: float | None = None
    # ChArUco / circle grids (gtforge.core.targets.models): board points found in each image and in both (None:
    # checkerboard)
    n_points_mech: int | None = None
    n_points_zed: int | None = None
    n_points_common: int | None = None

    @model_serializer(mode="wrap")
    def _compact(self, handler):
        d = handler(self)
        return {k: v for k, v in d.items() if not (k.startswith("n_points_") and v is None)}



class MethodResult(GTModel):
    method: Literal["reprojection", "depth"]
    T_zed_from_mech: list[list[float]]
    rms_zed_px: float
    rot_diff_to_primary_deg: float = 0.0
    trans_diff_to_primary_mm: float = 0.0



class SceneRefinement(GTModel):
    scene: str
    status: Literal["used", "excluded", "not usable"]
    reason: str = ""
    n_points: int = 0
    shift_before_px: float | None = None  # |texture shift| (whole area) with the starting calibration
    shift_after_px: float | None = None  # with the refined calibration
    fruit_shift_after_px: float | None = None
    heldout_shift_px: float | None = None  # refined WITHOUT this scene, measured on it (cross-validation)



class RefinementInfo(GTModel):
    """Provenance of a refined calibration (stored in the calibration file)."""

    refined_from: str  # the starting calibration file
    method: str = "scene texture alignment (direct photometric, Huber IRLS)"
    scenes_used: list[str]
    scenes_excluded: dict[str, str] = Field(default_factory=dict)
    scenes_not_selected: int = 0  # the session's scenes beyond RefineParams.max_scenes (those used evenly spread)
    change_rot_deg: float
    change_trans_mm: float
    heldout_shift_before_mean_px: float | None = None
    heldout_shift_after_mean_px: float | None = None
    sigma_jackknife_rot_deg: float | None = None
    sigma_jackknife_trans_mm: float | None = None
    scenes: list[SceneRefinement] = Field(default_factory=list)



class CalibrationFile(VersionedFile):
    """Output of ``gtforge calibrate``; ``rig`` is what every later stage uses."""

    KIND: ClassVar[str] = "gtforge calibration file (from gtforge calibrate)"

    @classmethod
    def read(cls, path: str | Path) -> "CalibrationFile":
        """Read a calibration file; a folder holding ``calibration.yaml`` (what ``calibrate -o DIR/`` writes) means
        that file."""
        p = Path(path)
        if p.is_dir() and (p / "calibration.yaml").is_file():
            p = p / "calibration.yaml"
        return super().read(p)

    @classmethod
    def known_extrinsic(cls, rig: Rig, sigma_rot_deg: float = 0.0, sigma_trans_mm: float = 0.0) -> "CalibrationFile":
        """A calibration file for a rig whose extrinsic is known (synthetic truth, benchmarks), reported with
        ``sigma_rot_deg`` / ``sigma_trans_mm`` per axis (the covariance's diagonal, independent axes; no covariance
        when both are 0)."""
        cov = None
        if sigma_rot_deg or sigma_trans_mm:
            cov = np.diag([np.radians(sigma_rot_deg) ** 2] * 3 + [sigma_trans_mm ** 2] * 3).tolist()
        return cls(rig=rig, board=BoardModel(), captures_used=[], rms_px=0.0, max_px=0.0,
                   sigma_rot_xyz_deg=[sigma_rot_deg] * 3, sigma_trans_xyz_mm=[sigma_trans_mm] * 3,
                   sigma_rot_deg=float(np.sqrt(3) * sigma_rot_deg), sigma_trans_mm=float(np.sqrt(3) * sigma_trans_mm),
                   poses=[], cov_extrinsic_rad_mm=cov)

    rig: Rig
    board: BoardModel
    method: Literal["reprojection", "depth"] = "reprojection"
    session_dir: str = ""
    captures_used: list[str]
    rms_px: float
    max_px: float
    sigma_rot_xyz_deg: list[float]
    sigma_trans_xyz_mm: list[float]
    sigma_rot_deg: float
    sigma_trans_mm: float
    loo_transfer_mean_px: float | None = None
    loo_transfer_max_px: float | None = None
    poses: list[PoseResult]
    methods: list[MethodResult] = Field(default_factory=list)
    residuals_by_region_px: dict[str, float] = Field(default_factory=dict)
    # Full covariance of the written extrinsic, parameterised as a left perturbation:
    # T_zed_from_mech = [exp(omega) R | t + delta_t] with omega (rad, 3) then delta_t (mm, 3); rows/columns in
    # that order (omega_x, omega_y, omega_z, t_x, t_y, t_z). sigma_* above are the square roots of its diagonal.
    cov_extrinsic_rad_mm: list[list[float]] | None = None
    # the factor the leave-one-out jackknife scaled cov_extrinsic_rad_mm by (>= 1): over board poses (calibrate) or,
    # in a refined file, over scenes (refine --loo); None: no jackknife was run for this covariance
    cov_jackknife_scale: float | None = None
    square_size_measured_mm: float | None = None  # from the depth camera's view of the board (median over poses)
    verdict: Literal["PASS", "WARN", "FAIL"] = "PASS"
    verdict_reasons: list[str] = Field(default_factory=list)
    refinement: RefinementInfo | None = None  # set by gtforge refine: the extrinsic was refined from scenes
    # where the board points fell and what to capture next (gtforge.core.targets.coverage)
    coverage: CoverageResult | None = None
    # set by gtforge calibrate-scale: baseline scale, right-camera yaw, depth scale/offset (applied in rig)
    scale_calibration: ScaleCalibration | None = None
    # set by gtforge align-depth: a separate depth camera's pose from the captures' edges (applied in rig)
    depth_alignment: DepthAlignment | None = None

    @property
    def scale_corrected(self) -> bool:
        """calibrate-scale has run on it (its record, or corrections in the rig): a second run would compound them,
        and align-depth, which changes the pose they were fitted through, comes before it."""
        return self.scale_calibration is not None or self.rig.scale_corrections is not None

    @property
    def zed_conf_reading(self) -> str | None:
        """The SN.conf reading later stages rectify raw ZED images with (None: not a raw + SN.conf session)."""
        return self.zed_conf.reading if self.zed_conf is not None else None

    @property
    def zed_right_correction(self) -> ZedRightCorrection | None:
        """The right camera's correction later stages rectify with (None: none was applied)."""
        s = self.zed_self_rectification
        return s.correction if s is not None and s.status == "applied" else None

    # the ZED pair's rectification (board corners in both rectified images) and, for raw images + SN.conf,
    # the conf reading chosen from the board images (gtforge.core.zed.rectification; later stages rectify with it)
    rectification: RectificationQuality | None = None
    zed_conf: ZedConfChoice | None = None
    # the ZED pair's self-rectification (gtforge.core.zed.selfcal): when applied, every later stage rectifies with its
    # correction
    zed_self_rectification: ZedSelfRectification | None = None
    time_s: float = 0.0
    # per-corner residuals for the report (not written into the calibration file)
    _residuals: dict = PrivateAttr(default_factory=dict)



class ScaleParams(GTModel):
    points_per_scene: int = Field(40000, ge=1000)  # textured GT pixels per scene, evenly subsampled
    huber: float = Field(0.5, gt=0)  # on normalised intensities
    iterations: int = Field(30, ge=1)  # Gauss-Newton steps per solve
    outer_iterations: int = Field(4, ge=1)  # solve, rebuild every scene's GT with the result, solve again...
    converged_px: float = Field(0.002, gt=0)  # ... until a pass moves the scenes' disparities by less than this
    cov_tile_px: int = Field(16, ge=1)
    # a parameter whose 1-sigma moves disparities (at the scenes' median depth) by more than this is not applied
    max_sigma_px: float = Field(0.1, gt=0)
    # a determined parameter is applied only when its estimate is more than this many sigma from 0 (an insignificant
    # correction would only move the GT by noise); the others are then solved again with it held at 0
    apply_z: float = Field(2.0, ge=0)
    use_boards: bool = True
    # the scenes used when none are named: at most this many, evenly spread over the session (None: every scene). Each
    # full-resolution scene holds about 160 MB and takes about 1.5 s here, so every scene of an 808-scene session
    # would need some 130 GB (benchmarks/RESULTS.md, round 22)
    max_scenes: int | None = Field(defaults.MAX_SCENES, ge=1)
    board_depth_window_px: int = Field(3, ge=1)  # half-size of the depth window fitted at each corner
    # the largest corrections a rig's files can need: beyond them the files or the session are wrong (a baseline in
    # metres, another rig's calibration), and calibrate-scale refuses rather than apply a "correction" of them. A ZED's
    # factory baseline and yaw and a structured-light unit's depth scale are good to about 0.1 %, 0.05 deg and 0.1 %
    max_scale_correction_frac: float = Field(0.05, gt=0)  # zed_baseline_frac, depth_scale_frac
    max_yaw_deg: float = Field(0.5, gt=0)
    max_depth_offset_mm: float = Field(20.0, gt=0)
    max_depth_pose_deg: float = Field(2.0, gt=0)  # a separate depth camera's rotation (align-depth's to correct)
    verify: VerifyParams = Field(default_factory=VerifyParams)



class ScaleTerm(GTModel):
    """One parameter: ``estimate`` +- ``sigma`` (every determined term free: the covariance's), ``value`` what was
    applied (0 unless "applied"; solved with the terms not applied held at 0), and where it came from.
    "not significant": the estimate is within ``ScaleParams.apply_z`` sigma of 0."""

    value: float
    estimate: float | None
    sigma: float | None
    status: Literal["applied", "not significant", "not determined", "not separable"]
    sources: list[str] = Field(default_factory=list)
    reason: str = ""



class SceneScaleResult(GTModel):
    scene: str
    excluded: str = ""  # why the scene was left out ("": used)
    n_points: int = 0
    disparity_bias_before_px: float | None = None  # mean (d_img - d_gt) over the used pixels, before



class ScaleCalibration(GTModel):
    """What ``gtforge calibrate-scale`` found and applied (stored in the calibration file)."""

    method: str = "scene stereo consistency (photometric Gauss-Newton) + board PnP, stereo and depth"
    calibrated_from: str
    # conventions: the ZED's true baseline = (1 + zed_baseline_frac) x the file's; the right camera turned by
    # zed_right_yaw_deg about its y axis; the depth map reads (1 + depth_scale_frac) z + depth_offset_mm; a separate
    # depth camera's true pose is T_mech_from_depth_file turned by the rotation vector depth_pose_r{x,y,z}_deg about its
    # centre, axes of the texture camera (the left perturbation, gtforge.core.geometry.perturb_left)
    terms: dict[str, ScaleTerm]
    # over PARAMS' order (fraction, deg, fraction, mm, then, with a separate depth camera, its rotation in deg: 7x7,
    # else 4x4); rows/columns of a term not determined are 0
    covariance: list[list[float]]
    # b + k (what scenes alone determine) with its sigma
    combined_scale_frac: float
    combined_scale_sigma_frac: float | None
    baseline_file_mm: float  # the baseline before this correction (rig.zed.baseline_mm now holds the corrected one)
    # a separate depth camera's pose before this correction (rig.T_mech_from_depth now holds the corrected one)
    T_mech_from_depth_file: list[list[float]] | None = None
    scenes_used: list[str]
    scenes_not_selected: int = 0  # the session's scenes beyond ScaleParams.max_scenes (those used evenly spread)
    board_poses_used: list[str] = Field(default_factory=list)  # any of the two measurements' below
    # the board poses each measurement used: "zed_pair" (corner disparities: every pose the ZED pair saw) and
    # "depth_map" (the depth against the texture camera's PnP: the poses the depth camera saw), so that a pose seen by
    # one camera only is counted where it was used (calibrate's extrinsic needs poses both cameras saw)
    board_poses_by_measurement: dict[str, list[str]] = Field(default_factory=dict)
    passes: int = 0
    scenes: list[SceneScaleResult] = Field(default_factory=list)
    time_s: float = 0.0
