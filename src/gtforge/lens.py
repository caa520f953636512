"""OpenCV lens distortion: every model ``cv2.projectPoints`` knows, forward and inverse.

Coefficients in OpenCV's order (docs/conventions.md, "Lens distortion")::

    (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]])

4 or 5: Brown-Conrady; 8: rational (k4-k6 divide the radial polynomial); 12: thin prism (s1-s4);
14: tilted sensor (tau_x, tau_y in radians). Shorter lists are read as zeros for the missing terms.

Forward (normalised ``(x, y)`` -> distorted normalised), exactly as OpenCV::

    r2 = x^2 + y^2
    radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    x'' = x radial + 2 p1 x y + p2 (r2 + 2 x^2) + s1 r2 + s2 r2^2
    y'' = y radial + p1 (r2 + 2 y^2) + 2 p2 x y + s3 r2 + s4 r2^2
    (x_d, y_d) = dehomogenise(M_tilt(tau_x, tau_y) @ (x'', y'', 1))

The inverse is a damped Newton solve with the analytic Jacobian, started from OpenCV's fixed-point estimate
and, where that fails, from the distorted point itself; it converges near the image corners of strong
rational lenses where the plain fixed-point iteration (``cv2.undistortPoints``) diverges.
"""
from __future__ import annotations

import numpy as np

N_COEFFS = 14


def full_coeffs(dist) -> np.ndarray:
    """Any OpenCV coefficient list -> the 14-vector (missing terms are zero)."""
    d = np.zeros(N_COEFFS)
    a = np.asarray(dist, np.float64).ravel()
    d[:len(a)] = a
    return d


def tilt_matrix(tau_x: float, tau_y: float) -> np.ndarray:
    """OpenCV's ``computeTiltProjectionMatrix``: the 3x3 homography of a sensor tilted by (tau_x, tau_y) rad."""
    cx, sx, cy, sy = np.cos(tau_x), np.sin(tau_x), np.cos(tau_y), np.sin(tau_y)
    rot_x = np.array([[1, 0, 0], [0, cx, sx], [0, -sx, cx]])
    rot_y = np.array([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]])
    rot_xy = rot_y @ rot_x
    proj_z = np.array([[rot_xy[2, 2], 0, -rot_xy[0, 2]], [0, rot_xy[2, 2], -rot_xy[1, 2]], [0, 0, 1]])
    return proj_z @ rot_xy


def distort(xy: np.ndarray, dist) -> np.ndarray:
    """Normalised ``(N, 2)`` -> distorted normalised ``(N, 2)``."""
    return _distort_and_jacobian(np.asarray(xy, np.float64).reshape(-1, 2), full_coeffs(dist), False)[0]


def _distort_and_jacobian(xy: np.ndarray, d: np.ndarray, jac: bool):
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4, tx, ty = d
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    xpp = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    ypp = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    tilted = tx != 0.0 or ty != 0.0
    if tilted:
        M = tilt_matrix(tx, ty)
        hx = M[0, 0] * xpp + M[0, 1] * ypp + M[0, 2]
        hy = M[1, 0] * xpp + M[1, 1] * ypp + M[1, 2]
        hw = M[2, 0] * xpp + M[2, 1] * ypp + M[2, 2]
        out = np.stack([hx / hw, hy / hw], axis=1)
    else:
        out = np.stack([xpp, ypp], axis=1)
    if not jac:
        return out, None
    # d radial / d r2
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    drad = (dnum * den - num * dden) / (den * den)
    # d r2 / dx = 2x, d r2 / dy = 2y
    dxpp_dx = radial + x * drad * 2 * x + 2 * p1 * y + p2 * 6 * x + (s1 + 2 * s2 * r2) * 2 * x
    dxpp_dy = x * drad * 2 * y + 2 * p1 * x + p2 * 2 * y + (s1 + 2 * s2 * r2) * 2 * y
    dypp_dx = y * drad * 2 * x + p1 * 2 * x + 2 * p2 * y + (s3 + 2 * s4 * r2) * 2 * x
    dypp_dy = radial + y * drad * 2 * y + p1 * 6 * y + 2 * p2 * x + (s3 + 2 * s4 * r2) * 2 * y
    J = np.empty((len(x), 2, 2))
    if tilted:
        # d(hx/hw) = (dhx * hw - hx * dhw) / hw^2, with dh = M[:, :2] @ d(xpp, ypp)
        for col, (dxc, dyc) in enumerate(((dxpp_dx, dypp_dx), (dxpp_dy, dypp_dy))):
            dhx = M[0, 0] * dxc + M[0, 1] * dyc
            dhy = M[1, 0] * dxc + M[1, 1] * dyc
            dhw = M[2, 0] * dxc + M[2, 1] * dyc
            J[:, 0, col] = (dhx * hw - hx * dhw) / (hw * hw)
            J[:, 1, col] = (dhy * hw - hy * dhw) / (hw * hw)
    else:
        J[:, 0, 0], J[:, 0, 1], J[:, 1, 0], J[:, 1, 1] = dxpp_dx, dxpp_dy, dypp_dx, dypp_dy
    return out, J


def undistort(xy_d: np.ndarray, dist, iterations: int = 40, tol: float = 1e-14) -> np.ndarray:
    """Distorted normalised ``(N, 2)`` -> undistorted normalised ``(N, 2)`` (NaN where no solution was found).

    Damped Newton on ``distort(x) = xy_d`` with backtracking; a point is solved when its residual is below
    ``1e-12`` (normalised; about 1e-9 px for f = 1000 px).
    """
    import cv2

    target = np.asarray(xy_d, np.float64).reshape(-1, 2)
    d = full_coeffs(dist)
    if not np.any(d):
        return target.copy()
    # first start: OpenCV's fixed-point estimate (fast, right almost everywhere), polished by Newton
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-14)
    x0 = cv2.undistortPointsIter(target.reshape(-1, 1, 2), np.eye(3), d, None, None, crit).reshape(-1, 2)
    x0[~np.isfinite(x0)] = target[~np.isfinite(x0)]
    x = _newton(x0, target, d, iterations, tol)
    res = np.linalg.norm(distort(x, d) - target, axis=1)
    bad = ~(res < 1e-12)
    if bad.any():  # where the fixed point diverged (strong rational lenses near the corners): start at xy_d
        x1 = _newton(target[bad].copy(), target[bad], d, iterations, tol)
        res1 = np.linalg.norm(distort(x1, d) - target[bad], axis=1)
        better = res1 < res[bad]
        idx = np.nonzero(bad)[0][better]
        x[idx] = x1[better]
        res[idx] = res1[better]
    x[~(res < 1e-10)] = np.nan
    return x


def _newton(x: np.ndarray, target: np.ndarray, d: np.ndarray, iterations: int, tol: float) -> np.ndarray:
    f, J = _distort_and_jacobian(x, d, True)
    r = f - target
    cost = np.einsum("ij,ij->i", r, r)
    active = np.ones(len(x), bool)
    for _ in range(iterations):
        active &= cost > tol * tol
        if not active.any():
            break
        a = np.nonzero(active)[0]
        Ja, ra = J[a], r[a]
        det = Ja[:, 0, 0] * Ja[:, 1, 1] - Ja[:, 0, 1] * Ja[:, 1, 0]
        ok = np.abs(det) > 1e-300
        det = np.where(ok, det, 1.0)
        step = np.stack([(Ja[:, 1, 1] * ra[:, 0] - Ja[:, 0, 1] * ra[:, 1]) / det,
                         (-Ja[:, 1, 0] * ra[:, 0] + Ja[:, 0, 0] * ra[:, 1]) / det], axis=1)
        step[~ok] = ra[~ok]  # singular Jacobian: a fixed-point step
        # backtracking: halve the step until the residual drops (at most 30 halvings)
        lam = np.ones(len(a))
        pending = np.ones(len(a), bool)
        xa_new = x[a].copy()
        fa_new = f[a].copy()
        Ja_new = J[a].copy()
        ca_new = cost[a].copy()
        for _ in range(30):
            p = np.nonzero(pending)[0]
            if not len(p):
                break
            xt = x[a[p]] - lam[p, None] * step[p]
            ft, Jt = _distort_and_jacobian(xt, d, True)
            rt = ft - target[a[p]]
            ct = np.einsum("ij,ij->i", rt, rt)
            acc = ct < cost[a[p]]
            q = p[acc]
            xa_new[q], fa_new[q], Ja_new[q], ca_new[q] = xt[acc], ft[acc], Jt[acc], ct[acc]
            pending[q] = False
            lam[p[~acc]] *= 0.5
        stuck = pending  # no step decreased the residual: converged to machine precision or trapped
        x[a], f[a], J[a], cost[a] = xa_new, fa_new, Ja_new, ca_new
        r[a] = fa_new - target[a]
        active[a[stuck]] = False
    return x
