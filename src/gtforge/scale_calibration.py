"""The disparity-scale terms a vertical check cannot see (issue #25): the ZED's baseline scale, the right camera's yaw
(rotation about its vertical axis), the depth camera's scale and offset, and a separate depth camera's rotation.

Physics. The ground truth labels ``d_gt = f B / Z_depth - doffs``; the images show ``d_img = f B_true / Z - doffs``
through a right camera turned by ``psi`` about its y axis. With ``B_true = (1 + b) B``, ``Z_depth = (1 + k) Z + c``::

    d_img - d_gt ~ (b + k) * f B / Z  +  c * f B / Z^2  -  psi * f (1 + x_r^2)       (x_r = (u_r - cx_r) / f)

(the yaw also moves the right image's rows by ``psi * f x_r y_r``). So:

* **Scenes** (the GT disparity against the images' own photometric disparity, every textured GT pixel of every
  scene, one Gauss-Newton solve): the sum ``b + k`` (a 1/Z term), ``c`` (1/Z^2) and ``psi`` (a constant plus the
  x^2 curvature). ``b`` and ``k`` are **not separable** from scenes: only their sum. With a separate depth camera,
  its rotation ``omega`` too: each label moves by ``depth_pose_jacobian_px . omega`` (the surface tilted and slid).
* **Boards, ZED** (``board_zed_measurement``): the corners' stereo disparity against their depth from PnP in the
  ZED-left image (which uses the board's known square size, not the baseline): ``b`` and ``psi``. Any target
  (``board_measurements``): left and right points matched by id, circle centres bias-corrected in each image.
* **Boards, depth** (``board_depth_measurement``): the depth camera's z at each corner's ray against the corner's z
  from PnP in the texture image (the known square size again): ``z_depth - z_pnp = k z + c``: ``k`` and ``c``
  (with a separate depth camera, as a function of its rotation).

``calibrate_scale`` combines the three (generalised least squares, each with its covariance), rebuilds every scene's
ground truth with the result and solves again until the correction stops moving. A term is applied only when the
data determine it (its 1-sigma moves the scenes' disparities by at most ``ScaleParams.max_sigma_px``; else "not
determined") and it is significant (more than ``apply_z`` sigma from 0; else "not significant", held at 0 and the
others solved again). ``b`` and ``k`` without a board measurement of either are "not separable": their sum is applied
to the baseline, which keeps the disparity labels, depth0.tiff and calib.txt consistent with each other (see
docs/pipeline.md). The result is stored in the calibration file (``CalibrationFile.scale_calibration``: every term,
its sigma, the covariance and the captures it came from) and applied through the rig: ``rig.zed.baseline_mm``, and
``rig.scale_corrections`` (depth undone before reprojection; the yaw's homography composed with the ZED
self-rectification into the one resampling of the right image that opening the session makes,
``CalibrationFile.open_session``).

Covariances: the scenes' is a tile sandwich (scores summed over ``cov_tile_px`` tiles, as refine's), the boards' a
pose-clustered sandwich (a PnP pose's error moves all its corners together), raised where it is smaller than the
model's: each corner's own scatter plus its pose's PnP covariance (from the pose's reprojection residuals) carried to
the corners. A session's few poses make the clustered one alone a draw of a few degrees of freedom, now and then many
times too small (benchmarks/RESULTS.md, "calibrate-scale's sigma").

About 600 lines: the physics above, the three measurements and their combination read together.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from gtforge.core import bspline
from gtforge.core.targets.board import solve_pnp
from gtforge.core.camera import Rig, ScaleCorrections
from gtforge.core.geometry import invert_T, perturb_left, transform_points
from gtforge.core.alignment.photometric import (
    even_subset,
    huber_system,
    interior_mask,
    local_normalize,
    smooth_depth_mask,
    textured_mask,
    to_gray,
)
from gtforge.core.zed.rectification import matched_board_points
from gtforge.core.zed.scale_corrections import (
    apply_homography,
    depth_pose_jacobian_px,
    yaw_homography,
)
from gtforge.core.targets.detection import (
    PairSkipped,
    captures_detected_ahead,
    detect_target,
    pnp_bias_corrected,
    unmirror_symmetric_grid,
)
from gtforge.core.targets.models import MIN_COMMON_CORNERS, CircleGridSpec, collinear
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.dataset.scene_verification import verify_scene
from gtforge.errors import InputError
from gtforge.io.calibrated_session import open_calibrated_session
from gtforge.io.captures import missing_capture_file
from gtforge.records.calibration import (
    CalibrationFile,
    ScaleCalibration,
    ScaleParams,
    ScaleTerm,
    SceneScaleResult,
)
from gtforge.records.dataset import BuildParams

log = logging.getLogger("gtforge.scale_calibration")

# the parameters, in this order everywhere (vectors, covariance rows/columns)
# (the depth camera's rotation, the last three, only for a rig with a separate depth camera)
PARAMS = ("zed_baseline_frac", "zed_right_yaw_deg", "depth_scale_frac", "depth_offset_mm",
          "depth_pose_rx_deg", "depth_pose_ry_deg", "depth_pose_rz_deg")
IB, IY, IK, IC = range(4)
IP = slice(4, 7)  # the left perturbation of T_mech_from_depth (rad here, deg in the file)
COARSE_SIGMA_PX = 1.5  # the coarse pass's blur: brings shifts of a few px into the fine pass's reach


# ---- the right image's yaw ---------------------------------------------------------------------


# ---- scenes: stereo consistency -----------------------------------------------------------------
@dataclass
class SceneImages:
    """What a scene's fit reads from its two images, whatever its GT: computed once per scene, read by every pass of
    ``calibrate_scale`` (each pass rebuilds the GT with the pass before's result, never the images)."""
    left: np.ndarray  # (H, W) normalised left image (float32)
    left_blur: np.ndarray  # the same blurred (the coarse pass)
    textured: np.ndarray  # (H, W) bool: where the normalised left image has texture
    right_stack: np.ndarray  # (H, W, 3) B-spline coefficients (gtforge.core.bspline) of the normalised right image
    # (as captured) and of its x and y gradients
    right_stack_blur: np.ndarray  # the same blurred (the coarse pass; blurring the coefficients blurs the spline they
    # describe the same way)


def scene_images(zed_left: np.ndarray, zed_right: np.ndarray, params: ScaleParams) -> SceneImages:
    """``SceneImages`` of one scene's ZED pair."""
    sigma = params.verify.norm_sigma_px
    nl = local_normalize(to_gray(zed_left).astype(np.float32), None, sigma)
    nr = local_normalize(to_gray(zed_right).astype(np.float32), None, sigma)
    stack = bspline.coefficients(np.stack([nr, cv2.Sobel(nr, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8),
                                           cv2.Sobel(nr, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)], axis=2))
    return SceneImages(nl, cv2.GaussianBlur(nl, (0, 0), COARSE_SIGMA_PX), textured_mask(nl), stack,
                       cv2.GaussianBlur(stack, (0, 0), COARSE_SIGMA_PX))  # (each channel alike)


@dataclass
class ScenePixels:
    name: str
    u: np.ndarray  # ZED-left pixel columns / rows of the used GT pixels
    v: np.ndarray
    d_gt: np.ndarray  # GT disparity there (px) with the rig it was built with
    z_mm: np.ndarray  # GT depth there
    left: np.ndarray  # normalised left value there
    left_blur: np.ndarray  # the same of the normalised left image blurred (the coarse pass)
    right_stack: np.ndarray  # SceneImages.right_stack
    right_stack_blur: np.ndarray  # SceneImages.right_stack_blur
    g_pose: np.ndarray | None = None  # (N, 3) d(GT)/d(depth camera rotation) px/rad; None: one camera


def scene_pixels(name: str, depth_mm: np.ndarray, disparity_px: np.ndarray, nonoccluded: np.ndarray,
                 images: SceneImages, params: ScaleParams, rig: Rig | None = None) -> ScenePixels | None:
    """The textured GT pixels of one scene away from depth edges (as verify's stereo check selects them); with a
    ``rig`` that has a separate depth camera, the GT's sensitivity to that camera's rotation there."""
    ok = nonoccluded & np.isfinite(disparity_px)
    h, w = disparity_px.shape
    x_match = np.arange(w, dtype=np.float32)[None, :] - np.where(ok, disparity_px, 0)
    use = interior_mask(ok, 2) & (x_match > 8) & (x_match < w - 9) & images.textured & \
        smooth_depth_mask(disparity_px)
    use[:8], use[-8:] = False, False
    v, u = np.nonzero(use)
    if len(v) < params.verify.min_pixels:
        return None
    keep = even_subset(len(v), params.points_per_scene)
    v, u = v[keep], u[keep]
    g_pose = None
    if rig is not None and rig.separate_depth_camera:
        d = disparity_px.astype(np.float64)  # (interior_mask: both neighbours have GT)
        g_pose = depth_pose_jacobian_px(u, v, depth_mm[v, u], 0.5 * (d[v, u + 1] - d[v, u - 1]),
                                        0.5 * (d[v + 1, u] - d[v - 1, u]), rig)
    return ScenePixels(name, u, v, disparity_px[v, u].astype(np.float64), depth_mm[v, u].astype(np.float64),
                       images.left[v, u].astype(np.float64), images.left_blur[v, u].astype(np.float64),
                       images.right_stack, images.right_stack_blur, g_pose)


def _scene_system(sp: ScenePixels, theta: np.ndarray, rig: Rig, huber: float, tile_px: float | None = None,
                  coarse: bool = False):
    """Normal equations of one scene at ``theta = (ds, dc_mm, yaw_rad[, omega_rad (3)], dy0)`` (increments of the
    scale sum, the offset and the depth camera's rotation relative to the GT's rig, the yaw in total) plus the scene's
    nuisances (vertical offset ``dy0``, gain, offset): ``(H, g, S or None, residuals)`` over ``theta``, gain, offset."""
    zed = rig.zed
    f, fb = zed.f_px, zed.f_px * zed.baseline_mm
    g_s = fb / sp.z_mm  # d(d)/d(scale sum)
    g_c = fb / sp.z_mm ** 2  # d(d)/d(offset mm)
    ds, dc, yaw, dy0 = theta[0], theta[1], theta[2], theta[-1]
    shift = ds * g_s + dc * g_c
    if sp.g_pose is not None:
        shift = shift + sp.g_pose @ theta[3:6]
    xr = sp.u - sp.d_gt - shift  # where the rectified right image shows the left pixel
    yr = sp.v.astype(np.float64)
    H = yaw_homography(rig, yaw)
    ua, va = apply_homography(H, xr, yr)
    va = va + dy0
    right = sp.right_stack_blur if coarse else sp.right_stack
    left = sp.left_blur if coarse else sp.left
    # cubic B-spline at the exact positions, not verify's Keys cubic convolution: that one's error depends on the
    # sub-pixel phase, which along a row is the disparity's fractional part, so it correlates with depth, the very thing
    # the scale terms are fitted to. On the synthetic scenes (0.35x, right camera turned 0.15 deg) it biased the scenes'
    # estimate by (b + k, c, yaw) = (+0.0040, -1.6 mm, +0.0074 deg), about 4 sigma; with B-splines (+0.0005, -0.34 mm,
    # -0.0000 deg)
    w_, gx, gy = bspline.sample(right, ua, va).T
    # d(ua, va)/d(yaw) at the rectified position (to first order in yaw: f (1 + x^2), f x y)
    x = (xr - zed.right.cx_px) / f
    y = (yr - zed.right.cy_px) / f
    cols = [-gx * g_s, -gx * g_c, gx * f * (1 + x * x) + gy * f * x * y]
    if sp.g_pose is not None:
        cols += [-gx * sp.g_pose[:, 0], -gx * sp.g_pose[:, 1], -gx * sp.g_pose[:, 2]]
    J = np.stack(cols + [gy, left, np.ones_like(x)], axis=1)
    r = w_ - left
    H, g, _, S = huber_system(J, r, huber, sp.u, sp.v, tile_px)
    return H, g, S, r


def pose_effect_px(scenes: list[ScenePixels]) -> np.ndarray:
    """RMS over the scenes' pixels of how many px one rad of each depth-camera rotation component moves the GT (zeros
    with one camera)."""
    g = [sp.g_pose for sp in scenes if sp.g_pose is not None]
    return np.sqrt(np.mean(np.concatenate(g) ** 2, axis=0)) if g else np.zeros(3)


def solve_scenes(scenes: list[ScenePixels], rig: Rig, params: ScaleParams, yaw0_rad: float
                 ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Gauss-Newton (Huber IRLS, coarse pass on blurred images first) over ``(ds, dc_mm, yaw_rad)`` (and, with a
    separate depth camera, its rotation ``omega_rad``) and each scene's nuisances. Returns (the 3 or 6, their
    tile-sandwich covariance, each scene's nuisance vector)."""
    n = len(scenes)
    m = 6 if any(sp.g_pose is not None for sp in scenes) else 3
    theta = np.zeros(m)
    theta[2] = yaw0_rad
    nuis = [np.zeros(3) for _ in scenes]  # dy0, (gain, offset re-estimated at each step)
    # a step's size in px of disparity at the scenes' median depth (the stop test), in theta's order (ds, dc_mm, yaw)
    fb = rig.zed.f_px * rig.zed.baseline_mm
    z_mm = float(np.median(np.concatenate([sp.z_mm for sp in scenes])))
    step_px = np.r_[fb / z_mm, fb / z_mm ** 2, rig.zed.f_px, pose_effect_px(scenes)][:m]

    def index(k: int) -> np.ndarray:
        return np.r_[0:m, m + 3 * k: m + 3 + 3 * k]

    for level in (0, 1):
        for _ in range(params.iterations if level else 8):
            A = np.zeros((m + 3 * n, m + 3 * n))
            g = np.zeros(m + 3 * n)
            for k, sp in enumerate(scenes):
                Hk, gk, _, _ = _scene_system(sp, np.r_[theta, nuis[k][0]], rig, params.huber, coarse=not level)
                idx = index(k)
                A[np.ix_(idx, idx)] += Hk
                g[idx] += gk
            scale = np.sqrt(np.maximum(np.diag(A), 1e-30))
            step = -np.linalg.solve(A / np.outer(scale, scale), g / scale) / scale
            theta = theta + step[:m]
            for k in range(n):
                nuis[k][0] += step[m + 3 * k]
            # stop when the step moves disparities by < 1e-4 px
            if float(np.abs(step[:m]) @ step_px) < 1e-4 and level:
                break
    # covariance: H^-1 S H^-1 (cluster-robust over tiles)
    A = np.zeros((m + 3 * n, m + 3 * n))
    S = np.zeros_like(A)
    for k, sp in enumerate(scenes):
        Hk, _, Sk, _ = _scene_system(sp, np.r_[theta, nuis[k][0]], rig, params.huber, float(params.cov_tile_px))
        idx = index(k)
        A[np.ix_(idx, idx)] += Hk
        S[np.ix_(idx, idx)] += Sk
    Ai = np.linalg.inv(A)
    C = (Ai @ S @ Ai)[:m, :m]
    return theta, 0.5 * (C + C.T), nuis


# ---- boards --------------------------------------------------------------------------------------
@dataclass
class BoardMeasurement:
    """A linear(ised) measurement ``A x ~ y`` of the parameters with covariance ``C`` (``x`` in PARAMS' order, angles
    in rad here)."""

    A: np.ndarray
    y: np.ndarray
    C: np.ndarray
    source: str
    poses: list[str]
    kind: str = ""  # "zed_pair" or "depth_map" (ScaleCalibration.board_poses_by_measurement)


def pnp_pose_covariance(X_cam: np.ndarray, uv: np.ndarray, cam) -> np.ndarray:
    """The 6x6 covariance of a PnP pose, as a left perturbation ``(omega_rad, tau_mm)`` of the points ``X_cam``
    (N, 3) in the camera's frame: ``s^2 (J^T J)^-1`` with ``J`` the pinhole projection's derivative and ``s^2`` the
    pose's own reprojection residual variance (``uv`` (N, 2) the detected points it was solved from: 2N - 6 degrees
    of freedom, stable where the pose-clustered spread of a few poses is not)."""
    X = np.asarray(X_cam, np.float64)
    x, y, z = X.T
    res = np.asarray(uv, np.float64) - cam.project(X)
    s2 = float(np.sum(res ** 2)) / max(2 * len(X) - 6, 1)
    zero = np.zeros_like(z)
    dX = point_along_pose(X)
    du = np.stack([cam.fx_px / z, zero, -cam.fx_px * x / z ** 2], 1)[:, None, :]
    dv = np.stack([zero, cam.fy_px / z, -cam.fy_px * y / z ** 2], 1)[:, None, :]
    J = np.concatenate([(du @ dX)[:, 0], (dv @ dX)[:, 0]])
    return s2 * np.linalg.inv(J.T @ J)


def point_along_pose(X_cam: np.ndarray) -> np.ndarray:
    """(N, 3, 6): how each point moves with its pose's left perturbation ``(omega_rad, tau_mm)``."""
    x, y, z = np.asarray(X_cam, np.float64).T
    zero, one = np.zeros_like(z), np.ones_like(z)
    return np.stack([np.stack([zero, z, -y, one, zero, zero], 1),
                     np.stack([-z, zero, x, zero, one, zero], 1),
                     np.stack([y, -x, zero, zero, zero, one], 1)], 1)


def _psd_max(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A covariance at least as large as ``A`` (positive definite) and ``B`` in every direction: ``B`` in ``A``'s
    whitened frame, its eigenvalues raised to 1 where below."""
    L = np.linalg.cholesky(A)
    Li = np.linalg.inv(L)
    lam, Q = np.linalg.eigh(Li @ B @ Li.T)
    C = L @ Q @ np.diag(np.maximum(lam, 1.0)) @ Q.T @ L.T
    return 0.5 * (C + C.T)


def _cluster_ls(J: np.ndarray, r: np.ndarray, clusters: np.ndarray, K: list[np.ndarray] | None = None,
                pose_covs: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Least squares ``J x ~ r`` (clusters: a pose's corners) and its covariance: the pose-clustered sandwich, and
    where ``K`` (each cluster's residuals' derivative by its pose, rows in the cluster's order) and ``pose_covs``
    (each pose's PnP covariance) are given, at least the model's: each residual's own scatter plus its pose's error
    carried through ``K``. With a few poses the clustered spread alone is one draw of a few degrees of freedom and now
    and then far too small (benchmarks/RESULTS.md, "calibrate-scale's sigma")."""
    x, *_ = np.linalg.lstsq(J, r, rcond=None)
    e = r - J @ x
    Hi = np.linalg.inv(J.T @ J)
    ids = np.unique(clusters)
    g = np.stack([J[clusters == c].T @ e[clusters == c] for c in ids])
    G = len(ids)
    C = Hi @ (g.T @ g) @ Hi * (G / max(G - J.shape[1], 1))
    if K is None or pose_covs is None:
        return x, C
    # each residual's own scatter: what is left once each pose's own motion (K's columns) is fitted out of its
    # residuals (else the poses' errors, carried through K below, would be counted twice)
    within, dof, carried = 0.0, len(e) - J.shape[1], []
    for c, Kc, Pc in zip(ids, K, pose_covs):
        sel = clusters == c
        beta, _, rank, _ = np.linalg.lstsq(Kc, e[sel], rcond=None)
        within += float(np.sum((e[sel] - Kc @ beta) ** 2))
        dof -= rank
        M = J[sel].T @ Kc
        carried.append(M @ Pc @ M.T)
    meat = within / max(dof, 1) * (J.T @ J)
    for term in carried:  # (added in this order: the same sum, bit for bit, as when each was added in turn)
        meat += term
    return x, _psd_max(Hi @ meat @ Hi, C)


def board_zed_measurement(poses: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]], rig: Rig
                          ) -> BoardMeasurement | None:
    """``b`` and ``yaw`` from board corners: ``poses`` are (name, corners in the ZED-left frame from PnP in the
    ZED-left image (N, 3) mm, left corners (N, 2), right corners (N, 2) as detected in the right image as captured).
    The right corner predicted from the left one, the PnP depth and the parameters is fitted to the detected one
    (Gauss-Newton on the exact yaw homography)."""
    if len(poses) < 3:
        return None
    zed = rig.zed
    f, fb = zed.f_px, zed.f_px * zed.baseline_mm
    Z = np.concatenate([p[1][:, 2] for p in poses])
    ul = np.concatenate([p[2] for p in poses])
    ur = np.concatenate([p[3] for p in poses])
    clusters = np.concatenate([np.full(len(p[1]), i) for i, p in enumerate(poses)])
    pose_covs = [p[4] for p in poses] if all(len(p) > 4 for p in poses) else None
    d0 = fb / Z - zed.doffs_px
    x = np.zeros(3)  # b, yaw, dy0 (a vertical rectification offset, not ours)
    for _ in range(5):
        xr = ul[:, 0] - d0 - x[0] * fb / Z
        ua, va = apply_homography(yaw_homography(rig, x[1]), xr, ul[:, 1])
        xn, yn = (xr - zed.right.cx_px) / f, (ul[:, 1] - zed.right.cy_px) / f
        r = np.concatenate([ur[:, 0] - ua, ur[:, 1] - (va + x[2])])
        zero = np.zeros_like(Z)
        J = np.concatenate([np.stack([-fb / Z, f * (1 + xn * xn), zero], axis=1),
                            np.stack([zero, f * xn * yn, np.ones_like(Z)], axis=1)])
        K = None
        if pose_covs is not None:  # a pose's depth error moves its right points along x: d(xr)/dZ = f B (1 + b) / Z^2
            K = [np.concatenate([(-fb * (1 + x[0]) / p[1][:, 2] ** 2)[:, None] * point_along_pose(p[1])[:, 2],
                                 np.zeros((len(p[1]), 6))]) for p in poses]
        dx, C = _cluster_ls(J, r, np.concatenate([clusters, clusters]), K, pose_covs)
        x = x + dx
        if np.abs(dx[:2]).max() < 1e-9:
            break
    A = np.zeros((2, len(PARAMS)))
    A[0, IB], A[1, IY] = 1.0, 1.0
    return BoardMeasurement(A, x[:2], C[:2, :2], "boards: corner disparity against ZED-left PnP depth",
                            [p[0] for p in poses], "zed_pair")


def depth_at_rays(depth_mm: np.ndarray, uv: np.ndarray, half_px: int) -> np.ndarray:
    """The depth map's z along each depth-camera pixel ``uv`` (N, 2): ``1/z`` fitted as a plane in (u, v) over a
    ``2 half_px + 1`` window (exact on a planar surface), NaN where the window has fewer than half its pixels."""
    h, w = depth_mm.shape
    out = np.full(len(uv), np.nan)
    for i, (u, v) in enumerate(uv):
        iu, iv = int(round(u)), int(round(v))
        if iu - half_px < 0 or iv - half_px < 0 or iu + half_px >= w or iv + half_px >= h:
            continue
        win = depth_mm[iv - half_px: iv + half_px + 1, iu - half_px: iu + half_px + 1].astype(np.float64)
        vv, uu = np.mgrid[-half_px: half_px + 1, -half_px: half_px + 1]
        ok = np.isfinite(win) & (win > 0)
        if ok.sum() < 0.5 * win.size:
            continue
        A = np.stack([np.ones(ok.sum()), uu[ok] + iu - u, vv[ok] + iv - v], axis=1)
        coef, *_ = np.linalg.lstsq(A, 1.0 / win[ok], rcond=None)
        out[i] = 1.0 / coef[0]
    return out


def board_depth_measurement(poses: list[tuple[str, np.ndarray, np.ndarray]], rig: Rig, half_px: int
                            ) -> BoardMeasurement | None:
    """``k`` and ``c`` from board corners: ``poses`` are (name, corners in the texture camera's frame from PnP in the
    texture image (N, 3) mm, the raw depth map). Each corner's depth-camera z against the depth map's z along its
    ray: ``z_depth - z = k z + c``.

    With a separate depth camera, turning it by ``omega`` (``depth_pose_jacobian_px``'s rotation) also moves the
    board's plane along that ray, ``(z / h) omega . (n x q)`` (``n``, ``h``: the board's plane ``n . X = h`` in the
    depth camera, ``n`` in the texture camera's axes; ``q`` the corner from the depth camera's centre). The fit stays
    ``(k, c)``; the measurement says what it equals, ``(k, c) + P omega`` (``P``: the fit applied to that motion).
    Not ``omega`` itself: a PnP pose error moves a board's corners by a plane, as ``omega`` does, so only the poses
    tell them apart, and the pose-clustered covariance of five parameters from five poses is singular."""
    zs, dz, jp, cl, names, K, pose_covs = [], [], [], [], [], [], []
    T_mech_from_depth = rig.T_mech_from_depth_or_identity
    T_depth_from_mech = invert_T(T_mech_from_depth)
    cam = rig.depth_camera
    for i, (name, X_mech, depth, *pose_cov) in enumerate(poses):
        X = transform_points(T_depth_from_mech, X_mech)
        zm = depth_at_rays(depth, cam.project(X), half_px)
        ok = np.isfinite(zm)
        if ok.sum() < 10:
            continue
        zs.append(X[ok, 2])
        dz.append(zm[ok] - X[ok, 2])
        if rig.separate_depth_camera:
            q = X_mech[ok] - T_mech_from_depth[:3, 3]
            n_mech = np.linalg.svd(X_mech - X_mech.mean(axis=0))[2][2]  # the board's normal (its corners' plane)
            h = q @ n_mech  # (the same in the depth camera's frame: a rotation and its centre)
            jp.append((X[ok, 2] / h)[:, None] * np.cross(n_mech, q))
        cl.append(np.full(ok.sum(), i))
        names.append(name)
        if pose_cov:  # the texture camera's PnP error moves each corner's z in the depth camera: dz = -d(z)
            K.append(-(T_depth_from_mech[2, :3] @ point_along_pose(X_mech[ok])))
            pose_covs.append(pose_cov[0])
    if len(names) < 3:
        return None
    z = np.concatenate(zs)
    J = np.stack([z, np.ones_like(z)], axis=1)
    full = len(pose_covs) == len(names)
    x, C = _cluster_ls(J, np.concatenate(dz), np.concatenate(cl), K if full else None, pose_covs if full else None)
    A = np.zeros((2, len(PARAMS)))
    A[0, IK], A[1, IC] = 1.0, 1.0
    if rig.separate_depth_camera:
        A[:, IP] = np.linalg.lstsq(J, np.concatenate(jp), rcond=None)[0]
    return BoardMeasurement(A, x, C, "boards: depth map against texture-camera PnP depth", names, "depth_map")


def board_measurements(session, dirs, rig: Rig, board, params: ScaleParams,
                       progress: Callable[[str], None] | None = None) -> list[BoardMeasurement]:
    """Detect the board in every board capture (texture, ZED left and right images) and measure from them.

    Any target (``gtforge.core.targets.models``). ZED: the left and right points matched by id
    (``gtforge.core.zed.rectification.matched_board_points``: a symmetric grid numbered alike, circle centres corrected
    for their perspective bias at each image's own PnP pose, so the right points are where the circles' centres show);
    the corners' ZED-left coordinates from PnP on every left point. Depth: PnP on every point the texture image shows.
    A view with fewer than 6 points (``MIN_COMMON_CORNERS``; left and right: in common) or collinear ones is left out,
    with the reason logged."""

    X = board.corners_board()
    zed_poses, depth_poses = [], []

    # each capture's board detections found ahead on a thread: the calls below get them remembered
    ahead = captures_detected_ahead(dirs, session.load_capture, board,
                                    lambda cap: [(cap.zed_left, rig.zed.left), (cap.zed_right, rig.zed.right),
                                                 (cap.mech_texture, rig.mech)])
    for k, (d, cap, exc) in enumerate(ahead):
        if progress:
            progress(f"board {d.name} ({k + 1}/{len(dirs)})")
        if exc is not None:  # as calibrate: a board capture's file missing skips it; a file wrong stops
            if not missing_capture_file(exc):
                raise exc
            log.warning("board capture %s skipped: %s", d.name, exc)
            continue
        dl = detect_target(cap.zed_left, board, rig.zed.left, where=f"{d.name}: ZED-left image")
        dr = detect_target(cap.zed_right, board, rig.zed.right, where=f"{d.name}: ZED-right image") \
            if cap.zed_right is not None else None
        if dl is not None and dr is not None:
            pair = matched_board_points(board, dl, rig.zed.left, dr, rig.zed.right)
            if isinstance(pair, PairSkipped):
                log.info("board capture %s: ZED left/right %s; not used", d.name, pair.reason)
            else:
                X_zed = transform_points(pair.T_a_from_board, X[pair.ids])
                zed_poses.append((d.name, X_zed, pair.uv_a, pair.uv_b,
                                  pnp_pose_covariance(X_zed, pair.uv_a, rig.zed.left)))
        dm = detect_target(cap.mech_texture, board, rig.mech, where=f"{d.name}: structured-light image")
        if dm is not None and cap.depth_mm is not None:
            ids = np.arange(len(dm.corners_uv)) if dm.ids is None else dm.ids
            if len(ids) < MIN_COMMON_CORNERS or collinear(X[ids]):
                log.info("board capture %s: %d board points in the structured-light image%s; not used for the depth",
                         d.name, len(ids), "" if len(ids) < MIN_COMMON_CORNERS else ", on one line")
                continue
            if isinstance(board, CircleGridSpec) and not board.asymmetric:
                dm = unmirror_symmetric_grid(board, dm, rig.mech, solve_pnp)
            T_mech_from_board, _ = pnp_bias_corrected(board, dm, rig.mech, solve_pnp)
            X_mech = transform_points(T_mech_from_board, X[ids])
            depth_poses.append((d.name, X_mech, cap.depth_mm, pnp_pose_covariance(X_mech, dm.corners_uv, rig.mech)))
    out = [m for m in (board_zed_measurement(zed_poses, rig),
                       board_depth_measurement(depth_poses, rig, params.board_depth_window_px)) if m is not None]
    return out


# ---- combining and applying ----------------------------------------------------------------------
def combine(measurements: list[tuple[np.ndarray, np.ndarray, np.ndarray]], free: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Generalised least squares over the parameters flagged ``free`` (the others held at 0): each measurement
    ``(A, y, C)`` says ``A x ~ y`` with covariance ``C``. Returns (x with 0 where not free, covariance with zero rows
    there)."""
    idx = np.flatnonzero(free)
    x = np.zeros(len(free))
    cov = np.zeros((len(free), len(free)))
    if not len(idx):
        return x, cov
    H = np.zeros((len(idx), len(idx)))
    g = np.zeros(len(idx))
    for A, y, C in measurements:
        Ai = A[:, idx]
        W = np.linalg.inv(C)
        H += Ai.T @ W @ Ai
        g += Ai.T @ W @ y
    Hi = np.linalg.inv(H)
    x[idx] = Hi @ g
    cov[np.ix_(idx, idx)] = Hi
    return x, cov


def apply_scale(rig: Rig, baseline_file_mm: float, x: np.ndarray) -> Rig:
    """The rig with the parameters ``x`` (PARAMS' order, angles in rad) applied: the baseline ``(1 + b)`` times the
    file's, the depth scale/offset and yaw in ``scale_corrections``, and a separate depth camera's rotation as the
    left perturbation of ``T_mech_from_depth`` (``perturb_left``: about the depth camera's centre)."""
    zed = rig.zed.model_copy(update={"baseline_mm": baseline_file_mm * (1.0 + x[IB])})
    corr = ScaleCorrections(depth_scale=1.0 + x[IK], depth_offset_mm=float(x[IC]),
                            zed_right_yaw_deg=float(np.degrees(x[IY])))
    update = {"zed": zed.model_dump(), "scale_corrections": corr.model_dump()}
    if np.any(x[IP]):
        update["T_mech_from_depth"] = perturb_left(rig.T_mech_from_depth_or_identity, np.r_[x[IP], 0.0, 0.0, 0.0])
    return Rig.model_validate({**rig.model_dump(), **update})


def _disparity_effect_px(rig: Rig, z_mm: float, pose_px: np.ndarray) -> np.ndarray:
    """How many px one unit of each parameter moves a disparity at depth ``z_mm`` (angles per rad; the depth camera's
    rotation: ``pose_px``, ``pose_effect_px``)."""
    fb = rig.zed.f_px * rig.zed.baseline_mm
    return np.r_[fb / z_mm, rig.zed.f_px, fb / z_mm, fb / z_mm ** 2, pose_px]


def _refuse_implausible(x: np.ndarray, applied: np.ndarray, params: ScaleParams, calib_path: Path,
                        baseline_file_mm: float) -> None:
    """A correction larger than any rig's files need (``ScaleParams.max_*``) is a symptom, not a correction: a length
    in another unit, another rig's calibration, a session of another camera. Refused (nothing written), naming it."""
    limits = {IB: (params.max_scale_correction_frac, 1.0, ""), IY: (params.max_yaw_deg, np.degrees(1.0), " deg"),
              IK: (params.max_scale_correction_frac, 1.0, ""), IC: (params.max_depth_offset_mm, 1.0, " mm")}
    limits.update({i: (params.max_depth_pose_deg, np.degrees(1.0), " deg") for i in range(IP.start, IP.stop)})
    for i, (limit, unit, suffix) in limits.items():
        if i < len(x) and applied[i] and abs(x[i] * unit) > limit:
            value = f"{x[i]:+.4g} ({x[i]:+.2%})" if suffix == "" else f"{x[i] * unit:+.4g}{suffix}"
            raise InputError(calib_path, PARAMS[i], f"a correction within +-{limit:g}{suffix} (what a rig's files "
                             "can be off by)", f"{value} from the scenes and boards",
                             f"the files or the session are wrong, not the rig: the ZED baseline here is "
                             f"{baseline_file_mm:g} mm (a ZED Mini's is 63 mm); check the camera files' units (mm) and "
                             "that -c is this rig's calibration; nothing was written")


def calibrate_scale(session_dir: str | Path, calibration: str | Path, out_path: str | Path | None = None,
                    params: ScaleParams | None = None, scenes: list[str] | None = None,
                    progress: Callable[[str], None] | None = None):
    """Estimate and apply the disparity-scale terms (module docstring); writes ``out_path`` when given. Returns the
    corrected calibration file (``scale_calibration`` says what was found and applied)."""

    t0 = time.perf_counter()
    params = params or ScaleParams()
    calib_path = Path(calibration)
    calib = CalibrationFile.read(calib_path)
    if calib.scale_corrected:
        raise InputError(calib_path, "scale_calibration", "a calibration without a scale correction",
                         "one already corrected", "run calibrate-scale on the calibration calibrate (or align-depth) "
                         "wrote")
    if calib.refinement is not None:
        # refine fits the extrinsic to the scenes through the uncorrected depth: it takes up part of a depth scale or
        # offset error in the translation, which the terms found here would then correct a second time
        start = calib.refinement.refined_from
        raise InputError(calib_path, "refinement", "a calibration refine has not moved (calibrate-scale runs before "
                         "refine: refine fits the extrinsic through the depth, and would take up part of a depth "
                         "scale or offset error that calibrate-scale then corrects again)",
                         f"one refined from {start}",
                         f"run calibrate-scale on {start}, then refine its output (docs/pipeline.md)")
    # the session as the calibration sees it: its SN.conf reading and ZED self-rectification (no yaw yet: a calibration
    # with one is refused above), so the yaw is measured on the right images as the self-rectification leaves them
    session, out_path = open_calibrated_session(session_dir, calib, calib_path, out_path, "scaled.yaml")
    rig_file = calib.rig
    B_file = rig_file.zed.baseline_mm
    # the boards first: absolute measurements, independent of the scenes' GT
    boards = []
    board_root = session.root / session.config.board_dir
    board_dirs = session.select("board", None) if params.use_boards and board_root.is_dir() and any(
        p.is_dir() for p in board_root.iterdir()) else []
    if board_dirs:
        boards = board_measurements(session, board_dirs, rig_file, calib.board.spec(), params, progress)
    have_b = any(m.A[:, IB].any() for m in boards)
    have_k = any(m.A[:, IK].any() for m in boards)
    dirs, not_selected = session.select_scenes(scenes, params.max_scenes)
    build = BuildParams()
    x = np.zeros(len(PARAMS))
    rig = apply_scale(rig_file, B_file, x)
    separate = rig_file.separate_depth_camera
    reports = {d.name: SceneScaleResult(scene=d.name) for d in dirs}
    # each scene's depth and fruit mask (what every pass rebuilds its GT from) and what the fit reads from its images;
    # the decoded images themselves are not kept
    scenes_kept: dict[str, tuple[np.ndarray, np.ndarray | None, SceneImages]] = {}
    for d in dirs:
        if progress:
            progress(f"scene {d.name}")
        cap = session.load_capture(d)
        # a scene whose fruit moved between the captures (its texture shift over the fruit differs from the whole
        # area's) has a GT the images do not show: left out (a uniform shift, which a depth scale error also causes,
        # is kept)
        sd, region, _ = build_scene_arrays(cap.depth_mm, rig, build, cap.fruit_mask)
        ver, _ = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, cap.zed_left, None,
                              cap.mech_texture, rig, params.verify)
        a, f = ver.texture_all, ver.texture_fruit
        if a.dx_px is not None and f.dx_px is not None and \
                np.hypot(f.dx_px - a.dx_px, f.dy_px - a.dy_px) > params.verify.max_shift_px:
            reports[d.name].excluded = (f"the fruit's texture shift differs from the whole area's by "
                                        f"{np.hypot(f.dx_px - a.dx_px, f.dy_px - a.dy_px):.2f} px (did it move?)")
            continue
        scenes_kept[d.name] = cap.depth_mm, cap.fruit_mask, scene_images(cap.zed_left, cap.zed_right, params)
    # without a board measurement of b or of k, scenes see only b + k: one term, carried by b
    # the depth camera's rotation: only a separate depth camera has one of its own (else it is the extrinsic's)
    free = np.array([True, True, have_k or have_b, True] + [separate] * 3)
    cov = np.zeros((len(PARAMS), len(PARAMS)))
    passes = 0
    determined = free.copy()
    for outer in range(params.outer_iterations):
        passes = outer + 1
        pix = []
        for s, (depth_mm, fruit_mask, images) in scenes_kept.items():
            if progress:
                progress(f"pass {outer + 1}: scene {s}")
            sd, _, _ = build_scene_arrays(depth_mm, rig, build, fruit_mask)
            sp = scene_pixels(s, sd.depth_mm, sd.disparity_px, sd.nonoccluded, images, params, rig)
            if sp is not None:
                pix.append(sp)
                reports[s].n_points = len(sp.u)
        if not pix:
            raise InputError(session.root / session.config.scenes_dir, None, "scenes with textured ground truth",
                             "none", "add scene captures with texture")
        z_med = float(np.median(np.concatenate([sp.z_mm for sp in pix])))
        theta, C_s, nuis = solve_scenes(pix, rig, params, x[IY])
        if outer == 0:
            for sp, nu in zip(pix, nuis):
                fb = rig.zed.f_px * rig.zed.baseline_mm
                reports[sp.name].disparity_bias_before_px = float(np.mean(
                    theta[0] * fb / sp.z_mm + theta[1] * fb / sp.z_mm ** 2
                    + (0.0 if sp.g_pose is None else sp.g_pose @ theta[3:6])
                    - (apply_homography(yaw_homography(rig, theta[2]), sp.u - sp.d_gt, sp.v)[0] - (sp.u - sp.d_gt))))
        # the scenes measure (b + k, c, yaw) as increments on the current rig (b and k carried additively: their
        # product is below 1e-5)
        A_s = np.zeros((len(theta), len(PARAMS)))
        A_s[0, IB] = A_s[0, IK] = 1.0
        A_s[1, IC] = A_s[2, IY] = 1.0
        y_s = np.array([x[IB] + x[IK] + theta[0], x[IC] + theta[1] * (1.0 + x[IK]), theta[2]])
        if len(theta) > 3:  # the depth camera's rotation, an increment on the current rig's
            A_s[3:, IP] = np.eye(3)
            y_s = np.r_[y_s, x[IP] + theta[3:]]
        meas = [(A_s, y_s, C_s)] + [(m.A, m.y, m.C) for m in boards]
        determined = free.copy()
        x_new, cov = combine(meas, determined)
        eff = _disparity_effect_px(rig, z_med, pose_effect_px(pix))
        for _ in range(4):  # leave out what the data do not determine, solve again without it
            bad = determined & (np.sqrt(np.maximum(np.diag(cov), 0)) * eff > params.max_sigma_px)
            if not bad.any():
                break
            determined &= ~bad
            x_new, cov = combine(meas, determined)
        x_est, cov_est, applied = x_new, cov, determined.copy()
        while applied.any():  # hold the least significant term at 0 while any is within apply_z sigma of it
            z = np.where(applied, np.abs(x_new) / np.sqrt(np.maximum(np.diag(cov), 1e-300)), np.inf)
            if z.min() > params.apply_z:
                break
            applied[int(np.argmin(z))] = False
            x_new, cov = combine(meas, applied)
        moved = float(np.abs((x_new - x) * eff).max())
        x = x_new
        rig = apply_scale(rig_file, B_file, x)
        if progress:
            progress(f"pass {outer + 1}: correction moved disparities by {moved:.4f} px")
        if moved < params.converged_px:
            break
    _refuse_implausible(x, applied, params, calib_path, B_file)
    # reported: every determined term's estimate and the covariance with all of them free (the uncertainty the labels
    # carry, applied or not); applied: x
    sig = np.sqrt(np.maximum(np.diag(cov_est), 0))
    src_scene = "scenes: stereo consistency"
    srcs = {i: [] if i == IK else [src_scene] for i in range(len(PARAMS))}
    for m in boards:
        for i in range(len(PARAMS)):
            if m.A[:, i].any():
                srcs[i].append(m.source)
    if not have_k and have_b:  # k from the scenes' b + k less the boards' b
        srcs[IK] = [src_scene] + [m.source for m in boards if m.A[:, IB].any()]
    if not have_b and have_k:  # b from the scenes' b + k less the boards' k
        srcs[IB] += [m.source for m in boards if m.A[:, IK].any()]
    unit = np.array([1.0, np.degrees(1.0), 1.0, 1.0] + [np.degrees(1.0)] * 3)  # angles to degrees in the file
    n_out = len(PARAMS) if separate else 4  # the depth camera's rotation: only with a separate depth camera
    terms = {}
    sig_held = np.sqrt(np.maximum(np.diag(cov), 0))  # the applied terms' sigmas with the others held at 0
    for i, name in enumerate(PARAMS[:n_out]):
        if applied[i]:
            # significance is decided with the terms not applied held at 0 (a correlated term held takes its share);
            # where the all-free estimate alone would not be significant, the line says which figures decided it
            why = "" if abs(x_est[i]) > params.apply_z * sig[i] else (
                f"significant with the terms not applied held at 0: {x[i] * unit[i]:+.4g} +- "
                f"{sig_held[i] * unit[i]:.3g}; with every term free within {params.apply_z:g} sigma of 0")
            terms[name] = ScaleTerm(value=float(x[i] * unit[i]), estimate=float(x_est[i] * unit[i]),
                                    sigma=float(sig[i] * unit[i]), status="applied", sources=srcs[i], reason=why)
        elif determined[i]:
            why = f"within {params.apply_z:g} sigma of 0: not applied" if abs(x_est[i]) <= params.apply_z * sig[i] \
                else (f"within {params.apply_z:g} sigma of 0 when it was held (the least significant term first, "
                      f"the others solved again each time), though the all-free estimate is not: not applied")
            terms[name] = ScaleTerm(value=0.0, estimate=float(x_est[i] * unit[i]), sigma=float(sig[i] * unit[i]),
                                    status="not significant", sources=srcs[i], reason=why)
        elif not free[i]:
            terms[name] = ScaleTerm(value=0.0, estimate=None, sigma=None, status="not separable", sources=[],
                                    reason="no board capture measures the depth scale or the baseline: scenes see "
                                           "only their sum, applied to the baseline "
                                           "(zed_baseline_frac holds the sum)")
        else:
            terms[name] = ScaleTerm(value=0.0, estimate=None, sigma=None, status="not determined", sources=srcs[i],
                                    reason=f"its 1-sigma would move disparities by more than {params.max_sigma_px} px")
    if not free[IK] and determined[IB]:
        terms[PARAMS[IB]].reason = ("the sum of the baseline and depth scales (not separable without board captures)"
                                    + ("" if applied[IB] else f"; within {params.apply_z:g} sigma of 0: not applied"))
    D = np.diag(unit[:n_out])
    covariance = (D @ cov_est[:n_out, :n_out] @ D)
    s_var = cov_est[IB, IB] + cov_est[IK, IK] + 2 * cov_est[IB, IK]
    info = ScaleCalibration(
        calibrated_from=str(calib_path.resolve()), terms=terms, covariance=covariance.tolist(),
        combined_scale_frac=float(x_est[IB] + x_est[IK]),
        combined_scale_sigma_frac=float(np.sqrt(s_var)) if determined[IB] else None,
        baseline_file_mm=B_file,
        T_mech_from_depth_file=rig_file.T_mech_from_depth_or_identity.tolist() if separate else None,
        scenes_used=[sp.name for sp in pix], scenes_not_selected=not_selected,
        board_poses_used=sorted({p for m in boards for p in m.poses}),
        board_poses_by_measurement={m.kind: sorted(m.poses) for m in boards}, passes=passes,
        scenes=[reports[s] for s in sorted(reports)], time_s=time.perf_counter() - t0)
    out = calib.model_copy(update=dict(rig=rig, scale_calibration=info))
    out = CalibrationFile.model_validate(out.model_dump())
    if out_path is not None:
        out.write(out_path)
    return out
