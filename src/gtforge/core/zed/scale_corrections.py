"""Applying calibrate-scale's corrections (``Rig.scale_corrections``; ``gtforge.scale_calibration`` estimates them):
the right camera's yaw as a homography (``yaw_homography``; the session folds it into its one resampling of the right
image, ``gtforge.core.zed.selfcal.corrected_right``), the ground truth's sigma widened by the terms' covariance, and the
disparity a turned right camera shows (the generator's truth). ``corrected_right_image`` is the second resampling the
stages did before the yaw went into the session's (kept as the reference the single resampling is compared with)."""
from __future__ import annotations

from typing import Protocol

import numpy as np

from gtforge.core import bspline
from gtforge.core.camera import Rig
from gtforge.core.geometry import invert_T


class ScaleCovariance(Protocol):
    """What the sigma map needs of calibrate-scale's record (``gtforge.records.calibration.ScaleCalibration``): the
    applied terms' covariance in the file's units (4x4, or 7x7 with a separate depth camera's rotation)."""

    covariance: list[list[float]]


def yaw_homography(rig: Rig, yaw_rad: float) -> np.ndarray:
    """``H``: rectified right pixel -> pixel of the right image as captured by a right camera turned by ``yaw_rad``
    about its y axis (``K_r R_y(yaw) K_r^-1``, homogeneous)."""
    return right_yaw_homography(rig.zed.right.K, yaw_rad)


def right_yaw_homography(K_right: np.ndarray, yaw_rad: float) -> np.ndarray:
    """``yaw_homography`` for the rectified right camera matrix ``K_right``."""
    K = K_right
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return K @ R @ np.linalg.inv(K)


def apply_homography(H: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w = H[2, 0] * u + H[2, 1] * v + H[2, 2]
    return (H[0, 0] * u + H[0, 1] * v + H[0, 2]) / w, (H[1, 0] * u + H[1, 1] * v + H[1, 2]) / w



def corrected_right_image(image: np.ndarray | None, rig: Rig) -> np.ndarray | None:
    """The right image re-rectified for ``rig.scale_corrections``' yaw (the image itself when none): each rectified
    pixel sampled (cubic B-spline, exact positions; black outside) where the turned camera saw it.

    The second resampling the stages used to make of a right image the session had already rectified; the session now
    folds the yaw into its own (``CalibrationFile.open_session``). Kept as the reference of that two-pass path: for
    an image rectified before gtforge with the yaw alone it is exactly what the session gives."""
    yaw = rig.zed_right_yaw_deg
    if image is None or yaw == 0.0:
        return image
    return bspline.resample_homography(image, yaw_homography(rig, np.radians(yaw)))



def depth_pose_jacobian_px(u: np.ndarray, v: np.ndarray, z_mm: np.ndarray, du: np.ndarray, dv: np.ndarray,
                           rig: Rig) -> np.ndarray:
    """(N, 3) px per rad: how the ground truth at ZED-left pixels ``(u, v)`` (GT depth ``z_mm``, the GT disparity's
    slopes ``du``, ``dv`` per px there) changes when the depth camera is turned by ``omega`` (the left perturbation of
    ``rig.T_mech_from_depth``, ``gtforge.core.geometry.perturb_left``: a rotation about the depth camera's centre,
    axes of the texture camera).

    A depth point ``X`` moves by ``dX_mech = omega x (X_mech - t_mech_from_depth)``; the label at a fixed pixel changes
    by its own disparity change less the GT's slope times its image motion, ``(dd/dX - grad d . du/dX) dX``
    (the sigma map's rule, docs/design/accuracy.md)."""
    zed = rig.zed
    f, fb = zed.f_px, zed.f_px * zed.baseline_mm
    xn = (np.asarray(u, np.float64) - zed.left.cx_px) / f
    yn = (np.asarray(v, np.float64) - zed.left.cy_px) / f
    z = np.asarray(z_mm, np.float64)
    X_zed = np.stack([xn * z, yn * z, z], axis=-1)
    T_mech_from_zed = invert_T(rig.T_zed_from_mech)
    q = X_zed @ T_mech_from_zed[:3, :3].T + T_mech_from_zed[:3, 3] - rig.T_mech_from_depth_or_identity[:3, 3]
    # d(label)/d(X_zed): dd/dX less the slopes times du/dX, dv/dX (f / Z (1, 0, -x), f / Z (0, 1, -y))
    a = np.stack([-du * f / z, -dv * f / z, -fb / z ** 2 + (du * xn + dv * yn) * f / z], axis=-1)
    w = a @ rig.T_zed_from_mech[:3, :3]  # the same per mm of motion in the texture camera's axes
    return np.cross(q, w)  # w . (omega x q) = omega . (q x w)


def depth_pose_jacobian_image(depth_mm: np.ndarray, rig: Rig) -> np.ndarray:
    """``depth_pose_jacobian_px`` at every ZED-left pixel of a GT depth image (H, W, 3); slopes by central differences
    of ``f B / Z`` (0 where a neighbour has no depth)."""
    zed = rig.zed
    z = np.asarray(depth_mm, np.float64)
    d = zed.f_px * zed.baseline_mm / z
    dv, du = np.gradient(d)
    v, u = np.mgrid[0:z.shape[0], 0:z.shape[1]].astype(np.float64)
    return depth_pose_jacobian_px(u, v, z, np.nan_to_num(du), np.nan_to_num(dv), rig)


def scale_sigma_px(depth_mm: np.ndarray, rig: Rig, info: ScaleCovariance) -> np.ndarray:
    """Each GT pixel's 1-sigma (px) from the applied scale terms' covariance: ``sqrt(J C J^T)`` with
    ``J = (f B / Z, f (1 + x^2) pi / 180, f B / Z, f B / Z^2)`` (per unit of each parameter in the file's units), and
    with a separate depth camera's rotation (a 7x7 covariance) its ``depth_pose_jacobian_image`` per degree."""
    zed = rig.zed
    fb = zed.f_px * zed.baseline_mm
    z = np.asarray(depth_mm, np.float64)
    x = (np.arange(z.shape[1], dtype=np.float64)[None, :] - zed.left.cx_px) / zed.f_px
    J = [fb / z, np.broadcast_to(zed.f_px * (1 + x * x) * np.pi / 180.0, z.shape), fb / z, fb / z ** 2]
    C = np.asarray(info.covariance, np.float64)
    if len(C) > 4:
        Jp = depth_pose_jacobian_image(z, rig) * (np.pi / 180.0)
        J += [Jp[..., 0], Jp[..., 1], Jp[..., 2]]
    var = np.zeros(z.shape)
    for i in range(len(C)):
        for j in range(len(C)):
            if C[i, j] != 0.0:
                var += J[i] * C[i, j] * J[j]
    return np.sqrt(np.maximum(var, 0.0))



def add_scale_sigma(sigma_px: np.ndarray, depth_mm: np.ndarray, rig: Rig, info: ScaleCovariance) -> np.ndarray:
    """``sigma_px`` (float32, +inf where no GT) with the scale terms' sigma added in quadrature."""
    s = scale_sigma_px(depth_mm, rig, info)
    with np.errstate(invalid="ignore"):
        out = np.sqrt(np.asarray(sigma_px, np.float64) ** 2 + np.where(np.isfinite(s), s, 0.0) ** 2)
    return out.astype(np.float32)



def depth_pose_sigma_px(depth_mm: np.ndarray, rig: Rig, cov_rad_mm) -> np.ndarray:
    """Each GT pixel's 1-sigma (px) from the covariance of a separate depth camera's rotation (the left perturbation
    of ``rig.T_mech_from_depth``; a 6x6 ``(omega rad, delta_t mm)`` covariance whose rotation block is used, as
    ``gtforge align-depth`` writes it): ``sqrt(J C J^T)`` with ``J = depth_pose_jacobian_image`` (per rad)."""
    C = np.asarray(cov_rad_mm, np.float64)[:3, :3]
    z = np.asarray(depth_mm, np.float64)
    if not C.any():
        return np.zeros(z.shape)
    J = depth_pose_jacobian_image(z, rig)
    return np.sqrt(np.maximum(np.einsum("...i,ij,...j->...", J, C, J), 0.0))


def add_depth_pose_sigma(sigma_px: np.ndarray, depth_mm: np.ndarray, rig: Rig, cov_rad_mm) -> np.ndarray:
    """``sigma_px`` (float32, +inf where no GT) with ``depth_pose_sigma_px`` added in quadrature."""
    s = depth_pose_sigma_px(depth_mm, rig, cov_rad_mm)
    with np.errstate(invalid="ignore"):
        out = np.sqrt(np.asarray(sigma_px, np.float64) ** 2 + np.where(np.isfinite(s), s, 0.0) ** 2)
    return out.astype(np.float32)


def shown_disparity_px(disp_true_px: np.ndarray, rig: Rig, yaw_true_deg: float) -> np.ndarray:
    """What the dataset's pair shows (synthetic truth): the left image against the right image re-rectified with
    ``rig``'s yaw when the right camera is really turned by ``yaw_true_deg``; ``disp_true_px`` is the ideal rectified
    pair's disparity at ZED-left pixel centres. (The left pixel's match in the re-rectified image is
    ``H(yaw_rig)^-1 H(yaw_true)`` of its ideal match.)"""
    h, w = disp_true_px.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    xr = u - disp_true_px
    ua, va = apply_homography(yaw_homography(rig, np.radians(yaw_true_deg)), xr, v)
    ui, _ = apply_homography(np.linalg.inv(yaw_homography(rig, np.radians(rig.zed_right_yaw_deg))), ua, va)
    return (u - ui).astype(np.float32)
