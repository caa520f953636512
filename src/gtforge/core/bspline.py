"""Cubic B-spline resampling of an image with ``scipy.ndimage``'s arithmetic, compiled: the coefficients of
``spline_filter(order=3, mode="mirror")`` and the samples of ``map_coordinates(order=3, prefilter=False,
mode="mirror")``, the same float64 operations in the same order, so the same values to the last bit (checked against
SciPy in tests/core/test_bspline.py, on random and on real images). SciPy evaluates one channel at a time, computing
each point's weights and border taps again for every channel, in generic N-d code: 0.93-1.1 CPU s for a 2208x1242 RGB
image on the project's Xeon, against 0.18-0.19 s for these kernels (benchmarks/RESULTS.md, "Round 7"), 0.15 s since
round 9; ``resample_homography`` 0.065 s on the Zen 4 VM of round 21.

The recursive prefilter is Unser, Aldroubi and Eden's (IEEE PAMI 13(3), 1991): the gain, then one causal and one
anti-causal first-order recursion with the pole ``sqrt(3) - 2``, initialised for a whole-sample mirror boundary (the
causal one from the whole mirrored line, as SciPy does: no truncation, whatever the line's length; its terms past
``z^i``'s underflow are zeros, summed only where they can still change the sum). Taps beyond the
border are mirrored about the edge pixels' centres.

The image is kept channel-last: the coefficients are ``(H, W, K)`` float64, filtered along the columns as one (H, W*K)
array (each line's recursion independent, the inner loop across lines, which the compiler vectorises), then along the
rows, a block of rows at a time as the columns of its transposed view (a few independent recursions a step, each
sample read where it lies). Each point's taps and weights serve all its channels.

``resample_homography`` keeps them channel by channel instead, ``(K, H, W)`` (the same values: each line is filtered
alone either way): along a row of output pixels whose taps move one column a pixel (a run), each channel's taps are
then consecutive values, which the compiler loads as vectors, each pixel in its own lane with its own sums in SciPy's
order."""
from __future__ import annotations

import math

import numba
import numpy as np

# the cubic B-spline's pole, sqrt(3) - 2, as SciPy writes it (a literal; math.sqrt(3.0) - 2.0 is one ulp away)
POLE = -0.267949192431122706472553658494127633


@numba.njit(cache=True)
def _filter_lines(src, c, z, finite):
    """``c`` (N, M) float64: the cubic B-spline prefilter of every column of ``src`` (N, M; ``c`` itself, or an image
    of another type) along axis 0. ``finite``: every value of ``src`` is finite (the causal initialisation may then
    stop early, with the same result)."""
    n, m = c.shape
    if n < 2:
        for i in range(n):
            for j in range(m):
                c[i, j] = np.float64(src[i, j])
        return
    gain = 1.0 * ((1.0 - z) * (1.0 - 1.0 / z))
    for i in range(n):
        for j in range(m):
            c[i, j] = np.float64(src[i, j]) * gain
    # causal initialisation: sum over the mirrored line (z^(n-1) underflows to 0 past a few hundred samples)
    zn1 = math.pow(z, float(n - 1))
    first = np.empty(m)
    for j in range(m):
        first[j] = c[0, j] + zn1 * c[n - 1, j]
    zi = z
    i = 1
    while i < n - 1 and not (finite and zi == 0.0):
        for j in range(m):
            first[j] += zi * (c[i, j] + zn1 * c[n - 1 - i, j])
        zi *= z
        i += 1
    if i < n - 1:
        # z^i has underflowed to zero (past about 566 samples): each remaining term is a zero (its factors finite),
        # which leaves a nonzero sum as it is and can change only a zero sum's sign (IEEE: +0 + -0 = +0). So only the
        # lines whose sum is zero take the remaining terms, with the same signed factors.
        for j in range(m):
            if first[j] == 0.0:
                zt = zi
                for ii in range(i, n - 1):
                    first[j] += zt * (c[ii, j] + zn1 * c[n - 1 - ii, j])
                    zt *= z
    d = 1.0 - zn1 * zn1
    for j in range(m):
        c[0, j] = first[j] / d
    for i in range(1, n):
        for j in range(m):
            c[i, j] += z * c[i - 1, j]
    # anti-causal initialisation (mirror)
    q = z * z - 1.0
    for j in range(m):
        c[n - 1, j] = (z * c[n - 2, j] + c[n - 1, j]) * z / q
    for i in range(n - 2, -1, -1):
        for j in range(m):
            c[i, j] = z * (c[i + 1, j] - c[i, j])


def coefficients(image: np.ndarray) -> np.ndarray:
    """The cubic B-spline coefficients of ``image`` (H, W) or (H, W, K), as (H, W, K) float64: SciPy's
    ``spline_filter(image[..., k], order=3, mode="mirror")`` of every channel ``k``."""
    a = np.ascontiguousarray(image)
    h, w = a.shape[:2]
    k = 1 if a.ndim == 2 else a.shape[2]
    c = np.empty((h, w, k))
    finite = _stays_finite(a)
    _filter_lines(a.reshape(h, w * k), c.reshape(h, w * k), POLE, finite)  # along the columns (SciPy's first axis)
    _filter_rows(c, POLE, finite)  # then along the rows
    return c


def _stays_finite(a: np.ndarray) -> bool:
    """Every value the two passes see is finite: an integer image's, and a float image's whose values are finite and
    far from overflowing (each pass multiplies a line's values by at most about 20). ``_filter_lines``' ``finite``."""
    return bool(np.issubdtype(a.dtype, np.integer)
                or (a.size and np.isfinite(a).all() and float(np.abs(a).max()) < 1e300))


def _planar_coefficients(image: np.ndarray) -> np.ndarray:
    """``coefficients(image)`` as ``(K, H, W)``: each channel's own (H, W) plane, filtered alone (the same values)."""
    a = np.ascontiguousarray(image)
    h, w = a.shape[:2]
    a3 = a.reshape(h, w, -1)
    k = a3.shape[2]
    finite = _stays_finite(a)
    c = np.empty((k, h, w))
    for j in range(k):
        # (a contiguous copy of the channel: the same compiled filter as ``coefficients``' and unit-stride reads)
        _filter_lines(np.ascontiguousarray(a3[:, :, j]), c[j], POLE, finite)
        _filter_rows(c[j].reshape(h, w, 1), POLE, finite)
    return c


# rows ``_filter_rows`` filters together: each step along the rows advances this many independent recursions, which
# the processor overlaps, and the block stays in the L2 cache (16 rows of 2208 x K doubles: 0.28 MB for a plane,
# 0.85 MB for a channel-last RGB image, whose cache lines hold all three channels)
_ROWS = 16


@numba.njit(cache=True)
def _filter_rows(c, z, finite):
    """In place: the cubic B-spline prefilter of every row of every channel of ``c`` (H, W, K) float64, ``_ROWS``
    rows of a channel at a time, filtered where they are as the columns of their transposed view (``_filter_lines``:
    each line's recursion alone, so the same values as a row filtered by itself). ``finite``: as
    ``_filter_lines``'s."""
    H, W, K = c.shape
    for y0 in range(0, H, _ROWS):
        for k in range(K):
            lines = c[y0:y0 + _ROWS, :, k].T
            _filter_lines(lines, lines, z, finite)


@numba.njit(cache=True, inline="always")
def _weights(x):
    """The four cubic B-spline weights of the taps ``floor(x) - 1 .. floor(x) + 2`` (SciPy's expressions, the last
    one as 1 less the others, subtracted in order)."""
    x -= math.floor(x)
    y = x
    z = 1.0 - x
    w1 = (y * y * (y - 2.0) * 3.0 + 4.0) / 6.0
    w2 = (z * z * (z - 2.0) * 3.0 + 4.0) / 6.0
    w0 = z * z * z / 6.0
    return w0, w1, w2, ((1.0 - w0) - w1) - w2


@numba.njit(cache=True, inline="always")
def _tap(idx, n):
    """Tap ``idx`` of a line of ``n`` samples, mirrored beyond its ends."""
    if n <= 1:
        return 0
    if 0 <= idx < n:
        return idx
    s2 = 2 * n - 2
    if idx < 0:
        idx = s2 * (-idx // s2) + idx
        return idx + s2 if idx <= 1 - n else -idx
    idx -= s2 * (idx // s2)
    return s2 - idx if idx >= n else idx


@numba.njit(cache=True, inline="always")
def _mirror_coordinate(x, n):
    """A coordinate beyond a line of ``n`` samples mirrored into it (SciPy's ``map_coordinate``, mode "mirror")."""
    if x < 0.0:
        if n <= 1:
            return 0.0
        s2 = 2 * n - 2
        x = s2 * float(int(-x / s2)) + x
        return x + s2 if x <= 1 - n else -x
    if x > n - 1:
        if n <= 1:
            return 0.0
        s2 = 2 * n - 2
        x -= s2 * float(int(x / s2))
        if x >= n:
            x = s2 - x
    return x


@numba.njit(cache=True, inline="always")
def _row_of_taps(c, y, k, x0, x1, x2, x3, wy, wx0, wx1, wx2, wx3, t):
    """``t`` plus one row of a point's taps, each product ``c * wy * wx``, in SciPy's order."""
    t += c[y, x0, k] * wy * wx0
    t += c[y, x1, k] * wy * wx1
    t += c[y, x2, k] * wy * wx2
    t += c[y, x3, k] * wy * wx3
    return t


@numba.njit(cache=True, inline="always")
def _stencil(H, W, u, v):
    """A point's taps (columns x0..x3, rows y0..y3, mirrored beyond the border) and weights (wx0..wx3, wy0..wy3)."""
    x = int(math.floor(u)) - 1
    y = int(math.floor(v)) - 1
    if 0 <= x and x + 3 < W:
        xs = (x, x + 1, x + 2, x + 3)
    else:
        xs = (_tap(x, W), _tap(x + 1, W), _tap(x + 2, W), _tap(x + 3, W))
    if 0 <= y and y + 3 < H:
        ys = (y, y + 1, y + 2, y + 3)
    else:
        ys = (_tap(y, H), _tap(y + 1, H), _tap(y + 2, H), _tap(y + 3, H))
    return xs, ys, _weights(u), _weights(v)


@numba.njit(cache=True, inline="always")
def _sum_taps(c, k, xs, ys, wx, wy):
    """Channel ``k`` of the spline whose coefficients are ``c`` (H, W, K) over a point's ``_stencil``: the 16 taps'
    products summed row of taps by row, as SciPy sums them."""
    x0, x1, x2, x3 = xs
    y0, y1, y2, y3 = ys
    wx0, wx1, wx2, wx3 = wx
    wy0, wy1, wy2, wy3 = wy
    t = _row_of_taps(c, y0, k, x0, x1, x2, x3, wy0, wx0, wx1, wx2, wx3, 0.0)
    t = _row_of_taps(c, y1, k, x0, x1, x2, x3, wy1, wx0, wx1, wx2, wx3, t)
    t = _row_of_taps(c, y2, k, x0, x1, x2, x3, wy2, wx0, wx1, wx2, wx3, t)
    return _row_of_taps(c, y3, k, x0, x1, x2, x3, wy3, wx0, wx1, wx2, wx3, t)


@numba.njit(cache=True)
def _samples(coef, us, vs, out):
    """``out`` (N, K) float64: the spline at ``(us, vs)``, points beyond the image mirrored into it."""
    H, W, K = coef.shape
    for p in range(us.shape[0]):
        xs, ys, wx, wy = _stencil(H, W, _mirror_coordinate(us[p], W), _mirror_coordinate(vs[p], H))
        for k in range(K):
            out[p, k] = _sum_taps(coef, k, xs, ys, wx, wy)


@numba.njit(cache=True, inline="always")
def _rounded(t, top):
    """``t`` rounded half to even and clipped to [0, top] (``np.round``, ``np.clip``)."""
    r = np.rint(t)
    if r < 0.0:
        return 0.0
    return top if r > top else r


@numba.njit(cache=True, inline="always")
def _resample_point(coef, u, v, top, out, p):
    """``out[p]``: the image whose coefficients are ``coef`` (H, W, K) at ``(u, v)``, rounded half to even and
    clipped to [0, top]; 0 outside the image."""
    H, W, K = coef.shape
    if not (u >= 0.0 and u <= W - 1 and v >= 0.0 and v <= H - 1):
        for k in range(K):
            out[p, k] = 0
        return
    xs, ys, wx, wy = _stencil(H, W, u, v)
    for k in range(K):
        out[p, k] = _rounded(_sum_taps(coef, k, xs, ys, wx, wy), top)


@numba.njit(cache=True)
def _resample(coef, us, vs, top, out):
    """``out`` (N, K): ``_resample_point`` at each ``(us, vs)`` (N,)."""
    for p in range(us.shape[0]):
        _resample_point(coef, us[p], vs[p], top, out, p)


@numba.njit(cache=True, inline="always")
def _run_row_of_taps(R, i, wy, wx0, wx1, wx2, wx3, t):
    """``t`` plus one row of a run's pixel ``i``'s taps, ``R[i .. i + 3]``, each product ``c * wy * wx`` in SciPy's
    order (``_row_of_taps`` over a row slice)."""
    t += R[i] * wy * wx0
    t += R[i + 1] * wy * wx1
    t += R[i + 2] * wy * wx2
    t += R[i + 3] * wy * wx3
    return t


@numba.njit(cache=True)
def _run_taps(R0, R1, R2, R3, wx0, wx1, wx2, wx3, wy0, wy1, wy2, wy3, out):
    """``out[i]``: the sum of a run's pixel ``i`` over its 4 x 4 taps, rows ``R0..R3`` (one channel's coefficients from
    the run's first tap column on: pixel ``i``'s taps are ``R[i .. i + 3]``), weights ``wx0[i]..wx3[i]``,
    ``wy0[i]..wy3[i]``; summed as ``_sum_taps`` sums them. Unit strides (every argument a slice of one row) and no
    branch: the compiler runs it over several pixels at a time."""
    for i in range(out.shape[0]):
        a0, a1, a2, a3 = wx0[i], wx1[i], wx2[i], wx3[i]
        t = _run_row_of_taps(R0, i, wy0[i], a0, a1, a2, a3, 0.0)
        t = _run_row_of_taps(R1, i, wy1[i], a0, a1, a2, a3, t)
        t = _run_row_of_taps(R2, i, wy2[i], a0, a1, a2, a3, t)
        out[i] = _run_row_of_taps(R3, i, wy3[i], a0, a1, a2, a3, t)


# numpy's error model: a division by a zero homogeneous coordinate gives a non-finite position (a black pixel), and
# without Python's zero test before each division the compiler vectorises the row's positions and weights
@numba.njit(cache=True, error_model="numpy")
def _resample_homography(coef, M, h, w, top, out):
    """``out`` (h * w, K): ``_resample_point`` at ``M`` (3x3) times each output pixel, row-major, in
    ``gtforge.core.zed.scale_corrections.apply_homography``'s arithmetic; ``coef`` (K, H, W): ``_planar_coefficients``.
    A row's positions and weights first; then its runs (pixels whose 4 x 4 taps are inside the image, in the same rows,
    one column further each pixel: nearly every pixel of a small turn), each channel's sums by ``_run_taps``; the other
    pixels one by one, with the border's mirroring. Each value as ``_resample_point``'s."""
    K, H, W = coef.shape
    xs, ys = np.empty(w), np.empty(w)
    wt = np.empty((8, w))  # each pixel's wx0..wx3, wy0..wy3
    x0s, y0s = np.empty(w, np.int64), np.empty(w, np.int64)
    inner = np.empty(w, np.bool_)
    sums = np.zeros((K, w))  # (a pixel outside every run keeps an earlier, finite sum: rounded, then overwritten)
    m00, m01, m02 = M[0, 0], M[0, 1], M[0, 2]
    m10, m11, m12 = M[1, 0], M[1, 1], M[1, 2]
    m20, m21, m22 = M[2, 0], M[2, 1], M[2, 2]
    for v in range(h):
        y = float(v)
        for u in range(w):
            x = float(u)
            d = m20 * x + m21 * y + m22
            px = (m00 * x + m01 * y + m02) / d
            py = (m10 * x + m11 * y + m12) / d
            xs[u], ys[u] = px, py
            wt[0, u], wt[1, u], wt[2, u], wt[3, u] = _weights(px)
            wt[4, u], wt[5, u], wt[6, u], wt[7, u] = _weights(py)
        for u in range(w):
            px, py = xs[u], ys[u]
            inside = px >= 0.0 and px <= W - 1 and py >= 0.0 and py <= H - 1
            x0 = int(math.floor(px)) - 1 if inside else -1
            y0 = int(math.floor(py)) - 1 if inside else -1
            inner[u] = inside and 0 <= x0 and x0 + 3 < W and 0 <= y0 and y0 + 3 < H
            x0s[u], y0s[u] = x0, y0
        u = 0
        while u < w:
            if not inner[u]:
                u += 1
                continue
            e = u + 1
            while e < w and inner[e] and y0s[e] == y0s[u] and x0s[e] == x0s[u] + (e - u):
                e += 1
            n = e - u
            x0, y0 = x0s[u], y0s[u]
            for k in range(K):
                c = coef[k]
                _run_taps(c[y0, x0:x0 + n + 3], c[y0 + 1, x0:x0 + n + 3], c[y0 + 2, x0:x0 + n + 3],
                          c[y0 + 3, x0:x0 + n + 3], wt[0, u:e], wt[1, u:e], wt[2, u:e], wt[3, u:e], wt[4, u:e],
                          wt[5, u:e], wt[6, u:e], wt[7, u:e], sums[k, u:e])
            u = e
        p0 = v * w
        for k in range(K):  # every pixel as if in a run (no branch: the compiler vectorises it) ...
            for u in range(w):
                out[p0 + u, k] = _rounded(sums[k, u], top)
        for u in range(w):  # ... then the others
            if inner[u]:
                continue
            p = p0 + u
            px, py = xs[u], ys[u]
            if not (px >= 0.0 and px <= W - 1 and py >= 0.0 and py <= H - 1):
                for k in range(K):
                    out[p, k] = 0
                continue
            xs4, ys4, _, _ = _stencil(H, W, px, py)
            wx4 = (wt[0, u], wt[1, u], wt[2, u], wt[3, u])
            wy4 = (wt[4, u], wt[5, u], wt[6, u], wt[7, u])
            for k in range(K):  # (a plane as (H, W, 1): C-order indexing, 3 s less to compile than a transpose)
                out[p, k] = _rounded(_sum_taps(coef[k].reshape(H, W, 1), 0, xs4, ys4, wx4, wy4), top)


def sample(coef: np.ndarray, us: np.ndarray, vs: np.ndarray) -> np.ndarray:
    """(N, K) float64: the spline whose coefficients are ``coef`` (``coefficients``: (H, W, K)) at the points
    ``(us, vs)`` (N,); points beyond the image mirrored into it. SciPy's ``map_coordinates(c, [vs, us], order=3,
    prefilter=False, mode="mirror")`` of each channel's coefficients ``c``, to the last bit."""
    out = np.empty((len(us), coef.shape[2]))
    _samples(coef, np.ascontiguousarray(us, np.float64), np.ascontiguousarray(vs, np.float64), out)
    return out


def _checked(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"resample: expected an 8- or 16-bit image, got {img.dtype}")
    return img


def resample_homography(image: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``resample`` at ``M`` (3x3) times every pixel of an image of ``image``'s size: the same pixels as ``resample``
    of ``apply_homography(M, u, v)`` over the pixel grid (float64, row-major), without the grid's arrays."""
    img = _checked(image)
    h, w = img.shape[:2]
    k = 1 if img.ndim == 2 else img.shape[2]
    out = np.empty((h, w, k), img.dtype)
    _resample_homography(_planar_coefficients(img), np.ascontiguousarray(M, np.float64), h, w,
                         float(np.iinfo(img.dtype).max), out.reshape(-1, k))
    return out[..., 0] if img.ndim == 2 else out


def resample(image: np.ndarray, us: np.ndarray, vs: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    """An ``out_hw`` image of ``image``'s type (8- or 16-bit, grey or with channels) whose pixels (row-major) are
    ``image`` sampled at ``(us, vs)`` (flat float64, one per output pixel): cubic B-spline at the exact positions,
    rounded half to even and clipped to the type's range, black where a position is outside ``image``. The same
    pixels as SciPy's ``map_coordinates`` of ``spline_filter``'s coefficients, then ``np.round`` and ``np.clip``."""
    img = _checked(image)
    k = 1 if img.ndim == 2 else img.shape[2]
    out = np.empty((*out_hw, k), img.dtype)
    _resample(coefficients(img), np.ascontiguousarray(us, np.float64), np.ascontiguousarray(vs, np.float64),
              float(np.iinfo(img.dtype).max), out.reshape(-1, k))
    return out[..., 0] if img.ndim == 2 else out
