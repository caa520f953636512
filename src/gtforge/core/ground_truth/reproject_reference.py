"""A slow, obvious float64 reference of the reprojection core (``reproject.project_depth_to_camera``).

Written for clarity, in plain numpy, independently of the fast numba kernels: it states what the kernels compute,
and benchmarks and tests compare the kernels with it (benchmarks/README.md: speed work never changes results).
Everything is float64 until the depth is stored, which is float32 as in the kernels' z-buffer.

* splat: every valid depth sample is projected; its pixel is the nearest one, ``floor(u + 0.5)``,
  ``floor(v + 0.5)``; the nearest Z wins.
* mesh: every 2x2 quad ``a b / c d`` of the organised grid is split along the diagonal with the smaller depth
  change (a-d or b-c) into two triangles; a triangle is drawn when its three corners are valid and none of its
  edges is a depth jump (``|za - zb| <= (za + zb) * k + abs_tol``, depths in the depth camera, ``k`` for a grid
  edge or for the diagonal). A pixel centre belongs to a drawn triangle when its three barycentric coordinates are
  at least ``-PIXEL_CENTRE_TOL`` (a centre on an edge belongs to the triangle); within one quad a centre is tested
  against one triangle only, the one on its side of the shared diagonal (the first triangle when it lies on the
  diagonal, the other when only that one is drawn), so no centre is drawn twice by the two halves of one quad.
  The depth at the centre is 1 / (1/Z interpolated barycentrically), exact for planar surfaces. The nearest depth
  wins; ``span_mm`` is the winning triangle's max - min vertex Z; between equal float32 depths the first quad in
  grid order (row by row) wins, as in the kernels' sequential z-buffer. Such ties are the rule, not the exception,
  where the target shares the depth camera's rows (a rectified pair): every pixel centre then lies on the edge two
  quads share and both draw it (Middlebury Motorcycle: 302,843 of 311,222 pixels tied, 220,180 of them with a
  different span).

The arithmetic of every float64 expression is written in the same order as in the kernels (a different but equally
exact order would move the last bit of some depths): the reference defines it, and the kernels must match it bit for
bit (tests/core/test_reproject_reference.py). Pixel-centre candidates of a quad are the integer centres in the box of
its drawn triangles, widened by the tolerance. The kernels' one-pixel shortcut (a quad with four valid corners whose
box holds one centre) tests the centre of the four corners' box instead, a box that holds the drawn triangles'
box; a centre outside the latter passes the barycentric test only within about 1e-9 x the triangle's size beyond its
tolerance-widened box, so the two can differ only there (never seen: the tests and the benchmark's check find no
pixel that differs).
"""
from __future__ import annotations

import math

import numpy as np

from gtforge.core.camera import PinholeCamera
from gtforge.core.ground_truth.reproject import _EPS as PIXEL_CENTRE_TOL
from gtforge.core.ground_truth.reproject import ReprojectParams

_DEFAULT = ReprojectParams()  # the kernels' defaults
QUAD_ROWS_PER_BLOCK = 64  # mesh: grid rows handled at once (bounds the memory of the per-quad arrays)


def project_depth_reference(depth_mm: np.ndarray, depth_cam: PinholeCamera, T_cam_from_depth: np.ndarray,
                            cam: PinholeCamera, params: ReprojectParams = _DEFAULT, *,
                            return_span: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The same arguments and results as ``reproject.project_depth_to_camera``: depth ``(Hm, Wm)`` float32 mm
    (NaN invalid) seen by ``depth_cam`` (its lens model included) -> z-depth ``(H, W)`` float32 mm in the undistorted
    ``cam``, NaN where nothing lands; with ``return_span`` (mesh) also the winning triangle's Z range (mm)."""
    depth = np.asarray(depth_mm, dtype=np.float32)
    if depth.shape != (depth_cam.height_px, depth_cam.width_px):
        raise ValueError(f"{depth.shape=} but the depth camera is {depth_cam.height_px}x{depth_cam.width_px}")
    if cam.has_distortion:
        raise ValueError("the target camera must be undistorted (rectified)")
    if params.mode not in ("mesh", "splat"):
        raise ValueError(f"mode {params.mode!r}, expected 'mesh' or 'splat'")
    if return_span and params.mode != "mesh":
        raise ValueError("return_span needs mode 'mesh'")
    u, v, inv_z, Zc, valid = project_points(depth, depth_cam, T_cam_from_depth, cam)
    if params.mode == "splat":
        return _splat(u, v, Zc, valid, cam)
    out, span = _mesh(depth.astype(np.float64), u, v, inv_z, valid, depth_cam, cam, params)
    return (out, span) if return_span else out


def project_points(depth: np.ndarray, depth_cam: PinholeCamera, T_cam_from_depth: np.ndarray, cam: PinholeCamera):
    """Every grid point in the target camera: ``u``, ``v`` (px), ``1/Z`` (1/mm), ``Z`` (mm) and ``valid`` (a finite
    positive depth in front of the target camera), all ``(Hm, Wm)``."""
    z = depth.astype(np.float64)
    rays = depth_cam.ray_grid()  # normalised x, y of every depth-camera pixel centre through its lens, float64
    x, y = rays[..., 0] * z, rays[..., 1] * z
    T_cam_from_depth = np.asarray(T_cam_from_depth, np.float64)
    R, t = T_cam_from_depth[:3, :3], T_cam_from_depth[:3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        # the terms summed left to right, as the kernels do
        Xc = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
        Yc = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
        Zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
        inv_z = 1.0 / Zc
        u = cam.fx_px * Xc * inv_z + cam.cx_px
        v = cam.fy_px * Yc * inv_z + cam.cy_px
        valid = (z > 0.0) & (z < np.inf) & (Zc > 0.0)
    return u, v, inv_z, Zc, valid


def _zbuffer(shape: tuple[int, int], pixel: np.ndarray, z32: np.ndarray, *extra: np.ndarray):
    """The nearest of the candidates ``(pixel index, float32 depth)`` at each pixel (NaN where none), the first one
    (in the given order) among equal depths, and each ``extra`` array's value of the winner."""
    out = np.full(shape, np.nan, np.float32)
    extra_out = [np.full(shape, np.nan, np.float32) for _ in extra]
    order = np.lexsort((np.arange(len(pixel)), z32, pixel))  # by pixel, then depth, then candidate order
    p = pixel[order]
    first = np.ones(len(p), bool)
    first[1:] = p[1:] != p[:-1]
    win = order[first]
    out.reshape(-1)[pixel[win]] = z32[win]
    for e, eo in zip(extra, extra_out):
        eo.reshape(-1)[pixel[win]] = e[win]
    return out, extra_out


def _splat(u, v, Zc, valid, cam: PinholeCamera) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        ui, vi = np.floor(u + 0.5), np.floor(v + 0.5)  # the nearest pixel: rounded, never truncated
        keep = valid & (ui >= 0) & (ui < cam.width_px) & (vi >= 0) & (vi < cam.height_px)
    pixel = vi[keep].astype(np.int64) * cam.width_px + ui[keep].astype(np.int64)
    out, _ = _zbuffer((cam.height_px, cam.width_px), pixel, Zc[keep].astype(np.float32))
    return out


def slant_bounds(depth_cam: PinholeCamera, params: ReprojectParams) -> tuple[float, float]:
    """The continuity bound's ``k`` for a grid edge (1 px long) and for a quad's diagonal (sqrt 2 px): the depth
    change per unit of depth that a surface at ``max_slant_deg`` to the image plane spans over that length."""
    k_edge = 0.5 * math.tan(math.radians(params.max_slant_deg)) / (0.5 * (depth_cam.fx_px + depth_cam.fy_px))
    return k_edge, k_edge * math.sqrt(2.0)


def _continuous(za, zb, k, abs_tol_mm):
    return np.abs(za - zb) <= (za + zb) * k + abs_tol_mm


def _mesh(z, u, v, inv_z, valid, depth_cam: PinholeCamera, cam: PinholeCamera, params: ReprojectParams):
    k_edge, k_diag = slant_bounds(depth_cam, params)
    Hm, Wm = z.shape
    pixels, depths, spans, orders = [], [], [], []
    for r0 in range(0, Hm - 1, QUAD_ROWS_PER_BLOCK):
        r1 = min(r0 + QUAD_ROWS_PER_BLOCK, Hm - 1)  # quads of grid rows r0 .. r1 - 1 (and the row below each)
        got = _mesh_block(z[r0:r1 + 1], u[r0:r1 + 1], v[r0:r1 + 1], inv_z[r0:r1 + 1], valid[r0:r1 + 1],
                          k_edge, k_diag, params.abs_tol_mm, cam)
        pixels.append(got[0])
        depths.append(got[1])
        spans.append(got[2])
        orders.append(got[3] + r0 * (Wm - 1))
    shape = (cam.height_px, cam.width_px)
    pixel, z32, span = np.concatenate(pixels), np.concatenate(depths), np.concatenate(spans)
    order = np.argsort(np.concatenate(orders), kind="stable")  # grid order of the quads, for the ties
    out, (span_out,) = _zbuffer(shape, pixel[order], z32[order], span[order])
    return out, span_out


def _mesh_block(z, u, v, w, valid, k_edge, k_diag, abs_tol_mm, cam: PinholeCamera):
    """Candidates ``(pixel index, float32 depth, float32 span, quad index in the block)`` of the quads between the
    grid rows of this block."""
    def corners(a):  # a b / c d of every quad
        return a[:-1, :-1], a[:-1, 1:], a[1:, :-1], a[1:, 1:]

    za, zb, zc, zd = corners(z)
    fa, fb, fc, fd = corners(valid)
    with np.errstate(invalid="ignore"):
        e_ab, e_cd = _continuous(za, zb, k_edge, abs_tol_mm), _continuous(zc, zd, k_edge, abs_tol_mm)
        e_ac, e_bd = _continuous(za, zc, k_edge, abs_tol_mm), _continuous(zb, zd, k_edge, abs_tol_mm)
        e_ad, e_bc = _continuous(za, zd, k_diag, abs_tol_mm), _continuous(zb, zc, k_diag, abs_tol_mm)
        # the diagonal with the smaller depth change; the only possible one when a corner off it is invalid
        split_ad = fa & fd & (~(fb & fc) | (np.abs(za - zd) <= np.abs(zb - zc)))
    # split a-d: triangles (b; a, d) and (c; a, d); split b-c: (a; b, c) and (d; b, c). Written as the apex r1 of the
    # first triangle, r2 of the second, and the diagonal p-q they share.
    draw1 = np.where(split_ad, fa & fd & fb & e_ad & e_ab & e_bd, fb & fc & fa & e_bc & e_ab & e_ac)
    draw2 = np.where(split_ad, fa & fd & fc & e_ad & e_ac & e_cd, fb & fc & fd & e_bc & e_bd & e_cd)
    quad = np.flatnonzero(draw1 | draw2)
    if len(quad) == 0:
        return np.empty(0, np.int64), np.empty(0, np.float32), np.empty(0, np.float32), np.empty(0, np.int64)
    ad, t1, t2 = split_ad.ravel()[quad], draw1.ravel()[quad], draw2.ravel()[quad]

    def pick(a):  # the quads' p, q, r1, r2 values of the (Hm, Wm) array a
        ca, cb, cc, cd = (x.ravel()[quad] for x in corners(a))
        return np.where(ad, ca, cb), np.where(ad, cd, cc), np.where(ad, cb, ca), np.where(ad, cc, cd)

    (up, uq, u1, u2), (vp, vq, v1, v2), (wp, wq, w1, w2) = pick(u), pick(v), pick(w)

    # candidate pixel centres: those in the box of the quad's drawn triangles (widened by the tolerance), in the image
    def drawn_vertices(p, q, r1, r2, fill):  # the apex of a triangle not drawn replaced by fill
        return [p, q, np.where(t1, r1, fill), np.where(t2, r2, fill)]

    H, W = cam.height_px, cam.width_px
    lo_u = np.minimum.reduce(drawn_vertices(up, uq, u1, u2, np.inf))
    hi_u = np.maximum.reduce(drawn_vertices(up, uq, u1, u2, -np.inf))
    lo_v = np.minimum.reduce(drawn_vertices(vp, vq, v1, v2, np.inf))
    hi_v = np.maximum.reduce(drawn_vertices(vp, vq, v1, v2, -np.inf))
    # clipped on both sides before the integer cast, so that a vertex projected absurdly far cannot overflow it
    u_min = np.clip(np.ceil(lo_u - PIXEL_CENTRE_TOL), 0, W).astype(np.int64)
    u_max = np.clip(np.floor(hi_u + PIXEL_CENTRE_TOL), -1, W - 1).astype(np.int64)
    v_min = np.clip(np.ceil(lo_v - PIXEL_CENTRE_TOL), 0, H).astype(np.int64)
    v_max = np.clip(np.floor(hi_v + PIXEL_CENTRE_TOL), -1, H - 1).astype(np.int64)
    n_u = np.maximum(u_max - u_min + 1, 0)
    n_v = np.maximum(v_max - v_min + 1, 0)
    n = n_u * n_v
    i = np.repeat(np.arange(len(quad)), n)  # one entry per (quad, candidate centre)
    k = np.arange(len(i)) - np.repeat(np.cumsum(n) - n, n)
    px = (u_min[i] + k % n_u[i]).astype(np.float64)
    py = (v_min[i] + k // n_u[i]).astype(np.float64)

    up, vp, wp, uq, vq, wq = up[i], vp[i], wp[i], uq[i], vq[i], wq[i]
    u1, v1, w1, u2, v2, w2 = u1[i], v1[i], w1[i], u2[i], v2[i], w2[i]
    dqu, dqv = uq - up, vq - vp
    # twice the signed areas of (p, q, r1) and (p, q, r2); a degenerate triangle covers nothing
    a1 = dqu * (v1 - vp) - dqv * (u1 - up)
    a2 = dqu * (v2 - vp) - dqv * (u2 - up)
    ok1 = t1[i] & (np.abs(a1) >= 1e-12)
    ok2 = t2[i] & (np.abs(a2) >= 1e-12)
    # the centre's weight of the apex, times the area: which side of the diagonal p-q it lies on
    e_r = dqu * (py - vp) - dqv * (px - up)
    use1 = ok1 & ((e_r * a1 >= 0.0) | ~ok2)  # its own side's triangle (the first one on the diagonal)
    ur, vr, wr, a = np.where(use1, u1, u2), np.where(use1, v1, v2), np.where(use1, w1, w2), np.where(use1, a1, a2)
    # barycentric weights (times the area a) of r, q and p; a centre belongs when none is below -tolerance
    e_q = (up - ur) * (py - vr) - (vp - vr) * (px - ur)
    e_p = a - e_r - e_q
    s = np.where(a > 0.0, 1.0, -1.0)
    tol = -PIXEL_CENTRE_TOL * np.abs(a)
    with np.errstate(invalid="ignore", divide="ignore"):
        z64 = a / (e_r * wr + e_q * wq + e_p * wp)  # 1 / (1/Z interpolated)
        z32 = z64.astype(np.float32)
        inside = (ok1 | ok2) & (s * e_r >= tol) & (s * e_q >= tol) & (s * e_p >= tol) & (z32 > 0.0)
        span = (1.0 / np.minimum(np.minimum(wr, wp), wq) - 1.0 / np.maximum(np.maximum(wr, wp), wq)).astype(np.float32)
    pixel = py.astype(np.int64) * W + px.astype(np.int64)
    return pixel[inside], z32[inside], span[inside], quad[i[inside]]
