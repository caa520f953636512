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
  ``gtforge.core.rectification`` reports it for board corners), per region. A textured pixel's match is "clearly worse" when the
  5x5 sum of absolute normalised differences at its GT disparity exceeds the best within +-1 px (steps of 0.5 px) by
  more than ``bad_match_ratio``; their share is reported.

A scene is **flagged** when a figure passes its threshold (``VerifyParams``, documented defaults in px at the
dataset's resolution). Nothing here changes the ground truth.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Callable, ClassVar, Literal, NamedTuple

import cv2
import numba
import numpy as np
from pydantic import Field

from gtforge.core import lens
from gtforge.core.camera import Rig
from gtforge.errors import InputError
from gtforge.core.geometry import finite_box, mask_bounding_box, transform_points
from gtforge.io.formats import to_gray
from gtforge.core.rectification import VERTICAL_WARN_PX
from gtforge.core.schema import GTModel, VersionedFile

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
    x = np.ascontiguousarray(img, np.float32) if mask is None else np.where(mask, img, 0).astype(np.float32)
    if mask is None:  # the weights are all 1: no normalisation by them
        w, m = np.ones((1, 1), np.float32), np.ones((1, 1), np.bool_)
    else:
        m = np.ascontiguousarray(mask, np.bool_)
        w = cv2.GaussianBlur(m.astype(np.float32), k, sigma_px)
    out = np.empty(x.shape, np.float32)
    _normalized(x, cv2.GaussianBlur(x, k, sigma_px), cv2.GaussianBlur(x * x, k, sigma_px), w, m, mask is not None,
                out)
    return out


@numba.njit(cache=True, error_model="numpy")
def _normalized(x, blur_x, blur_xx, w, mask, weighted, out):
    """``local_normalize``'s arithmetic after its blurs, in one pass with numpy's float32 operations in numpy's order:
    mean = blur(x) [/ w], var = blur(x^2) [/ w] - mean^2, (x - mean) / sqrt(max(var, 1e-6) + 1) (+1 grey level^2: flat
    areas stay near 0), 0 outside the mask (or where w <= 0.5) and where not finite (the same values as the numpy
    expression it replaces, which took 2 ms of a 700x460 image in a dozen passes)."""
    H, W = x.shape
    eps, one, half = np.float32(1e-6), np.float32(1.0), np.float32(0.5)
    for v in range(H):
        for u in range(W):
            mean, sq = blur_x[v, u], blur_xx[v, u]
            if weighted:
                mean, sq = mean / w[v, u], sq / w[v, u]
            var = sq - mean * mean
            var = var if (var >= eps) | (var != var) else eps  # np.maximum: NaN stays NaN
            o = (x[v, u] - mean) / np.sqrt(var + one)
            if weighted and not (mask[v, u] and w[v, u] > half):
                o = np.float32(0.0)
            out[v, u] = o if abs(o) < np.inf else np.float32(0.0)  # (NaN compares false)


def interior_mask(mask: np.ndarray, radius_px: int) -> np.ndarray:
    """Mask pixels whose whole ``radius_px`` neighbourhood is in the mask (normalisation and gradients are exact)."""
    k = 2 * radius_px + 1
    return cv2.erode(mask.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)


def render_texture(depth_zed_mm: np.ndarray, rig: Rig, texture: np.ndarray, occlusion_tol_mm: float = 2.0,
                   origin_px: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """The texture image rendered into the ZED-left view through the GT depth: ``(float32 image, valid mask)``.

    Each ZED-left pixel with GT depth is back-projected, moved into the texture camera (``T_mech_from_zed``),
    projected with its lens model and sampled bilinearly. A point the texture camera cannot see (outside its image,
    or hidden behind another GT point by more than ``occlusion_tol_mm``) is left out. ``depth_zed_mm`` may be a
    window of the ZED-left image whose pixel ``[0, 0]`` is the image's pixel ``(u, v) = origin_px``."""
    zed, mech = rig.zed.left, rig.mech
    T = rig.T_mech_from_zed
    d = lens.full_coeffs(mech.dist_coeffs)
    tilted = bool(d[12] != 0.0 or d[13] != 0.0)
    out = np.zeros(depth_zed_mm.shape, np.float32)
    ok = np.zeros(depth_zed_mm.shape, bool)
    _render_kernel(np.asarray(depth_zed_mm, np.float32), float(origin_px[0]), float(origin_px[1]),
                   np.array([zed.fx_px, zed.fy_px, zed.cx_px, zed.cy_px]), np.ascontiguousarray(T[:3, :3]),
                   np.ascontiguousarray(T[:3, 3]), np.array([mech.fx_px, mech.fy_px, mech.cx_px, mech.cy_px]), d,
                   lens.tilt_matrix(d[12], d[13]), tilted, np.ascontiguousarray(to_gray(texture)),
                   rig.separate_depth_camera, float(occlusion_tol_mm), out, ok)
    return out, ok


@numba.njit(cache=True, error_model="numpy")
def _render_kernel(depth, x0, y0, k_zed, R, t, k_tex, dist, M, tilted, tex, zbuffer, tol_mm, out, ok):
    """``render_texture``'s loop over the pixels: texture-camera position and depth of each GT pixel (depth NaN: not
    seen), the z-buffer of those (only with ``zbuffer``: a separate depth camera), then the bilinear samples."""
    H, W = depth.shape
    th, tw = tex.shape
    # the positions as three planes, every pixel computed and the unseen ones marked by a NaN depth at the end: no
    # branch in the loop, so the compiler vectorises it (the same arithmetic, the same positions)
    pu, pv, pz = np.empty((H, W)), np.empty((H, W)), np.empty((H, W))
    for v in range(H):
        ru, rv, rz, drow = pu[v], pv[v], pz[v], depth[v]
        for u in range(W):
            z = np.float64(drow[u])
            X = (u + x0 - k_zed[2]) / k_zed[0] * z
            Y = (v + y0 - k_zed[3]) / k_zed[1] * z
            Zm = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * z + t[2]
            Xm = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * z + t[0]
            Ym = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * z + t[1]
            xd, yd = lens.distort_point(Xm / Zm, Ym / Zm, dist, M, tilted)
            ut = k_tex[0] * xd + k_tex[2]
            vt = k_tex[1] * yd + k_tex[3]
            seen = (abs(z) < np.inf) & (Zm > 0) & (ut >= 0) & (ut <= tw - 1) & (vt >= 0) & (vt <= th - 1)
            ru[u] = ut
            rv[u] = vt
            rz[u] = Zm if seen else np.nan
    zbuf = np.full((th, tw) if zbuffer else (1, 1), np.inf)
    if zbuffer:  # the depth camera saw these points; the texture camera may not: z-buffer them in the texture image
        for v in range(H):
            for u in range(W):
                if math.isfinite(pz[v, u]):
                    ti, tj = int(np.rint(pv[v, u])), int(np.rint(pu[v, u]))
                    zbuf[ti, tj] = min(zbuf[ti, tj], pz[v, u])
    for v in range(H):
        for u in range(W):
            ut, vt, Zm = pu[v, u], pv[v, u], pz[v, u]
            if not math.isfinite(Zm) or (zbuffer and Zm > zbuf[int(np.rint(vt)), int(np.rint(ut))] + tol_mm):
                continue
            # bilinear at the exact position (cv2.remap would round it to 1/32 px)
            i = min(int(ut), tw - 2) if tw > 1 else 0
            j = min(int(vt), th - 2) if th > 1 else 0
            fx, fy = ut - i, vt - j
            i1, j1 = min(i + 1, tw - 1), min(j + 1, th - 1)
            top = (1.0 - fx) * tex[j, i] + fx * tex[j, i1]
            bot = (1.0 - fx) * tex[j1, i] + fx * tex[j1, i1]
            out[v, u] = (1.0 - fy) * top + fy * bot
            ok[v, u] = True


def smooth_depth_mask(disparity_px: np.ndarray, radius_px: int = 3, max_range_px: float = 1.0) -> np.ndarray:
    """Pixels whose GT disparity varies by less than ``max_range_px`` within ``radius_px`` (away from depth edges,
    where a rendering through the GT mixes fore- and background and biases an alignment)."""
    k = np.ones((2 * radius_px + 1,) * 2, np.uint8)
    d = disparity_px.astype(np.float32)
    hi = cv2.dilate(np.where(np.isfinite(d), d, -1e6).astype(np.float32), k)
    lo = cv2.erode(np.where(np.isfinite(d), d, 1e6).astype(np.float32), k)
    return (hi - lo) < max_range_px


@numba.njit(cache=True)
def _cubic_at(imgs, x, y, out):
    """Keys cubic convolution (a = -0.5, interpolating) of each image of the stack ``imgs`` (K, H, W) at exact
    positions into ``out`` (K, N); borders replicated. A point's 4 + 4 weights are computed once, for every image."""
    K, H, W = imgs.shape
    for k in range(x.shape[0]):
        fx = math.floor(x[k])
        fy = math.floor(y[k])
        ix = int(fx)
        iy = int(fy)
        # the Keys kernel at the 4 taps ix - 1 .. ix + 2 (offsets 1 + t, t, 1 - t, 2 - t), as polynomials in t
        t = x[k] - fx
        t2 = t * t
        t3 = t2 * t
        wx0, wx1, wx2, wx3 = (-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1.0, -1.5 * t3 + 2.0 * t2 + 0.5 * t,
                              0.5 * t3 - 0.5 * t2)
        t = y[k] - fy
        t2 = t * t
        t3 = t2 * t
        wy0, wy1, wy2, wy3 = (-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1.0, -1.5 * t3 + 2.0 * t2 + 0.5 * t,
                              0.5 * t3 - 0.5 * t2)
        if 1 <= ix <= W - 3 and 1 <= iy <= H - 3:  # all 16 taps inside
            x0, x1, x2, x3, y0, y1, y2, y3 = ix - 1, ix, ix + 1, ix + 2, iy - 1, iy, iy + 1, iy + 2
        else:
            x0, x1, x2, x3 = (min(max(ix - 1, 0), W - 1), min(max(ix, 0), W - 1), min(max(ix + 1, 0), W - 1),
                              min(max(ix + 2, 0), W - 1))
            y0, y1, y2, y3 = (min(max(iy - 1, 0), H - 1), min(max(iy, 0), H - 1), min(max(iy + 1, 0), H - 1),
                              min(max(iy + 2, 0), H - 1))
        for c in range(K):
            r0 = wx0 * imgs[c, y0, x0] + wx1 * imgs[c, y0, x1] + wx2 * imgs[c, y0, x2] + wx3 * imgs[c, y0, x3]
            r1 = wx0 * imgs[c, y1, x0] + wx1 * imgs[c, y1, x1] + wx2 * imgs[c, y1, x2] + wx3 * imgs[c, y1, x3]
            r2 = wx0 * imgs[c, y2, x0] + wx1 * imgs[c, y2, x1] + wx2 * imgs[c, y2, x2] + wx3 * imgs[c, y2, x3]
            r3 = wx0 * imgs[c, y3, x0] + wx1 * imgs[c, y3, x1] + wx2 * imgs[c, y3, x2] + wx3 * imgs[c, y3, x3]
            out[c, k] = wy0 * r0 + wy1 * r1 + wy2 * r2 + wy3 * r3


def sample_cubic(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Cubic samples of ``img`` (H, W), or of each image of a stack (K, H, W) -> (K, N), at the points ``(x, y)``
    (exact sub-pixel positions: ``cv2.remap`` rounds them to 1/32 px, the size of the shifts measured here)."""
    imgs = np.ascontiguousarray(img, np.float32)
    out = np.empty((1 if imgs.ndim == 2 else imgs.shape[0], len(x)))
    _cubic_at(imgs.reshape((-1,) + imgs.shape[-2:]), np.ascontiguousarray(x, np.float64),
              np.ascontiguousarray(y, np.float64), out)
    return out[0] if imgs.ndim == 2 else out


# the pixels an estimate uses at most: a larger set is subsampled evenly (the estimate's noise stays far below the
# thresholds)
MAX_POINTS = 30000


def even_subset(n: int, max_points: int) -> np.ndarray | slice:
    """Indices of at most ``max_points`` of ``n`` listed items, evenly spread (all of them: ``slice(None)``)."""
    return np.linspace(0, n - 1, max_points).round().astype(np.int64) if n > max_points else slice(None)


def pixels_of(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(v, u, flat index)`` of a 2-D mask's pixels in row-major order (``np.nonzero``'s order; flat indices are 4-5x
    faster to find and to gather with, ``take_at``)."""
    idx = np.flatnonzero(mask)
    v, u = np.divmod(idx, mask.shape[1])
    return v, u, idx


def take_at(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[v, u]`` for the flat indices ``idx`` of ``(v, u)`` in a 2-D array (a gather, not numpy's multi-index
    iterator: 6x faster; an array that is not C-contiguous is copied first)."""
    return np.ascontiguousarray(a).reshape(-1).take(idx)


class ShiftAligner:
    """Translation ``d`` with ``img(u + d) ~ ref(u)`` over any mask of pixels (both images already normalised).

    Inverse-compositional Lucas-Kanade (the Hessian from ``ref``'s gradients) with a free gain and offset, ``img``
    sampled by cubic splines at the mask's points only; a coarse pass on copies blurred by 2 px first, so shifts of a
    few pixels converge. The image pyramids are built once and shared by every mask (whole area, fruit, tiles)."""

    SIGMAS = (2.0, 0.0)
    COARSE_TOL_PX = 0.01

    def __init__(self, ref: np.ndarray, img: np.ndarray):
        self.ref = ref
        self.levels = []
        for sigma in self.SIGMAS:
            r = cv2.GaussianBlur(ref, (0, 0), sigma) if sigma else ref
            i = cv2.GaussianBlur(img, (0, 0), sigma) if sigma else img
            self.levels.append((r, cv2.Sobel(r, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8),
                                cv2.Sobel(r, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8), np.ascontiguousarray(i, np.float32)))

    def align(self, mask: np.ndarray, min_pixels: int = 400, iterations: int = 30, tol_px: float = 1e-4,
              max_points: int = MAX_POINTS) -> ShiftEstimate:
        """``max_points``: a larger mask is subsampled evenly (the estimate's noise is far below the thresholds)."""
        v, u, _ = pixels_of(mask)
        return self.align_at(v, u, min_pixels, iterations, tol_px, max_points)

    def align_at(self, v: np.ndarray, u: np.ndarray, min_pixels: int = 400, iterations: int = 30,
                 tol_px: float = 1e-4, max_points: int = MAX_POINTS) -> ShiftEstimate:
        """``align`` over the pixels ``(v, u)`` of a mask, listed in ``np.nonzero``'s (row-major) order."""
        n = len(v)
        if n < min_pixels:
            return ShiftEstimate(n_pixels=n)
        keep = even_subset(n, max_points)
        v, u = v[keep], u[keep]
        uf, vf = u.astype(np.float64), v.astype(np.float64)
        idx = v * self.ref.shape[1] + u
        d = np.zeros(2)
        for level, (r, gx, gy, coeffs) in enumerate(self.levels):
            # the coarse pass only brings the fine one near its solution: a loose tolerance there
            tol = tol_px if level == len(self.levels) - 1 else self.COARSE_TOL_PX
            rv = take_at(r, idx).astype(np.float64)
            # img(u + d) * (1 + g) + o ~ ref(u): unknowns (step in d, g, o), linearised at the template
            At = np.stack([take_at(gx, idx), take_at(gy, idx), rv, np.ones_like(rv)]).astype(np.float64)
            try:
                inv = np.linalg.inv(At @ At.T)
            except np.linalg.LinAlgError:
                return ShiftEstimate(n_pixels=n)
            for _ in range(iterations):
                step = inv @ (At @ (sample_cubic(coeffs, uf + d[0], vf + d[1]) - rv))
                d -= step[:2]  # inverse composition of a translation
                if np.abs(d).max() > 20:  # diverged: nothing to align
                    return ShiftEstimate(n_pixels=n)
                if np.abs(step[:2]).max() < tol:
                    break
        w = sample_cubic(self.levels[-1][3], uf + d[0], vf + d[1])
        rv = take_at(self.ref, idx).astype(np.float64)
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
    return cv2.magnitude(gx, gy) > thresh


# ---- the checks -----------------------------------------------------------------------------------
class Window(NamedTuple):
    """Where the arrays a check is given lie in the (work-resolution) ZED images: the ZED-left arrays' pixel ``[0, 0]``
    is the image's pixel ``(x0_px, y0_px)``, the ZED-right image's is ``(xr0_px, y0_px)``; the images are
    ``width_px`` x ``height_px``."""

    x0_px: int
    y0_px: int
    xr0_px: int
    width_px: int
    height_px: int


# Margin (work px) of the window around the ground truth's bounding box: covers the local normalisation (Gaussian
# sigma 3 px: 12 px), the aligner's 2 px blur (8 px), Sobel and cubic taps (3 px) and shifts of a few px, so that every
# figure is the one computed on the whole image.
WINDOW_MARGIN_PX = 32


def texture_alignment(depth_zed_mm: np.ndarray, region: np.ndarray, zed_left: np.ndarray, texture: np.ndarray,
                      rig: Rig, params: VerifyParams, left_norm: np.ndarray | None = None, window: Window | None = None,
                      smooth: np.ndarray | None = None
                      ) -> tuple[ShiftEstimate, ShiftEstimate, Callable[[], list], np.ndarray, np.ndarray]:
    """(whole valid area, fruit, a function computing the tiles' shifts, rendered texture normalised, mask used).

    The arrays may be a ``window`` of the ZED-left image (its tiles and their centres are the whole image's).
    ``smooth``: ``smooth_depth_mask`` of the depth's disparity, if the caller has it."""
    h, w = depth_zed_mm.shape
    window = window or Window(0, 0, 0, w, h)
    rend, ok = render_texture(depth_zed_mm, rig, texture, params.texture_occlusion_tol_mm,
                              (window.x0_px, window.y0_px))
    r = int(np.ceil(2 * params.norm_sigma_px))
    ok_support = interior_mask(ok, r)
    n_rend = local_normalize(rend, ok, params.norm_sigma_px)
    n_zed = left_norm if left_norm is not None else \
        local_normalize(to_gray(zed_left).astype(np.float32), None, params.norm_sigma_px)
    if smooth is None:
        smooth = smooth_depth_mask(rig.zed.depth_to_disparity(depth_zed_mm))
    use = ok_support & textured_mask(n_rend) & smooth
    v, u, idx = pixels_of(use)
    reg = take_at(region, idx)
    fruit = (reg == REGION_CENTRE) | (reg == REGION_EDGE)
    aligner = ShiftAligner(n_rend, n_zed)
    e_all = aligner.align_at(v, u, params.min_pixels)
    e_fruit = aligner.align_at(v[fruit], u[fruit], params.min_pixels)

    def tile_shifts() -> list[list[float | None]]:
        out = []
        W, H = window.width_px, window.height_px
        vi, ui = v + window.y0_px, u + window.x0_px  # image pixels
        nx, ny = params.tiles
        for j in range(ny):
            for i in range(nx):
                ya, yb, xa, xb = j * H // ny, (j + 1) * H // ny, i * W // nx, (i + 1) * W // nx
                m = (vi >= ya) & (vi < yb) & (ui >= xa) & (ui < xb)
                e = aligner.align_at(v[m], u[m], params.min_pixels)
                out.append([(xa + xb - 1) / 2, (ya + yb - 1) / 2, e.dx_px, e.dy_px])
        return out

    return e_all, e_fruit, tile_shifts, n_rend, use


def stereo_consistency(zed_left: np.ndarray, zed_right: np.ndarray, disparity_px: np.ndarray, nonoccluded: np.ndarray,
                       region: np.ndarray, params: VerifyParams, left_norm: np.ndarray | None = None,
                       window: Window | None = None, smooth: np.ndarray | None = None) -> dict[str, StereoEstimate]:
    """Disparity bias, vertical offset and the share of clearly worse matches, per region (all, fruit, background).

    The arrays may be a ``window`` of the images (``zed_right`` then covers the same rows and the columns the ground
    truth's matches fall in). ``smooth``: ``smooth_depth_mask(disparity_px)``, if the caller has it."""
    h, w = disparity_px.shape
    window = window or Window(0, 0, 0, w, h)
    nl = left_norm if left_norm is not None else \
        local_normalize(to_gray(zed_left).astype(np.float32), None, params.norm_sigma_px)
    nr = local_normalize(to_gray(zed_right).astype(np.float32), None, params.norm_sigma_px)
    ok = nonoccluded & np.isfinite(disparity_px)
    d = np.where(ok, disparity_px, 0).astype(np.float32)
    x_match = np.arange(window.x0_px, window.x0_px + w, dtype=np.float32) - d  # image column of the GT match
    v_img = np.arange(window.y0_px, window.y0_px + h, dtype=np.float32)[:, None]
    # border pixels of the GT (the disparity may jump there) and pixels whose match falls off the image stay out
    base = interior_mask(ok, 2) & (x_match > 3) & (x_match < window.width_px - 4) & (v_img > 3) & \
        (v_img < window.height_px - 4)
    use = base & textured_mask(nl) & (smooth_depth_mask(disparity_px) if smooth is None else smooth)
    v, u, idx = pixels_of(use)
    reg = take_at(region, idx)
    regions = {"all": None, "fruit": (reg == REGION_CENTRE) | (reg == REGION_EDGE), "background": reg == REGION_BG}
    # the right image, its gradients: one stack, sampled together
    right = np.stack([nr, cv2.Sobel(nr, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8),
                      cv2.Sobel(nr, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)])
    # share of clearly worse matches: 5x5 SAD of the normalised images at GT and at GT +- 0.5, +- 1 px, over the used
    # pixels' bounding box + 2 px (the SAD window)
    worse = np.zeros(len(v), bool)  # at the used pixels (v, u)
    if len(v):
        sub = (slice(max(int(v.min()) - 2, 0), int(v.max()) + 3), slice(max(int(u.min()) - 2, 0), int(u.max()) + 3))
        map_x = x_match[sub] - np.float32(window.xr0_px)  # exact: integers subtracted
        map_y = np.broadcast_to(np.arange(h, dtype=np.float32)[sub[0], None], map_x.shape)
        nl_sub = nl[sub]
        idx_sub = (v - sub[0].start) * map_x.shape[1] + (u - sub[1].start)

        def cost(o):  # at (v, u): the 5x5 SAD of the left image and the right one warped to x_match - o
            warped = cv2.remap(nr, map_x - np.float32(o), map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
            return take_at(cv2.boxFilter(cv2.absdiff(nl_sub, warped), -1, (5, 5), normalize=True), idx_sub)

        best_other = np.minimum.reduce([cost(o) for o in (-1.0, -0.5, 0.5, 1.0)])
        worse = cost(0.0) > params.bad_match_ratio * best_other
    # the matches in the right array's pixels
    xr_all = (u + (window.x0_px - window.xr0_px)) - take_at(d, idx).astype(np.float64)
    out = {}
    for name, sel in regions.items():
        vs, us, xr, wr = (v, u, xr_all, worse) if sel is None else (v[sel], u[sel], xr_all[sel], worse[sel])
        n = len(vs)
        if n < params.min_pixels:
            out[name] = StereoEstimate(n_pixels=n)
            continue
        keep = even_subset(n, MAX_POINTS)
        vk, uk, xr = vs[keep], us[keep], xr[keep]
        b, dy = 0.0, 0.0
        lv = take_at(nl, vk * w + uk).astype(np.float64)
        yr = vk.astype(np.float64)
        for _ in range(20):
            w_, wx, wy = sample_cubic(right, xr - b, yr + dy)
            # right(u - d - b, v + dy): d/db = -gx, d/d(dy) = +gy
            A = np.stack([-wx, wy, lv, np.ones_like(lv)], axis=1)
            step = np.linalg.solve(A.T @ A, -(A.T @ (w_ - lv)))
            b, dy = b + step[0], dy + step[1]
            if max(abs(step[0]), abs(step[1])) < 1e-4 or max(abs(b), abs(dy)) > 10:
                break
        if max(abs(b), abs(dy)) > 10:
            out[name] = StereoEstimate(n_pixels=n)
            continue
        # vertical disparity v_left - v_right, as gtforge.core.rectification reports it for board corners
        out[name] = StereoEstimate(disparity_bias_px=float(b), vertical_px=float(-dy),
                                   bad_match_pct=float(100.0 * wr.mean()), n_pixels=n)
    return out


def _scaled_shift(e: ShiftEstimate, f: int) -> ShiftEstimate:
    return e if e.dx_px is None else e.model_copy(update={"dx_px": e.dx_px * f, "dy_px": e.dy_px * f})


def _area(a: np.ndarray, f: int) -> np.ndarray:
    """The mean of each f x f block (NaN if any pixel of it is NaN)."""
    h, w = a.shape[0] // f, a.shape[1] // f
    return cv2.resize(a[:h * f, :w * f], (w, h), interpolation=cv2.INTER_AREA) if f > 1 else a


def _work_arrays(f: int, depth, disp, noc, region, left, right, rig: Rig):
    """The arrays the checks run on: everything a factor ``f`` smaller, in the window around the ground truth
    (``Window``, margin ``WINDOW_MARGIN_PX``). Images are reduced by area averaging, depth by the mean of fully valid
    f x f blocks (the block centre's depth on a locally flat surface), labels by the block's top-left pixel; the ZED
    camera is scaled the same way (pixel centres stay at integer coordinates). Returns ``(depth, disparity,
    nonoccluded, region, left, right, rig, window)``."""
    H, W = depth.shape
    h, w = H // f, W // f
    rig_w = rig
    if f > 1:
        zed = rig.zed.model_copy(update={"left": rig.zed.left.scaled(1.0 / f).model_copy(update={"width_px": w,
                                                                                                 "height_px": h}),
                                         "doffs_px": rig.zed.doffs_px / f})
        rig_w = rig.model_copy(update={"zed": zed})
    depth = np.asarray(depth, np.float32)
    # only the block rows of the GT's rows (no valid block above or below them), each whole: OpenCV's vectorised
    # averages depend on where a row's columns start, so a column crop could change a value's last bit
    gy0, gy1 = finite_box(depth)[:2]
    depth_w = np.full((h, w), np.nan, np.float32)
    by0, by1 = gy0 // f, min(-(-gy1 // f), h)
    if by1 > by0:
        depth_w[by0:by1] = _area(depth[by0 * f:by1 * f], f)
    valid = np.isfinite(depth_w)
    if f == 1:
        valid |= np.isfinite(disp)
    box = mask_bounding_box(valid)
    m = WINDOW_MARGIN_PX
    if box:
        y0, y1, x0, x1 = max(box[0] - m, 0), min(box[1] + m, h), max(box[2] - m, 0), min(box[3] + m, w)
    else:
        y0, y1, x0, x1 = 0, h, 0, w
    depth_c = depth_w[y0:y1, x0:x1]
    disp_c = rig_w.zed.depth_to_disparity(depth_c) if f > 1 else disp[y0:y1, x0:x1]
    finite = disp_c[np.isfinite(disp_c)]
    if finite.size:  # the right image: the columns the matches fall in
        xr0, xr1 = max(x0 - math.ceil(float(finite.max())), 0), min(x1 - math.floor(float(finite.min())), w)
        xr0, xr1 = min(xr0, w - 1), max(xr1, xr0 + 1)
    else:
        xr0, xr1 = x0, x1

    def cut(a, xa, xb):  # rows y0:y1, columns xa:xb of the work-resolution image, from a dataset-resolution array
        return a[y0 * f:y1 * f, xa * f:xb * f]

    noc_c = _area(cut(noc, x0, x1).astype(np.float32), f) == 1.0
    region_c = np.ascontiguousarray(cut(region, x0, x1)[::f, ::f])
    left_c = _area(cut(left, x0, x1), f)
    right_c = None if right is None else _area(cut(right, xr0, xr1), f)
    return depth_c, disp_c, noc_c, region_c, left_c, right_c, rig_w, Window(int(x0), int(y0), int(xr0), w, h)


def _work_factor(width_px: int, params: VerifyParams) -> int:
    """The integer factor the checks reduce the ZED images by (``VerifyParams.work_width_px``)."""
    return max(1, int(np.ceil(width_px / params.work_width_px)))


def zed_rows_used(depth_zed_mm: np.ndarray, params: VerifyParams | None = None) -> int:
    """How many of the ZED images' rows, from the top, ``verify_scene`` reads for this ground truth: the end of the
    window around it (``_work_arrays``: the GT's last row, reduced by the work factor, plus ``WINDOW_MARGIN_PX``), at
    the dataset's resolution. A build decodes the ZED images only that far (``Session.decoded_images``)."""
    params = params or VerifyParams()
    H, W = depth_zed_mm.shape
    f = _work_factor(W, params)
    end = _rows_with_values(depth_zed_mm)  # every GT pixel lies in rows [0, end)
    # a work pixel is valid only where its whole f x f block is: the window's rows end at most here
    return (min(-(-end // f) + WINDOW_MARGIN_PX, H // f) if end else H // f) * f


@numba.njit(cache=True)
def _rows_with_values(a):
    """1 + the last row of ``a`` holding a finite value (0: none), scanning from the bottom (only the rows below the
    ground truth are read)."""
    H, W = a.shape
    for v in range(H - 1, -1, -1):
        for u in range(W):
            if abs(a[v, u]) < np.inf:
                return v + 1
    return 0


def verify_scene(depth_zed_mm: np.ndarray, disparity_px: np.ndarray, nonoccluded: np.ndarray, region: np.ndarray,
                 zed_left: np.ndarray, zed_right: np.ndarray | None, texture: np.ndarray | None, rig: Rig,
                 params: VerifyParams | None = None) -> tuple[SceneVerification, np.ndarray | None]:
    """Both checks for one scene (ZED-left arrays at the dataset's resolution, uncropped; see module docstring).
    ``zed_left`` and ``zed_right`` may hold only their first ``zed_rows_used(depth_zed_mm, params)`` rows.
    Returns the verification and the rendered, normalised texture (at the work resolution, for overlays; None when not
    measured). The checks run in the window around the ground truth (``Window``): the same figures as on the whole
    image, at a fraction of the cost."""
    params = params or VerifyParams()
    reasons: list[str] = []
    if texture is None:
        return SceneVerification(status="not verifiable", reasons=["no texture image"]), None
    if float(cv2.meanStdDev(to_gray(texture))[1][0, 0]) < 1.0:
        return SceneVerification(status="not verifiable", reasons=["the texture image is blank (no contrast)"]), None
    f = _work_factor(depth_zed_mm.shape[1], params)
    for name, img in (("zed_left", zed_left), ("zed_right", zed_right)):
        if img is not None and img.shape[0] < depth_zed_mm.shape[0] \
                and img.shape[0] < (need := zed_rows_used(depth_zed_mm, params)):
            raise ValueError(f"{name}.shape={img.shape} but the checks read its first {need} rows")
    depth_c, disp_c, noc_c, region_c, left_c, right_c, rig_w, win = _work_arrays(
        f, depth_zed_mm, disparity_px, nonoccluded, region, zed_left, zed_right, rig)
    left_norm = local_normalize(to_gray(left_c).astype(np.float32), None, params.norm_sigma_px)  # shared by both
    # away from depth edges, for both checks (disp_c is the window's GT disparity, as depth_to_disparity gives it)
    smooth = smooth_depth_mask(disp_c)
    e_all, e_fruit, tile_shifts, n_rend_c, _ = texture_alignment(depth_c, region_c, left_c, texture, rig_w, params,
                                                                 left_norm, win, smooth)
    stereo = stereo_consistency(left_c, right_c, disp_c, noc_c, region_c, params, left_norm, win, smooth) \
        if right_c is not None else {}
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
    n_rend = np.zeros((win.height_px, win.width_px), np.float32)
    n_rend[win.y0_px:win.y0_px + n_rend_c.shape[0], win.x0_px:win.x0_px + n_rend_c.shape[1]] = n_rend_c
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
    from gtforge.infra.scheduling import prestart_pool, run_tasks

    prestart_pool(verify_one_scene.__module__, workers, scheduler)  # its imports overlap the checks of the dataset
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

    cal = CalibrationFile.read(calib)
    check_rig_matches_session(cal.rig, cal.open_session(sess), calib,
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
