"""The depth camera's texture image rendered into the ZED-left view through ground-truth depth (what verify and refine
compare with the ZED's own image)."""
from __future__ import annotations

import math

import numba
import numpy as np

from gtforge.core import lens
from gtforge.core.camera import Rig
from gtforge.core.geometry import finite_box
from gtforge.core.alignment.photometric import to_gray


def render_texture(depth_zed_mm: np.ndarray, rig: Rig, texture: np.ndarray, occlusion_tol_mm: float = 2.0,
                   origin_px: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """The texture image rendered into the ZED-left view through the GT depth: ``(float32 image, valid mask)``.

    Each ZED-left pixel with GT depth is back-projected, moved into the texture camera (``T_mech_from_zed``),
    projected with its lens model and sampled bilinearly. A point the texture camera cannot see (outside its image,
    or hidden behind another GT point by more than ``occlusion_tol_mm``) is left out. ``depth_zed_mm`` may be a
    window of the ZED-left image whose pixel ``[0, 0]`` is the image's pixel ``(u, v) = origin_px``."""
    zed, mech = rig.zed.left, rig.mech
    T_mech_from_zed = rig.T_mech_from_zed
    d = lens.full_coeffs(mech.dist_coeffs)
    tilted = bool(d[12] != 0.0 or d[13] != 0.0)
    out = np.zeros(depth_zed_mm.shape, np.float32)
    ok = np.zeros(depth_zed_mm.shape, bool)
    depth = np.asarray(depth_zed_mm, np.float32)
    # only the depth's finite box: a pixel without depth is not rendered (a window around the GT has a margin)
    y0, y1, x0, x1 = finite_box(depth)
    if y1 == 0:
        return out, ok
    _render_kernel(np.ascontiguousarray(depth[y0:y1, x0:x1]), float(origin_px[0] + x0), float(origin_px[1] + y0),
                   np.array([zed.fx_px, zed.fy_px, zed.cx_px, zed.cy_px]),
                   np.ascontiguousarray(T_mech_from_zed[:3, :3]), np.ascontiguousarray(T_mech_from_zed[:3, 3]),
                   np.array([mech.fx_px, mech.fy_px, mech.cx_px, mech.cy_px]), d,
                   lens.tilt_matrix(d[12], d[13]), tilted, np.ascontiguousarray(to_gray(texture)),
                   rig.separate_depth_camera, float(occlusion_tol_mm), out[y0:y1, x0:x1], ok[y0:y1, x0:x1])
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
    # the ray's x / z of each column (and y / z of each row, below) divided once, not at every pixel: the same values
    x_over_z = np.empty(W)
    for u in range(W):
        x_over_z[u] = (u + x0 - k_zed[2]) / k_zed[0]
    for v in range(H):
        ru, rv, rz, drow = pu[v], pv[v], pz[v], depth[v]
        y_over_z = (v + y0 - k_zed[3]) / k_zed[1]
        for u in range(W):
            z = np.float64(drow[u])
            X = x_over_z[u] * z
            Y = y_over_z * z
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
