"""What validate writes: ``validation.json`` (``ValidationResult``, one ``PoseValidation`` per board capture), its
thresholds and the published reference figures the report compares against, with their source."""
from __future__ import annotations

from typing import ClassVar

from pydantic import ConfigDict, Field

from gtforge.core.measure.gauges import GaugesResult
from gtforge.core.schema import GTModel, VersionedFile
from gtforge.core.targets.models import BoardModel
from gtforge.core.zed.rectification import RectificationQuality
from gtforge.infra import defaults

REFERENCE_XY_PX = 0.56



REFERENCE_Z_PCT = 0.08



class ValidateParams(GTModel):
    # every figure finite: an infinite threshold (--xy-threshold-px inf) passed everything and failed in the report's
    # plot (a traceback)
    model_config = ConfigDict(allow_inf_nan=False)

    board: BoardModel | None = None  # None: the board stored in the calibration file
    xy_threshold_px: float = Field(defaults.XY_THRESHOLD_PX, gt=0)
    z_threshold_pct: float = Field(defaults.Z_THRESHOLD_PCT, gt=0)
    corner_radius_px: int = 8  # depth patch radius for the per-corner plane fit
    mode: str = "mesh"
    max_slant_deg: float = defaults.MAX_SLANT_DEG



class PoseValidation(GTModel):
    capture: str
    used_for_calibration: bool
    n_corners: int
    xy_mean_px: float
    xy_median_px: float
    xy_rms_px: float
    xy_max_px: float
    # the corner detectors' own noise, and XY with it removed (corners predicted by per-pose board models)
    xy_noise_floor_px: float
    xy_model_mean_px: float
    detector_rms_mech_px: float
    detector_rms_zed_px: float
    z_diagonal_calc_mm: float
    z_diagonal_true_mm: float
    z_error_pct: float  # corners from a homography fit of all detected ZED corners
    z_error_raw_corners_pct: float  # the two detected corners as they are
    z_pairs_mean_abs_pct: float
    z_pairs_max_abs_pct: float
    flatness_rms_mm: float
    scale_error_pct: float



class ValidationResult(VersionedFile):

    KIND: ClassVar[str] = "validation report (validation.json from gtforge validate)"
    calibration_path: str
    session_dir: str
    thresholds: dict[str, float]
    reference: dict[str, float] = Field(default_factory=lambda: {"xy_px": REFERENCE_XY_PX, "z_pct": REFERENCE_Z_PCT})
    xy_mean_px: float
    xy_median_px: float
    xy_rms_px: float
    xy_max_px: float
    xy_noise_floor_px: float  # mean XY error the two corner detectors' noise alone would give
    xy_model_mean_px: float  # XY with both detections replaced by per-pose board models (noise removed)
    z_error_mean_pct: float
    z_error_max_pct: float
    flatness_rms_mm: float
    scale_error_pct: float
    board: BoardModel
    pass_xy: bool
    pass_z: bool
    passed: bool
    warnings: list[str] = Field(default_factory=list)
    skipped: dict[str, str] = Field(default_factory=dict)
    poses: list[PoseValidation]
    corner_errors: list[list[float]] = Field(default_factory=list)  # (u_zed, v_zed, du, dv) per corner
    # vertical disparity of the board corners in both rectified ZED images (gtforge.core.zed.rectification)
    rectification: RectificationQuality | None = None
    # VDI/VDE 2634-2 figures on the session's gauge objects (gtforge.core.measure.gauges); absent: no gauges/gauges.yaml
    gauges: GaugesResult | None = None


REFERENCE_SOURCE = "Li et al., MI-ACVNet (MDPI, 2026)"  # where the published 0.56 px / 0.08 % come from
