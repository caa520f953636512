"""Reprojection core: structured-light depth -> rectified ZED-left depth with a z-buffer.

``splat``: every depth sample to its nearest pixel (rounded, never truncated), nearest wins.
``mesh`` (default): two triangles per 2x2 quad of the organised depth grid; a triangle whose edges
span a depth jump steeper than ``max_slant_deg`` is rejected; the rest are rasterised at pixel
centres with a z-buffer, interpolating 1/Z (exact for planar surfaces). Pixels no valid triangle
covers stay NaN, so nothing is invented across occlusions or shadows.

How the mesh rasteriser is fast (benchmarks/RESULTS.md): the grid is denser than the target pixels, so
almost every quad holds at most one pixel centre. Each pair of grid rows is projected and then every
quad of the pair is evaluated in one branch-free loop that the compiler vectorises (edge continuity,
diagonal choice, the quad's pixel centre, which triangle holds it, its depth); only the quads that hit
a pixel reach the scalar z-buffer update, and the rare quad whose box holds several pixel centres goes
through the general triangle loop. With several numba threads the grid rows are cut into chunks, each
rasterised into its own window of target rows (the rows its points reach, from a first projection
pass) and the windows are merged by a per-pixel minimum: no full-size buffer per thread, no locks, and
chunks are handed out dynamically so a thread on a busy core takes fewer. The result does not depend
on the number of threads (the minimum is order-free). With two threads (2 cores) a mesh or a splat is drawn in
two halves of the grid's rows instead, one straight into the image, the other into a second buffer whose rows it
reaches are merged into the image afterwards: no first pass for the rows each part reaches, which on 2 cores cost the
windowed path more than the second thread gave.

Over 500 lines on purpose: the kernels and their hand-inlined copies of ``_pixel`` stay side by side so that they
change together (tests/core/test_reproject_reference.py pins every path to the float64 reference).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np

# numba: prefer OpenMP (TBB builds on Debian are often too old and only produce a warning)
numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]

from gtforge.core.camera import PinholeCamera, RectifiedStereo
from gtforge.core.geometry import finite_box
from gtforge.core.numba_threads import usable_threads

Mode = Literal["mesh", "splat"]

# error_model="numpy": a float division by zero gives inf/NaN instead of a Python exception check, which
# would keep the compiler from vectorising the row loops.
_JIT = {"cache": True, "error_model": "numpy"}
_EPS = 1e-9  # pixel-centre tolerance (px): a centre on a triangle's edge belongs to it
# Below this many numba threads the windowed path is not used: it adds a second projection pass, the windows and the
# merge, and each parallel region waits for the thread that shares a busy core, so on 2 cores it lost more than it
# gained (benchmarks/RESULTS.md, "Figures from code comments").
MIN_PARALLEL_THREADS = 3
# From this many threads (and below MIN_PARALLEL_THREADS) a mesh or a splat is drawn by two threads, each drawing half
# the grid's rows (``_mesh_halves``, ``_splat_halves``): on 2 cores faster than one thread (benchmarks/RESULTS.md,
# issue 39, rounds 18 and 19).
HALVES_MIN_THREADS = 2


@functools.lru_cache(maxsize=4)
def _ray_planes(cam_json: str) -> tuple[np.ndarray, np.ndarray]:
    """The camera's ray grid (normalised x, y of every pixel centre) as two contiguous float64 planes.

    Not float32: its rounding (3e-8, 3e-5 px in the target image) is far above the pixel-centre tolerance ``_EPS``,
    so a centre lying on a triangle's edge (every centre of a row, where the target shares the depth camera's rows,
    as in a rectified pair) falls outside both triangles beside a rejected one. On Middlebury 2014 Motorcycle that
    cost 1.4 % more holes and 0.02 px EPE (tests/core/test_real_reprojection.py) at no measurable gain in speed."""
    rx, ry = PinholeCamera.model_validate_json(cam_json).ray_planes()
    return rx, ry


def prepare_rays(depth_cam: PinholeCamera) -> None:
    """Compute and keep (per process) the ray grid that reprojecting ``depth_cam``'s depth uses: 0.3-0.6 CPU s at
    1920x1200 with a lens model (its undistortion: ``lens.undistort``). The local pool's fork server calls it before it
    forks the build workers, which then share it instead of each computing it for its first scene."""
    _ray_planes(depth_cam.model_dump_json())


# ---- projection ------------------------------------------------------------------------------
@numba.njit(inline="always", **_JIT)
def _project_point(depth, rx, ry, R, t, fx, fy, cx, cy, r, c):
    """Grid point ``(r, c)`` in the target camera: ``(u, v, Z, 1/Z, ok)``, ``ok`` False where the depth is invalid
    (NaN, <= 0, inf) or the point is not in front of the camera. Branch-free, so that a loop over a row vectorises.
    The mesh's rows (``_project_row``) and the splat's (``_splat_row``) both project with it: the same bits."""
    z = np.float64(depth[r, c])
    x = rx[r, c] * z
    y = ry[r, c] * z
    Zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
    inv = 1.0 / Zc
    u = fx * (R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]) * inv + cx
    v = fy * (R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]) * inv + cy
    ok = (z > 0.0) & (z < np.inf) & (Zc > 0.0)
    return u, v, Zc, inv, ok


@numba.njit(inline="always", **_JIT)
def _project_row(depth, rx, ry, R, t, fx, fy, cx, cy, r, U, V, IZ):
    """Project grid row ``r`` into the target camera: ``U``, ``V`` (px) and ``IZ`` = 1/Z (1/mm), with
    ``IZ`` = 0 where the depth is invalid (NaN, <= 0, inf) or the point is not in front of the camera.
    Branch-free so that it vectorises."""
    for c in range(depth.shape[1]):
        u, v, _, inv, ok = _project_point(depth, rx, ry, R, t, fx, fy, cx, cy, r, c)
        U[c] = u
        V[c] = v
        IZ[c] = inv if ok else 0.0


@numba.njit(inline="always", **_JIT)
def _project_row_stereo(depth, rx, ry, R, t, t_r0, fx, fy, cx, cy, cx_r, r, U, V, IZ, Ur):
    """``_project_row`` into two cameras that differ only by the x translation (``t_r0`` instead of ``t[0]``) and cx
    (``cx_r``): the left view's ``U``, ``V``, ``IZ`` and the right view's ``Ur``, each the same expression as
    ``_project_row``'s, so the same bits; the right view's V and 1/Z are the left's (the same expressions as well).
    One division a point for both views."""
    for c in range(depth.shape[1]):
        z = np.float64(depth[r, c])
        x = rx[r, c] * z
        y = ry[r, c] * z
        Zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
        inv = 1.0 / Zc
        X = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z
        U[c] = fx * (X + t[0]) * inv + cx
        Ur[c] = fx * (X + t_r0) * inv + cx_r
        V[c] = fy * (R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]) * inv + cy
        ok = (z > 0.0) & (z < np.inf) & (Zc > 0.0)
        IZ[c] = inv if ok else 0.0


@numba.njit(**_JIT)
def _v_range(depth, rx, ry, R, t, fy, cy, r0, r1):
    """Smallest and largest target ``v`` of the valid points of grid rows ``r0 <= r < r1`` (inf, -inf if
    none); the same arithmetic as ``_project_row``."""
    a = np.inf
    b = -np.inf
    for r in range(r0, r1):
        for c in range(depth.shape[1]):
            z = np.float64(depth[r, c])
            x = rx[r, c] * z
            y = ry[r, c] * z
            Zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
            v = fy * (R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]) * (1.0 / Zc) + cy
            ok = (z > 0.0) & (z < np.inf) & (Zc > 0.0)
            a = min(a, v if ok else np.inf)
            b = max(b, v if ok else -np.inf)
    return a, b


# ---- splat -----------------------------------------------------------------------------------
@numba.njit(inline="always", **_JIT)
def _splat_row(depth, rx, ry, R, t, fx, fy, cx, cy, r, y_off, Wf, Hf, U, V, Z, Zf, idx):
    """Grid row ``r``'s points: ``idx`` each one's index in a buffer of ``Hf`` rows of ``Wf`` pixels holding target
    rows ``y_off ..`` (nearest pixel, rounded, never truncated; -1: none) and ``Zf`` its depth; ``U``, ``V``,
    ``Z``: work rows.
    Two passes, each one simple enough to vectorise well: the projection (as _project_row, Z <= 0 marks an invalid
    point) and the rounding to a pixel index. One loop doing both took 9.2 CPU ms at full resolution against 4.5 + 1.2
    for the two (benchmarks/RESULTS.md, "Where the kernels' time goes"); the values are the same float64 expressions,
    so the same bits."""
    for c in range(depth.shape[1]):
        u, v, Zc, _, ok = _project_point(depth, rx, ry, R, t, fx, fy, cx, cy, r, c)
        U[c] = u
        V[c] = v
        Z[c] = Zc if ok else -1.0
    for c in range(depth.shape[1]):
        ui = np.floor(U[c] + 0.5)
        vi = np.floor(V[c] + 0.5) - y_off
        ok = (Z[c] > 0.0) & (ui >= 0.0) & (ui < Wf) & (vi >= 0.0) & (vi < Hf)
        idx[c] = np.int64(vi * Wf + ui) if ok else -1
        Zf[c] = np.float32(Z[c])


@numba.njit(inline="always", **_JIT)
def _splat_zbuffer(flat, idx, Zf):
    """The scalar z-buffer update of one grid row's points (``_splat_row``) into the flattened buffer: nearest wins,
    the earlier point on a tie."""
    for c in range(idx.shape[0]):
        i = idx[c]
        if i >= 0:
            zf = Zf[c]
            old = flat[i]
            flat[i] = old if old <= zf else zf  # empty (NaN) or farther: replaced


@numba.njit(inline="always", **_JIT)
def _splat_work_rows(Wm):
    """The splat kernels' work rows for a grid ``Wm`` points wide: ``U``, ``V``, ``Z``, ``Zf``, ``idx``
    (``_splat_row``); each written before it is read."""
    return np.empty(Wm), np.empty(Wm), np.empty(Wm), np.empty(Wm, np.float32), np.empty(Wm, np.int64)


@numba.njit(**_JIT)
def _splat_rows(buf, y_off, depth, rx, ry, R, t, fx, fy, cx, cy, r0, r1):
    """Splat grid rows ``r0 <= r < r1`` into ``buf`` (holds target rows ``y_off ..``; its contents are ignored: every
    row is set to NaN = empty before the first point lands on it, which it then does while in cache):
    nearest pixel (rounded, never truncated), nearest depth wins."""
    Hb, W = buf.shape
    U, V, Z, Zf, idx = _splat_work_rows(depth.shape[1])
    flat = buf.reshape(-1)
    Wf, Hf = np.float64(W), np.float64(Hb)
    filled = 0  # rows buf[:filled] are initialised
    for r in range(r0, r1):
        _splat_row(depth, rx, ry, R, t, fx, fy, cx, cy, r, y_off, Wf, Hf, U, V, Z, Zf, idx)
        last = -1
        for c in range(idx.shape[0]):
            last = max(last, idx[c])
        if last >= 0 and last // W >= filled:
            buf[filled:last // W + 1] = np.nan
            filled = last // W + 1
        _splat_zbuffer(flat, idx, Zf)
    buf[filled:] = np.nan


@numba.njit(**_JIT)
def _splat_rows_window(buf, window, depth, rx, ry, R, t, fx, fy, cx, cy, r0, r1):
    """``_splat_rows`` of grid rows ``r0..r1`` into the image-sized ``buf`` with only the target rows its points reach
    initialised (to NaN), as they are reached, upwards or downwards; ``window`` gets those rows' range ``[lo, hi)``
    (``lo == hi``: none). Its other rows are left as they were."""
    H, W = buf.shape
    U, V, Z, Zf, idx = _splat_work_rows(depth.shape[1])
    flat = buf.reshape(-1)
    Wf, Hf = np.float64(W), np.float64(H)
    none = np.int64(H) * W
    lo = hi = 0
    for r in range(r0, r1):
        _splat_row(depth, rx, ry, R, t, fx, fy, cx, cy, r, 0, Wf, Hf, U, V, Z, Zf, idx)
        first = none
        last = np.int64(-1)
        for c in range(idx.shape[0]):
            first = min(first, idx[c] if idx[c] >= 0 else none)
            last = max(last, idx[c])
        if last >= 0:
            want_lo, want_hi = first // W, last // W + 1
            if lo == hi:
                lo = hi = want_lo
            if want_lo < lo:
                buf[want_lo:lo] = np.nan
                lo = want_lo
            if want_hi > hi:
                buf[hi:want_hi] = np.nan
                hi = want_hi
        _splat_zbuffer(flat, idx, Zf)
    window[0], window[1] = lo, hi


@numba.njit(parallel=True, **_JIT)
def _splat_halves(out, aux, window, depth, rx, ry, R, t, fx, fy, cx, cy, mid):
    """Two threads: grid rows ``0..mid`` splatted straight into ``out``, rows ``mid..`` into the rows of ``aux`` they
    reach (``window``), to be merged into ``out`` by ``_merge_window`` (``out``'s on a tie: the point a one-thread splat
    meets first). The same image as ``_splat_rows`` over the whole grid."""
    for k in numba.prange(2):
        if k == 0:
            _splat_rows(out, 0, depth, rx, ry, R, t, fx, fy, cx, cy, 0, mid)
        else:
            _splat_rows_window(aux, window, depth, rx, ry, R, t, fx, fy, cx, cy, mid, depth.shape[0])


# ---- mesh ------------------------------------------------------------------------------------
@numba.njit(inline="always", **_JIT)
def _edge_ok(za, zb, k, abs_tol):
    """Continuity of a grid edge between depth-camera depths ``za``, ``zb``: the jump is at most what a surface
    at ``max_slant_deg`` spans over the edge (``k`` = tan(max_slant) * edge length / (2 f)), plus ``abs_tol``."""
    return abs(za - zb) <= (za + zb) * k + abs_tol


@numba.njit(inline="always", **_JIT)
def _pixel(buf, sbuf, want_span, y_off, px, py, up, vp, wp, uq, vq, wq, dqu, dqv, u1, v1, w1, a1, ok1,
           u2, v2, w2, a2, ok2):
    """Pixel centre (px, py) against the triangles (r1, p, q) and (r2, p, q) sharing the diagonal p-q."""
    er = dqu * (py - vp) - dqv * (px - up)  # apex weight x area: the side of the diagonal
    use1 = ok1 & ((er * a1 >= 0.0) | ~ok2)  # the triangle on the centre's side (else the other one)
    ur = u1 if use1 else u2
    vr = v1 if use1 else v2
    wr = w1 if use1 else w2
    a = a1 if use1 else a2
    s = 1.0 if a > 0.0 else -1.0
    tol = -_EPS * abs(a)
    eq = (up - ur) * (py - vr) - (vp - vr) * (px - ur)
    ep = a - er - eq
    zf = np.float32(a / (er * wr + eq * wq + ep * wp))  # 1 / (interpolated 1/Z)
    b = py - y_off
    if (ok1 | ok2) & (s * er >= tol) & (s * eq >= tol) & (s * ep >= tol) & (zf > 0.0) & ~(buf[b, px] <= zf):
        buf[b, px] = zf
        if want_span:
            sbuf[b, px] = 1.0 / min(wr, wp, wq) - 1.0 / max(wr, wp, wq)


@numba.njit(**_JIT)
def _quad_general(buf, sbuf, want_span, y_off, y_lo, y_hi, up, vp, wp, uq, vq, wq, u1, v1, w1, ok1,
                  u2, v2, w2, ok2):
    """Every pixel centre in the box of the triangles (r1, p, q) (if ok1) and (r2, p, q) (if ok2)."""
    W = buf.shape[1]
    lo_u = min(min(up, uq), min(u1 if ok1 else np.inf, u2 if ok2 else np.inf))
    hi_u = max(max(up, uq), max(u1 if ok1 else -np.inf, u2 if ok2 else -np.inf))
    lo_v = min(min(vp, vq), min(v1 if ok1 else np.inf, v2 if ok2 else np.inf))
    hi_v = max(max(vp, vq), max(v1 if ok1 else -np.inf, v2 if ok2 else -np.inf))
    umin = max(math.ceil(lo_u - _EPS), 0)
    umax = min(math.floor(hi_u + _EPS), W - 1)
    vmin = max(math.ceil(lo_v - _EPS), y_lo)
    vmax = min(math.floor(hi_v + _EPS), y_hi)
    dqu, dqv = uq - up, vq - vp
    a1 = dqu * (v1 - vp) - dqv * (u1 - up)  # twice the signed area of (p, q, r1)
    a2 = dqu * (v2 - vp) - dqv * (u2 - up)
    ok1 = ok1 & (abs(a1) >= 1e-12)
    ok2 = ok2 & (abs(a2) >= 1e-12)
    for py in range(vmin, vmax + 1):
        for px in range(umin, umax + 1):
            _pixel(buf, sbuf, want_span, y_off, px, py, up, vp, wp, uq, vq, wq, dqu, dqv, u1, v1, w1, a1, ok1,
                   u2, v2, w2, a2, ok2)


@numba.njit(**_JIT)
def _quad_flags(zt, zbr, Wt, Wb, k1, k2, abs_tol, F):
    """Which triangles of each quad ``a b / c d`` between two grid rows are drawn, from the depth-camera depths
    (``zt``, ``zbr``) and the corners' validity (``Wt``, ``Wb`` = 1/Z, 0 where invalid): ``F[c]`` bit 0 the first
    triangle, bit 1 the second, bit 2 the split along a-d, bit 3 all four corners valid. The same for every target
    camera with the same z axis (the rectified ZED's two views): computed once for both (``_mesh_rows_stereo``).
    Branch-free so that it vectorises."""
    for c in range(zt.shape[0] - 1):
        za, zb, zc, zd = np.float64(zt[c]), np.float64(zt[c + 1]), np.float64(zbr[c]), np.float64(zbr[c + 1])
        fa, fb, fc, fd = Wt[c] > 0.0, Wt[c + 1] > 0.0, Wb[c] > 0.0, Wb[c + 1] > 0.0
        e_ab, e_cd = _edge_ok(za, zb, k1, abs_tol), _edge_ok(zc, zd, k1, abs_tol)
        e_ac, e_bd = _edge_ok(za, zc, k1, abs_tol), _edge_ok(zb, zd, k1, abs_tol)
        # split along the diagonal with the smaller depth change: a-d gives (b, a, d) and (c, a, d),
        # b-c gives (a, b, c) and (d, b, c); a triangle is drawn when none of its edges is a jump
        ad = fa & fd & (~(fb & fc) | (abs(za - zd) <= abs(zb - zc)))
        e_ad, e_bc = _edge_ok(za, zd, k2, abs_tol), _edge_ok(zb, zc, k2, abs_tol)
        t1 = (ad & e_ad & fb & e_ab & e_bd) | (~ad & fb & fc & e_bc & fa & e_ab & e_ac)
        t2 = (ad & e_ad & fc & e_ac & e_cd) | (~ad & fb & fc & e_bc & fd & e_bd & e_cd)
        all4 = fa & fb & fc & fd
        F[c] = np.uint8(t1) | (np.uint8(t2) << 1) | (np.uint8(ad) << 2) | (np.uint8(all4) << 3)


@numba.njit(**_JIT)
def _raster_quads(buf, sbuf, want_span, y_off, y_lo, y_hi, Ut, Vt, Wt, Ub, Vb, Wb, F, Q, S, cand):
    """Rasterise the quads between two projected grid rows (``_project_row``'s U, V, 1/Z of the top and bottom row)
    whose triangles ``F`` (``_quad_flags``) says are drawn, into target rows ``y_lo..y_hi`` of ``buf`` (row ``y``
    stored at ``y - y_off``; NaN = empty); ``sbuf`` (when ``want_span``): the winning triangle's vertex Z range (mm).
    ``Q``, ``S``, ``cand``: work rows."""
    W = buf.shape[1]
    ylo, yhi, umax_f = np.float64(y_lo), np.float64(y_hi), W - 1.0
    Wm = Ut.shape[0]
    # every quad at once (vectorised: no branches, no bool arrays)
    for c in range(Wm - 1):
        fl = F[c]
        t1, t2, ad, all4 = (fl & 1) != 0, (fl & 2) != 0, (fl & 4) != 0, (fl & 8) != 0
        ua, ub, uc, ud = Ut[c], Ut[c + 1], Ub[c], Ub[c + 1]
        va, vb, vc, vd = Vt[c], Vt[c + 1], Vb[c], Vb[c + 1]
        wa, wb, wc, wd = Wt[c], Wt[c + 1], Wb[c], Wb[c + 1]
        px = np.ceil(min(min(ua, ub), min(uc, ud)) - _EPS)
        py = np.ceil(min(min(va, vb), min(vc, vd)) - _EPS)
        nu = np.floor(max(max(ua, ub), max(uc, ud)) + _EPS) - px  # pixel centres in the box, minus one
        nv = np.floor(max(max(va, vb), max(vc, vd)) + _EPS) - py
        single = (nu == 0.0) & (nv == 0.0) & (px >= 0.0) & (px <= umax_f) & (py >= ylo) & (py <= yhi)
        up, vp, wp = (ua, va, wa) if ad else (ub, vb, wb)  # diagonal p-q, apexes r1 (of t1) and r2
        uq, vq, wq = (ud, vd, wd) if ad else (uc, vc, wc)
        u1, v1, w1 = (ub, vb, wb) if ad else (ua, va, wa)
        u2, v2, w2 = (uc, vc, wc) if ad else (ud, vd, wd)
        dqu, dqv = uq - up, vq - vp
        a1 = dqu * (v1 - vp) - dqv * (u1 - up)
        a2 = dqu * (v2 - vp) - dqv * (u2 - up)
        ok1 = t1 & (abs(a1) >= 1e-12)
        ok2 = t2 & (abs(a2) >= 1e-12)
        # _pixel's test, written out: an inlined helper shared with it was slower (benchmarks/RESULTS.md)
        er = dqu * (py - vp) - dqv * (px - up)
        use1 = ok1 & ((er * a1 >= 0.0) | ~ok2)
        ur = u1 if use1 else u2
        vr = v1 if use1 else v2
        wr = w1 if use1 else w2
        a = a1 if use1 else a2
        s = 1.0 if a > 0.0 else -1.0
        tol = -_EPS * abs(a)
        eq = (up - ur) * (py - vr) - (vp - vr) * (px - ur)
        ep = a - er - eq
        z = a / (er * wr + eq * wq + ep * wp)
        hit = single & (ok1 | ok2) & (s * er >= tol) & (s * eq >= tol) & (s * ep >= tol) & (z > 0.0)
        general = (t1 | t2) & ((all4 & ~single & (nu >= 0.0) & (nv >= 0.0)) | ~all4)
        Q[0, c] = 1.0 if hit else (2.0 if general else 0.0)
        Q[1, c] = (py - y_off) * W + px  # a hit's index in buf, flattened (exact in float64)
        Q[2, c] = z
        if want_span:
            S[c] = 1.0 / min(min(wr, wp), wq) - 1.0 / max(max(wr, wp), wq)
    flat, sflat = buf.reshape(-1), sbuf.reshape(-1)
    n = 0
    for c in range(Wm - 1):  # compact the quads with work (branch-free)
        cand[n] = c
        n += Q[0, c] != 0.0
    for i in range(n):
        c = np.uint64(cand[i])  # unsigned indices (never negative here) need no wraparound test
        if Q[0, c] == 1.0:
            j = np.uint64(Q[1, c])
            zf = np.float32(Q[2, c])
            old = flat[j]
            keep = old <= zf  # else empty (NaN) or farther: replaced
            flat[j] = old if keep else zf
            if want_span:
                sflat[j] = sflat[j] if keep else S[c]
        else:  # several pixel centres in the box, or a quad with three valid corners
            fl = F[c]
            ad, c1 = (fl & 4) != 0, c + np.uint64(1)
            _quad_general(buf, sbuf, want_span, y_off, y_lo, y_hi,
                          Ut[c] if ad else Ut[c1], Vt[c] if ad else Vt[c1], Wt[c] if ad else Wt[c1],
                          Ub[c1] if ad else Ub[c], Vb[c1] if ad else Vb[c], Wb[c1] if ad else Wb[c],
                          Ut[c1] if ad else Ut[c], Vt[c1] if ad else Vt[c], Wt[c1] if ad else Wt[c], (fl & 1) != 0,
                          Ub[c] if ad else Ub[c1], Vb[c] if ad else Vb[c1], Wb[c] if ad else Wb[c1], (fl & 2) != 0)


@numba.njit(**_JIT)
def _rows_reached(V, IZ):
    """An end (exclusive) for the target rows that the triangles of a projected grid row (``_project_row``'s V, 1/Z)
    can touch: beyond its valid points' largest v, with a margin for the pixel-centre tolerance (0 if none).
    Vectorised: an integer maximum (a float one would be a serial chain without fastmath)."""
    m = np.int64(-1)
    for c in range(V.shape[0]):
        v = min(V[c] if IZ[c] > 0.0 else -1.0, 1e9)  # finite where valid; clipped so that the conversion is defined
        m = max(m, np.int64(v))
    return m + 3


@numba.njit(**_JIT)
def _init_rows(buf, sbuf, want_span, filled, end):
    """Set rows ``filled..end`` of ``buf`` (and ``sbuf``) to NaN = empty, just before triangles may reach them (while
    they are then in cache, instead of a full-image fill beforehand); returns the new end of the initialised rows."""
    end = min(end, buf.shape[0])
    if end > filled:
        buf[filled:end] = np.nan
        if want_span:
            sbuf[filled:end] = np.nan
        return end
    return filled


@numba.njit(inline="always", **_JIT)
def _mesh_work_rows(Wm):
    """The mesh kernels' work rows for a grid ``Wm`` points wide: ``P`` two row slots of u, v, 1/Z; per quad ``Q`` its
    code (0 nothing, 1 one pixel hit, 2 general), the hit's index and depth, ``S`` the hit triangle's span, ``F`` its
    triangles (``_quad_flags``); ``cand`` the compacted quads. ``S`` is zeroed, not np.empty: ``_raster_quads`` stores
    into it with an AVX-512 masked store whose mask is empty without span_mm, and such a store to a page this process
    or thread has not written (a thread's fresh malloc arena, a page shared copy-on-write with the fork server) takes a
    microcode assist every time: 2.7x the time of the whole call (benchmarks/RESULTS.md, "The masked store")."""
    return (np.empty((2, 3, Wm)), np.empty((3, Wm)), np.zeros(Wm), np.empty(Wm, np.uint8),
            np.empty(Wm, np.int64))


@numba.njit(**_JIT)
def _mesh_rows(buf, sbuf, want_span, y_off, y_lo, y_hi, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2, abs_tol,
               r0, r1):
    """Triangles of the quads between grid rows ``r`` and ``r + 1`` for ``r0 <= r < r1``, rasterised into
    target rows ``y_lo..y_hi`` of ``buf`` (row ``y`` stored at ``y - y_off``; NaN = empty; its contents on entry are
    ignored: ``_init_rows``). ``sbuf`` (when ``want_span``): the winning triangle's vertex Z range (mm)."""
    Wm = depth.shape[1]
    P, Q, S, F, cand = _mesh_work_rows(Wm)
    _project_row(depth, rx, ry, R, t, fx, fy, cx, cy, r0, P[0, 0], P[0, 1], P[0, 2])
    filled = 0
    top = _rows_reached(P[0, 1], P[0, 2])
    for r in range(r0, r1):
        a_ = (r - r0) & 1
        b_ = 1 - a_
        _project_row(depth, rx, ry, R, t, fx, fy, cx, cy, r + 1, P[b_, 0], P[b_, 1], P[b_, 2])
        bottom = _rows_reached(P[b_, 1], P[b_, 2])
        filled = _init_rows(buf, sbuf, want_span, filled, max(top, bottom) - y_off)
        top = bottom
        _quad_flags(depth[r], depth[r + 1], P[a_, 2], P[b_, 2], k1, k2, abs_tol, F)
        _raster_quads(buf, sbuf, want_span, y_off, y_lo, y_hi, P[a_, 0], P[a_, 1], P[a_, 2], P[b_, 0], P[b_, 1],
                      P[b_, 2], F, Q, S, cand)
    _init_rows(buf, sbuf, want_span, filled, buf.shape[0])


@numba.njit(**_JIT)
def _rows_from(V, IZ):
    """A start (inclusive) for the target rows that the triangles of a projected grid row can touch: before its valid
    points' smallest v, with ``_rows_reached``'s margin (a huge value if none). Vectorised, as ``_rows_reached``."""
    m = np.int64(4_000_000_000_000_000_000)
    for c in range(V.shape[0]):
        v = max(V[c] if IZ[c] > 0.0 else 4e18, -1e9)  # finite where valid; clipped so that the conversion is defined
        m = min(m, np.int64(v))
    return m - 2


@numba.njit(**_JIT)
def _mesh_rows_window(buf, sbuf, want_span, window, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2, abs_tol, r0, r1):
    """``_mesh_rows`` of grid rows ``r0..r1`` into the image-sized ``buf`` (and ``sbuf``) with only the target rows its
    triangles may reach initialised (to NaN), as they are reached; ``window`` gets those rows' range ``[lo, hi)``
    (``lo == hi``: none). Its other rows are left as they were (``np.empty``'s pages never touched)."""
    Wm = depth.shape[1]
    H = buf.shape[0]
    P, Q, S, F, cand = _mesh_work_rows(Wm)
    _project_row(depth, rx, ry, R, t, fx, fy, cx, cy, r0, P[0, 0], P[0, 1], P[0, 2])
    lo = hi = 0
    top_lo, top_hi = _rows_from(P[0, 1], P[0, 2]), _rows_reached(P[0, 1], P[0, 2])
    for r in range(r0, r1):
        a_ = (r - r0) & 1
        b_ = 1 - a_
        _project_row(depth, rx, ry, R, t, fx, fy, cx, cy, r + 1, P[b_, 0], P[b_, 1], P[b_, 2])
        bot_lo, bot_hi = _rows_from(P[b_, 1], P[b_, 2]), _rows_reached(P[b_, 1], P[b_, 2])
        want_lo, want_hi = max(min(top_lo, bot_lo), 0), min(max(top_hi, bot_hi), H)
        top_lo, top_hi = bot_lo, bot_hi
        if want_lo < want_hi:
            if lo == hi:
                lo = hi = want_lo
            if want_lo < lo:
                _init_rows(buf, sbuf, want_span, want_lo, lo)
                lo = want_lo
            hi = _init_rows(buf, sbuf, want_span, hi, want_hi)
        _quad_flags(depth[r], depth[r + 1], P[a_, 2], P[b_, 2], k1, k2, abs_tol, F)
        _raster_quads(buf, sbuf, want_span, 0, lo, hi - 1, P[a_, 0], P[a_, 1], P[a_, 2], P[b_, 0], P[b_, 1],
                      P[b_, 2], F, Q, S, cand)
    window[0], window[1] = lo, hi


@numba.njit(parallel=True, **_JIT)
def _mesh_halves(out, sout, aux, saux, want_span, window, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2, abs_tol, mid):
    """Two threads: the quads of grid rows ``0..mid`` straight into ``out`` (``sout``), those of ``mid..`` into the
    rows of ``aux`` (``saux``) they reach, then merged into ``out`` by a per-pixel minimum, ``out``'s on a tie: the
    quad a thread raster of the whole grid meets first. No first pass over the grid for the rows each half reaches
    (the windowed path's ``_v_range``), and one extra buffer; the same image and span as ``_mesh_rows``."""
    H = out.shape[0]
    Hm = depth.shape[0]
    for k in numba.prange(2):
        if k == 0:
            _mesh_rows(out, sout, want_span, 0, 0, H - 1, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2, abs_tol, 0,
                       mid)
        else:
            _mesh_rows_window(aux, saux, want_span, window, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2, abs_tol,
                              mid, Hm - 1)


@numba.njit(inline="always", **_JIT)
def _nearer(z, o):
    """Whether depth ``z`` wins a merge against ``o`` (NaN = empty): nearer, or ``o`` empty and ``z`` not; a tie keeps
    ``o``. Branch-free so that the merges' pixel loops vectorise."""
    return (z < o) | (np.isnan(o) & ~np.isnan(z))


@numba.njit(parallel=True, **_JIT)
def _merge_window(out, sout, aux, saux, want_span, lo, hi):
    """Rows ``lo..hi`` of ``aux`` (``saux``) merged into ``out`` (``sout``): a per-pixel minimum, ``out``'s on a tie."""
    W = out.shape[1]
    for y in numba.prange(lo, hi):
        if want_span:  # (outside the pixel loop: inside, it compiled to a masked store, slow on unwritten pages)
            for u in range(W):
                z = aux[y, u]
                o = out[y, u]
                take = _nearer(z, o)
                out[y, u] = z if take else o
                sout[y, u] = saux[y, u] if take else sout[y, u]
        else:
            for u in range(W):
                z = aux[y, u]
                o = out[y, u]
                out[y, u] = z if _nearer(z, o) else o


@numba.njit(**_JIT)
def _mesh_rows_stereo(buf, sbuf, want_span, buf_r, depth, rx, ry, R, t, fx, fy, cx, cy, t_r, cx_r, k1, k2, abs_tol):
    """``_mesh_rows`` over the whole grid into two cameras that differ only by a translation along x and their cx
    (the rectified ZED's left, ``buf``/``sbuf``, and right, ``buf_r``, no span): their 1/Z is the same, so is which
    triangles are drawn (``_quad_flags``, computed once for both). The same images as two ``_mesh_rows`` calls."""
    Hm, Wm = depth.shape
    H = buf.shape[0]
    P, Q, S, F, cand = _mesh_work_rows(Wm)
    Ur = np.empty((2, Wm))  # the right view's u (its v and 1/Z are P's)
    _project_row_stereo(depth, rx, ry, R, t, t_r[0], fx, fy, cx, cy, cx_r, 0, P[0, 0], P[0, 1], P[0, 2], Ur[0])
    # the two views' v are the same (the same expression: t and t_r differ only in x), so are the rows reached
    filled = 0
    top = _rows_reached(P[0, 1], P[0, 2])
    for r in range(Hm - 1):
        a_ = r & 1
        b_ = 1 - a_
        _project_row_stereo(depth, rx, ry, R, t, t_r[0], fx, fy, cx, cy, cx_r, r + 1, P[b_, 0], P[b_, 1], P[b_, 2],
                            Ur[b_])
        bottom = _rows_reached(P[b_, 1], P[b_, 2])
        _init_rows(buf_r, sbuf, False, filled, max(top, bottom))
        filled = _init_rows(buf, sbuf, want_span, filled, max(top, bottom))
        top = bottom
        _quad_flags(depth[r], depth[r + 1], P[a_, 2], P[b_, 2], k1, k2, abs_tol, F)
        _raster_quads(buf, sbuf, want_span, 0, 0, H - 1, P[a_, 0], P[a_, 1], P[a_, 2], P[b_, 0], P[b_, 1],
                      P[b_, 2], F, Q, S, cand)
        _raster_quads(buf_r, sbuf, False, 0, 0, H - 1, Ur[a_], P[a_, 1], P[a_, 2], Ur[b_], P[b_, 1], P[b_, 2], F, Q,
                      S, cand)
    _init_rows(buf_r, sbuf, False, filled, H)
    _init_rows(buf, sbuf, want_span, filled, H)


# ---- several threads: chunks of grid rows, each into its own window of target rows ------------
# ``arena[k]`` is chunk k's image-sized slot, of which only its window rows (``wlo[k]..whi[k]``: the rows
# its points reach) are touched: untouched pages of np.empty cost nothing. One parallel region rasterises
# the chunks (dynamically scheduled), a second merges the windows by a per-pixel minimum.
@numba.njit(parallel=True, **_JIT)
def _mesh_chunks(arena, sarena, want_span, wlo, whi, rows, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2, abs_tol):
    H = arena.shape[1]
    for k in numba.prange(len(rows) - 1):
        lo, hi = _v_range(depth, rx, ry, R, t, fy, cy, rows[k], rows[k + 1] + 1)  # quad rows + the row below
        wlo[k] = max(math.ceil(lo - _EPS), 0) if lo < np.inf else H
        whi[k] = min(math.floor(hi + _EPS), H - 1) if hi > -np.inf else -1
        if whi[k] < wlo[k]:
            continue
        buf = arena[k, wlo[k]:whi[k] + 1]
        sbuf = sarena[k, wlo[k]:whi[k] + 1] if want_span else sarena[0, 0:1]
        _mesh_rows(buf, sbuf, want_span, wlo[k], wlo[k], whi[k], depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2,
                   abs_tol, rows[k], rows[k + 1])


@numba.njit(parallel=True, **_JIT)
def _splat_chunks(arena, wlo, whi, rows, depth, rx, ry, R, t, fx, fy, cx, cy):
    H = arena.shape[1]
    for k in numba.prange(len(rows) - 1):
        lo, hi = _v_range(depth, rx, ry, R, t, fy, cy, rows[k], rows[k + 1])
        wlo[k] = max(math.floor(lo + 0.5), 0) if lo < np.inf else H
        whi[k] = min(math.floor(hi + 0.5), H - 1) if hi > -np.inf else -1
        if whi[k] < wlo[k]:
            continue
        buf = arena[k, wlo[k]:whi[k] + 1]
        _splat_rows(buf, wlo[k], depth, rx, ry, R, t, fx, fy, cx, cy, rows[k], rows[k + 1])


@numba.njit(parallel=True, **_JIT)
def _merge_windows(out, sout, want_span, arena, sarena, wlo, whi):
    """Each target row: the nearest depth over the windows holding it (NaN where none does); with
    ``want_span``, the span from the window that won (the first one on a tie)."""
    H, W = out.shape
    for y in numba.prange(H):
        out[y, :] = np.nan
        if want_span:
            sout[y, :] = np.nan
        for k in range(len(wlo)):
            if wlo[k] <= y <= whi[k]:
                for u in range(W):
                    z = arena[k, y, u]
                    if _nearer(z, out[y, u]):
                        out[y, u] = z
                        if want_span:
                            sout[y, u] = sarena[k, y, u]


@dataclass(frozen=True)
class ReprojectParams:
    mode: Mode = "mesh"
    max_slant_deg: float = 85.0  # mesh: reject triangles steeper than this (surface vs image plane)
    abs_tol_mm: float = 0.5  # mesh: depth-noise allowance added to the slant bound


def project_depth_to_camera(depth_mm: np.ndarray, depth_cam: PinholeCamera, T_cam_from_depth: np.ndarray,
                            cam: PinholeCamera, params: ReprojectParams = ReprojectParams(), *,
                            return_span: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Structured-light depth ``(Hm, Wm)`` mm (NaN invalid) -> z-depth ``(H, W)`` float32 mm in ``cam``
    (an undistorted camera, e.g. the rectified ZED left), NaN where no measurement lands.

    ``return_span`` (mesh only): also return ``span_mm`` ``(H, W)`` float32: for the triangle that won the
    z-buffer at each pixel, max - min of its three vertices' Z in ``cam`` (mm); NaN where no triangle.
    Uses ``numba.get_num_threads()`` threads (one in a child forked after OpenMP started: ``numba_threads``): the
    windowed path from ``MIN_PARALLEL_THREADS``, two halves from ``HALVES_MIN_THREADS``; the result is the same for any
    number."""
    depth = np.asarray(depth_mm)
    if depth.shape != (depth_cam.height_px, depth_cam.width_px):
        raise ValueError(f"{depth.shape=} but expected {(depth_cam.height_px, depth_cam.width_px)} from the depth "
                         "camera's intrinsics")
    if cam.has_distortion:
        raise ValueError("the target camera must be undistorted (rectified)")
    if params.mode not in ("mesh", "splat"):
        raise ValueError(f"mode {params.mode!r}, expected 'mesh' or 'splat'")
    if return_span and params.mode != "mesh":
        raise ValueError("return_span needs mode 'mesh' (a splat has no triangles)")
    mesh = params.mode == "mesh"
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    T_cam_from_depth = np.asarray(T_cam_from_depth, np.float64)
    R, t = np.ascontiguousarray(T_cam_from_depth[:3, :3]), np.ascontiguousarray(T_cam_from_depth[:3, 3])
    rx, ry = _ray_planes(depth_cam.model_dump_json())
    H, W = cam.height_px, cam.width_px
    fx, fy, cx, cy = cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px
    k1, k2 = _slant_bounds(depth_cam, params)
    Hm = depth.shape[0]
    n_threads = usable_threads()
    if HALVES_MIN_THREADS <= n_threads < MIN_PARALLEL_THREADS and Hm >= 8:
        out = np.empty((H, W), np.float32)
        span = np.empty((H, W) if return_span else (1, 1), np.float32)
        aux = np.empty((H, W), np.float32)  # (only the rows the second half reaches are touched)
        saux = np.empty((H, W) if return_span else (1, 1), np.float32)
        window = np.zeros(2, np.int64)
        if mesh:
            _mesh_halves(out, span, aux, saux, return_span, window, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2,
                         params.abs_tol_mm, (Hm - 1) // 2)
        else:
            _splat_halves(out, aux, window, depth, rx, ry, R, t, fx, fy, cx, cy, Hm // 2)
        _merge_window(out, span, aux, saux, return_span, window[0], window[1])  # (after: it reads the halves' window)
        return (out, span) if return_span else out
    if n_threads < MIN_PARALLEL_THREADS or Hm < 8:
        out = np.empty((H, W), np.float32)  # the kernels set each row to NaN as they reach it
        span = np.empty((H, W) if return_span else (1, 1), np.float32)
        if mesh:
            _mesh_rows(out, span, return_span, 0, 0, H - 1, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2,
                       params.abs_tol_mm, 0, Hm - 1)
        else:
            _splat_rows(out, 0, depth, rx, ry, R, t, fx, fy, cx, cy, 0, Hm)
        return (out, span) if return_span else out
    n_rows = Hm - 1 if mesh else Hm  # quad rows (mesh) or point rows (splat)
    n_chunks = min(4 * n_threads, 32, n_rows)  # arena: n_chunks image-sized slots, mostly never touched
    rows = np.linspace(0, n_rows, n_chunks + 1).round().astype(np.int64)
    wlo = np.empty(n_chunks, np.int64)
    whi = np.empty(n_chunks, np.int64)
    arena = np.empty((n_chunks, H, W), np.float32)
    sarena = np.empty((n_chunks, H, W) if return_span else (1, 1, 1), np.float32)
    previous = numba.set_parallel_chunksize(1)  # dynamic: a thread slowed by a busy core takes fewer chunks
    try:
        if mesh:
            _mesh_chunks(arena, sarena, return_span, wlo, whi, rows, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2,
                         params.abs_tol_mm)
        else:
            _splat_chunks(arena, wlo, whi, rows, depth, rx, ry, R, t, fx, fy, cx, cy)
        numba.set_parallel_chunksize(8)
        out = np.empty((H, W), np.float32)
        span = np.empty((H, W), np.float32) if return_span else np.empty((1, 1), np.float32)
        _merge_windows(out, span, return_span, arena, sarena, wlo, whi)
    finally:
        numba.set_parallel_chunksize(previous)
    return (out, span) if return_span else out


def _slant_bounds(mech: PinholeCamera, params: ReprojectParams) -> tuple[float, float]:
    """``_edge_ok``'s ``k`` for a grid edge (1 px) and for a quad's diagonal."""
    k1 = 0.5 * math.tan(math.radians(params.max_slant_deg)) / (0.5 * (mech.fx_px + mech.fy_px))  # 1 px edge
    return k1, k1 * math.sqrt(2.0)  # the quad diagonal


def _project_depth_to_stereo(depth_mech_mm: np.ndarray, mech: PinholeCamera, T_zed_from_mech: np.ndarray,
                             T_zedr_from_mech: np.ndarray, zed: RectifiedStereo, params: ReprojectParams,
                             return_span: bool) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """``project_depth_to_camera`` (mesh, one thread) into the rectified ZED's left and right cameras in one pass:
    ``(depth_left, span_left or None, depth_right)``, the same arrays as the two calls. The views differ only by the
    baseline along x and cx (``doffs``): the same 1/Z, so the same drawn triangles, decided once."""
    depth = np.ascontiguousarray(depth_mech_mm, dtype=np.float32)
    T_zed_from_mech = np.asarray(T_zed_from_mech, np.float64)
    T_zedr_from_mech = np.asarray(T_zedr_from_mech, np.float64)
    R, t = np.ascontiguousarray(T_zed_from_mech[:3, :3]), np.ascontiguousarray(T_zed_from_mech[:3, 3])
    t_r = np.ascontiguousarray(T_zedr_from_mech[:3, 3])
    if not (np.array_equal(T_zedr_from_mech[:3, :3], R) and np.array_equal(T_zedr_from_mech[1:3, 3], t[1:3])):
        raise ValueError("the right camera must differ from the left by a translation along x only (rectified)")
    rx, ry = _ray_planes(mech.model_dump_json())
    cam, cam_r = zed.left, zed.right
    H, W = cam.height_px, cam.width_px
    k1, k2 = _slant_bounds(mech, params)
    out = np.empty((H, W), np.float32)  # _mesh_rows_stereo sets each row to NaN as it reaches it
    out_r = np.empty((H, W), np.float32)
    span = np.empty((H, W) if return_span else (1, 1), np.float32)
    _mesh_rows_stereo(out, span, return_span, out_r, depth, rx, ry, R, t, cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px,
                      t_r, cam_r.cx_px, k1, k2, params.abs_tol_mm)
    return out, (span if return_span else None), out_r


@dataclass
class StereoDepth:
    depth_mm: np.ndarray  # ZED-left z-depth, float32, NaN invalid
    disparity_px: np.ndarray  # float32, NaN invalid
    depth_right_mm: np.ndarray  # the same measurement seen from the right camera (z-buffer)
    nonoccluded: np.ndarray  # bool: valid and the match is visible in the right image
    span_mm: np.ndarray | None = None  # mesh, when asked: Z range of the winning triangle (see project_depth_to_camera)


def reproject_to_zed(depth_mm: np.ndarray, depth_cam: PinholeCamera, T_zed_from_depth: np.ndarray,
                     zed: RectifiedStereo, params: ReprojectParams = ReprojectParams(),
                     occlusion_rel_tol: float = 0.01, occlusion_abs_tol_mm: float = 0.5, *,
                     left_span: bool = False) -> StereoDepth:
    """ZED-left depth, disparity ``d = f*B/Z - doffs`` and the non-occluded mask (right-view z-buffer).
    ``left_span`` (mesh): also the left view's ``span_mm``."""
    span = None
    T_zedr_from_depth = zed.T_zedr_from_zed @ T_zed_from_depth
    if params.mode == "mesh" and usable_threads() < MIN_PARALLEL_THREADS and np.shape(depth_mm)[0] >= 8 \
            and not zed.left.has_distortion and np.shape(depth_mm) == (depth_cam.height_px, depth_cam.width_px):
        # one thread (a build worker): both views in one pass over the grid, the same images as the two calls below
        depth_l, span, depth_r = _project_depth_to_stereo(depth_mm, depth_cam, T_zed_from_depth, T_zedr_from_depth, zed,
                                                          params, left_span)
    else:
        if left_span:
            depth_l, span = project_depth_to_camera(depth_mm, depth_cam, T_zed_from_depth, zed.left, params,
                                                    return_span=True)
        else:
            depth_l = project_depth_to_camera(depth_mm, depth_cam, T_zed_from_depth, zed.left, params)
        depth_r = project_depth_to_camera(depth_mm, depth_cam, T_zedr_from_depth, zed.right, params)
    disp, noc = disparity_and_nonoccluded(depth_l, depth_r, zed, occlusion_rel_tol, occlusion_abs_tol_mm)
    return StereoDepth(depth_l, disp, depth_r, noc, span)


def disparity_and_nonoccluded(depth_l: np.ndarray, depth_r: np.ndarray, zed: RectifiedStereo, rel_tol: float = 0.01,
                              abs_tol_mm: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """``zed.depth_to_disparity(depth_l)`` and ``nonoccluded_mask(depth_l, disparity, depth_r, ...)`` in one
    compiled pass (identical results, without numpy's index arrays, gathers and temporaries)."""
    if depth_l.shape != depth_r.shape:
        raise ValueError(f"{depth_l.shape=} but {depth_r.shape=}")
    return _disparity_nonoccluded(np.ascontiguousarray(depth_l, np.float32), np.ascontiguousarray(depth_r, np.float32),
                                  zed.f_px * zed.baseline_mm, zed.doffs_px, rel_tol, abs_tol_mm, False)


@numba.njit(**_JIT)
def _disparity_nonoccluded(depth_l, depth_r, fB, doffs, rel_tol, abs_tol_mm, mirrored):
    """``RectifiedStereo.depth_to_disparity`` and ``nonoccluded_mask`` in one pass, with the same arithmetic
    (the occlusion threshold in float32, as numpy computes it for a float32 depth). ``mirrored``: the same on both
    images mirrored left-right and the results mirrored back (the right view: ``depth_l`` is then the right view's
    z-buffer, ``depth_r`` the left's, and the match lies at ``u + d``), without copying any array."""
    H, W = depth_l.shape
    disp = np.empty((H, W), np.float32)
    noc = np.zeros((H, W), np.bool_)
    keep = np.float32(1 - rel_tol)
    tol = np.float32(abs_tol_mm)
    nan32 = np.float32(np.nan)
    y0, y1, x0, x1 = finite_box(depth_l)  # no depth outside it: no disparity, nothing non-occluded
    disp[:y0] = nan32
    disp[y1:] = nan32
    # near_mm[k]: the nearer of the two other-view samples around a match, fmin(rrow[k - 1], rrow[k]) (rrow[0] and
    # rrow[W - 1] at the ends): match column u0 (clamped to 0..W-1, and its neighbour u0 + 1 clamped) reads
    # near_mm[u0 + 1], or near_mm[W - 1 - u0] in the mirrored image's columns. One load a pixel instead of two
    near_mm = np.empty(W + 1, np.float32)
    near_mid_mm = near_mm[1:W]
    ka, ks = (W - 1, -1) if mirrored else (1, 1)  # near_mm's index of u0: ka + ks * u0
    ub, us = (W - 1 - x0, -1) if mirrored else (x0, 1)  # the (mirrored) image's column of box column i: ub + us * i
    Wm1 = W - 1.0
    J = np.empty(W, np.uint32)  # a row's work: near_mm's index, the occlusion threshold, a match in the image
    z_limit_mm = np.empty(W, np.float32)
    has_match = np.empty(W, np.bool_)
    for v in range(y0, y1):
        drow, rrow = disp[v], depth_r[v]
        drow[:x0] = nan32
        drow[x1:] = nan32
        # the box's columns as slices from index 0: plain loads and stores (a column index the compiler cannot prove
        # non-negative would make them gathers)
        zs, ds, ns = depth_l[v, x0:x1], drow[x0:x1], noc[v, x0:x1]
        for i in range(x1 - x0):  # no branch, so the compiler vectorises the divisions
            zl = zs[i]
            q = np.float32(fB / np.float64(zl) - doffs)
            ds[i] = q if zl > 0.0 else nan32
        ra, rb = rrow[:W - 1], rrow[1:]
        for k in range(W - 1):
            near_mid_mm[k] = np.fmin(ra[k], rb[k])  # NaN only if both are NaN
        near_mm[0] = rrow[0]
        near_mm[W] = rrow[W - 1]
        # the occlusion test in two passes: the match's table index, threshold and range check for every pixel
        # (branch-free, vectorised), then the table look-ups where there is a match (scalar loads: a vectorised
        # gather was slower)
        for i in range(x1 - x0):
            d = ds[i]
            fin = abs(d) < np.inf
            ur = np.float64(ub + us * i) - np.float64(d if fin else np.float32(0.0))  # in the (mirrored) image
            # floor(ur) clamped to 0..W-1: truncation equals floor for the non-negative values clamping leaves
            u0 = np.int64(min(max(ur, 0.0), Wm1))
            J[i] = np.uint32(ka + ks * u0)
            z_limit_mm[i] = np.float32(np.float32(zs[i] * keep) - tol)  # an other-view depth below it occludes
            has_match[i] = fin & (ur >= -0.5) & (ur <= W - 0.5)
        for i in range(x1 - x0):
            if has_match[i]:
                zr = near_mm[np.uint64(J[i])]  # an unsigned index (never negative) needs no wraparound test
                ns[i] = ~((abs(zr) < np.inf) & (zr < z_limit_mm[i]))
    return disp, noc


def right_view_disparity(depth_l: np.ndarray, depth_r: np.ndarray, zed: RectifiedStereo, rel_tol: float = 0.01,
                         abs_tol_mm: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The right view's ground truth (Middlebury ``disp1``): disparity ``f*B/Z_right - doffs`` at ZED-right pixel
    centres, whose match is left pixel ``u + d``, and the mask of right pixels visible in the left image. The same
    computation as the left view's, on the images mirrored left-right (the match then lies at ``u' - d``)."""
    if depth_l.shape != depth_r.shape:
        raise ValueError(f"{depth_l.shape=} but {depth_r.shape=}")
    return _disparity_nonoccluded(np.ascontiguousarray(depth_r, np.float32), np.ascontiguousarray(depth_l, np.float32),
                                  zed.f_px * zed.baseline_mm, zed.doffs_px, rel_tol, abs_tol_mm, True)


def nonoccluded_mask(depth_l: np.ndarray, disp: np.ndarray, depth_r: np.ndarray, rel_tol: float = 0.01,
                     abs_tol_mm: float = 0.5) -> np.ndarray:
    """A left pixel is non-occluded when its match ``u - d`` lies in the right image and the right-view
    z-buffer there is not clearly nearer than the pixel's own depth."""
    H, W = depth_l.shape
    valid = np.isfinite(disp)
    v, u = np.nonzero(valid)
    ur = u - disp[v, u].astype(np.float64)
    inside = (ur >= -0.5) & (ur <= W - 0.5)
    u0 = np.clip(np.floor(ur).astype(np.int64), 0, W - 1)
    u1 = np.clip(u0 + 1, 0, W - 1)
    z0, z1 = depth_r[v, u0], depth_r[v, u1]
    zr = np.fmin(z0, z1)  # NaN only if both are NaN
    zl = depth_l[v, u]
    occluded = np.isfinite(zr) & (zr < zl * (1 - rel_tol) - abs_tol_mm)
    out = np.zeros((H, W), bool)
    out[v, u] = inside & ~occluded
    return out
