"""Photometric alignment of two images of one scene: local normalisation (gain, offset and shading removed), masks of
the pixels a gradient method can use, cubic sampling, and the translation between two images (inverse-compositional
Lucas-Kanade). Used by verify (texture shift, stereo consistency), refine and calibrate-scale."""
from __future__ import annotations

import itertools
import math

import cv2
import numba
import numpy as np

from gtforge.core.schema import GTModel


class ShiftEstimate(GTModel):
    dx_px: float | None = None
    dy_px: float | None = None
    correlation: float | None = None  # ZNCC of the normalised images after alignment
    n_pixels: int = 0
    # noise floors (1 sigma) of the figures above: what exact labels give on this scene, from the spread of the
    # estimates of NOISE_BLOCKS bands of the pixels (``block_noise``); None where not measured
    dx_noise_px: float | None = None
    dy_noise_px: float | None = None
    correlation_noise: float | None = None

    @property
    def magnitude_px(self) -> float | None:
        return None if self.dx_px is None else float(np.hypot(self.dx_px, self.dy_px))



def local_normalize(img: np.ndarray, mask: np.ndarray | None, sigma_px: float) -> np.ndarray:
    """Zero local mean, unit local standard deviation within a Gaussian window, using only ``mask`` pixels
    (normalised convolution; ``None``: every pixel); 0 outside the mask. Removes gain, offset and slow shading
    differences."""
    k = (0, 0)
    if mask is None:  # the weights are all 1: no normalisation by them
        x = np.ascontiguousarray(img, np.float32)
        xx = x * x
        w, m = np.ones((1, 1), np.float32), np.ones((1, 1), np.bool_)
    else:
        m = np.ascontiguousarray(mask, np.bool_)
        x, xx, mf = np.empty(m.shape, np.float32), np.empty(m.shape, np.float32), np.empty(m.shape, np.float32)
        _masked_inputs(np.asarray(img), m, x, xx, mf)
        w = cv2.GaussianBlur(mf, k, sigma_px)
    out = np.empty(x.shape, np.float32)
    _normalized(x, cv2.GaussianBlur(x, k, sigma_px), cv2.GaussianBlur(xx, k, sigma_px), w, m, mask is not None, out)
    return out


@numba.njit(cache=True)
def _masked_inputs(img, mask, x, xx, mf):
    """The masked image ``x`` (``img`` rounded to float32, 0 outside ``mask``: ``np.where(mask, img, 0)``), its square
    (float32) and the mask as float32, in one pass."""
    H, W = mask.shape
    zero = np.float32(0.0)
    for v in range(H):
        for u in range(W):
            a = np.float32(img[v, u]) if mask[v, u] else zero
            x[v, u] = a
            xx[v, u] = a * a
            mf[v, u] = np.float32(mask[v, u])



@numba.njit(cache=True, error_model="numpy")
def _normalized(x, blur_x, blur_xx, w, mask, weighted, out):
    """``local_normalize``'s arithmetic after its blurs, in one pass with numpy's float32 operations in numpy's order:
    mean = blur(x) [/ w], var = blur(x^2) [/ w] - mean^2, (x - mean) / sqrt(max(var, 1e-6) + 1) (+1 grey level^2: flat
    areas stay near 0), 0 outside the mask (or where w <= 0.5) and where not finite (the same values as the numpy
    expression it replaces, in one pass instead of its dozen)."""
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
    if mask.dtype == np.bool_:  # its bytes are 0 / 1 already: eroded as they are, no copies
        return cv2.erode(np.ascontiguousarray(mask).view(np.uint8), np.ones((k, k), np.uint8)).view(np.bool_)
    return cv2.erode(mask.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)



def smooth_depth_mask(disparity_px: np.ndarray, radius_px: int = 3, max_range_px: float = 1.0) -> np.ndarray:
    """Pixels whose GT disparity varies by less than ``max_range_px`` within ``radius_px`` (away from depth edges,
    where a rendering through the GT mixes fore- and background and biases an alignment)."""
    k = np.ones((2 * radius_px + 1,) * 2, np.uint8)
    d = np.ascontiguousarray(disparity_px)  # (one compiled version for a whole image and for a window of it)
    # the disparity as float32, -1e6 (for the maximum) and 1e6 (for the minimum) where not finite
    hi, lo = np.empty(d.shape, np.float32), np.empty(d.shape, np.float32)
    _finite_or(d, hi, lo)
    out = np.empty(d.shape, np.bool_)
    # (numpy compares a float32 array with a Python float in float32)
    _range_below(cv2.dilate(hi, k), cv2.erode(lo, k), np.float32(max_range_px), out)
    return out


@numba.njit(cache=True)
def _finite_or(d, hi, lo):
    """``hi``, ``lo``: ``d`` rounded to float32, -1e6 / 1e6 where that is not finite."""
    H, W = d.shape
    for v in range(H):
        for u in range(W):
            x = np.float32(d[v, u])
            fin = abs(x) < np.inf
            hi[v, u] = x if fin else np.float32(-1e6)
            lo[v, u] = x if fin else np.float32(1e6)


@numba.njit(cache=True)
def _range_below(hi, lo, max_range, out):
    """``out = (hi - lo) < max_range`` (float32)."""
    H, W = out.shape
    for v in range(H):
        for u in range(W):
            out[v, u] = (hi[v, u] - lo[v, u]) < max_range



@numba.njit(cache=True, inline="always")
def _keys_weights(t, w, j):
    """The Keys kernel (a = -0.5) at the 4 taps ix - 1 .. ix + 2 of a point at ix + t (offsets 1 + t, t, 1 - t,
    2 - t), as polynomials in t, into ``w[:, j]``."""
    t2 = t * t
    t3 = t2 * t
    w[0, j] = -0.5 * t3 + t2 - 0.5 * t
    w[1, j] = 1.5 * t3 - 2.5 * t2 + 1.0
    w[2, j] = -1.5 * t3 + 2.0 * t2 + 0.5 * t
    w[3, j] = 0.5 * t3 - 0.5 * t2


@numba.njit(cache=True, inline="always")
def _bspline_weights(t, w, dw, j, derivs):
    """The cubic B-spline's weights at the 4 taps ix - 1 .. ix + 2 of a point at ix + t into ``w[:, j]``, and with
    ``derivs`` their derivatives in t into ``dw[:, j]``."""
    s6 = 1.0 / 6.0
    u1 = 1.0 - t
    w[0, j] = u1 * u1 * u1 * s6
    w[1, j] = (3.0 * t * t * t - 6.0 * t * t + 4.0) * s6
    w[2, j] = (-3.0 * t * t * t + 3.0 * t * t + 3.0 * t + 1.0) * s6
    w[3, j] = t * t * t * s6
    if derivs:
        dw[0, j] = -0.5 * u1 * u1
        dw[1, j] = 1.5 * t * t - 2.0 * t
        dw[2, j] = -1.5 * t * t + t + 0.5
        dw[3, j] = 0.5 * t * t


@numba.njit(cache=True)
def _cubic_at(imgs, x, y, out):
    """Keys cubic convolution (a = -0.5, interpolating) of each image of the stack ``imgs`` (K, H, W) at exact
    positions into ``out`` (K, N); borders replicated. A point's 4 + 4 weights are computed once, for every image:
    in chunks of points (a loop the compiler vectorises) before their samples, as ``_spline_loop`` does."""
    K, H, W = imgs.shape
    ixs, iys = np.empty(_SPLINE_CHUNK, np.int64), np.empty(_SPLINE_CHUNK, np.int64)
    wx, wy = np.empty((4, _SPLINE_CHUNK)), np.empty((4, _SPLINE_CHUNK))
    for k0 in range(0, x.shape[0], _SPLINE_CHUNK):
        n = min(_SPLINE_CHUNK, x.shape[0] - k0)
        for j in range(n):
            fx = math.floor(x[k0 + j])
            fy = math.floor(y[k0 + j])
            ixs[j] = int(fx)
            iys[j] = int(fy)
            _keys_weights(x[k0 + j] - fx, wx, j)
            _keys_weights(y[k0 + j] - fy, wy, j)
        for j in range(n):
            k = k0 + j
            ix, iy = ixs[j], iys[j]
            wx0, wx1, wx2, wx3 = wx[0, j], wx[1, j], wx[2, j], wx[3, j]
            wy0, wy1, wy2, wy3 = wy[0, j], wy[1, j], wy[2, j], wy[3, j]
            if 1 <= ix <= W - 3 and 1 <= iy <= H - 3:  # all 16 taps inside
                x0, x1, x2, x3, y0, y1, y2, y3 = ix - 1, ix, ix + 1, ix + 2, iy - 1, iy, iy + 1, iy + 2
            else:
                x0, x1, x2, x3 = (min(max(ix - 1, 0), W - 1), min(max(ix, 0), W - 1), min(max(ix + 1, 0), W - 1),
                                  min(max(ix + 2, 0), W - 1))
                y0, y1, y2, y3 = (min(max(iy - 1, 0), H - 1), min(max(iy, 0), H - 1), min(max(iy + 1, 0), H - 1),
                                  min(max(iy + 2, 0), H - 1))
            for c in range(K):
                im = imgs[c]
                r0 = wx0 * im[y0, x0] + wx1 * im[y0, x1] + wx2 * im[y0, x2] + wx3 * im[y0, x3]
                r1 = wx0 * im[y1, x0] + wx1 * im[y1, x1] + wx2 * im[y1, x2] + wx3 * im[y1, x3]
                r2 = wx0 * im[y2, x0] + wx1 * im[y2, x1] + wx2 * im[y2, x2] + wx3 * im[y2, x3]
                r3 = wx0 * im[y3, x0] + wx1 * im[y3, x1] + wx2 * im[y3, x2] + wx3 * im[y3, x3]
                out[c, k] = wy0 * r0 + wy1 * r1 + wy2 * r2 + wy3 * r3


def sample_cubic(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Cubic samples of ``img`` (H, W), or of each image of a stack (K, H, W) -> (K, N), at the points ``(x, y)``
    (exact sub-pixel positions: ``cv2.remap`` rounds them to 1/32 px, the size of the shifts measured here)."""
    imgs = np.ascontiguousarray(img, np.float32)
    out = np.empty((1 if imgs.ndim == 2 else imgs.shape[0], len(x)))
    _cubic_at(imgs.reshape((-1,) + imgs.shape[-2:]), np.ascontiguousarray(x, np.float64),
              np.ascontiguousarray(y, np.float64), out)
    return out[0] if imgs.ndim == 2 else out



def spline_prefilter(img: np.ndarray) -> np.ndarray:
    """Cubic B-spline coefficients of ``img`` (H, W), or of each image of a stack (K, H, W), float64 (mirror
    boundary): what ``sample_spline`` interpolates. The same coefficients as scipy's ``spline_filter``
    (``mode="mirror"``) within 1e-12 relative (``gtforge.core.bspline`` has them to the last bit, for the images
    gtforge resamples; these feed only the verification's own fits)."""
    a = np.asarray(img)
    if a.dtype not in (np.float32, np.float64):
        a = a.astype(np.float64)
    stack = a.reshape((-1,) + a.shape[-2:])
    out = np.empty(stack.shape, np.float64)
    for i in range(stack.shape[0]):
        _bspline_2d(stack[i], out[i])
    return out.reshape(a.shape)


# rows filtered together by ``_bspline_2d``'s row pass (one cache line of float64 per row and step)
_ROW_BLOCK = 8


@numba.njit(cache=True)
def _bspline_2d(x, c):
    """``c`` (H, W) float64: the cubic B-spline coefficients of ``x`` (H, W): ``_bspline_axis0`` along the columns,
    then along the rows, without the transposed copies (each row's recursion is the same arithmetic in the same
    order, so the same coefficients to the last bit). The row pass runs on ``_ROW_BLOCK`` rows at a time, whose
    recursions are independent (a single row's is a chain of dependent multiply-adds)."""
    H, W = x.shape
    for v in range(H):
        for u in range(W):
            c[v, u] = np.float64(x[v, u])
    _bspline_axis0(c)
    if W == 1:
        return
    z = math.sqrt(3.0) - 2.0
    period = 2 * W - 2
    horizon = min(period, 40)
    scale = 1.0 / (1.0 - z ** period) if horizon == period else 1.0
    f = z / (z * z - 1.0)
    first = np.zeros(_ROW_BLOCK)
    for v0 in range(0, H, _ROW_BLOCK):
        n = min(_ROW_BLOCK, H - v0)
        for r in range(n):
            row = c[v0 + r]
            for u in range(W):
                row[u] *= 6.0
            first[r] = 0.0
        zk = 1.0
        for k in range(horizon):
            kk = k if k < W else period - k
            for r in range(n):
                first[r] += zk * c[v0 + r, kk]
            zk *= z
        for r in range(n):
            c[v0 + r, 0] = first[r] * scale
        for k in range(1, W):
            for r in range(n):
                c[v0 + r, k] += z * c[v0 + r, k - 1]
        for r in range(n):
            c[v0 + r, W - 1] = f * (c[v0 + r, W - 1] + z * c[v0 + r, W - 2])
        for k in range(W - 2, -1, -1):
            for r in range(n):
                c[v0 + r, k] = z * (c[v0 + r, k + 1] - c[v0 + r, k])


@numba.njit(cache=True)
def _bspline_axis0(c):
    """In place: the cubic B-spline prefilter of every column of ``c`` (N, M) along axis 0 (Unser's causal and
    anti-causal recursions with pole sqrt(3) - 2, whole-sample mirror boundary, gain 6), the inner loop along the
    contiguous rows."""
    N, M = c.shape
    if N == 1:
        return
    z = math.sqrt(3.0) - 2.0
    for j in range(M):
        c[0, j] *= 6.0
    for k in range(1, N):
        for j in range(M):
            c[k, j] *= 6.0
    # causal initialisation: sum_k z^k s~(k) over the mirror-extended signal's period 2N - 2 (/(1 - z^(2N-2))), or
    # the first terms where z^k is below double precision
    period = 2 * N - 2
    horizon = min(period, 40)
    first = np.zeros(M)
    zk = 1.0
    for k in range(horizon):
        kk = k if k < N else period - k
        for j in range(M):
            first[j] += zk * c[kk, j]
        zk *= z
    scale = 1.0 / (1.0 - z ** period) if horizon == period else 1.0
    for j in range(M):
        c[0, j] = first[j] * scale
    for k in range(1, N):
        for j in range(M):
            c[k, j] += z * c[k - 1, j]
    # anti-causal initialisation (mirror): z / (z^2 - 1) (c+[N-1] + z c+[N-2])
    f = z / (z * z - 1.0)
    for j in range(M):
        c[N - 1, j] = f * (c[N - 1, j] + z * c[N - 2, j])
    for k in range(N - 2, -1, -1):
        for j in range(M):
            c[k, j] = z * (c[k + 1, j] - c[k, j])


@numba.njit(cache=True, inline="always")
def _mirror(i, n):
    """scipy's ``mode="mirror"`` index (reflection about the edge pixels' centres: -1 -> 1, n -> n - 2)."""
    if n == 1:
        return 0
    period = 2 * n - 2
    i = abs(i) % period
    return i if i < n else period - i


@numba.njit(cache=True)
def _spline_at(coeffs, x, y, out, derivs):
    """Cubic B-spline interpolation of each coefficient image of ``coeffs`` (K, H, W) at exact positions: ``out``
    (K, N) holds the values, or (3K, N) with ``derivs`` the values, then d/dx, then d/dy of every image (the
    spline's own derivatives, consistent with its values). Taps beyond the border mirrored (scipy's ``mirror``)."""
    # the loop compiled once with and once without the derivatives (a constant in each: no branch per point)
    if derivs:
        _spline_loop(coeffs, x, y, out, True)
    else:
        _spline_loop(coeffs, x, y, out, False)


# points whose weights ``_spline_loop`` computes together before it samples them
_SPLINE_CHUNK = 256


@numba.njit(cache=True, inline="always")
def _spline_loop(coeffs, x, y, out, derivs):
    """``_spline_at``'s loop over the points, in chunks: each chunk's tap positions and weights first (a loop the
    compiler vectorises), then its samples (the same expressions, in the same order, as one loop doing both)."""
    K, H, W = coeffs.shape
    ixs, iys = np.empty(_SPLINE_CHUNK, np.int64), np.empty(_SPLINE_CHUNK, np.int64)
    wx, wy = np.empty((4, _SPLINE_CHUNK)), np.empty((4, _SPLINE_CHUNK))
    dxw, dyw = np.empty((4, _SPLINE_CHUNK)), np.empty((4, _SPLINE_CHUNK))
    for k0 in range(0, x.shape[0], _SPLINE_CHUNK):
        n = min(_SPLINE_CHUNK, x.shape[0] - k0)
        for j in range(n):
            fx = math.floor(x[k0 + j])
            fy = math.floor(y[k0 + j])
            ixs[j] = int(fx)
            iys[j] = int(fy)
            _bspline_weights(x[k0 + j] - fx, wx, dxw, j, derivs)
            _bspline_weights(y[k0 + j] - fy, wy, dyw, j, derivs)
        for j in range(n):
            k = k0 + j
            ix, iy = ixs[j], iys[j]
            wx0, wx1, wx2, wx3 = wx[0, j], wx[1, j], wx[2, j], wx[3, j]
            wy0, wy1, wy2, wy3 = wy[0, j], wy[1, j], wy[2, j], wy[3, j]
            if 1 <= ix <= W - 3 and 1 <= iy <= H - 3:  # all 16 taps inside
                x0, x1, x2, x3, y0, y1, y2, y3 = ix - 1, ix, ix + 1, ix + 2, iy - 1, iy, iy + 1, iy + 2
            else:
                x0, x1, x2, x3 = _mirror(ix - 1, W), _mirror(ix, W), _mirror(ix + 1, W), _mirror(ix + 2, W)
                y0, y1, y2, y3 = _mirror(iy - 1, H), _mirror(iy, H), _mirror(iy + 1, H), _mirror(iy + 2, H)
            for c in range(K):
                cf = coeffs[c]
                r0 = wx0 * cf[y0, x0] + wx1 * cf[y0, x1] + wx2 * cf[y0, x2] + wx3 * cf[y0, x3]
                r1 = wx0 * cf[y1, x0] + wx1 * cf[y1, x1] + wx2 * cf[y1, x2] + wx3 * cf[y1, x3]
                r2 = wx0 * cf[y2, x0] + wx1 * cf[y2, x1] + wx2 * cf[y2, x2] + wx3 * cf[y2, x3]
                r3 = wx0 * cf[y3, x0] + wx1 * cf[y3, x1] + wx2 * cf[y3, x2] + wx3 * cf[y3, x3]
                out[c, k] = wy0 * r0 + wy1 * r1 + wy2 * r2 + wy3 * r3
                if derivs:
                    dx0, dx1, dx2, dx3 = dxw[0, j], dxw[1, j], dxw[2, j], dxw[3, j]
                    dy0, dy1, dy2, dy3 = dyw[0, j], dyw[1, j], dyw[2, j], dyw[3, j]
                    out[K + c, k] = (wy0 * (dx0 * cf[y0, x0] + dx1 * cf[y0, x1]
                                            + dx2 * cf[y0, x2] + dx3 * cf[y0, x3])
                                     + wy1 * (dx0 * cf[y1, x0] + dx1 * cf[y1, x1]
                                              + dx2 * cf[y1, x2] + dx3 * cf[y1, x3])
                                     + wy2 * (dx0 * cf[y2, x0] + dx1 * cf[y2, x1]
                                              + dx2 * cf[y2, x2] + dx3 * cf[y2, x3])
                                     + wy3 * (dx0 * cf[y3, x0] + dx1 * cf[y3, x1]
                                              + dx2 * cf[y3, x2] + dx3 * cf[y3, x3]))
                    out[2 * K + c, k] = dy0 * r0 + dy1 * r1 + dy2 * r2 + dy3 * r3


def sample_spline(coeffs: np.ndarray, x: np.ndarray, y: np.ndarray, derivs: bool = False) -> np.ndarray:
    """Cubic B-spline samples of the image whose coefficients are ``coeffs`` (``spline_prefilter``, float64 or float32;
    (H, W) -> (N,), or a stack (K, H, W) -> (K, N)) at the exact points ``(x, y)``; with ``derivs`` also its x and y
    derivatives: (3, N), or (3K, N) (values, d/dx, d/dy).

    Phase-unbiased where ``sample_cubic`` is not: Keys' convolution (a = -0.5) smooths and shifts a texture by an
    amount that depends on the sample's sub-pixel phase, which in a stereo check at the ground truth's disparities is
    the disparity's fractional part (on a fronto-parallel textured plane, one phase everywhere: a false disparity bias
    of up to +-0.03 px on the 400x200 sweep in tests/stages/test_verify_phase_bias.py; with the B-spline under
    0.003 px). Same cost per point as ``sample_cubic``, plus one prefilter of the image."""
    c = np.ascontiguousarray(coeffs, coeffs.dtype if coeffs.dtype in (np.float32, np.float64) else np.float64)
    stack = c.reshape((-1,) + c.shape[-2:])
    K = stack.shape[0]
    out = np.empty((3 * K if derivs else K, len(x)))
    _spline_at(stack, np.ascontiguousarray(x, np.float64), np.ascontiguousarray(y, np.float64), out, derivs)
    return out[0] if (c.ndim == 2 and not derivs) else out


# the pixels an estimate uses at most: a larger set is subsampled evenly (the estimate's noise stays far below the
# thresholds)
MAX_POINTS = 30000



def even_subset(n: int, max_points: int) -> np.ndarray | slice:
    """Indices of at most ``max_points`` of ``n`` listed items, evenly spread (all of them: ``slice(None)``)."""
    return np.linspace(0, n - 1, max_points).round().astype(np.int64) if n > max_points else slice(None)



def pixels_of(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(v, u, flat index)`` of a 2-D mask's pixels in row-major order (``np.nonzero``'s order; flat indices are
    faster to find and to gather with: one index array, ``take_at``)."""
    m = np.ascontiguousarray(mask if mask.dtype == np.bool_ else mask != 0)
    n = np.count_nonzero(m)
    v, u, idx = np.empty(n + 1, np.int64), np.empty(n + 1, np.int64), np.empty(n + 1, np.int64)
    _pixels(m, v, u, idx)
    return v[:n], u[:n], idx[:n]


@numba.njit(cache=True)
def _pixels(mask, v, u, idx):
    """``pixels_of``'s lists in one pass over the mask: every pixel written at the next free slot, which advances
    only at a mask pixel (no branch; the lists have one slot more than the mask has pixels)."""
    H, W = mask.shape
    k = 0
    for r in range(H):
        row = mask[r]
        for c in range(W):
            v[k] = r
            u[k] = c
            idx[k] = r * W + c
            k += row[c]



def take_at(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``a[v, u]`` for the flat indices ``idx`` of ``(v, u)`` in a 2-D array (a gather, not numpy's multi-index
    iterator, which is much slower; an array that is not C-contiguous is copied first)."""
    return np.ascontiguousarray(a).reshape(-1).take(idx)



class ShiftAligner:
    """Translation ``d`` with ``img(u + d) ~ ref(u)`` over any mask of pixels (both images already normalised).

    Inverse-compositional Lucas-Kanade (the Hessian from ``ref``'s gradients) with a free gain and offset, ``img``
    sampled at the mask's points only, by cubic B-spline (``sample_spline``, phase-unbiased) in the fine pass; a
    coarse pass on copies blurred by 2 px first (Keys' cubic), so shifts of a few pixels converge. The image pyramids
    are built once and shared by every mask (whole area, fruit, tiles)."""

    SIGMAS = (2.0, 0.0)
    COARSE_TOL_PX = 0.01

    def __init__(self, ref: np.ndarray, img: np.ndarray,
                 ref_gradients: tuple[np.ndarray, np.ndarray] | None = None):
        """``ref_gradients``: ``sobel_gradients(ref)``, if the caller has them (``textured_mask``'s)."""
        self.ref = ref
        self.levels = []
        for sigma in self.SIGMAS:
            r = cv2.GaussianBlur(ref, (0, 0), sigma) if sigma else ref
            i = cv2.GaussianBlur(img, (0, 0), sigma) if sigma else img
            self.levels.append((r, *(ref_gradients if not sigma and ref_gradients is not None else
                                     sobel_gradients(r)),
                                # the coarse pass only brings the fine one near its solution: Keys' cubic there (no
                                # prefilter); the fine pass, which gives the figure, samples the B-spline
                                spline_prefilter(i) if sigma == self.SIGMAS[-1]
                                else np.ascontiguousarray(i, np.float32)))

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
            At = np.empty((4, len(rv)))
            At[0], At[1], At[2], At[3] = take_at(gx, idx), take_at(gy, idx), rv, 1.0
            try:
                inv = np.linalg.inv(At @ At.T)
            except np.linalg.LinAlgError:
                return ShiftEstimate(n_pixels=n)
            for _ in range(iterations):
                sampled = sample_spline(coeffs, uf + d[0], vf + d[1]) if level == len(self.levels) - 1 else \
                    sample_cubic(coeffs, uf + d[0], vf + d[1])
                step = inv @ (At @ (sampled - rv))
                d -= step[:2]  # inverse composition of a translation
                if np.abs(d).max() > 20:  # diverged: nothing to align
                    return ShiftEstimate(n_pixels=n)
                if np.abs(step[:2]).max() < tol:
                    break
        w = sample_spline(self.levels[-1][3], uf + d[0], vf + d[1])
        rv = take_at(self.ref, idx).astype(np.float64)
        a, b = rv - rv.mean(), w - w.mean()
        # plain sums, not BLAS dot products: the same digits whatever the thread count (builds are byte-identical)
        saa, sbb, sab = float(np.sum(a * a)), float(np.sum(b * b)), float(np.sum(a * b))
        zncc = sab / np.sqrt(saa * sbb) if saa > 0 and sbb > 0 else None
        # noise floors: the last linearisation per band of pixels (block_noise), the correlation's over the same bands
        noise = block_noise(At.T, w - rv, 2)
        edges = np.linspace(0, len(w), NOISE_BLOCKS + 1).astype(np.int64)
        zb = []
        for i0, i1 in itertools.pairwise(edges):
            ab, bb = rv[i0:i1] - rv[i0:i1].mean(), w[i0:i1] - w[i0:i1].mean()
            den = float(np.sum(ab * ab)) * float(np.sum(bb * bb))
            if den > 0:
                zb.append(float(np.sum(ab * bb)) / math.sqrt(den))
        zn = float(np.std(zb, ddof=1) / math.sqrt(len(zb))) if noise is not None and len(zb) > 2 else None
        return ShiftEstimate(dx_px=float(d[0]), dy_px=float(d[1]), correlation=zncc, n_pixels=n,
                             dx_noise_px=None if noise is None else float(noise[0]),
                             dy_noise_px=None if noise is None else float(noise[1]), correlation_noise=zn)



# the noise floor of an estimate: the pixels (row-major order) are cut into this many bands of consecutive pixels,
# each solved alone at the estimate; the spread of the bands' solutions / sqrt(NOISE_BLOCKS) is the estimate's 1 sigma
# (image noise, texture and the match's own artefacts, the pixels' spatial correlation included within a band)
NOISE_BLOCKS = 16


def block_noise(A: np.ndarray, r: np.ndarray, n_params: int) -> np.ndarray | None:
    """1-sigma noise of the first ``n_params`` unknowns of the least-squares step ``argmin |A x + r|`` at a converged
    solution (``A`` (N, p) the linearised model, ``r`` (N,) the residuals, rows in row-major pixel order): the
    standard error of ``NOISE_BLOCKS`` bands' own solutions. A handful of small solves: cheap beside the estimate.
    None when there are too few rows."""
    n = len(r)
    if n < NOISE_BLOCKS * 4 * A.shape[1]:
        return None
    edges = np.linspace(0, n, NOISE_BLOCKS + 1).astype(np.int64)
    p = A.shape[1]
    normal, rhs = np.empty((NOISE_BLOCKS, p, p)), np.empty((NOISE_BLOCKS, p, 1))
    for k, (a, b) in enumerate(itertools.pairwise(edges)):
        Ab, rb = A[a:b], r[a:b]
        normal[k], rhs[k, :, 0] = Ab.T @ Ab, -(Ab.T @ rb)
    try:  # the bands' systems solved in one call (LAPACK's gesv on each, as one call per band solves them)
        sols = np.linalg.solve(normal, rhs)[:, :n_params, 0]
    except np.linalg.LinAlgError:
        return None
    return np.std(sols, axis=0, ddof=1) / math.sqrt(NOISE_BLOCKS)


def estimate_shift(ref: np.ndarray, img: np.ndarray, mask: np.ndarray, min_pixels: int = 400) -> ShiftEstimate:
    """One translation ``d`` with ``img(u + d) ~ ref(u)`` over ``mask`` (see ``ShiftAligner``)."""
    return ShiftAligner(ref, img).align(mask, min_pixels)



def sobel_gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(d/dx, d/dy)`` of ``img`` (float32, 3x3 Sobel / 8: per pixel)."""
    return (cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8),
            cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8))


def textured_mask(norm_img: np.ndarray, thresh: float = 0.15,
                  gradients: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Pixels whose gradient magnitude exceeds ``thresh``. ``gradients``: ``sobel_gradients(norm_img)``, if the
    caller has them."""
    gx, gy = gradients if gradients is not None else sobel_gradients(norm_img)
    return cv2.magnitude(gx, gy) > thresh


def to_gray(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


# tile keys ty * TILE_KEY + tx sort as (ty, tx): the tiles' order, and so the sums below, do not depend on the
# image size
TILE_KEY = 1 << 32


def huber_system(J: np.ndarray, r: np.ndarray, huber: float, u: np.ndarray | None = None,
                 v: np.ndarray | None = None, tile_px: float | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """One Gauss-Newton step's Huber-IRLS normal equations for residuals ``r`` with Jacobian ``J`` (photometric fits:
    refine's extrinsic, calibrate-scale's terms): ``(J^T W J, J^T W r, w, S)``, ``w`` the Huber weights. With
    ``tile_px``, ``S`` sums the outer products of the score summed over ``tile_px``-square tiles of the image the
    points ``(u, v)`` lie in: the cluster-robust "meat" of the sandwich covariance ``H^-1 S H^-1`` (neighbouring pixels'
    residuals are correlated; tiles are about independent)."""
    w = np.where(np.abs(r) <= huber, 1.0, huber / np.maximum(np.abs(r), 1e-12))
    Jw = J * w[:, None]
    S = None
    if tile_px is not None:
        psi = Jw * r[:, None]  # each point's score
        tile = np.floor(v / tile_px).astype(np.int64) * TILE_KEY + np.floor(u / tile_px).astype(np.int64)
        _, idx = np.unique(tile, return_inverse=True)
        g = np.stack([np.bincount(idx.ravel(), weights=psi[:, j]) for j in range(J.shape[1])], axis=1)
        S = g.T @ g
    return Jw.T @ J, Jw.T @ r, w, S
