"""What verification writes: ``VerifyParams`` (thresholds) and ``verification.json`` (``VerificationResult``:
every scene's ``SceneVerification``). Written by build-dataset and verify, read by the reports."""
from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import ConfigDict, Field

from gtforge.core.alignment.photometric import ShiftEstimate
from gtforge.core.zed.rectification import VERTICAL_WARN_PX
from gtforge.core.schema import GTModel, VersionedFile


class VerifyParams(GTModel):
    """Thresholds (px at the dataset's resolution) and settings of the per-scene checks."""

    # every figure finite: an infinite threshold (verify --max-shift-px inf) reached the workers as JSON null, a
    # traceback
    model_config = ConfigDict(allow_inf_nan=False)

    max_shift_px: float = Field(0.25, gt=0)  # |texture shift| over the fruit or the whole valid area
    min_correlation: float = Field(0.5, ge=-1, le=1)  # normalised cross-correlation after alignment
    max_disparity_bias_px: float = Field(0.1, gt=0)  # |stereo disparity bias| in any region
    # |vertical disparity v_left - v_right| over the whole area; the board figure's threshold
    max_vertical_px: float = Field(VERTICAL_WARN_PX, gt=0)
    max_bad_match_pct: float = Field(10.0, gt=0)  # share of textured pixels with a clearly worse match at the GT
    bad_match_ratio: float = Field(1.5, gt=1)  # "clearly worse": cost at GT > ratio * best cost within +-1 px
    norm_sigma_px: float = Field(3.0, gt=0)  # Gaussian window of the local normalisation
    min_pixels: int = Field(400, ge=50)  # fewer usable pixels in a region: that region is not measured
    tiles: tuple[int, int] = (4, 3)  # shift map: tiles across x, y
    # the checks run on images reduced by an integer factor to at most this width (2208 -> 1104: factor 2); figures
    # are reported in the dataset's pixels
    work_width_px: int = Field(1200, ge=64)
    texture_occlusion_tol_mm: float = 2.0  # a GT point hidden from the texture camera by more than this is skipped



class StereoEstimate(GTModel):
    disparity_bias_px: float | None = None
    vertical_px: float | None = None
    bad_match_pct: float | None = None
    n_pixels: int = 0
    # noise floors (1 sigma, px) of the two figures: what exact labels give on this scene
    # (gtforge.core.alignment.photometric.block_noise); None where not measured
    disparity_bias_noise_px: float | None = None
    vertical_noise_px: float | None = None



class MotionParams(GTModel):
    """Settings of the motion compensation of a scene whose fruit moved between the structured-light exposure and the
    ZED exposure (``gtforge.dataset.motion_compensation``, docs/design/motion-compensation.md)."""

    compensate: bool = True  # try it on a scene verification flags for fruit motion (--no-motion-compensation: off)
    # the largest motion rebuilt: beyond it the ZED may see surface the depth camera never saw (the scene stays flagged)
    max_translation_mm: float = Field(6.0, gt=0)
    max_rotation_deg: float = Field(4.0, gt=0)
    # the motion's uncertainty, as 1-sigma disparity over the fruit's pixels (95th percentile, px at the dataset's
    # resolution), at most this for the fruit to be compensated; above, the fruit's pixels lose their ground truth
    # (holes) and the rest of the scene is compensated. 0.01: at full resolution every fruit under it met 0.01 px
    # EPE, those over it (0.016-0.019: partly out of the depth camera's view) did not always (benchmarks/RESULTS.md)
    max_sigma_px: float = Field(0.01, gt=0)
    # a fruit is moved only when its motion is significant: its squared Mahalanobis distance from no motion above this
    # (chi-square, 6 degrees of freedom, 99.9 %); below, it stayed still and keeps its ground truth
    min_chi2: float = Field(22.46, gt=0)
    texture_term: bool = True  # the structured-light texture vs ZED-left term beside the stereo term


class FruitMotion(GTModel):
    """One fruit's estimated motion (ZED-left frame): ``X' = R(rotvec) (X - centre) + centre + t``."""

    component: int  # 1, 2, ...: the fruit's connected component of the ZED-left fruit mask, in raster order
    n_pixels: int = 0  # ground-truth pixels the fit used
    centre_zed_mm: list[float] | None = None  # the centroid of the points fitted, at the depth exposure
    T_zed_moved_from_zed: list[list[float]] | None = None  # where a point was at the depth exposure -> at the ZED's
    rotvec_deg: list[float] | None = None
    translation_mm: list[float] | None = None
    sigma_rot_deg: list[float] | None = None  # 1 sigma of each rotation-vector component
    sigma_translation_mm: list[float] | None = None
    cov_rad_mm: list[list[float]] | None = None  # 6x6: (omega rad, t mm), a left perturbation
    disparity_sigma_px: float | None = None  # the motion's 1-sigma disparity, 95th percentile over the fruit's pixels
    chi2_still: float | None = None  # squared Mahalanobis distance of "no motion" from the estimate
    residual_rms: float | None = None
    status: Literal["moved", "still", "beyond limit", "undetermined", "not estimated", "no ground truth"]
    reason: str = ""


class MotionCompensation(GTModel):
    """What the motion compensation did to a scene: ``compensated`` (the ground truth was rebuilt with the fruit moved
    and passed verification) or ``not compensated`` (the scene keeps its ground truth and its flag: ``reasons``)."""

    status: Literal["compensated", "not compensated"]
    reasons: list[str] = Field(default_factory=list)
    fruit: list[FruitMotion] = Field(default_factory=list)
    before: "SceneVerification | None" = None  # the verification of the ground truth as built before compensation
    time_s: float = 0.0


class SceneVerification(GTModel):
    status: Literal["ok", "flagged", "not verifiable"]
    reasons: list[str] = Field(default_factory=list)
    texture_all: ShiftEstimate = Field(default_factory=ShiftEstimate)
    texture_fruit: ShiftEstimate = Field(default_factory=ShiftEstimate)
    texture_tiles: list[list[float | None]] = Field(default_factory=list)  # rows of (u_centre, v_centre, dx, dy)
    stereo: dict[str, StereoEstimate] = Field(default_factory=dict)  # region name -> estimate
    # a scene verification flagged for fruit motion: what the motion compensation did (its ground truth rebuilt, or
    # why not); None: not tried (not flagged, or compensation off)
    motion_compensation: MotionCompensation | None = None

    @property
    def compensated(self) -> bool:
        return self.motion_compensation is not None and self.motion_compensation.status == "compensated"

    @property
    def compensated_label(self) -> str:
        """What the reports add to a compensated scene's status: " (fruit motion compensated)", with the count of fruit
        whose motion was too uncertain (holes); "" when not compensated."""
        if not self.compensated:
            return ""
        n = sum(f.status == "no ground truth" for f in self.motion_compensation.fruit)
        return " (fruit motion compensated" + (f"; {n} fruit too uncertain: no ground truth" if n else "") + ")"

    @property
    def worst_shift_px(self) -> float:
        vals = [e.magnitude_px for e in (self.texture_all, self.texture_fruit) if e.magnitude_px is not None]
        return max(vals) if vals else float("nan")



class VerificationResult(VersionedFile):
    """``verification.json`` in a dataset: every scene's checks and the thresholds they were judged by."""

    KIND: ClassVar[str] = "verification report (verification.json from gtforge build-dataset / verify)"
    # 2: figures measured with phase-unbiased (cubic B-spline) sampling, each with its noise floor (issue 41)
    # 3: each scene's motion_compensation (issue 37)
    SCHEMA_VERSION: ClassVar[int] = 3
    schema_version: int = 3
    dataset_dir: str
    params: VerifyParams
    scenes: dict[str, SceneVerification]

    @property
    def flagged(self) -> dict[str, list[str]]:
        return {s: v.reasons for s, v in self.scenes.items() if v.status == "flagged"}


class VerifyJournalEntry(GTModel):
    inputs_stamp: str  # the sizes and modification times of the files the scene was checked from (verify.inputs_stamp)
    verification: SceneVerification


class VerifyJournal(VersionedFile):
    """``.verify-partial.json`` in a dataset: the scenes an interrupted ``gtforge verify`` had checked, which the next
    verify with the same thresholds, calibration and session takes over for every scene whose files have not changed
    since; removed once a verify completes."""

    KIND: ClassVar[str] = "record of an interrupted verify (.verify-partial.json)"
    SCHEMA_VERSION: ClassVar[int] = 1
    schema_version: int = 1
    params: VerifyParams
    calibration_sha256: str
    session_dir: str
    scenes: dict[str, VerifyJournalEntry]


MotionCompensation.model_rebuild()
