"""ZED self-rectification: the right camera's residual rotation, estimated from left-right feature matches.

A real ZED's factory file (or the rectified model derived from it) leaves the rectified rows 0.4-2.3 px apart
(issue 25: ZED Mini HD 0.46 px, ZED HD 1.2 px, ZED FHD 2.3 px median |vertical disparity| of SIFT matches), mostly a
constant offset plus small slopes across the image: a residual rotation of the right camera of about 0.1 deg, which
the vendor's SDK corrects when it opens the camera. Every capture of a session holds what is needed to correct it:
points matched between the rectified left and right images must lie on the same row.

**Model.** A correction of the right camera only (the left rectified camera is the frame of the ground truth and of
``T_zed_from_mech``, so nothing else moves): the right camera's rectifying rotation gets a small extra rotation
``R_delta = exp(omega)`` and its focal length a scale ``1 + s``. On the rectified right image that is the homography
``H = K_s R_delta K^-1`` (``K``: the rectified right camera, ``K_s``: the same with ``f (1 + s)``), which maps a pixel
of the current right image to the corrected one. For raw images + SN.conf the correction is folded into the
rectification maps (one interpolation, as before); for images rectified before gtforge (the ZED SDK) the right image
is warped by ``H``. calibrate-scale's yaw of the right camera (``Rig.scale_corrections``) goes into the same
resampling (``corrected_right``): a right image is interpolated once, whatever its corrections.

**What vertical disparity determines.** To first order a right pixel ``(x, y)`` (normalised) moves vertically by
``f (omega_x (1 + y^2) - omega_y x y - omega_z x + s y)``: ``omega_x`` (the constant offset), ``omega_z`` (the slope
along u) and ``s`` (the slope along v) are well determined by matches spread over the image. ``omega_y`` (the rotation
about the vertical axis) appears only in the second-order ``x y`` term, while it shifts every *horizontal*
disparity by about ``f omega_y``: it is estimated here for information only and never applied (the horizontal terms
need an independent depth measurement). A vertical principal-point offset of the right camera is, to first order,
the same as ``omega_x`` and is not separated from it.

**When it is applied.** Only when the captures determine it: enough matches (``min_matches``), captures that agree
(no capture's rows off the common fit by more than ``disagree_px``: a rig knocked between captures, or images of
another unit, give "not determined"), and a correction that moves some pixel of the image by at least
``apply_min_px`` and is significant (3 sigma). A correction below that is reported as "not needed" and the images
stay exactly as they were.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np
from pydantic import Field

from gtforge.core.bspline import resample_homography
from gtforge.core.camera import RectifiedStereo
from gtforge.core.zed.scale_corrections import right_yaw_homography
from gtforge.core.schema import GTModel
from gtforge.infra import defaults

if TYPE_CHECKING:
    pass

log = logging.getLogger("gtforge.core.zed.selfcal")


class SelfRectifyParams(GTModel):
    min_matches: int = Field(60, ge=10)  # over all captures
    min_matches_per_capture: int = Field(12, ge=3)  # a capture with fewer counts for nothing (not for the check either)
    disagree_px: float = Field(0.3, gt=0)  # |median residual row offset| of one capture after the common fit
    apply_min_px: float = Field(0.03, ge=0)  # the correction's largest vertical move over the image
    max_features: int = Field(8000, ge=100)  # SIFT features per image
    # scene captures matched at most, evenly spread over the session (None: every scene; every board capture always).
    # A full-resolution capture's matching costs 1.1 s on two cores, so every scene of an 808-scene session would take
    # 15 min, while the fit's estimate stops moving after a few thousand matches (benchmarks/RESULTS.md, round 22)
    max_scenes: int | None = Field(defaults.MAX_SCENES, ge=1)
    # a yaw (rotation about y) moves rows by psi x y: where the matches determine it within this 1-sigma, it is fitted
    # with the rest and left out of the correction (calibrate-scale measures the yaw from disparities), so that it
    # does not leak into the focal scale and the roll, which also move columns; else the 3-parameter fit
    yaw_nuisance_max_sigma_deg: float = Field(0.005, ge=0)


class ZedRightCorrection(GTModel):
    """The correction applied to the right rectified camera: ``H = K_s R_delta K^-1`` (module docstring)."""

    rotvec_rad: list[float]  # R_delta = Rodrigues(rotvec_rad), composed onto the right camera's rectifying rotation
    focal_scale: float = 0.0  # s: the right camera's focal length times (1 + s)

    def R_delta(self) -> np.ndarray:
        return cv2.Rodrigues(np.asarray(self.rotvec_rad, np.float64).reshape(3, 1))[0]

    def K_right(self, stereo: RectifiedStereo) -> np.ndarray:
        """The rectified right camera's matrix (``f``, ``cx + doffs``, ``cy``)."""
        r = stereo.right
        return np.array([[r.fx_px, 0.0, r.cx_px], [0.0, r.fy_px, r.cy_px], [0.0, 0.0, 1.0]])

    def homography(self, stereo: RectifiedStereo) -> np.ndarray:
        """``H``: a pixel of the current rectified right image -> the corrected image."""
        K = self.K_right(stereo)
        K_s = K.copy()
        K_s[0, 0] *= 1.0 + self.focal_scale
        K_s[1, 1] *= 1.0 + self.focal_scale
        return K_s @ self.R_delta() @ np.linalg.inv(K)

    def max_vertical_move_px(self, stereo: RectifiedStereo) -> float:
        """The largest vertical move ``H`` makes over the image (its corners and edge midpoints)."""
        w, h = stereo.left.width_px - 1, stereo.left.height_px - 1
        pts = np.array([[u, v] for u in (0, w / 2, w) for v in (0, h / 2, h)], np.float64)
        moved = _apply_h(self.homography(stereo), pts)
        return float(np.max(np.abs(moved[:, 1] - pts[:, 1])))


def _apply_h(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    p = np.column_stack([uv, np.ones(len(uv))]) @ H.T
    return p[:, :2] / p[:, 2:3]


class CaptureRows(GTModel):
    """One capture's matches: ``v_left - v_right`` before and after the correction (px)."""

    capture: str
    n_matches: int
    median_before_px: float
    median_abs_before_px: float
    median_abs_after_px: float
    median_after_px: float


class ZedSelfRectification(GTModel):
    """What ``self_rectify`` found and did (recorded in the calibration file as ``zed_self_rectification``)."""

    status: Literal["applied", "not needed", "not determined"]
    reason: str
    correction: ZedRightCorrection | None = None  # set when applied: every stage rectifies with it
    # the fit (omega_x, omega_z, s), whether applied or not; sigma from the residual scatter
    rotvec_rad: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0])  # (omega_x, 0, omega_z)
    sigma_rotvec_rad: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0])  # omega_y's: not estimated (0)
    focal_scale: float = 0.0
    sigma_focal_scale: float = 0.0
    cov_rad_rad_1: list[list[float]] | None = None  # (omega_x, omega_z, s)
    # omega_y as far as vertical disparity alone shows it (second order): information, never applied
    omega_y_vertical_only_rad: float | None = None
    sigma_omega_y_vertical_only_rad: float | None = None
    max_vertical_move_px: float = 0.0  # of the fitted correction over the image
    n_matches: int = 0
    median_abs_before_px: float | None = None
    median_abs_after_px: float | None = None
    rectified_by: str = ""  # the rectification the matches were made in
    captures: list[CaptureRows] = Field(default_factory=list)
    skipped: dict[str, str] = Field(default_factory=dict)  # capture -> why it gave no matches
    scenes_not_matched: int = 0  # scene captures beyond SelfRectifyParams.max_scenes (the matched ones evenly spread)

    def summary_line(self) -> str:
        if self.status == "applied":
            w = np.degrees(self.rotvec_rad)
            return (f"ZED self-rectification applied: right camera rotated ({w[0]:+.4f}, 0, {w[2]:+.4f}) deg, focal "
                    f"scale {self.focal_scale:+.2e}; median |vertical disparity| {self.median_abs_before_px:.3f} -> "
                    f"{self.median_abs_after_px:.3f} px over {self.n_matches} matches in {len(self.captures)} captures"
                    + self.scenes_note())
        return f"ZED self-rectification {self.status}: {self.reason}" + self.scenes_note()

    def scenes_note(self) -> str:
        """"" when every scene capture was matched; otherwise how many were not (SelfRectifyParams.max_scenes)."""
        if not self.scenes_not_matched:
            return ""
        return f" ({self.scenes_not_matched} scene captures not matched: max_scenes, the matched ones evenly spread)"


@dataclass
class Matches:
    capture: str
    left_uv: np.ndarray  # (N, 2) rectified left
    right_uv: np.ndarray  # (N, 2) rectified right


def _vertical_residual(theta: np.ndarray, pl: np.ndarray, pr: np.ndarray, stereo: RectifiedStereo,
                       with_omega_y: bool) -> np.ndarray:
    """``v_left - v_right'`` with the right points moved by the correction ``theta``: (omega_x, omega_z, s) or, with
    ``with_omega_y``, (omega_x, omega_y, omega_z, s)."""
    wx, wy, wz, s = (theta if with_omega_y else (theta[0], 0.0, theta[1], theta[2]))
    H = ZedRightCorrection(rotvec_rad=[wx, wy, wz], focal_scale=s).homography(stereo)
    return pl[:, 1] - _apply_h(H, pr)[:, 1]


def _robust_fit(pl, pr, stereo, with_omega_y):
    from scipy.optimize import least_squares  # here, not at import: io/captures imports this module on every build

    n = 4 if with_omega_y else 3
    scale = np.full(n, 1e-3)
    fun = lambda th: _vertical_residual(th, pl, pr, stereo, with_omega_y)  # noqa: E731
    first = least_squares(fun, np.zeros(n), loss="soft_l1", f_scale=0.2, x_scale=scale)
    r = first.fun
    mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    keep = np.abs(r) <= max(5.0 * mad, 0.3)
    fun_k = lambda th: _vertical_residual(th, pl[keep], pr[keep], stereo, with_omega_y)  # noqa: E731
    fit = least_squares(fun_k, first.x, x_scale=scale)
    dof = max(int(keep.sum()) - n, 1)
    s2 = float(np.sum(fit.fun ** 2) / dof)
    try:
        cov = np.linalg.inv(fit.jac.T @ fit.jac) * s2
    except np.linalg.LinAlgError:
        cov = np.full((n, n), np.inf)
    return fit.x, cov, keep


def fit_self_rectification(matches: list[Matches], stereo: RectifiedStereo, params: SelfRectifyParams | None = None,
                           rectified_by: str = "", skipped: dict[str, str] | None = None) -> ZedSelfRectification:
    """The right camera's correction from ``matches`` (rectified pixels), with the decision whether to apply it."""
    params = params or SelfRectifyParams()
    skipped = dict(skipped or {})
    used = []
    for m in matches:
        if len(m.left_uv) < params.min_matches_per_capture:
            skipped[m.capture] = f"{len(m.left_uv)} matches (< {params.min_matches_per_capture})"
        else:
            used.append(m)
    n = sum(len(m.left_uv) for m in used)
    base = dict(rectified_by=rectified_by, skipped=skipped, n_matches=n)
    if n < params.min_matches:
        return ZedSelfRectification(status="not determined", reason=f"only {n} left-right matches over "
                                    f"{len(used)} captures (at least {params.min_matches} needed): too little "
                                    "texture, or the right images are missing", **base)
    pl = np.concatenate([m.left_uv for m in used])
    pr = np.concatenate([m.right_uv for m in used])
    theta4, cov4, _ = _robust_fit(pl, pr, stereo, with_omega_y=True)
    yaw_nuisance = bool(np.sqrt(max(cov4[1, 1], 0.0)) <= np.radians(params.yaw_nuisance_max_sigma_deg))
    if yaw_nuisance:  # (omega_x, omega_z, s) of the 4-parameter fit, the yaw fitted but not applied
        keep = [0, 2, 3]
        theta, cov = theta4[keep], cov4[np.ix_(keep, keep)]
    else:
        theta, cov, _ = _robust_fit(pl, pr, stereo, with_omega_y=False)
    corr = ZedRightCorrection(rotvec_rad=[float(theta[0]), 0.0, float(theta[1])], focal_scale=float(theta[2]))
    H = corr.homography(stereo)
    rows = []
    for m in used:
        before = m.left_uv[:, 1] - m.right_uv[:, 1]
        after = m.left_uv[:, 1] - _apply_h(H, m.right_uv)[:, 1]
        rows.append(CaptureRows(capture=m.capture, n_matches=len(before), median_before_px=float(np.median(before)),
                                median_abs_before_px=float(np.median(np.abs(before))),
                                median_abs_after_px=float(np.median(np.abs(after))),
                                median_after_px=float(np.median(after))))
    dv_before = pl[:, 1] - pr[:, 1]
    dv_after = pl[:, 1] - _apply_h(H, pr)[:, 1]
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    move = corr.max_vertical_move_px(stereo)
    fields = dict(rotvec_rad=corr.rotvec_rad, sigma_rotvec_rad=[float(sig[0]), 0.0, float(sig[1])],
                  focal_scale=corr.focal_scale, sigma_focal_scale=float(sig[2]), cov_rad_rad_1=cov.tolist(),
                  omega_y_vertical_only_rad=float(theta4[1]),
                  sigma_omega_y_vertical_only_rad=float(np.sqrt(max(cov4[1, 1], 0.0))), max_vertical_move_px=move,
                  median_abs_before_px=float(np.median(np.abs(dv_before))),
                  median_abs_after_px=float(np.median(np.abs(dv_after))), captures=rows, **base)
    off = [r for r in rows if abs(r.median_after_px) > params.disagree_px]
    if off and len(rows) > 1:
        worst = max(off, key=lambda r: abs(r.median_after_px))
        return ZedSelfRectification(
            status="not determined", reason=f"the captures disagree: after the common fit capture {worst.capture}'s "
            f"rows are still {worst.median_after_px:+.2f} px apart (> {params.disagree_px} px; {len(off)} of "
            f"{len(rows)} captures): was the rig knocked between captures, or are some images from another unit? "
            "Calibrate each group of captures separately", **fields)
    significant = bool(np.any(np.abs(theta) > 3.0 * sig))
    if move < params.apply_min_px or not significant:
        return ZedSelfRectification(
            status="not needed", reason=f"the fitted correction moves no pixel by more than {move:.3f} px "
            f"(threshold {params.apply_min_px} px{'' if significant else ', and it is within 3 sigma of zero'}): "
            "the images are left as they are", **fields)
    yaw_note = (f"; the yaw the rows show ({np.degrees(theta4[1]):+.4f} +- {np.degrees(np.sqrt(cov4[1, 1])):.4f} deg) "
                "was fitted with them and left to calibrate-scale, which measures it from disparities"
                if yaw_nuisance else "")
    return ZedSelfRectification(status="applied", reason="the captures determine the right camera's residual "
                                "rotation (about x and z) and focal scale" + yaw_note, correction=corr, **fields)


# ---- applying it ---------------------------------------------------------------------------------------------------
def corrected_rectification(rect, correction: ZedRightCorrection | None, right_yaw_deg: float = 0.0):
    """A ``ZedRectification`` (raw images + SN.conf) whose right maps include ``correction``: for a corrected pixel
    ``p`` the raw ray is ``(R_delta R_rect_from_raw_right)^T K_s^-1 p`` (module docstring), one interpolation.

    ``right_yaw_deg`` (calibrate-scale's yaw, ``corrected_right``): the maps also undo it, ``p`` sampling the
    self-corrected image at ``H_yaw p``, so the raw ray is ``(R_delta R_rect)^T K_s^-1 H_yaw p``. ``correction`` may
    then be None (the yaw alone). The right image is sampled at the maps with cubic B-splines at the exact positions
    (``ZedRectification.interpolation``; why not ``cv2.remap``: ``RightImageCorrection``)."""
    import dataclasses

    if correction is None and right_yaw_deg == 0.0:
        return rect
    if correction is not None:
        K_s = correction.K_right(rect.stereo)
        K_s[0, 0] *= 1.0 + correction.focal_scale
        K_s[1, 1] *= 1.0 + correction.focal_scale
        R_right = correction.R_delta() @ rect.R_rect_from_raw_right
    else:
        K_s, R_right = rect.stereo.right.K, rect.R_rect_from_raw_right
    f = rect.factory
    size = f.size_wh
    # the right image sampled at its maps' exact positions (cv2.remap rounds them to 1/32 px: RightImageCorrection)
    extra = {"interpolation": "cubic-bspline"}
    if right_yaw_deg != 0.0:
        # initUndistortRectifyMap takes any 3x3 "new camera matrix" A: the ray of pixel p is (A R)^-1 p
        K_s = np.linalg.inv(right_yaw_homography(rect.stereo.right.K, np.radians(right_yaw_deg))) @ K_s
        extra["right_yaw_deg"] = float(right_yaw_deg)
    maps_r = cv2.initUndistortRectifyMap(f.right.K, f.right.dist, R_right, K_s, size, cv2.CV_32FC1)
    return dataclasses.replace(rect, maps_right=maps_r, R_rect_from_raw_right=R_right, correction=correction, **extra)


def right_sampling_homography(stereo: RectifiedStereo, correction: ZedRightCorrection | None,
                              right_yaw_deg: float) -> np.ndarray:
    """``M``: a pixel of the corrected right image -> the pixel of the right image as rectified before gtforge that
    it shows. The self-rectification maps an image pixel ``q`` to ``H q`` (``ZedRightCorrection.homography``);
    calibrate-scale measured its yaw on that self-corrected image, whose pixel ``H_yaw p``
    (``gtforge.core.zed.scale_corrections.yaw_homography``: ideal rectified pixel -> turned camera's pixel) shows what
    the ideal right camera sees at ``p``. So ``M = H^-1 H_yaw``: the yaw is undone first, then the
    self-rectification."""
    H_yaw = right_yaw_homography(stereo.right.K, np.radians(right_yaw_deg))
    return H_yaw if correction is None else np.linalg.inv(correction.homography(stereo)) @ H_yaw


@dataclass
class CorrectedRightImage:
    """Images rectified before gtforge (ZED SDK) with calibrate-scale's yaw, and the self-rectification when it was
    applied: the left image as it is, the right one resampled once (cubic B-spline at ``right_sampling_homography``'s
    exact positions, black outside; with the yaw alone exactly what the stages' second resampling gave,
    ``gtforge.core.zed.scale_corrections.corrected_right_image``)."""

    stereo: RectifiedStereo
    correction: ZedRightCorrection | None
    right_yaw_deg: float
    inner: object | None = None  # not used: images come rectified
    left_unchanged: bool = True  # the left image is the file's pixels (Session.load_capture keeps it verbatim)

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # (bspline.resample of apply_homography over the pixel grid, without the grid's arrays: the same pixels)
        return left, resample_homography(right, right_sampling_homography(self.stereo, self.correction,
                                                                          self.right_yaw_deg))


@dataclass
class RightImageCorrection:
    """The self-rectification alone on images rectified before gtforge: the right image resampled at ``H^-1 p``, as
    ``CorrectedRightImage`` does without a yaw (whose ``rectify`` it calls). Not ``cv2.warpPerspective``: OpenCV's warps
    and remaps round every sample position to 1/32 px, and on a session whose right camera was turned 0.15 deg about
    x and z that rounding alone took calibrate-scale's baseline to +0.47 % (truth +0.30 %, 7 sigma) and its yaw 5 sigma
    off (docs/design/accuracy.md)."""

    correction: ZedRightCorrection
    stereo: RectifiedStereo
    inner: object | None = None  # not used: images come rectified
    left_unchanged: bool = True  # the left image is the file's pixels (Session.load_capture keeps it verbatim)

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return CorrectedRightImage(self.stereo, self.correction, 0.0).rectify(left, right)


def corrected_right(rect, stereo: RectifiedStereo, correction: ZedRightCorrection | None, right_yaw_deg: float = 0.0):
    """What a session rectifies its ZED images with, given the right camera's corrections a calibration recorded:
    the self-rectification (``correction``) and calibrate-scale's yaw (``right_yaw_deg``), in one resampling of the
    right image. ``rect``: the SN.conf rectification of raw images (None: images rectified before gtforge).

    Neither: ``rect`` as it is. The self-rectification alone: as before the yaw joined it (folded into the maps, or
    ``RightImageCorrection``'s resampling). With the yaw: ``corrected_rectification``'s maps, or
    ``CorrectedRightImage``."""
    if right_yaw_deg == 0.0:
        if correction is None:
            return rect
        return (corrected_rectification(rect, correction) if rect is not None
                else RightImageCorrection(correction, stereo))
    if rect is not None:
        return corrected_rectification(rect, correction, right_yaw_deg)
    return CorrectedRightImage(stereo, correction, float(right_yaw_deg))
