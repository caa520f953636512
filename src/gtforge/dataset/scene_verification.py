"""One scene's verification: does its ground truth match the images it labels? (build-dataset runs it on each scene
it builds, ``gtforge verify`` on an existing dataset, refine and calibrate-scale on the scenes they fit.)

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
  ``gtforge.core.zed.rectification`` reports it for board corners), per region; it starts from ``b = 0`` unless a whole
  offset within +-24 px correlates clearly better (``_coarse_disparity_offset``: its reach is a pixel or two, and
  labels 5-8 px off converged to a tiny bias). The right image is sampled by cubic
  B-spline with its own derivatives (``sample_spline``): phase-unbiased, where Keys' cubic convolution read a false
  bias on surfaces of one disparity phase (a fronto-parallel table, issue 41). A textured pixel's match is "clearly
  worse" when the 5x5 sum of absolute normalised differences at its GT disparity exceeds the best within +-1 px (steps
  of 0.5 px) by more than ``bad_match_ratio``; their share is reported.

Every figure comes with its noise floor (``*_noise_px``, ``correlation_noise``: 1 sigma, what exact labels give on
this scene; ``gtforge.core.alignment.photometric.block_noise``). A scene is **flagged** when a figure passes its
threshold (``VerifyParams``, documented defaults in px at the dataset's resolution). Nothing here changes the ground
truth.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, NamedTuple

import cv2
import numba
import numpy as np

from gtforge.core.camera import Rig
from gtforge.core.geometry import finite_box, finite_rows, mask_bounding_box, transform_points
from gtforge.core.alignment.photometric import (
    MAX_POINTS,
    ShiftAligner,
    ShiftEstimate,
    block_noise,
    even_subset,
    interior_mask,
    local_normalize,
    pixels_of,
    sample_spline,
    smooth_depth_mask,
    sobel_gradients,
    spline_prefilter,
    take_at,
    textured_mask,
    to_gray,
)
from gtforge.core.ground_truth.regions import REGION_BG, REGION_CENTRE, REGION_EDGE
from gtforge.core.ground_truth.render import render_texture
from gtforge.io.formats import write_image
from gtforge.records.verification import SceneVerification, StereoEstimate, VerifyParams


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
# Gaussian blur (work px) of both normalised images before the stereo check's Gauss-Newton: takes out the texture near
# the Nyquist frequency, where every cubic interpolator's error depends on the sub-pixel phase (and where a reduction
# by the work factor aliases); with the B-spline sampling it leaves at most 0.002 px of phase-dependent bias on the
# textured-plane sweep (docs/design/accuracy.md, issue 41)
STEREO_BLUR_PX = 1.0
# The stereo check's search for a ground truth off by more than its Gauss-Newton reaches (``_coarse_disparity_offset``):
# the offsets tried (work px; within the window's margin, WINDOW_MARGIN_PX, less the spline's taps), the pixels it
# correlates over, and by how much an offset must correlate better than the ground truth's own matches to be taken
STEREO_SEARCH_PX = 24
STEREO_SEARCH_POINTS = 2000
STEREO_SEARCH_MARGIN = 0.1
# below this correlation at every offset searched the right image matches the labels nowhere (random texture gives
# about 0; exact labels 0.99 on the generator's scenes, 0.96 on Middlebury 2014 Motorcycle): no bias is fitted, and the
# scene is flagged for it
STEREO_MIN_MATCH_CORRELATION = 0.2


def texture_alignment(depth_zed_mm: np.ndarray, region: np.ndarray, zed_left: np.ndarray, texture: np.ndarray,
                      rig: Rig, params: VerifyParams, left_norm: np.ndarray | None = None, window: Window | None = None,
                      smooth: np.ndarray | None = None, moved: tuple[np.ndarray, dict] | None = None
                      ) -> tuple[ShiftEstimate, ShiftEstimate, Callable[[], list], np.ndarray, np.ndarray,
                                 list[ShiftEstimate]]:
    """(whole valid area, fruit, a function computing the tiles' shifts, rendered texture normalised, mask used, each
    fruit's own when there are several: connected components of the fruit regions in raster order, else empty).

    The arrays may be a ``window`` of the ZED-left image (its tiles and their centres are the whole image's).
    ``smooth``: ``smooth_depth_mask`` of the depth's disparity, if the caller has it. ``moved``: a ground truth rebuilt
    with fruit moved between the exposures (``gtforge.dataset.motion_compensation``): ``(owner, motions)``, which
    fruit each pixel shows (0 none) and each one's ``T_zed_moved_from_zed``; the texture camera saw those pixels'
    points where they were before the motion."""
    h, w = depth_zed_mm.shape
    window = window or Window(0, 0, 0, w, h)
    rend, ok = render_texture(depth_zed_mm, rig, texture, params.texture_occlusion_tol_mm,
                              (window.x0_px, window.y0_px))
    if moved is not None:
        owner, motions = moved
        for k, T_zed_moved_from_zed in motions.items():
            sel = owner == k
            if sel.any():  # a fruit's point as the texture camera saw it: T_mech_from_zed @ T_zed_moved_from_zed^-1
                r_k, ok_k = render_texture(np.where(sel, depth_zed_mm, np.nan),
                                           rig.with_extrinsic(T_zed_moved_from_zed @ rig.T_zed_from_mech), texture,
                                           params.texture_occlusion_tol_mm, (window.x0_px, window.y0_px))
                rend[sel], ok[sel] = r_k[sel], ok_k[sel]
    r = int(np.ceil(2 * params.norm_sigma_px))
    ok_support = interior_mask(ok, r)
    n_rend = local_normalize(rend, ok, params.norm_sigma_px)
    n_zed = left_norm if left_norm is not None else \
        local_normalize(to_gray(zed_left).astype(np.float32), None, params.norm_sigma_px)
    if smooth is None:
        smooth = smooth_depth_mask(rig.zed.depth_to_disparity(depth_zed_mm))
    grads = sobel_gradients(n_rend)  # the mask's and the aligner's (its fine level is n_rend itself)
    use = ok_support & textured_mask(n_rend, gradients=grads) & smooth
    v, u, idx = pixels_of(use)
    reg = take_at(region, idx)
    fruit = (reg == REGION_CENTRE) | (reg == REGION_EDGE)
    aligner = ShiftAligner(n_rend, n_zed, grads)
    e_all = aligner.align_at(v, u, params.min_pixels)
    e_fruit = aligner.align_at(v[fruit], u[fruit], params.min_pixels)
    # several fruit: each one's own shift too (fruit moved in different directions average out over all of them)
    e_each: list[ShiftEstimate] = []
    fruit_img = (region == REGION_CENTRE) | (region == REGION_EDGE)
    n_cc, labels = cv2.connectedComponents(fruit_img.view(np.uint8), connectivity=8)
    if n_cc > 2:
        lab = take_at(labels, idx)
        e_each = [aligner.align_at(v[lab == k], u[lab == k], params.min_pixels) for k in range(1, n_cc)]

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

    return e_all, e_fruit, tile_shifts, n_rend, use, e_each


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
    # the GT's pixels, their disparity (0 elsewhere), the image column of each one's match, and whether pixel and
    # match lie inside the image's borders
    ok, d, x_match, inside = (np.empty((h, w), t) for t in (np.bool_, np.float32, np.float32, np.bool_))
    _stereo_pixels(np.ascontiguousarray(nonoccluded, np.bool_), np.ascontiguousarray(disparity_px), window.x0_px,
                   window.y0_px, window.width_px, window.height_px, ok, d, x_match, inside)
    # border pixels of the GT (the disparity may jump there) and pixels whose match falls off the image stay out
    use = interior_mask(ok, 2) & inside & textured_mask(nl) & \
        (smooth_depth_mask(disparity_px) if smooth is None else smooth)
    v, u, idx = pixels_of(use)
    reg = take_at(region, idx)
    regions = {"all": None, "fruit": (reg == REGION_CENTRE) | (reg == REGION_EDGE), "background": reg == REGION_BG}
    # the right image as a cubic B-spline (sampled with its own derivatives: phase-unbiased, sample_spline; Keys'
    # cubic convolution and Sobel gradients gave up to +-0.03 px of false bias depending on the disparity's phase)
    right = spline_prefilter(cv2.GaussianBlur(nr, (0, 0), STEREO_BLUR_PX) if STEREO_BLUR_PX else nr)
    nl_gn = cv2.GaussianBlur(nl, (0, 0), STEREO_BLUR_PX) if STEREO_BLUR_PX else nl
    # share of clearly worse matches: 5x5 SAD of the normalised images at GT and at GT +- 0.5, +- 1 px, over the used
    # pixels' bounding box + 2 px (the SAD window)
    worse = np.zeros(len(v), bool)  # at the used pixels (v, u)
    if len(v):
        # (v is sorted: pixels_of lists the rows in order)
        sub = (slice(max(int(v[0]) - 2, 0), int(v[-1]) + 3), slice(max(int(u.min()) - 2, 0), int(u.max()) + 3))
        map_x = x_match[sub] - np.float32(window.xr0_px)  # exact: integers subtracted
        # contiguous once (a broadcast view is copied by every remap call)
        map_y = np.ascontiguousarray(np.broadcast_to(np.arange(h, dtype=np.float32)[sub[0], None], map_x.shape))
        nl_sub = nl[sub]
        idx_sub = np.empty(len(v), np.int64)
        _offset_flat(v, u, sub[0].start, sub[1].start, map_x.shape[1], idx_sub)

        def cost(o):  # at (v, u): the 5x5 SAD of the left image and the right one warped to x_match - o
            warped = cv2.remap(nr, map_x - np.float32(o), map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
            return take_at(cv2.boxFilter(cv2.absdiff(nl_sub, warped), -1, (5, 5), normalize=True), idx_sub)

        best_other = cost(-1.0)
        for o in (-0.5, 0.5, 1.0):  # (a minimum is exact: the order does not matter)
            np.minimum(best_other, cost(o), out=best_other)
        worse = cost(0.0) > params.bad_match_ratio * best_other
    # where the Gauss-Newton starts: the ground truth's own matches, or, where those are off by more than its reach
    # (a pixel or two), the whole offset that matches best
    b0, matched = _coarse_disparity_offset(right, nl_gn, v, u, take_at(d, idx), window, w) \
        if len(v) >= params.min_pixels else (0.0, 1.0)
    out = {}
    for name, sel in regions.items():
        at = None if sel is None else np.flatnonzero(sel)  # the region's used pixels
        wr = worse if sel is None else worse[sel]
        n = len(wr)
        if n < params.min_pixels or matched < STEREO_MIN_MATCH_CORRELATION:  # (the latter: no bias to fit)
            out[name] = StereoEstimate(n_pixels=n)
            continue
        keep = even_subset(n, MAX_POINTS)
        at = keep if at is None else at[keep]
        vk, uk = v[at], u[at]
        # the matches in the right array's pixels
        xr = (uk + (window.x0_px - window.xr0_px)) - take_at(d, idx[at]).astype(np.float64)
        b, dy = b0, 0.0
        lv = take_at(nl_gn, vk * w + uk).astype(np.float64)
        yr = vk.astype(np.float64)
        A = np.empty((len(lv), 4))  # the linearised model's columns: d/db, d/d(dy), gain, offset
        A[:, 2], A[:, 3] = lv, 1.0
        for _ in range(20):
            w_, wx, wy = sample_spline(right, xr - b, yr + dy, derivs=True)
            # right(u - d - b, v + dy): d/db = -gx, d/d(dy) = +gy
            np.negative(wx, out=A[:, 0])
            A[:, 1] = wy
            step = np.linalg.solve(A.T @ A, -(A.T @ (w_ - lv)))
            b, dy = b + step[0], dy + step[1]
            if max(abs(step[0]), abs(step[1])) < 1e-4 or max(abs(b - b0), abs(dy)) > 10:
                break
        if max(abs(b - b0), abs(dy)) > 10:
            out[name] = StereoEstimate(n_pixels=n)
            continue
        # the noise floor: the last linearisation solved per band of pixels (block_noise; A, w_ are at the solution
        # within 1e-4 px)
        noise = block_noise(A, w_ - lv, 2)
        # vertical disparity v_left - v_right, as gtforge.core.zed.rectification reports it for board corners
        out[name] = StereoEstimate(disparity_bias_px=float(b), vertical_px=float(-dy),
                                   bad_match_pct=float(100.0 * wr.mean()), n_pixels=n,
                                   disparity_bias_noise_px=None if noise is None else float(noise[0]),
                                   vertical_noise_px=None if noise is None else float(noise[1]))
    return out


def _coarse_disparity_offset(right: np.ndarray, left: np.ndarray, v: np.ndarray, u: np.ndarray, d: np.ndarray,
                             window: Window, w: int) -> tuple[float, float]:
    """The whole disparity offset (work px, within +-``STEREO_SEARCH_PX``) at which the right image matches the left
    best over an even subset of the used pixels ``(v, u)`` (their GT disparities ``d``): their Pearson correlation, the
    right image sampled from its B-spline ``right`` at each offset, the left one from ``left``. The ground truth's own
    matches (0) unless an offset of 2 px or more correlates better by ``STEREO_SEARCH_MARGIN``: the Gauss-Newton
    reaches a pixel or so, and from 0 a label 5-8 px off converged to a local minimum and a tight, tiny bias.
    Returns ``(offset, the best correlation found)``."""
    keep = even_subset(len(v), STEREO_SEARCH_POINTS)
    vk, uk = v[keep], u[keep]
    lv = take_at(left, vk * w + uk).astype(np.float64)
    lv -= lv.mean()
    norm = float(np.linalg.norm(lv))
    if norm == 0.0:
        return 0.0, 0.0
    xr = (uk + (window.x0_px - window.xr0_px)) - d[keep].astype(np.float64)
    offsets = np.arange(-STEREO_SEARCH_PX, STEREO_SEARCH_PX + 1, dtype=np.float64)
    r = sample_spline(right, (xr[None, :] - offsets[:, None]).ravel(),
                      np.tile(vk.astype(np.float64), len(offsets))).reshape(len(offsets), -1)
    r -= r.mean(axis=1, keepdims=True)
    corr = (r @ lv) / np.maximum(np.linalg.norm(r, axis=1) * norm, 1e-300)
    k = int(np.argmax(corr))
    if abs(offsets[k]) >= 2 and corr[k] > corr[STEREO_SEARCH_PX] + STEREO_SEARCH_MARGIN:
        return float(offsets[k]), float(corr[k])
    return 0.0, float(corr[k])


@numba.njit(cache=True)
def _offset_flat(v, u, v0, u0, width, out):
    """``out = (v - v0) * width + (u - u0)``: the flat indices of the pixels ``(v, u)`` in an array of ``width``
    columns whose pixel ``[0, 0]`` is ``(v0, u0)``."""
    for k in range(len(v)):
        out[k] = (v[k] - v0) * width + (u[k] - u0)


@numba.njit(cache=True)
def _stereo_pixels(noc, disp, x0, y0, width, height, ok, d, x_match, inside):
    """``stereo_consistency``'s per-pixel inputs in one pass: ``ok`` non-occluded with a finite disparity, ``d`` the
    disparity there (float32, 0 elsewhere), ``x_match = float32(x0 + u) - d`` the image column of the GT match, and
    ``inside``: ``3 < x_match < width - 4`` and ``3 < y0 + v < height - 4`` (the float32 comparisons numpy makes)."""
    H, W = d.shape
    lo, hx, hy = np.float32(3.0), np.float32(width - 4), np.float32(height - 4)
    for v in range(H):
        vi = np.float32(y0 + v)
        row_in = (vi > lo) & (vi < hy)
        for u in range(W):
            o = noc[v, u] & (abs(disp[v, u]) < np.inf)
            dd = np.float32(disp[v, u]) if o else np.float32(0.0)
            xm = np.float32(x0 + u) - dd
            ok[v, u] = o
            d[v, u] = dd
            x_match[v, u] = xm
            inside[v, u] = row_in & (xm > lo) & (xm < hx)


def _decimals(limit: float, least: int) -> int:
    """Decimals for a figure shown against ``limit``: at least ``least``, and one more than the limit's first digit
    needs, at most 6 (a 0.002 px limit gets 4: "0.0031 px > 0.002 px", not "0.00 px > 0.002 px")."""
    return min(6, max(least, 1 - math.floor(math.log10(limit)))) if limit > 0 else least


def _pm(noise_px: float | None) -> str:
    """`` ± noise`` for a figure's reason (its noise floor), empty when not measured."""
    return "" if noise_px is None else f" ± {noise_px:.3f}"


def _scaled_shift(e: ShiftEstimate, f: int) -> ShiftEstimate:
    return e if e.dx_px is None else e.model_copy(update={
        k: None if getattr(e, k) is None else getattr(e, k) * f
        for k in ("dx_px", "dy_px", "dx_noise_px", "dy_noise_px")})


def _area(a: np.ndarray, f: int) -> np.ndarray:
    """The mean of each f x f block (NaN if any pixel of it is NaN)."""
    h, w = a.shape[0] // f, a.shape[1] // f
    return cv2.resize(a[:h * f, :w * f], (w, h), interpolation=cv2.INTER_AREA) if f > 1 else a


def _work_arrays(f: int, depth, disp, noc, region, left, right, rig: Rig, rows: tuple[int, int] | None = None):
    """The arrays the checks run on: everything a factor ``f`` smaller, in the window around the ground truth
    (``Window``, margin ``WINDOW_MARGIN_PX``). Images are reduced by area averaging, depth by the mean of fully valid
    f x f blocks (the block centre's depth on a locally flat surface), labels by the block's top-left pixel; the ZED
    camera is scaled the same way (pixel centres stay at integer coordinates). ``rows``: ``finite_rows`` of the
    float32 depth, if the caller has it. Returns ``(depth, disparity, nonoccluded, region, left, right, rig,
    window)``."""
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
    gy0, gy1 = rows if rows is not None else finite_rows(depth)
    by0, by1 = gy0 // f, min(-(-gy1 // f), h)
    by1 = max(by1, by0)
    # the work image's rows by0:by1 (NaN above and below them)
    depth_rows = _area(depth[by0 * f:by1 * f], f) if by1 > by0 else np.empty((0, w), np.float32)
    if f == 1:
        valid = np.zeros((h, w), bool)
        valid[by0:by1] = np.isfinite(depth_rows)
        box = mask_bounding_box(valid | np.isfinite(disp))
    else:
        box = finite_box(depth_rows) if by1 > by0 else (0, 0, 0, 0)
        box = (box[0] + by0, box[1] + by0, box[2], box[3]) if box[1] else None
    m = WINDOW_MARGIN_PX
    if box:
        y0, y1, x0, x1 = max(box[0] - m, 0), min(box[1] + m, h), max(box[2] - m, 0), min(box[3] + m, w)
    else:
        y0, y1, x0, x1 = 0, h, 0, w
    depth_c = np.full((y1 - y0, x1 - x0), np.nan, np.float32)
    ra, rb = max(by0, y0), min(by1, y1)
    if rb > ra:
        depth_c[ra - y0:rb - y0] = depth_rows[ra - by0:rb - by0, x0:x1]
    if f > 1:  # depth_to_disparity's arithmetic, and the range of its finite values, in one pass
        disp_c = np.empty(depth_c.shape, np.float32)
        n_finite, d_min, d_max = _disparity_and_range(depth_c, rig_w.zed.f_px * rig_w.zed.baseline_mm,
                                                      rig_w.zed.doffs_px, disp_c)
    else:
        disp_c = disp[y0:y1, x0:x1]
        finite = disp_c[np.isfinite(disp_c)]
        n_finite = finite.size
        d_min, d_max = (finite.min(), finite.max()) if n_finite else (0.0, 0.0)
    if n_finite:  # the right image: the columns the matches fall in
        xr0, xr1 = max(x0 - math.ceil(float(d_max)), 0), min(x1 - math.floor(float(d_min)), w)
        xr0, xr1 = min(xr0, w - 1), max(xr1, xr0 + 1)
    else:
        xr0, xr1 = x0, x1

    def cut(a, xa, xb):  # rows y0:y1, columns xa:xb of the work-resolution image, from a dataset-resolution array
        return a[y0 * f:y1 * f, xa * f:xb * f]

    if f == 2 and noc.dtype == np.bool_:  # a block's mean is 1 exactly where its 4 pixels are (0.25 x a sum of 0/1)
        noc_c = np.empty((y1 - y0, x1 - x0), np.bool_)
        _all_of_2x2(np.ascontiguousarray(noc), y0 * f, x0 * f, noc_c)
    else:
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
    return _rows_used(finite_rows(depth_zed_mm)[1], H, f)


def _rows_used(end: int, H: int, f: int) -> int:
    """``zed_rows_used`` for a ground truth whose values lie in rows [0, end) of H, work factor f."""
    # a work pixel is valid only where its whole f x f block is: the window's rows end at most here
    return (min(-(-end // f) + WINDOW_MARGIN_PX, H // f) if end else H // f) * f


@numba.njit(cache=True)
def _all_of_2x2(a, ya, xa, out):
    """``out[i, j]``: all four pixels of ``a``'s 2x2 block at (ya + 2i, xa + 2j) are True."""
    h, w = out.shape
    for i in range(h):
        r0, r1 = a[ya + 2 * i], a[ya + 2 * i + 1]
        for j in range(w):
            out[i, j] = r0[xa + 2 * j] & r0[xa + 2 * j + 1] & r1[xa + 2 * j] & r1[xa + 2 * j + 1]


@numba.njit(cache=True, error_model="numpy")
def _disparity_and_range(depth, f_b, doffs, out):
    """``out`` = ``StereoCamera.depth_to_disparity(depth)`` (float64 ``f_b / z - doffs``, NaN where not ``z > 0``,
    rounded to float32), and ``(count, min, max)`` of its finite values (0.0, 0.0 where none)."""
    H, W = depth.shape
    n, lo, hi = 0, np.float32(np.inf), np.float32(-np.inf)
    for v in range(H):
        for u in range(W):
            z = np.float64(depth[v, u])
            d = np.float32(f_b / z - doffs) if z > 0 else np.float32(np.nan)
            out[v, u] = d
            if abs(d) < np.inf:
                n += 1
                lo = min(lo, d)
                hi = max(hi, d)
    return (n, lo, hi) if n else (0, np.float32(0.0), np.float32(0.0))


def verify_scene(depth_zed_mm: np.ndarray, disparity_px: np.ndarray, nonoccluded: np.ndarray, region: np.ndarray,
                 zed_left: np.ndarray, zed_right: np.ndarray | None, texture: np.ndarray | None, rig: Rig,
                 params: VerifyParams | None = None, moved: tuple[np.ndarray, dict] | None = None
                 ) -> tuple[SceneVerification, np.ndarray | None]:
    """Both checks for one scene (ZED-left arrays at the dataset's resolution, uncropped; see module docstring).
    ``zed_left`` and ``zed_right`` may hold only their first ``zed_rows_used(depth_zed_mm, params)`` rows.
    Returns the verification and the rendered, normalised texture (at the work resolution, for overlays; None when not
    measured). The checks run in the window around the ground truth (``Window``): the same figures as on the whole
    image, at a fraction of the cost. ``moved``: ``(owner, motions)`` of a ground truth rebuilt with fruit moved
    (``texture_alignment``; ``owner`` at the dataset's resolution)."""
    params = params or VerifyParams()
    reasons: list[str] = []
    if texture is None:
        return SceneVerification(status="not verifiable", reasons=["no texture image"]), None
    if float(cv2.meanStdDev(to_gray(texture))[1][0, 0]) < 1.0:
        return SceneVerification(status="not verifiable", reasons=["the texture image is blank (no contrast)"]), None
    f = _work_factor(depth_zed_mm.shape[1], params)
    depth32 = np.asarray(depth_zed_mm, np.float32)
    rows = finite_rows(depth32)  # the GT's rows: the image rows the checks read and the work arrays' rows
    for name, img in (("zed_left", zed_left), ("zed_right", zed_right)):
        if img is not None and img.shape[0] < depth_zed_mm.shape[0] and img.shape[0] < (need := _rows_used(
                (rows if depth_zed_mm.dtype == np.float32 else finite_rows(depth_zed_mm))[1],
                depth_zed_mm.shape[0], f)):
            raise ValueError(f"{name}.shape={img.shape} but the checks read its first {need} rows")
    depth_c, disp_c, noc_c, region_c, left_c, right_c, rig_w, win = _work_arrays(
        f, depth32, disparity_px, nonoccluded, region, zed_left, zed_right, rig, rows)
    left_norm = local_normalize(to_gray(left_c).astype(np.float32), None, params.norm_sigma_px)  # shared by both
    # away from depth edges, for both checks (disp_c is the window's GT disparity, as depth_to_disparity gives it)
    smooth = smooth_depth_mask(disp_c)
    if moved is not None:  # the owner labels cut as the region's (each block's top-left pixel)
        hc, wc = depth_c.shape
        moved = (np.ascontiguousarray(moved[0][win.y0_px * f:(win.y0_px + hc) * f:f,
                                               win.x0_px * f:(win.x0_px + wc) * f:f]), moved[1])
    e_all, e_fruit, tile_shifts, n_rend_c, _, e_each = texture_alignment(depth_c, region_c, left_c, texture, rig_w,
                                                                         params, left_norm, win, smooth, moved)
    stereo = stereo_consistency(left_c, right_c, disp_c, noc_c, region_c, params, left_norm, win, smooth) \
        if right_c is not None else {}
    if f > 1:  # back to the dataset's pixels
        e_all, e_fruit = _scaled_shift(e_all, f), _scaled_shift(e_fruit, f)
        e_each = [_scaled_shift(e, f) for e in e_each]
        stereo = {k: v.model_copy(update={key: None if getattr(v, key) is None else getattr(v, key) * f
                                          for key in ("disparity_bias_px", "vertical_px", "disparity_bias_noise_px",
                                                      "vertical_noise_px")})
                  for k, v in stereo.items()}
        tile_fn = tile_shifts

        def tile_shifts():
            return [[(x + 0.5) * f - 0.5, (y + 0.5) * f - 0.5, None if dx is None else dx * f,
                     None if dy is None else dy * f] for x, y, dx, dy in tile_fn()]
    if e_all.dx_px is None:
        return SceneVerification(status="not verifiable", reasons=[
            f"too little textured ground truth to align ({e_all.n_pixels} px < {params.min_pixels})"],
            texture_all=e_all, texture_fruit=e_fruit, stereo=stereo), None
    nd = _decimals(params.max_shift_px, 2)
    for name, e in (("whole area", e_all), ("fruit", e_fruit)):
        if e.magnitude_px is not None and e.magnitude_px > params.max_shift_px:
            reasons.append(f"texture shift over the {name} {e.magnitude_px:.{nd}f} px > {params.max_shift_px} px "
                           f"(dx {e.dx_px:+.{nd}f}, dy {e.dy_px:+.{nd}f})")
        if e.correlation is not None and e.correlation < params.min_correlation:
            reasons.append(f"texture correlation over the {name} {e.correlation:.2f} < {params.min_correlation} "
                           "(the scene changed between the captures?)")
    for k, e in enumerate(e_each, 1):
        if e.magnitude_px is not None and e.magnitude_px > params.max_shift_px:
            reasons.append(f"texture shift over fruit {k} of {len(e_each)} {e.magnitude_px:.{nd}f} px > "
                           f"{params.max_shift_px} px (dx {e.dx_px:+.{nd}f}, dy {e.dy_px:+.{nd}f})")
    for name, s in stereo.items():
        if s.disparity_bias_px is not None and abs(s.disparity_bias_px) > params.max_disparity_bias_px:
            area = "whole area" if name == "all" else name  # the texture checks' words for the same areas
            reasons.append(f"stereo: disparity bias over the {area} "
                           f"{s.disparity_bias_px:+.{_decimals(params.max_disparity_bias_px, 3)}f}"
                           f"{_pm(s.disparity_bias_noise_px)} px (> {params.max_disparity_bias_px} px)")
        if name == "all" and s.disparity_bias_px is None and s.n_pixels >= params.min_pixels:
            reasons.append(f"stereo: no disparity bias found over the whole area's {s.n_pixels} textured pixels (the "
                           f"right image matches the labels nowhere within +-{STEREO_SEARCH_PX * f} px of them: labels "
                           "far off, or another scene's pair?)")
        if name == "all" and s.vertical_px is not None and abs(s.vertical_px) > params.max_vertical_px:
            reasons.append(f"stereo: vertical misalignment {s.vertical_px:+.{_decimals(params.max_vertical_px, 3)}f}"
                           f"{_pm(s.vertical_noise_px)} px "
                           f"(> {params.max_vertical_px} px; "
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
    """The texture shift ``(dx, dy)`` px an extrinsic error predicts: ground truth built with ``rig``
    (``depth_zed_mm``), the true extrinsic ``T_zed_from_mech_true``; the mean over GT pixels of where the truth puts
    each GT point minus where the GT puts it (the sign of ``ShiftEstimate``)."""
    v, u = np.nonzero(np.isfinite(depth_zed_mm))
    cam = rig.zed.left
    z = depth_zed_mm[v, u].astype(np.float64)
    P = cam.unproject(np.stack([u, v], axis=1), z)
    moved = transform_points(T_zed_from_mech_true @ rig.T_mech_from_zed, P)
    return (cam.project(moved) - np.stack([u, v], axis=1)).mean(axis=0)


def write_verification_overlay(path: Path, zed_left: np.ndarray, rendered_norm: np.ndarray) -> None:
    """A flagged scene's overlay for verification.html: ZED-left grey in green, the texture rendered through the
    ground truth in magenta (both locally normalised); aligned structures look grey, a shift shows as colour fringes."""

    gray = to_gray(zed_left)
    if gray.shape != rendered_norm.shape:  # verify_scene renders at its work resolution (a factor smaller)
        gray = cv2.resize(gray, rendered_norm.shape[::-1], interpolation=cv2.INTER_AREA)
    g = local_normalize(gray.astype(np.float32), None, 3.0)

    def to8(a):
        return np.clip(128 + 50 * a, 0, 255).astype(np.uint8)

    rgb = np.stack([to8(rendered_norm), to8(g), to8(rendered_norm)], axis=2)
    rgb[rendered_norm == 0] = np.stack([to8(g)] * 3, axis=2)[rendered_norm == 0] // 2
    scale = min(1.0, 1280 / rgb.shape[1])
    if scale < 1.0:
        rgb = cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    write_image(path, rgb)
