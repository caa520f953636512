"""Reprojection core: structured-light depth -> rectified ZED-left depth with a z-buffer.

``splat``: every depth sample to its nearest pixel (rounded, never truncated), nearest wins.
``mesh`` (default): two triangles per 2x2 quad of the organised depth grid; a triangle whose edges
span a depth jump steeper than ``max_slant_deg`` is rejected; the rest are rasterised at pixel
centres with a z-buffer, interpolating 1/Z (exact for planar surfaces). Pixels no valid triangle
covers stay NaN, so nothing is invented across occlusions or shadows.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np

# numba: prefer OpenMP (TBB builds on Debian are often too old and only produce a warning)
numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]

from gtforge.camera import PinholeCamera, RectifiedStereo

Mode = Literal["mesh", "splat"]


@numba.njit(parallel=True, cache=True)
def _min_merge(bufs):
    """Per-pixel minimum over the per-thread z-buffers; inf (nothing landed) -> NaN."""
    n, H, W = bufs.shape
    out = np.empty((H, W), np.float32)
    for v in numba.prange(H):
        for u in range(W):
            m = bufs[0, v, u]
            for k in range(1, n):
                if bufs[k, v, u] < m:
                    m = bufs[k, v, u]
            out[v, u] = m if m < np.inf else np.nan
    return out


@numba.njit(cache=True, inline="always")
def _project_row(depth, rays, R, t, fx, fy, cx, cy, r, U, V, Z):
    """Project one row of the depth grid into the target camera (NaN where invalid or behind it)."""
    for c in range(depth.shape[1]):
        z = depth[r, c]
        U[c] = np.nan
        V[c] = np.nan
        Z[c] = np.nan
        if not (z > 0.0) or not math.isfinite(z):
            continue
        x = rays[r, c, 0] * z
        y = rays[r, c, 1] * z
        Zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
        if Zc <= 0.0:
            continue
        U[c] = fx * (R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]) / Zc + cx
        V[c] = fy * (R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]) / Zc + cy
        Z[c] = Zc


@numba.njit(parallel=True, cache=True)
def _splat_fused(depth, rays, R, t, fx, fy, cx, cy, H, W, n_chunks):
    """Back-project, transform, project and z-buffer in one pass; one z-buffer per row chunk
    (no write races), merged by a parallel minimum."""
    Hm, Wm = depth.shape
    bufs = np.full((n_chunks, H, W), np.inf, np.float32)
    rows_per = (Hm + n_chunks - 1) // n_chunks
    for k in numba.prange(n_chunks):
        buf = bufs[k]
        U = np.empty(Wm)
        V = np.empty(Wm)
        Z = np.empty(Wm)
        for r in range(k * rows_per, min(Hm, (k + 1) * rows_per)):
            _project_row(depth, rays, R, t, fx, fy, cx, cy, r, U, V, Z)
            for c in range(Wm):
                if not math.isfinite(Z[c]):
                    continue
                ui = int(math.floor(U[c] + 0.5))  # nearest pixel centre: round, never truncate
                vi = int(math.floor(V[c] + 0.5))
                if 0 <= ui < W and 0 <= vi < H and Z[c] < buf[vi, ui]:
                    buf[vi, ui] = Z[c]
    return _min_merge(bufs)


@numba.njit(cache=True, inline="always")
def _edge_ok(za, zb, pixdist, tan_max, inv_f, abs_tol):
    zm = 0.5 * (za + zb)
    return abs(za - zb) <= zm * tan_max * pixdist * inv_f + abs_tol


@numba.njit(cache=True)
def _raster_tri(zbuf, u0, v0, w0, u1, v1, w1, u2, v2, w2):
    H, W = zbuf.shape
    area = (u1 - u0) * (v2 - v0) - (u2 - u0) * (v1 - v0)
    if abs(area) < 1e-12:
        return
    inv_area = 1.0 / area
    umin = max(int(math.ceil(min(u0, u1, u2) - 1e-9)), 0)
    umax = min(int(math.floor(max(u0, u1, u2) + 1e-9)), W - 1)
    vmin = max(int(math.ceil(min(v0, v1, v2) - 1e-9)), 0)
    vmax = min(int(math.floor(max(v0, v1, v2) + 1e-9)), H - 1)
    eps = -1e-9
    for py in range(vmin, vmax + 1):
        for px in range(umin, umax + 1):
            l1 = ((px - u0) * (v2 - v0) - (u2 - u0) * (py - v0)) * inv_area
            l2 = ((u1 - u0) * (py - v0) - (px - u0) * (v1 - v0)) * inv_area
            l0 = 1.0 - l1 - l2
            if l0 >= eps and l1 >= eps and l2 >= eps:
                w = l0 * w0 + l1 * w1 + l2 * w2
                if w > 0.0:
                    z = 1.0 / w
                    if z < zbuf[py, px]:
                        zbuf[py, px] = z


@numba.njit(parallel=True, cache=True)
def _mesh(depth, rays, R, t, fx, fy, cx, cy, H, W, tan_max, inv_f, abs_tol, n_chunks):
    """Rasterise the depth grid's triangles; one z-buffer per chunk of grid rows, merged by minimum.
    Each chunk projects its rows on the fly (two rows at a time), so no full-size U/V/Z arrays exist."""
    Hm, Wm = depth.shape
    bufs = np.full((n_chunks, H, W), np.inf, np.float32)
    rows_per = (Hm - 1 + n_chunks - 1) // n_chunks
    for k in numba.prange(n_chunks):
        r0, r1 = k * rows_per, min(Hm - 1, (k + 1) * rows_per)
        if r0 >= r1:
            continue
        U = np.empty((2, Wm))
        V = np.empty((2, Wm))
        Z = np.empty((2, Wm))
        _project_row(depth, rays, R, t, fx, fy, cx, cy, r0, U[0], V[0], Z[0])
        for r in range(r0, r1):
            a, b = (r - r0) % 2, (r - r0 + 1) % 2
            _project_row(depth, rays, R, t, fx, fy, cx, cy, r + 1, U[b], V[b], Z[b])
            _mesh_row_pair(bufs[k], U[a], V[a], Z[a], U[b], V[b], Z[b], depth[r], depth[r + 1], tan_max, inv_f, abs_tol)
    return _min_merge(bufs)


@numba.njit(cache=True)
def _mesh_row_pair(zbuf, Ut, Vt, Zt, Ub, Vb, Zb_, zmt, zmb, tan_max, inv_f, abs_tol):
    """Triangles of the quads between grid row ``t`` (top) and ``b`` (bottom)."""
    for c in range(Ut.shape[0] - 1):
        za, zb, zc, zd = zmt[c], zmt[c + 1], zmb[c], zmb[c + 1]
        ua, ub, uc, ud = Ut[c], Ut[c + 1], Ub[c], Ub[c + 1]
        va, vb, vc, vd = Vt[c], Vt[c + 1], Vb[c], Vb[c + 1]
        Za, Zb, Zc, Zd = Zt[c], Zt[c + 1], Zb_[c], Zb_[c + 1]
        fa, fb, fc, fd = math.isfinite(Za), math.isfinite(Zb), math.isfinite(Zc), math.isfinite(Zd)
        # split along the diagonal with the smaller depth change; each triangle has its right angle at
        # one quad corner (the first vertex passed) and the diagonal between the other two
        if fa and fd and (not (fb and fc) or abs(za - zd) <= abs(zb - zc)):
            if fb:  # (a, b, d)
                _tri_if_continuous(zbuf, ub, vb, Zb, zb, ua, va, Za, za, ud, vd, Zd, zd, tan_max, inv_f, abs_tol)
            if fc:  # (a, d, c)
                _tri_if_continuous(zbuf, uc, vc, Zc, zc, ua, va, Za, za, ud, vd, Zd, zd, tan_max, inv_f, abs_tol)
        elif fb and fc:
            if fa:  # (a, b, c)
                _tri_if_continuous(zbuf, ua, va, Za, za, ub, vb, Zb, zb, uc, vc, Zc, zc, tan_max, inv_f, abs_tol)
            if fd:  # (b, d, c)
                _tri_if_continuous(zbuf, ud, vd, Zd, zd, ub, vb, Zb, zb, uc, vc, Zc, zc, tan_max, inv_f, abs_tol)


@numba.njit(cache=True, inline="always")
def _tri_if_continuous(zbuf, ur, vr, Zr, zr, up, vp, Zp, zp, uq, vq, Zq, zq, tan_max, inv_f, abs_tol):
    """Rasterise the triangle (r, p, q) unless an edge spans a depth jump: r-p and r-q are grid edges
    (1 px in the depth image), p-q the quad diagonal (sqrt(2) px); ``z*`` are depth-camera depths."""
    if _edge_ok(zr, zp, 1.0, tan_max, inv_f, abs_tol) and _edge_ok(zr, zq, 1.0, tan_max, inv_f, abs_tol) \
            and _edge_ok(zp, zq, math.sqrt(2.0), tan_max, inv_f, abs_tol):
        _raster_tri(zbuf, ur, vr, 1.0 / Zr, up, vp, 1.0 / Zp, uq, vq, 1.0 / Zq)


@dataclass(frozen=True)
class ReprojectParams:
    mode: Mode = "mesh"
    max_slant_deg: float = 85.0  # mesh: reject triangles steeper than this (surface vs image plane)
    abs_tol_mm: float = 0.5  # mesh: depth-noise allowance added to the slant bound


def project_depth_to_camera(depth_mech_mm: np.ndarray, mech: PinholeCamera, T_cam_from_mech: np.ndarray,
                            cam: PinholeCamera, params: ReprojectParams = ReprojectParams()) -> np.ndarray:
    """Structured-light depth ``(Hm, Wm)`` mm (NaN invalid) -> z-depth ``(H, W)`` float32 mm in ``cam``
    (an undistorted camera, e.g. the rectified ZED left), NaN where no measurement lands."""
    depth = np.asarray(depth_mech_mm)
    if depth.shape != (mech.height_px, mech.width_px):
        raise ValueError(f"{depth.shape=} but expected {(mech.height_px, mech.width_px)} from the mech intrinsics")
    if cam.has_distortion:
        raise ValueError("the target camera must be undistorted (rectified)")
    if params.mode not in ("mesh", "splat"):
        raise ValueError(f"mode {params.mode!r}, expected 'mesh' or 'splat'")
    T = np.asarray(T_cam_from_mech, np.float64)
    R, t, rays = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), np.ascontiguousarray(mech.ray_grid())
    if params.mode == "splat":
        return _splat_fused(np.ascontiguousarray(depth, dtype=np.float32), rays, R, t, cam.fx_px, cam.fy_px,
                            cam.cx_px, cam.cy_px, cam.height_px, cam.width_px, max(1, numba.get_num_threads()))
    return _mesh(np.ascontiguousarray(depth, dtype=np.float32), rays, R, t, cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px,
                 cam.height_px, cam.width_px, math.tan(math.radians(params.max_slant_deg)),
                 1.0 / (0.5 * (mech.fx_px + mech.fy_px)), params.abs_tol_mm, max(1, numba.get_num_threads()))


@dataclass
class StereoDepth:
    depth_mm: np.ndarray  # ZED-left z-depth, float32, NaN invalid
    disparity_px: np.ndarray  # float32, NaN invalid
    depth_right_mm: np.ndarray  # the same measurement seen from the right camera (z-buffer)
    nonoccluded: np.ndarray  # bool: valid and the match is visible in the right image


def reproject_to_zed(depth_mech_mm: np.ndarray, mech: PinholeCamera, T_zed_from_mech: np.ndarray,
                     zed: RectifiedStereo, params: ReprojectParams = ReprojectParams(),
                     occlusion_rel_tol: float = 0.01, occlusion_abs_tol_mm: float = 0.5) -> StereoDepth:
    """ZED-left depth, disparity ``d = f*B/Z - doffs`` and the non-occluded mask (right-view z-buffer)."""
    depth_l = project_depth_to_camera(depth_mech_mm, mech, T_zed_from_mech, zed.left, params)
    depth_r = project_depth_to_camera(depth_mech_mm, mech, zed.T_zedr_from_zed @ T_zed_from_mech, zed.right, params)
    disp = zed.depth_to_disparity(depth_l)
    noc = nonoccluded_mask(depth_l, disp, depth_r, occlusion_rel_tol, occlusion_abs_tol_mm)
    return StereoDepth(depth_l, disp, depth_r, noc)


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
