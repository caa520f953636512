"""One fruit's rigid motion between the structured-light exposure and the ZED exposure (issue #37).

The fruit's surface points as the depth camera measured them (ZED-left frame, ``X``) are moved by a rigid motion about
their centroid ``c``, ``X' = exp(omega) (X - c) + c + t``, and projected into the rectified ZED left and right images.
At the right motion the two images show the same texture at those positions (the stereo term: the same instant, the
same shading, no cross-modal matching), and the ZED-left image shows there what the structured-light texture showed
at ``X`` (the texture term: the in-plane directions and the turn, which the stereo term alone sees only through the
fruit's shape: a sphere turned about its centre keeps its surface). Both are locally normalised images
(``local_normalize``), sampled by cubic B-spline with their own derivatives (``sample_spline``, as verification
samples them), each term with its own gain and offset. Gauss-Newton with Huber weights, coarse to fine (images blurred
by ``SIGMAS_PX``), started from the fruit's 2-D texture shift (``ShiftAligner``, the shift verification measures).

Covariance of the six parameters ``(omega_x, omega_y, omega_z)`` rad then ``(t_x, t_y, t_z)`` mm (a left perturbation
about the moved centroid, as the extrinsic's in docs/conventions.md): the cluster-robust sandwich
``H^-1 S H^-1`` of the Huber normal equations, the scores summed over ``TILE_PX``-square tiles (neighbouring pixels'
residuals are correlated by the blur, the interpolation and the normalisation; tiles are about independent:
``huber_system``), times ``COVARIANCE_INFLATION`` (measured: benchmarks/bench_motion_compensation.py)."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from gtforge.core.alignment.photometric import (
    ShiftAligner,
    even_subset,
    huber_system,
    sample_spline,
    spline_prefilter,
)
from gtforge.core.camera import RectifiedStereo
from gtforge.core.geometry import make_T

# blur (px at the images' resolution) of the coarse and the fine pass: the coarse one brings shifts of several pixels
# into the fine one's reach
SIGMAS_PX = (3.0, 1.0)
TILE_PX = 8.0  # the sandwich covariance's tiles (px)
TEXTURE_WEIGHT = 1.0  # the texture term's residuals against the stereo term's, each in units of its robust scale
HUBER = 1.345  # Huber's constant, in units of each term's robust residual scale
MAX_POINTS = 20000  # a larger fruit is subsampled evenly
MAX_ITERATIONS = 30
# the sandwich covariance scaled by this: measured, the sandwich alone leaves a systematic part out (the texture term's
# cross-modal residuals: the two cameras' shading, blur and sampling differ; larger tiles only make it worse). Over 28
# fruit of 7 draws at half resolution (benchmarks/bench_motion_compensation.py --scale 0.5) the median squared
# Mahalanobis distance to the truth was 21.3 (5.35 when honest) and its 90th percentile 45: x4 brings both in line
COVARIANCE_INFLATION = 4.0


def so3_exp(omega: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(omega, np.float64).reshape(3, 1))[0]


def so3_log(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()


@dataclass
class FruitMotionEstimate:
    """``T_zed_moved_from_zed``: where a fruit point was at the depth exposure -> where it was at the ZED's (ZED-left
    frame). ``rotvec_rad`` and ``translation_mm`` about ``centre_mm`` (the measured points' centroid):
    ``X' = R (X - c) + c + t``; ``cov_rad_mm`` their 6x6 covariance (left perturbation, order omega then t)."""

    centre_mm: np.ndarray
    rotvec_rad: np.ndarray
    translation_mm: np.ndarray
    cov_rad_mm: np.ndarray
    n_points: int
    iterations: int
    converged: bool
    residual_rms: float  # of the fine pass's normalised residuals (both terms)
    stereo_correlation: float | None  # of the left and right samples at the estimate
    points_mm: np.ndarray  # (N, 3) the points fitted, at the depth exposure

    @property
    def moved_points_mm(self) -> np.ndarray:
        return (self.points_mm - self.centre_mm) @ so3_exp(self.rotvec_rad).T + self.centre_mm + self.translation_mm

    @property
    def T_zed_moved_from_zed(self) -> np.ndarray:
        R = so3_exp(self.rotvec_rad)
        return make_T(R, self.centre_mm + self.translation_mm - R @ self.centre_mm)

    def params_from_T(self, T_zed_moved_from_zed: np.ndarray) -> np.ndarray:
        """Another motion (a truth) in this estimate's parameters about ``centre_mm``: ``(omega, t)``."""
        R, p = T_zed_moved_from_zed[:3, :3], T_zed_moved_from_zed[:3, 3]
        return np.r_[so3_log(R), R @ self.centre_mm + p - self.centre_mm]

    def mahalanobis_sq(self, T_zed_moved_from_zed: np.ndarray) -> float:
        """Squared Mahalanobis distance of ``T_zed_moved_from_zed`` from this estimate (chi-square with 6 degrees of
        freedom when the covariance is honest). The error is the left perturbation taking the estimate to it."""
        R_e = so3_exp(self.rotvec_rad)
        R_t, p_t = T_zed_moved_from_zed[:3, :3], T_zed_moved_from_zed[:3, 3]
        t_t = R_t @ self.centre_mm + p_t - self.centre_mm
        e = np.r_[so3_log(R_t @ R_e.T), t_t - self.translation_mm]
        return float(e @ np.linalg.solve(self.cov_rad_mm, e))


class MotionImages:
    """The scene's images prepared once for every fruit: the locally normalised ZED left and right (grey, float32) and
    the texture rendered into the ZED-left view through the ground truth (normalised; 0 where not rendered), as B-spline
    coefficients blurred by each of ``SIGMAS_PX``."""

    def __init__(self, left_norm: np.ndarray, right_norm: np.ndarray, rendered_norm: np.ndarray | None):
        self.left_norm = left_norm
        self.rendered_norm = rendered_norm
        self.levels = []
        for s in SIGMAS_PX:
            self.levels.append((spline_prefilter(cv2.GaussianBlur(left_norm, (0, 0), s)),
                                spline_prefilter(cv2.GaussianBlur(right_norm, (0, 0), s)),
                                None if rendered_norm is None else cv2.GaussianBlur(rendered_norm, (0, 0), s)))
        self._aligner = None

    def initial_shift_px(self, v: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The fruit's 2-D texture shift (ZED-left px, ``ShiftAligner`` as verification measures it), 0 without a
        texture or when it does not converge."""
        if self.rendered_norm is None:
            return np.zeros(2)
        if self._aligner is None:
            self._aligner = ShiftAligner(self.rendered_norm, self.left_norm)
        e = self._aligner.align_at(v, u, min_pixels=50)
        return np.zeros(2) if e.dx_px is None else np.array([e.dx_px, e.dy_px])


def _projections(X: np.ndarray, zed: RectifiedStereo):
    """Left and right pixels of ``X`` and their Jacobians d(u_l, u_r, v)/dX (N, 3, 3)."""
    f, fy = zed.left.fx_px, zed.left.fy_px
    cx, cy, cxr, B = zed.left.cx_px, zed.left.cy_px, zed.right.cx_px, zed.baseline_mm
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    iz = 1.0 / z
    ul, ur, v = f * x * iz + cx, f * (x - B) * iz + cxr, fy * y * iz + cy
    J = np.zeros((len(X), 3, 3))
    J[:, 0, 0] = f * iz
    J[:, 0, 2] = -f * x * iz * iz
    J[:, 1, 0] = f * iz
    J[:, 1, 2] = -f * (x - B) * iz * iz
    J[:, 2, 1] = fy * iz
    J[:, 2, 2] = -fy * y * iz * iz
    return ul, ur, v, J


def _robust_scale(r: np.ndarray) -> float:
    return max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-6)


def estimate_fruit_motion(points_zed_mm: np.ndarray, pixels_vu: tuple[np.ndarray, np.ndarray], images: MotionImages,
                          zed: RectifiedStereo, use_texture: bool = True, use_stereo: bool = True,
                          initial_T: np.ndarray | None = None) -> FruitMotionEstimate | None:
    """The rigid motion of one fruit (module docstring). ``points_zed_mm`` (N, 3): the fruit's ground-truth points
    (ZED-left frame, at the depth exposure), at the ZED-left pixels ``pixels_vu`` (integer rows, columns) where the
    ground truth put them. ``initial_T``: a start ``T_zed_moved_from_zed`` instead of the texture shift (diagnostics:
    each term's own optimum near the truth). None when too few points or the fit diverges."""
    v0, u0 = pixels_vu
    keep = even_subset(len(points_zed_mm), MAX_POINTS)
    X0 = np.asarray(points_zed_mm, np.float64)[keep]
    v0, u0 = np.asarray(v0)[keep], np.asarray(u0)[keep]
    n = len(X0)
    if n < 100:
        return None
    texture = use_texture and images.rendered_norm is not None
    if texture:  # points where the texture was rendered
        ok = images.rendered_norm[v0, u0] != 0
        X0, v0, u0 = X0[ok], v0[ok], u0[ok]
        n = len(X0)
        if n < 100:
            return None
    c = X0.mean(axis=0)
    Xc = X0 - c
    z_med = float(np.median(X0[:, 2]))
    if initial_T is None:
        d2 = images.initial_shift_px(v0, u0) if texture else np.zeros(2)
        omega = np.zeros(3)
        t = np.array([d2[0] * z_med / zed.left.fx_px, d2[1] * z_med / zed.left.fy_px, 0.0])
    else:
        Ri, pi = np.asarray(initial_T, np.float64)[:3, :3], np.asarray(initial_T, np.float64)[:3, 3]
        omega, t = so3_log(Ri), Ri @ c + pi - c
    converged, it_total, cov, rms = False, 0, None, float("nan")
    corr = None
    for level, (cl, cr, tex) in enumerate(images.levels):
        fine = level == len(images.levels) - 1
        t_vals = tex[v0, u0].astype(np.float64) if texture else None
        gains = np.array([1.0, 0.0, 1.0, 0.0])  # stereo a, b; texture a, b: left ~ a * other + b
        converged = False
        for _ in range(MAX_ITERATIONS):
            it_total += 1
            R = so3_exp(omega)
            RX = Xc @ R.T
            X = RX + c + t
            if np.any(X[:, 2] <= 1.0):
                return None
            ul, ur, v, Jp = _projections(X, zed)
            L, Lx, Ly = sample_spline(cl, ul, v, derivs=True)
            # dX/d(delta omega) = -[R (X0 - c)]_x, dX/dt = I
            dX = np.zeros((n, 3, 6))
            dX[:, 0, 1], dX[:, 0, 2] = RX[:, 2], -RX[:, 1]
            dX[:, 1, 0], dX[:, 1, 2] = -RX[:, 2], RX[:, 0]
            dX[:, 2, 0], dX[:, 2, 1] = RX[:, 1], -RX[:, 0]
            dX[:, :, 3:] = np.eye(3)
            dul = np.einsum("nj,njk->nk", Jp[:, 0], dX)
            dur = np.einsum("nj,njk->nk", Jp[:, 1], dX)
            dv = np.einsum("nj,njk->nk", Jp[:, 2], dX)
            dL = Lx[:, None] * dul + Ly[:, None] * dv
            blocks_J, blocks_r = [], []
            if use_stereo:
                Rr, Rx_, Ry_ = sample_spline(cr, ur, v, derivs=True)
                a, b = gains[0], gains[1]
                r_s = L - a * Rr - b
                J_s = np.zeros((n, 10))
                J_s[:, :6] = dL - a * (Rx_[:, None] * dur + Ry_[:, None] * dv)
                J_s[:, 6], J_s[:, 7] = -Rr, -1.0
                s = _robust_scale(r_s)
                blocks_J.append(J_s / s)
                blocks_r.append(r_s / s)
            if texture:
                a, b = gains[2], gains[3]
                r_t = L - a * t_vals - b
                J_t = np.zeros((n, 10))
                J_t[:, :6] = dL
                J_t[:, 8], J_t[:, 9] = -t_vals, -1.0
                s = _robust_scale(r_t) / TEXTURE_WEIGHT
                blocks_J.append(J_t / s)
                blocks_r.append(r_t / s)
            J = np.concatenate(blocks_J)
            r = np.concatenate(blocks_r)
            active = np.abs(J).sum(axis=0) > 0
            Ja = J[:, active]
            uu = np.tile(u0.astype(np.float64), len(blocks_J))
            vv = np.tile(v0.astype(np.float64), len(blocks_J))
            H, g, w, S = huber_system(Ja, r, HUBER, uu, vv, TILE_PX if fine else None)
            try:
                step_a = -np.linalg.solve(H, g)
            except np.linalg.LinAlgError:
                return None
            step = np.zeros(10)
            step[active] = step_a
            omega = so3_log(so3_exp(step[:3]) @ so3_exp(omega))
            # the left perturbation turns about the origin of the centred points: t is unchanged by it
            t = t + step[3:6]
            gains = gains + step[6:]
            if np.linalg.norm(t) > 100.0 or np.linalg.norm(omega) > 0.5:
                return None
            if np.abs(step[:3]).max() < 1e-6 and np.abs(step[3:6]).max() < 1e-4:
                converged = True
                break
        if fine:
            Hinv = np.linalg.inv(H)
            C = Hinv @ S @ Hinv
            # the six motion parameters (the active columns' first six are them)
            cov = COVARIANCE_INFLATION * C[:6, :6]
            rms = float(np.sqrt(np.mean(r * r)))
            if use_stereo:
                a_, b_ = L - L.mean(), Rr - Rr.mean()
                den = float(np.sqrt(np.sum(a_ * a_) * np.sum(b_ * b_)))
                corr = float(np.sum(a_ * b_) / den) if den > 0 else None
    return FruitMotionEstimate(centre_mm=c, rotvec_rad=omega, translation_mm=t, cov_rad_mm=cov, n_points=n,
                               iterations=it_total, converged=converged, residual_rms=rms, stereo_correlation=corr,
                               points_mm=X0)
