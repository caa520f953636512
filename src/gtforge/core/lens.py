"""OpenCV lens distortion: every model ``cv2.projectPoints`` knows, forward and inverse.

Coefficients in OpenCV's order (docs/conventions.md, "Lens distortion"; docs/cameras.md)::

    (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]])

4 or 5: Brown-Conrady; 8: rational (k4-k6 divide the radial polynomial); 12: thin prism (s1-s4);
14: tilted sensor (tau_x, tau_y in radians). Shorter lists are read as zeros for the missing terms.

Forward (normalised ``(x, y)`` -> distorted normalised), exactly as OpenCV::

    r2 = x^2 + y^2
    radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    x'' = x radial + 2 p1 x y + p2 (r2 + 2 x^2) + s1 r2 + s2 r2^2
    y'' = y radial + p1 (r2 + 2 y^2) + 2 p2 x y + s3 r2 + s4 r2^2
    (x_d, y_d) = dehomogenise(M_tilt(tau_x, tau_y) @ (x'', y'', 1))

Inverse (:func:`undistort`): the tilt is a homography and is undone exactly; the rest is solved per point by a
damped Newton iteration (analytic Jacobian, step halving until the residual drops), compiled with numba and run in
parallel. It starts at ``(x'', y'')`` itself; where that does not reach a valid solution it starts again from the
exact root of the radial part alone on the lens's monotonic branch (safeguarded 1-D Newton). A solution counts
only when its residual is below :data:`ACCEPT_TOL` and it lies inside :func:`valid_radius`, the radius up to which
the radial map ``r -> r * radial(r)`` still increases: beyond it the model folds back, and a "solution" there is
a second pre-image, not the ray the pixel saw. Elsewhere the result is NaN. Unlike the plain fixed-point iteration
of ``cv2.undistortPoints``, this converges near the image corners of strong rational lenses.
"""
from __future__ import annotations

import functools
import math
import types

import numba
import numpy as np

from gtforge.core.numba_threads import parallel_allowed

# numba: prefer OpenMP (as gtforge.core.ground_truth.reproject; TBB builds on Debian are often too old)
numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]

N_COEFFS = 14
ACCEPT_TOL = 1e-12  # normalised residual below which an inverse counts as solved (~1e-9 px at f = 1000 px)
_R_SCAN_MAX = 100.0  # normalised radius up to which valid_radius looks for the fold (89.4 deg off-axis)


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
    """Normalised ``(N, 2)`` -> distorted normalised ``(N, 2)`` (equals ``cv2.projectPoints``)."""
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


@numba.njit(cache=True, inline="always")
def distort_point(x, y, d, M, tilted):
    """``distort`` of one normalised point, for numba code: ``d`` from :func:`full_coeffs`, ``M`` the
    :func:`tilt_matrix` (used only when ``tilted``)."""
    gx, gy = _g_and_J(x, y, d)[:2]
    if not tilted:
        return gx, gy
    hw = M[2, 0] * gx + M[2, 1] * gy + M[2, 2]
    return (M[0, 0] * gx + M[0, 1] * gy + M[0, 2]) / hw, (M[1, 0] * gx + M[1, 1] * gy + M[1, 2]) / hw


# ---- validity: where the radial map is still one-to-one ---------------------------------------
def _radial_slope(r: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """d/dr of ``r * radial(r^2)``, and the radial numerator and denominator, at radii ``r``."""
    k1, k2, k3, k4, k5, k6 = d[0], d[1], d[4], d[5], d[6], d[7]
    r2 = r * r
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    dnum = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    dden = k4 + r2 * (2 * k5 + 3 * k6 * r2)
    radial = num / den
    drad_dr2 = (dnum * den - num * dden) / (den * den)
    return radial + 2 * r2 * drad_dr2, num, den


@functools.lru_cache(maxsize=64)
def _valid_radius_cached(radial_coeffs: tuple[float, ...]) -> float:
    d = np.zeros(N_COEFFS)
    d[[0, 1, 4, 5, 6, 7]] = radial_coeffs  # k1 k2 k3 k4 k5 k6
    r = np.linspace(0.0, _R_SCAN_MAX, 400_001)  # 2.5e-4 steps

    def bad(rr):
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            slope, num, den = _radial_slope(rr, d)
        return ~((slope > 0) & (num > 0) & (den > 0))

    b = bad(r)
    if not b.any():
        return math.inf
    i = int(np.argmax(b))  # first bad sample; r[i - 1] is good (r = 0 always is)
    lo, hi = float(r[i - 1]), float(r[i])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if bad(np.array([mid]))[0]:
            hi = mid
        else:
            lo = mid
    return lo


def valid_radius(dist) -> float:
    """The normalised radius up to which the radial part of the lens model is one-to-one (``inf`` if it never
    folds back within 89.4 deg of the axis): the first radius where ``d/dr (r * radial(r))`` reaches 0 or where
    the rational denominator or numerator reaches 0. Inverse solutions beyond it are refused (NaN)."""
    d = full_coeffs(dist)
    return _valid_radius_cached(tuple(float(x) for x in d[[0, 1, 4, 5, 6, 7]].tolist()))


# ---- inverse ----------------------------------------------------------------------------------
@numba.njit(cache=True, inline="always")
def _g_and_J(x, y, d):
    """Radial + tangential + thin prism (no tilt) and its Jacobian at one point."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7], \
        d[8], d[9], d[10], d[11]
    r2 = x * x + y * y
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
    radial = num / den
    gx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r2 * r2
    gy = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r2 * r2
    dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
    drad = (dnum * den - num * dden) / (den * den)
    sx = s1 + 2.0 * s2 * r2
    sy = s3 + 2.0 * s4 * r2
    j00 = radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x + 2.0 * x * sx
    j01 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * y * sx
    j10 = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y + 2.0 * x * sy
    j11 = radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x + 2.0 * y * sy
    return gx, gy, j00, j01, j10, j11


@numba.njit(cache=True)
def _newton(x, y, tx, ty, d, max_iter, stop2):
    """Damped Newton on g(x, y) = (tx, ty) from (x, y). Returns (x, y, residual^2, det J at the end)."""
    gx, gy, j00, j01, j10, j11 = _g_and_J(x, y, d)
    rx, ry = gx - tx, gy - ty
    c = rx * rx + ry * ry
    for _ in range(max_iter):
        if not c > stop2:  # converged (or NaN, which no step improves)
            break
        det = j00 * j11 - j01 * j10
        if det == 0.0 or not math.isfinite(det):
            break
        sx = (j11 * rx - j01 * ry) / det
        sy = (-j10 * rx + j00 * ry) / det
        lam = 1.0
        accepted = False
        for _h in range(40):
            xn, yn = x - lam * sx, y - lam * sy
            gxn, gyn, a00, a01, a10, a11 = _g_and_J(xn, yn, d)
            rxn, ryn = gxn - tx, gyn - ty
            cn = rxn * rxn + ryn * ryn
            if cn < c:
                x, y, rx, ry, c = xn, yn, rxn, ryn, cn
                j00, j01, j10, j11 = a00, a01, a10, a11
                accepted = True
                break
            lam *= 0.5
        if not accepted:  # no step lowers the residual: at machine precision, or trapped
            break
    return x, y, c, j00 * j11 - j01 * j10


@numba.njit(cache=True)
def _radial_root(rd, d, r_hi, f_hi):
    """The r in [0, r_hi] with r * radial(r) = rd on the monotonic branch (safeguarded Newton + bisection)."""
    if not rd < f_hi:
        return np.nan
    k1, k2, k3, k4, k5, k6 = d[0], d[1], d[4], d[5], d[6], d[7]
    lo, hi = 0.0, r_hi
    r = rd if rd < r_hi else 0.5 * r_hi
    for _ in range(200):
        r2 = r * r
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        f = r * num / den - rd
        if f > 0.0:
            hi = r
        else:
            lo = r
        if hi - lo < 1e-15 * (1.0 + hi):
            break
        fp = num / den + 2.0 * r2 * (dnum * den - num * dden) / (den * den)
        rn = r - f / fp if fp > 0.0 else -1.0
        r = rn if lo < rn < hi else 0.5 * (lo + hi)
    return r


@numba.njit(parallel=True, cache=True)
def _undistort_kernel(xy_d, d, Minv, tilted, r_valid2, r_hi, f_hi, max_iter, stop2, accept2, out):
    n = xy_d.shape[0]
    for i in numba.prange(n):
        xd, yd = xy_d[i, 0], xy_d[i, 1]
        if tilted:  # undo the sensor tilt exactly: (x'', y'') = dehomogenise(M^-1 (x_d, y_d, 1))
            hx = Minv[0, 0] * xd + Minv[0, 1] * yd + Minv[0, 2]
            hy = Minv[1, 0] * xd + Minv[1, 1] * yd + Minv[1, 2]
            hw = Minv[2, 0] * xd + Minv[2, 1] * yd + Minv[2, 2]
            tx, ty = hx / hw, hy / hw
        else:
            tx, ty = xd, yd
        out[i, 0] = np.nan
        out[i, 1] = np.nan
        if not (math.isfinite(tx) and math.isfinite(ty)):
            continue
        # start 1: the distorted point itself
        x, y, c, det = _newton(tx, ty, tx, ty, d, max_iter, stop2)
        if c <= accept2 and det > 0.0 and x * x + y * y < r_valid2:
            out[i, 0] = x
            out[i, 1] = y
            continue
        # start 2: the radial part's root on the monotonic branch, in the direction of (x'', y'')
        rd = math.sqrt(tx * tx + ty * ty)
        r = _radial_root(rd, d, r_hi, f_hi)
        if not math.isfinite(r):
            continue
        s = r / rd if rd > 0.0 else 0.0
        x, y, c, det = _newton(tx * s, ty * s, tx, ty, d, max_iter, stop2)
        if c <= accept2 and det > 0.0 and x * x + y * y < r_valid2:
            out[i, 0] = x
            out[i, 1] = y


def _renamed(f, name: str):
    """``f``'s code as a function of its own name: numba names a kernel's cache files by the function's qualified name
    (and line), and its cache index does not tell a parallel compilation from a serial one, so the two compilations of
    one function would share, and overwrite, one cache entry."""
    g = types.FunctionType(f.__code__, f.__globals__, name, f.__defaults__, f.__closure__)
    g.__qualname__, g.__module__ = name, f.__module__
    return g


# The same loop compiled without ``parallel``: each point's arithmetic is the same (identical results, tested), and it
# starts no OpenMP runtime. Used where numba may run one thread only (a build worker, the pool's fork server): GNU
# OpenMP, once started in a process, aborts every child that process forks, and the fork server computes the depth
# camera's ray grid for its workers (``reproject.prepare_rays``).
_undistort_kernel_serial = numba.njit(cache=True)(_renamed(_undistort_kernel.py_func, "_undistort_kernel_serial"))


def undistort(xy_d: np.ndarray, dist, iterations: int = 40, tol: float = 1e-15, *,
              serial: bool | None = None) -> np.ndarray:
    """Distorted normalised ``(N, 2)`` -> undistorted normalised ``(N, 2)``.

    NaN where no valid solution exists (outside :func:`valid_radius`, or residual above :data:`ACCEPT_TOL`).
    ``iterations``: Newton iterations per start; ``tol``: the residual (normalised) at which a point stops.
    ``serial``: the serial compilation (the same values; no OpenMP runtime started); default where this process's
    numba runs one thread (``NUMBA_NUM_THREADS`` = 1: a local pool's workers and fork server) or may use only one (a
    child forked after OpenMP started: ``numba_threads``).
    """
    target = np.ascontiguousarray(np.asarray(xy_d, np.float64).reshape(-1, 2))
    d = full_coeffs(dist)
    if not np.any(d):
        return target.copy()
    tilted = bool(d[12] != 0.0 or d[13] != 0.0)
    Minv = np.linalg.inv(tilt_matrix(d[12], d[13])) if tilted else np.eye(3)
    r_valid = valid_radius(d)
    r_hi = min(r_valid, _R_SCAN_MAX)
    _, num, den = _radial_slope(np.array([r_hi]), d)
    f_hi = float(r_hi * num[0] / den[0])  # the largest distorted radius of the monotonic branch
    out = np.empty_like(target)
    if serial is None:
        serial = numba.config.NUMBA_NUM_THREADS == 1 or not parallel_allowed()
    kernel = _undistort_kernel_serial if serial else _undistort_kernel
    kernel(target, d, Minv, tilted, r_valid * r_valid, r_hi, f_hi, int(iterations), tol * tol, ACCEPT_TOL * ACCEPT_TOL,
           out)
    return out
