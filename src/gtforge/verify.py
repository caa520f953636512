"""Per-scene verification: does a scene's ground truth match the images it labels?

Two independent checks per scene (docs/pipeline.md, "verify"):

* **Texture alignment (XY)**: the structured-light texture image is rendered into the ZED-left view through the
  ground-truth geometry (ZED-left pixel + GT depth -> 3-D -> texture-camera pixel with its lens model -> bilinear
  sample). Both images are locally normalised (zero mean, unit variance in a Gaussian window, masked), which removes
  the two cameras' different colours, exposures and shading; the residual translation between them is found by
  iterative Lucas-Kanade (Gauss-Newton on the normalised intensities), over the fruit and over the whole valid area,
  and on a coarse grid of tiles (a shift map). ``shift = where the ZED image shows a structure - where the ground
  truth puts it`` (px, ZED-left). The zero-mean normalised cross-correlation of the aligned pair catches a scene whose
  content changed (not just shifted).
* **Stereo consistency (disparity)**: the ZED-right image is warped into the left view through the GT disparity;
  Gauss-Newton finds the disparity bias ``b`` and vertical offset ``dy`` that best explain the residual
  (``left(u, v) ~ right(u - d - b, v + dy)``; reported as the vertical disparity ``v_left - v_right = -dy``, as
  ``gtforge.rectification`` reports it for board corners), per region. A textured pixel's match is "clearly worse" when the
  5x5 sum of absolute normalised differences at its GT disparity exceeds the best within +-1 px (steps of 0.5 px) by
  more than ``bad_match_ratio``; their share is reported.

A scene is **flagged** when a figure passes its threshold (``VerifyParams``, documented defaults in px at the
dataset's resolution). Nothing here changes the ground truth.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Callable, ClassVar, Literal

import cv2
import numba
import numpy as np
from pydantic import Field
from scipy import ndimage

from gtforge.camera import Rig
from gtforge.errors import InputError
from gtforge.geometry import transform_points
from gtforge.io.formats import to_gray
from gtforge.rectification import VERTICAL_WARN_PX
from gtforge.schema import GTModel, VersionedFile

log = logging.getLogger("gtforge.verify")

REGION_NONE, REGION_BG, REGION_CENTRE, REGION_EDGE = 0, 1, 2, 3  # as gtforge.build_dataset writes region.png


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


class ShiftEstimate(GTModel):
    dx_px: float | None = None
    dy_px: float | None = None
    correlation: float | None = None  # ZNCC of the normalised images after alignment
    n_pixels: int = 0

    @property
    def magnitude_px(self) -> float | None:
        return None if self.dx_px is None else float(np.hypot(self.dx_px, self.dy_px))


class StereoEstimate(GTModel):
    disparity_bias_px: float | None = None
    vertical_px: float | None = None
    bad_match_pct: float | None = None
    n_pixels: int = 0


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


class VerificationReport(VersionedFile):
    """``verification.json`` in a dataset: every scene's checks and the thresholds they were judged by."""

    KIND: ClassVar[str] = "verification report (verification.json from gtforge build-dataset / verify)"
    dataset_dir: str
    params: VerifyParams
    scenes: dict[str, SceneVerification]

    @property
    def flagged(self) -> dict[str, list[str]]:
        return {s: v.reasons for s, v in self.scenes.items() if v.status == "flagged"}


# ---- image helpers ------------------------------------------------------------------------------
def local_normalize(img: np.ndarray, mask: np.ndarray | None, sigma_px: float) -> np.ndarray:
    """Zero local mean, unit local standard deviation within a Gaussian window, using only ``mask`` pixels
    (normalised convolution; ``None``: every pixel); 0 outside the mask. Removes gain, offset and slow shading
    differences."""
    k = (0, 0)
    x = np.asarray(img, np.float32) if mask is None else np.where(mask, img, 0).astype(np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        if mask is None:  # the weights are all 1: no normalisation by them
            mean = cv2.GaussianBlur(x, k, sigma_px)
            var = cv2.GaussianBlur(x * x, k, sigma_px) - mean * mean
        else:
            w = cv2.GaussianBlur(mask.astype(np.float32), k, sigma_px)
            mean = cv2.GaussianBlur(x, k, sigma_px) / w
            var = cv2.GaussianBlur(x * x, k, sigma_px) / w - mean * mean
        out = (x - mean) / np.sqrt(np.maximum(var, 1e-6) + 1.0)  # +1 (grey level^2): flat areas stay near 0
    if mask is not None:
        out[~mask | ~(w > 0.5)] = 0.0
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)


def interior_mask(mask: np.ndarray, radius_px: int) -> np.ndarray:
    """Mask pixels whose whole ``radius_px`` neighbourhood is in the mask (normalisation and gradients are exact)."""
    k = 2 * radius_px + 1
    return cv2.erode(mask.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)


def render_texture(depth_zed_mm: np.ndarray, rig: Rig, texture: np.ndarray,
                   occlusion_tol_mm: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The texture image rendered into the ZED-left view through the GT depth: ``(float32 image, valid mask)``.

    Each ZED-left pixel with GT depth is back-projected, moved into the texture camera (``T_mech_from_zed``),
    projected with its lens model and sampled bilinearly. A point the texture camera cannot see (outside its image,
    or hidden behind another GT point by more than ``occlusion_tol_mm``) is left out."""
    H, W = depth_zed_mm.shape
    cam = rig.zed.left
    valid = np.isfinite(depth_zed_mm)
    v, u = np.nonzero(valid)
    z = depth_zed_mm[v, u].astype(np.float64)
    P = np.stack([(u - cam.cx_px) / cam.fx_px * z, (v - cam.cy_px) / cam.fy_px * z, z], axis=1)
    Pm = transform_points(rig.T_mech_from_zed, P)
    uv = rig.mech.project(Pm)
    tex = to_gray(texture).astype(np.float32)
    th, tw = tex.shape
    inside = (Pm[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= tw - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= th - 1)
    if rig.separate_depth_camera:
        # the depth camera saw these points; the texture camera may not: z-buffer them in the texture image
        ui = np.clip(np.round(uv[:, 0]).astype(np.int64), 0, tw - 1)
        vi = np.clip(np.round(uv[:, 1]).astype(np.int64), 0, th - 1)
        zbuf = np.full(th * tw, np.inf)
        np.minimum.at(zbuf, vi[inside] * tw + ui[inside], Pm[inside, 2])
        inside &= Pm[:, 2] <= zbuf[vi * tw + ui] + occlusion_tol_mm
    out = np.zeros((H, W), np.float32)
    ok = np.zeros((H, W), bool)
    ok[v[inside], u[inside]] = True
    # bilinear at the exact position (cv2.remap would round it to 1/32 px)
    out[v[inside], u[inside]] = ndimage.map_coordinates(tex, [uv[inside, 1], uv[inside, 0]], order=1, mode="nearest")
    return out, ok


def smooth_depth_mask(disparity_px: np.ndarray, radius_px: int = 3, max_range_px: float = 1.0) -> np.ndarray:
    """Pixels whose GT disparity varies by less than ``max_range_px`` within ``radius_px`` (away from depth edges,
    where a rendering through the GT mixes fore- and background and biases an alignment)."""
    k = np.ones((2 * radius_px + 1,) * 2, np.uint8)
    d = disparity_px.astype(np.float32)
    hi = cv2.dilate(np.where(np.isfinite(d), d, -1e6).astype(np.float32), k)
    lo = cv2.erode(np.where(np.isfinite(d), d, 1e6).astype(np.float32), k)
    return (hi - lo) < max_range_px


@numba.njit(cache=True, inline="always")
def _keys(s):
    s = abs(s)
    if s <= 1.0:
        return (1.5 * s - 2.5) * s * s + 1.0
    if s < 2.0:
        return ((-0.5 * s + 2.5) * s - 4.0) * s + 2.0
    return 0.0


@numba.njit(cache=True)
def _cubic_at(img, x, y, out):
    """Keys cubic convolution (a = -0.5, interpolating) at exact positions; borders replicated."""
    H, W = img.shape
    for k in range(x.shape[0]):
        fx = math.floor(x[k])
        fy = math.floor(y[k])
        tx = x[k] - fx
        ty = y[k] - fy
        ix = int(fx)
        iy = int(fy)
        acc = 0.0
        for j in range(4):
            yy = min(max(iy + j - 1, 0), H - 1)
            row = 0.0
            for i in range(4):
                xx = min(max(ix + i - 1, 0), W - 1)
                row += _keys(tx - (i - 1)) * img[yy, xx]
            acc += _keys(ty - (j - 1)) * row
        out[k] = acc


def sample_cubic(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Cubic samples of ``img`` at the points ``(x, y)`` (exact sub-pixel positions: ``cv2.remap`` rounds them to
    1/32 px, the size of the shifts measured here)."""
    out = np.empty(len(x))
    _cubic_at(np.ascontiguousarray(img, np.float32), np.ascontiguousarray(x, np.float64),
              np.ascontiguousarray(y, np.float64), out)
    return out


class ShiftAligner:
    """Translation ``d`` with ``img(u + d) ~ ref(u)`` over any mask of pixels (both images already normalised).

    Inverse-compositional Lucas-Kanade (the Hessian from ``ref``'s gradients) with a free gain and offset, ``img``
    sampled by cubic splines at the mask's points only; a coarse pass on copies blurred by 2 px first, so shifts of a
    few pixels converge. The image pyramids are built once and shared by every mask (whole area, fruit, tiles)."""

    SIGMAS = (2.0, 0.0)

    def __init__(self, ref: np.ndarray, img: np.ndarray):
        self.ref = ref
        self.levels = []
        for sigma in self.SIGMAS:
            r = cv2.GaussianBlur(ref, (0, 0), sigma) if sigma else ref
            i = cv2.GaussianBlur(img, (0, 0), sigma) if sigma else img
            self.levels.append((r, cv2.Sobel(r, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8),
                                cv2.Sobel(r, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8), np.ascontiguousarray(i, np.float32)))

    def align(self, mask: np.ndarray, min_pixels: int = 400, iterations: int = 30, tol_px: float = 1e-4,
              max_points: int = 30000) -> ShiftEstimate:
        """``max_points``: a larger mask is subsampled evenly (the estimate's noise is far below the thresholds)."""
        n = int(mask.sum())
        if n < min_pixels:
            return ShiftEstimate(n_pixels=n)
        v, u = np.nonzero(mask)
        if n > max_points:
            keep = np.linspace(0, n - 1, max_points).round().astype(np.int64)
            v, u = v[keep], u[keep]
        uf, vf = u.astype(np.float64), v.astype(np.float64)
        d = np.zeros(2)
        for r, gx, gy, coeffs in self.levels:
            rv = r[v, u].astype(np.float64)
            # img(u + d) * (1 + g) + o ~ ref(u): unknowns (step in d, g, o), linearised at the template
            A = np.stack([gx[v, u], gy[v, u], rv, np.ones_like(rv)], axis=1).astype(np.float64)
            try:
                pinv = np.linalg.solve(A.T @ A, A.T)
            except np.linalg.LinAlgError:
                return ShiftEstimate(n_pixels=n)
            for _ in range(iterations):
                step = pinv @ (sample_cubic(coeffs, uf + d[0], vf + d[1]) - rv)
                d -= step[:2]  # inverse composition of a translation
                if np.abs(d).max() > 20:  # diverged: nothing to align
                    return ShiftEstimate(n_pixels=n)
                if np.abs(step[:2]).max() < tol_px:
                    break
        w = sample_cubic(self.levels[-1][3], uf + d[0], vf + d[1])
        rv = self.ref[v, u].astype(np.float64)
        a, b = rv - rv.mean(), w - w.mean()
        # plain sums, not BLAS dot products: the same digits whatever the thread count (builds are byte-identical)
        saa, sbb, sab = float(np.sum(a * a)), float(np.sum(b * b)), float(np.sum(a * b))
        zncc = sab / np.sqrt(saa * sbb) if saa > 0 and sbb > 0 else None
        return ShiftEstimate(dx_px=float(d[0]), dy_px=float(d[1]), correlation=zncc, n_pixels=n)


def estimate_shift(ref: np.ndarray, img: np.ndarray, mask: np.ndarray, min_pixels: int = 400) -> ShiftEstimate:
    """One translation ``d`` with ``img(u + d) ~ ref(u)`` over ``mask`` (see ``ShiftAligner``)."""
    return ShiftAligner(ref, img).align(mask, min_pixels)


def textured_mask(norm_img: np.ndarray, thresh: float = 0.15) -> np.ndarray:
    gx = cv2.Sobel(norm_img, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(norm_img, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    return np.hypot(gx, gy) > thresh


# ---- the checks -----------------------------------------------------------------------------------
def texture_alignment(depth_zed_mm: np.ndarray, region: np.ndarray, zed_left: np.ndarray, texture: np.ndarray,
                      rig: Rig, params: VerifyParams, left_norm: np.ndarray | None = None
                      ) -> tuple[ShiftEstimate, ShiftEstimate, Callable[[], list], np.ndarray, np.ndarray]:
    """(whole valid area, fruit, a function computing the tiles' shifts, rendered texture normalised, mask used)."""
    rend, ok = render_texture(depth_zed_mm, rig, texture, params.texture_occlusion_tol_mm)
    r = int(np.ceil(2 * params.norm_sigma_px))
    ok_support = interior_mask(ok, r)
    n_rend = local_normalize(rend, ok, params.norm_sigma_px)
    gray = to_gray(zed_left).astype(np.float32)
    n_zed = left_norm if left_norm is not None else local_normalize(gray, None, params.norm_sigma_px)
    use = ok_support & textured_mask(n_rend) & smooth_depth_mask(rig.zed.depth_to_disparity(depth_zed_mm))
    fruit = use & ((region == REGION_CENTRE) | (region == REGION_EDGE))
    aligner = ShiftAligner(n_rend, n_zed)
    e_all = aligner.align(use, params.min_pixels)
    e_fruit = aligner.align(fruit, params.min_pixels)

    def tile_shifts() -> list[list[float | None]]:
        out = []
        H, W = gray.shape
        nx, ny = params.tiles
        for j in range(ny):
            for i in range(nx):
                sl = (slice(j * H // ny, (j + 1) * H // ny), slice(i * W // nx, (i + 1) * W // nx))
                m = np.zeros_like(use)
                m[sl] = use[sl]
                e = aligner.align(m, params.min_pixels)
                out.append([(sl[1].start + sl[1].stop - 1) / 2, (sl[0].start + sl[0].stop - 1) / 2, e.dx_px, e.dy_px])
        return out

    return e_all, e_fruit, tile_shifts, n_rend, use


def stereo_consistency(zed_left: np.ndarray, zed_right: np.ndarray, disparity_px: np.ndarray, nonoccluded: np.ndarray,
                       region: np.ndarray, params: VerifyParams, left_norm: np.ndarray | None = None
                       ) -> dict[str, StereoEstimate]:
    """Disparity bias, vertical offset and the share of clearly worse matches, per region (all, fruit, background)."""
    H, W = disparity_px.shape
    nl = left_norm if left_norm is not None else \
        local_normalize(to_gray(zed_left).astype(np.float32), None, params.norm_sigma_px)
    nr = local_normalize(to_gray(zed_right).astype(np.float32), None, params.norm_sigma_px)
    ok = nonoccluded & np.isfinite(disparity_px)
    d = np.where(ok, disparity_px, 0).astype(np.float32)
    gx_grid, gy_grid = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    # border pixels of the GT (the disparity may jump there) and pixels whose match falls off the image stay out
    base = interior_mask(ok, 2) & (gx_grid - d > 3) & (gx_grid - d < W - 4) & (gy_grid > 3) & (gy_grid < H - 4)
    use = base & textured_mask(nl) & smooth_depth_mask(disparity_px)
    regions = {"all": use, "fruit": use & ((region == REGION_CENTRE) | (region == REGION_EDGE)),
               "background": use & (region == REGION_BG)}
    gxr = cv2.Sobel(nr, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gyr = cv2.Sobel(nr, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    cr = nr

    def warp(a, extra_dx=0.0, dy=0.0):
        return cv2.remap(a, gx_grid - d - np.float32(extra_dx), gy_grid + np.float32(dy), cv2.INTER_CUBIC,
                         borderMode=cv2.BORDER_REPLICATE)

    # share of clearly worse matches: 5x5 SAD of the normalised images at GT and at GT +- 0.5, +- 1 px
    costs = {o: cv2.boxFilter(np.abs(nl - warp(nr, o)), -1, (5, 5), normalize=True) for o in (-1.0, -0.5, 0.0, 0.5, 1.0)}
    best_other = np.minimum.reduce([costs[o] for o in (-1.0, -0.5, 0.5, 1.0)])
    worse = costs[0.0] > params.bad_match_ratio * best_other
    out = {}
    for name, m in regions.items():
        n = int(m.sum())
        if n < params.min_pixels:
            out[name] = StereoEstimate(n_pixels=n)
            continue
        v, u = np.nonzero(m)
        if n > 30000:  # evenly subsampled: the estimate's noise stays far below the thresholds
            keep = np.linspace(0, n - 1, 30000).round().astype(np.int64)
            v, u = v[keep], u[keep]
        b, dy = 0.0, 0.0
        lv = nl[v, u].astype(np.float64)
        xr, yr = u - d[v, u].astype(np.float64), v.astype(np.float64)
        for _ in range(20):
            w = sample_cubic(cr, xr - b, yr + dy)
            wx = sample_cubic(gxr, xr - b, yr + dy)
            wy = sample_cubic(gyr, xr - b, yr + dy)
            # right(u - d - b, v + dy): d/db = -gx, d/d(dy) = +gy
            A = np.stack([-wx, wy, lv, np.ones_like(lv)], axis=1)
            step = np.linalg.solve(A.T @ A, -(A.T @ (w - lv)))
            b, dy = b + step[0], dy + step[1]
            if max(abs(step[0]), abs(step[1])) < 1e-5 or max(abs(b), abs(dy)) > 10:
                break
        if max(abs(b), abs(dy)) > 10:
            out[name] = StereoEstimate(n_pixels=n)
            continue
        # vertical disparity v_left - v_right, as gtforge.rectification reports it for board corners
        out[name] = StereoEstimate(disparity_bias_px=float(b), vertical_px=float(-dy),
                                   bad_match_pct=float(100.0 * worse[m].mean()), n_pixels=n)
    return out


def _scaled_shift(e: ShiftEstimate, f: int) -> ShiftEstimate:
    return e if e.dx_px is None else e.model_copy(update={"dx_px": e.dx_px * f, "dy_px": e.dy_px * f})


def _reduce(f: int, depth, disp, noc, region, left, right, rig: Rig):
    """Everything a factor ``f`` smaller: images by area averaging, depth by the mean of fully valid f x f blocks
    (the block centre's depth on a locally flat surface), labels by the block's top-left pixel; the ZED camera scaled
    the same way (pixel centres stay at integer coordinates)."""
    H, W = depth.shape
    h, w = H // f, W // f

    def area(a):  # the mean of each f x f block (NaN if any pixel of it is NaN)
        return cv2.resize(np.ascontiguousarray(a[:h * f, :w * f]), (w, h), interpolation=cv2.INTER_AREA)

    depth_r = area(depth.astype(np.float32))
    noc_r = area(noc.astype(np.float32)) == 1.0
    region_r = np.ascontiguousarray(region[:h * f:f, :w * f:f])
    left_r = cv2.resize(left[:h * f, :w * f], (w, h), interpolation=cv2.INTER_AREA)
    right_r = None if right is None else cv2.resize(right[:h * f, :w * f], (w, h), interpolation=cv2.INTER_AREA)
    zed = rig.zed.model_copy(update={"left": rig.zed.left.scaled(1.0 / f).model_copy(update={"width_px": w,
                                                                                             "height_px": h}),
                                     "doffs_px": rig.zed.doffs_px / f})
    rig_r = rig.model_copy(update={"zed": zed})
    return depth_r, zed.depth_to_disparity(depth_r), noc_r, region_r, left_r, right_r, rig_r


def verify_scene(depth_zed_mm: np.ndarray, disparity_px: np.ndarray, nonoccluded: np.ndarray, region: np.ndarray,
                 zed_left: np.ndarray, zed_right: np.ndarray | None, texture: np.ndarray | None, rig: Rig,
                 params: VerifyParams | None = None) -> tuple[SceneVerification, np.ndarray | None]:
    """Both checks for one scene (ZED-left arrays at the dataset's resolution, uncropped; see module docstring).
    Returns the verification and the rendered, normalised texture (for overlays; None when not measured)."""
    params = params or VerifyParams()
    reasons: list[str] = []
    if texture is None:
        return SceneVerification(status="not verifiable", reasons=["no texture image"]), None
    if float(to_gray(texture).std()) < 1.0:
        return SceneVerification(status="not verifiable", reasons=["the texture image is blank (no contrast)"]), None
    f = max(1, int(np.ceil(depth_zed_mm.shape[1] / params.work_width_px)))
    if f > 1:
        depth_zed_mm, disparity_px, nonoccluded, region, zed_left, zed_right, rig = _reduce(
            f, depth_zed_mm, disparity_px, nonoccluded, region, zed_left, zed_right, rig)
    left_norm = local_normalize(to_gray(zed_left).astype(np.float32), None, params.norm_sigma_px)  # shared by both
    e_all, e_fruit, tile_shifts, n_rend, _ = texture_alignment(depth_zed_mm, region, zed_left, texture, rig, params,
                                                               left_norm)
    stereo = stereo_consistency(zed_left, zed_right, disparity_px, nonoccluded, region, params, left_norm) \
        if zed_right is not None else {}
    if f > 1:  # back to the dataset's pixels
        e_all, e_fruit = _scaled_shift(e_all, f), _scaled_shift(e_fruit, f)
        stereo = {k: v.model_copy(update={"disparity_bias_px": None if v.disparity_bias_px is None
                                          else v.disparity_bias_px * f,
                                          "vertical_px": None if v.vertical_px is None else v.vertical_px * f})
                  for k, v in stereo.items()}
        tile_fn = tile_shifts

        def tile_shifts():
            return [[(x + 0.5) * f - 0.5, (y + 0.5) * f - 0.5, None if dx is None else dx * f,
                     None if dy is None else dy * f] for x, y, dx, dy in tile_fn()]
    if e_all.dx_px is None:
        return SceneVerification(status="not verifiable", reasons=[
            f"too little textured ground truth to align ({e_all.n_pixels} px < {params.min_pixels})"],
            texture_all=e_all, texture_fruit=e_fruit, stereo=stereo), None
    for name, e in (("whole area", e_all), ("fruit", e_fruit)):
        if e.magnitude_px is not None and e.magnitude_px > params.max_shift_px:
            reasons.append(f"texture shift over the {name} {e.magnitude_px:.2f} px > {params.max_shift_px} px "
                           f"(dx {e.dx_px:+.2f}, dy {e.dy_px:+.2f})")
        if e.correlation is not None and e.correlation < params.min_correlation:
            reasons.append(f"texture correlation over the {name} {e.correlation:.2f} < {params.min_correlation} "
                           "(the scene changed between the captures?)")
    for name, s in stereo.items():
        if s.disparity_bias_px is not None and abs(s.disparity_bias_px) > params.max_disparity_bias_px:
            reasons.append(f"stereo: disparity bias over the {name} {s.disparity_bias_px:+.3f} px "
                           f"(> {params.max_disparity_bias_px} px)")
        if name == "all" and s.vertical_px is not None and abs(s.vertical_px) > params.max_vertical_px:
            reasons.append(f"stereo: vertical misalignment {s.vertical_px:+.3f} px (> {params.max_vertical_px} px; "
                           "is the rectification the calibration's?)")
        if name == "all" and s.bad_match_pct is not None and s.bad_match_pct > params.max_bad_match_pct:
            reasons.append(f"stereo: {s.bad_match_pct:.1f} % of textured pixels match clearly better off the "
                           f"ground truth (> {params.max_bad_match_pct} %)")
    # the shift map is for looking at a flagged scene: only computed there
    tiles = tile_shifts() if reasons else []
    return SceneVerification(status="flagged" if reasons else "ok", reasons=reasons, texture_all=e_all,
                             texture_fruit=e_fruit, texture_tiles=tiles, stereo=stereo), n_rend


def predicted_shift(depth_zed_mm: np.ndarray, rig: Rig, T_zed_from_mech_true: np.ndarray) -> np.ndarray:
    """The texture shift ``(dx, dy)`` px an extrinsic error predicts: ground truth built with ``rig`` (``depth_zed_mm``),
    the true extrinsic ``T_zed_from_mech_true``; the mean over GT pixels of where the truth puts each GT point minus
    where the GT puts it (the sign of ``ShiftEstimate``)."""
    v, u = np.nonzero(np.isfinite(depth_zed_mm))
    cam = rig.zed.left
    z = depth_zed_mm[v, u].astype(np.float64)
    P = np.stack([(u - cam.cx_px) / cam.fx_px * z, (v - cam.cy_px) / cam.fy_px * z, z], axis=1)
    moved = transform_points(T_zed_from_mech_true @ rig.T_mech_from_zed, P)
    return (cam.project(moved) - np.stack([u, v], axis=1)).mean(axis=0)


def write_verification_report(report: VerificationReport, out_dir: str | Path) -> Path:
    """``verification.json`` + ``verification.html`` in ``out_dir``."""
    from gtforge.reports.verification import write_verification_html

    out = Path(out_dir)
    report.write(out / "verification.json")
    return write_verification_html(report, out)


def verify_dataset(dataset_dir: str | Path, params: VerifyParams | None = None, scenes: list[str] | None = None,
                   session_dir: str | Path | None = None, workers: int | None = None, scheduler: str | None = None,
                   quarantine: bool = False, progress: Callable[[str], None] | None = None) -> VerificationReport:
    """Re-run the checks on an existing dataset (its manifest names the session and calibration); writes
    ``verification.json``/``.html`` and the flagged list into ``manifest.json`` (and, with ``quarantine``, leaves
    flagged scenes out of the split lists)."""
    from gtforge.build_dataset import Manifest, final_splits, verify_one_scene, write_lists, write_split_views
    from gtforge.scheduling import run_tasks

    ds = Path(dataset_dir)
    man_path = ds / "manifest.json"
    if not man_path.is_file():
        raise InputError(ds, "manifest.json", "a dataset built by gtforge build-dataset", "no manifest.json",
                         "point verify at the dataset folder (the -o of build-dataset)")
    man = Manifest.read(man_path)
    sess = Path(session_dir) if session_dir else Path(man.session_dir)
    if not sess.is_dir():
        raise InputError(man_path, "session_dir", "the capture session the dataset was built from",
                         f"{sess} (no such folder)", "pass --session SESSION if the captures moved")
    calib = Path(man.calibration_path)
    if not calib.is_file():
        raise InputError(man_path, "calibration_path", "the calibration file the dataset was built from",
                         f"{calib} (no such file)", "restore it; verification needs the rig it was built with")
    from gtforge.calibrate import CalibrationFile, check_rig_matches_session
    from gtforge.io.captures import open_session

    cal = CalibrationFile.read(calib)
    check_rig_matches_session(cal.rig, open_session(sess, zed_conf_reading=cal.zed_conf_reading), calib,
                              f"is {sess} the session this dataset was built from?")
    params = params or man.params.verify
    ids = sorted(scenes or man.scenes)
    unknown = [s for s in ids if s not in man.scenes]
    if unknown:
        raise InputError(man_path, "scenes", "scenes of this dataset", ", ".join(unknown))
    args = [(str(sess.resolve()), str(ds.resolve()), sid, str(calib.resolve()), params.model_dump_json()) for sid in ids]
    results: dict[str, SceneVerification] = {}

    def handle(res):
        sid, ver = res
        results[sid] = SceneVerification.model_validate(ver)
        if progress:
            progress(f"verified {sid} ({len(results)}/{len(args)}): {results[sid].status}")

    run_tasks(verify_one_scene, args, handle, workers=workers, scheduler=scheduler,
              lost_result=lambda a, reason: (a[2], SceneVerification(status="not verifiable", reasons=[reason])
                                             .model_dump(mode="json")))
    old = {}
    rep_path = ds / "verification.json"
    if rep_path.is_file():
        old = VerificationReport.read(rep_path).scenes
    rep = VerificationReport(dataset_dir=str(ds.resolve()), params=params, scenes={**old, **results})
    write_verification_report(rep, ds)
    man.flagged = rep.flagged
    man.quarantined = sorted(rep.flagged) if quarantine else []
    man.splits = final_splits(sorted(man.scenes), {s: m.fruit_id for s, m in man.scenes.items()}, man.params,
                              man.quarantined)
    write_lists(ds, man.splits)
    write_split_views(ds, man.splits, man.params)
    man.write(man_path)
    return rep
