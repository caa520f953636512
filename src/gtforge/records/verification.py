"""What verification writes: ``VerifyParams`` (thresholds) and ``verification.json`` (``VerificationResult``:
every scene's ``SceneVerification``). Written by build-dataset and verify, read by the reports."""
from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field

from gtforge.core.alignment.photometric import ShiftEstimate
from gtforge.core.zed.rectification import VERTICAL_WARN_PX
from gtforge.core.schema import GTModel, VersionedFile


class VerifyParams(GTModel):
    """Thresholds (px at the dataset's resolution) and settings of the per-scene checks."""

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



class SceneVerification(GTModel):
    status: Literal["ok", "flagged", "not verifiable"]
    reasons: list[str] = Field(default_factory=list)
    texture_all: ShiftEstimate = Field(default_factory=ShiftEstimate)
    texture_fruit: ShiftEstimate = Field(default_factory=ShiftEstimate)
    texture_tiles: list[list[float | None]] = Field(default_factory=list)  # rows of (u_centre, v_centre, dx, dy)
    stereo: dict[str, StereoEstimate] = Field(default_factory=dict)  # region name -> estimate

    @property
    def worst_shift_px(self) -> float:
        vals = [e.magnitude_px for e in (self.texture_all, self.texture_fruit) if e.magnitude_px is not None]
        return max(vals) if vals else float("nan")



class VerificationResult(VersionedFile):
    """``verification.json`` in a dataset: every scene's checks and the thresholds they were judged by."""

    KIND: ClassVar[str] = "verification report (verification.json from gtforge build-dataset / verify)"
    # 2: figures measured with phase-unbiased (cubic B-spline) sampling, each with its noise floor (issue 41)
    SCHEMA_VERSION: ClassVar[int] = 2
    schema_version: int = 2
    dataset_dir: str
    params: VerifyParams
    scenes: dict[str, SceneVerification]

    @property
    def flagged(self) -> dict[str, list[str]]:
        return {s: v.reasons for s, v in self.scenes.items() if v.status == "flagged"}
