"""Least-squares fits of spheres, planes and resting ellipsoids to 3-D points (mm), for gauge validation
(VDI/VDE 2634 Part 2 figures, ``gtforge.core.measure.gauges``) and per-fruit size (``gtforge.core.measure.fruit_size``).

Every fit minimises a geometric residual with ``scipy.optimize.least_squares`` (the plane: SVD, exact) and
returns its residuals, so form figures come from the same numbers. A fit that cannot be made (too few points,
no convergence, a degenerate result) returns ``ok=False`` and a ``reason`` instead of raising: a gauge or a
fruit is then "not measurable", the rest of the report goes on.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

MIN_POINTS_SPHERE = 20
MIN_POINTS_PLANE = 20
MIN_POINTS_ELLIPSOID = 50
MIN_HEIGHT_MM = 5.0  # an object whose points rise less than this above its support plane has no measurable shape
# the robust refit's scale: residuals beyond about this many robust standard deviations (1.4826 MAD) of the plain
# fit's residuals count less and less; never under ROBUST_MIN_SCALE_MM (an exact surface has a MAD of ~0)
ROBUST_SCALE_SIGMAS = 3.0
ROBUST_MIN_SCALE_MM = 0.5


@dataclass
class SphereFit:
    ok: bool
    reason: str = ""
    centre_mm: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    radius_mm: float = float("nan")
    residuals_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))  # signed radial: |p - c| - r
    n_points: int = 0

    @property
    def diameter_mm(self) -> float:
        return 2.0 * self.radius_mm

    @property
    def form_range_mm(self) -> float:
        """VDI/VDE 2634-2 probing error, form: the range of the radial residuals."""
        return float(np.ptp(self.residuals_mm)) if self.residuals_mm.size else float("nan")

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_mm ** 2))) if self.residuals_mm.size else float("nan")


@dataclass
class PlaneFit:
    ok: bool
    reason: str = ""
    normal: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))  # unit; n . p = offset_mm
    offset_mm: float = float("nan")
    residuals_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))  # signed: n . p - offset
    n_points: int = 0

    @property
    def flatness_mm(self) -> float:
        """VDI/VDE 2634-2 flatness measurement error: the range of the signed distances to the fitted plane."""
        return float(np.ptp(self.residuals_mm)) if self.residuals_mm.size else float("nan")

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_mm ** 2))) if self.residuals_mm.size else float("nan")


def _finite_points(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, np.float64).reshape(-1, 3)
    return p[np.all(np.isfinite(p), axis=1)]


def fit_plane_lsq(points: np.ndarray, min_points: int = MIN_POINTS_PLANE) -> PlaneFit:
    """Total least squares plane (SVD of the centred points: the orthogonal-distance optimum)."""
    p = _finite_points(points)
    if len(p) < min_points:
        return PlaneFit(False, f"too few points ({len(p)} < {min_points})", n_points=len(p))
    c = p.mean(axis=0)
    _, s, vt = np.linalg.svd(p - c, full_matrices=False)
    if s[1] <= 1e-9 * max(s[0], 1e-300):
        return PlaneFit(False, "the points lie on a line", n_points=len(p))
    n = vt[-1]
    if n[2] > 0:  # camera frame: the normal points towards the camera (-z)
        n = -n
    off = float(n @ c)
    return PlaneFit(True, normal=n, offset_mm=off, residuals_mm=p @ n - off, n_points=len(p))


def fit_sphere(points: np.ndarray, min_points: int = MIN_POINTS_SPHERE,
               radius_hint_mm: float | None = None) -> SphereFit:
    """Geometric least-squares sphere: minimises ``sum (|p - c| - r)^2`` (Levenberg-Marquardt-type trust region)
    from the algebraic (linear) fit."""
    p = _finite_points(points)
    if len(p) < min_points:
        return SphereFit(False, f"too few points ({len(p)} < {min_points})", n_points=len(p))
    # algebraic start: |p|^2 = 2 c.p + (r^2 - |c|^2), linear in (c, k)
    A = np.column_stack([2 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(A, np.sum(p ** 2, axis=1), rcond=None)
    c0, k = sol[:3], sol[3]
    r0 = np.sqrt(max(k + c0 @ c0, 0.0))
    if not np.isfinite(r0) or r0 <= 0:
        r0 = radius_hint_mm or float(np.linalg.norm(p - p.mean(0), axis=1).max())

    def res(x):
        return np.linalg.norm(p - x[:3], axis=1) - x[3]

    try:
        out = least_squares(res, np.r_[c0, r0], method="lm", x_scale="jac")
    except (ValueError, np.linalg.LinAlgError) as exc:
        return SphereFit(False, f"the fit failed ({exc})", n_points=len(p))
    x = out.x
    if out.status <= 0 or not np.all(np.isfinite(x)) or x[3] <= 0:
        return SphereFit(False, f"the fit did not converge ({out.message})", n_points=len(p))
    if x[3] > 1e3 * np.linalg.norm(np.ptp(p, axis=0)):
        return SphereFit(False, "the points are (nearly) flat: no sphere", n_points=len(p))
    return SphereFit(True, centre_mm=x[:3].copy(), radius_mm=float(x[3]), residuals_mm=res(x), n_points=len(p))


# ---- resting ellipsoid (fruit) ----------------------------------------------------------------
@dataclass
class EllipsoidFit:
    """An ellipsoid with one principal axis along the support plane's normal.

    ``radii_mm = (a, b, c)``: ``a >= b`` the horizontal semi-axes (along ``axes[:, 0]``, ``axes[:, 1]``), ``c``
    the vertical one (``axes[:, 2]`` = the plane's upward normal). Columns of ``axes`` are unit vectors in the
    points' frame."""

    ok: bool
    reason: str = ""
    centre_mm: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    radii_mm: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    axes: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    residuals_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    n_points: int = 0
    constraint: str = "resting"

    @property
    def diameter_mm(self) -> float:
        """Equatorial diameter: of the circle with the area of the horizontal cross-section, ``2 sqrt(a b)``."""
        return float(2 * np.sqrt(self.radii_mm[0] * self.radii_mm[1]))

    @property
    def length_mm(self) -> float:
        return float(2 * self.radii_mm[0])

    @property
    def width_mm(self) -> float:
        return float(2 * self.radii_mm[1])

    @property
    def height_mm(self) -> float:
        return float(2 * self.radii_mm[2])

    @property
    def volume_ml(self) -> float:
        return float(4.0 / 3.0 * np.pi * np.prod(self.radii_mm) / 1000.0)  # 1 mL = 1000 mm^3

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_mm ** 2))) if self.residuals_mm.size else float("nan")


def _plane_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = a - (a @ n) * n
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def fit_resting_ellipsoid(points: np.ndarray, plane_normal: np.ndarray, plane_offset_mm: float,
                          constraint: str = "resting", min_points: int = MIN_POINTS_ELLIPSOID,
                          loss: str = "linear") -> EllipsoidFit:
    """Ellipsoid fitted to the visible surface of an object lying on a plane ``n . p = offset`` (``n`` pointing
    from the plane towards the object).

    Constraint (one top view sees about half the surface, so a free 9-parameter ellipsoid is ill-posed): one axis
    along ``n`` and, with ``constraint="resting"``, the lowest point on the plane (centre height = ``c``): 6
    parameters (2 for the foot point, the yaw of the horizontal axes, ``a``, ``b``, ``c``). ``"upright"``
    frees the centre height (7). Residual: the distance along the line to the centre from each point to the
    surface, ``(1 - 1/|q|) |p - centre|`` with ``q`` the point in unit-sphere coordinates (exact for a sphere).

    ``loss`` other than ``"linear"`` (one of ``scipy.optimize.least_squares``'s robust losses, e.g. ``"cauchy"``): the
    least-squares fit is refitted from where it ended with that loss at the scale
    ``max(ROBUST_MIN_SCALE_MM, ROBUST_SCALE_SIGMAS * 1.4826 * MAD)`` of its residuals, so a few points far off the
    surface do not pull the axes outwards. Not the default: on SGBM's predictions of the demo's scenes every robust
    loss sized the fruit worse against the generator's exact ellipsoids than least squares (docs/metrics.md)."""
    if constraint not in ("resting", "upright"):
        raise ValueError(f"constraint {constraint!r}: expected 'resting' or 'upright'")
    if loss not in ("linear", "soft_l1", "huber", "cauchy", "arctan"):
        raise ValueError(f"loss {loss!r}: expected one of scipy.optimize.least_squares's losses")
    p = _finite_points(points)
    if len(p) < min_points:
        return EllipsoidFit(False, f"too few points ({len(p)} < {min_points})", n_points=len(p), constraint=constraint)
    n = np.asarray(plane_normal, float)
    n = n / np.linalg.norm(n)
    e1, e2 = _plane_basis(n)
    h = p @ n - plane_offset_mm
    if np.median(h) < 0:
        return EllipsoidFit(False, "the points lie below the support plane", n_points=len(p), constraint=constraint)
    if np.percentile(h, 99) < MIN_HEIGHT_MM:
        return EllipsoidFit(False, f"the points rise less than {MIN_HEIGHT_MM:g} mm above the support plane",
                            n_points=len(p), constraint=constraint)
    # start: horizontal PCA of the points, height from the highest point
    xy = np.column_stack([p @ e1, p @ e2])
    m = xy.mean(0)
    evals, evecs = np.linalg.eigh(np.cov((xy - m).T))
    major = evecs[:, 1]
    yaw0 = float(np.arctan2(major[1], major[0]))
    proj = (xy - m) @ evecs
    a0 = max(float(np.ptp(proj[:, 1])) / 2, 1.0)
    b0 = max(float(np.ptp(proj[:, 0])) / 2, 1.0)
    c0 = max(float(np.percentile(h, 99.5)) / 2, 1.0)
    base = plane_offset_mm * n

    def unpack(x):
        s, t, yaw, la, lb, lc = x[:6]
        a, b, c = np.exp(np.clip([la, lb, lc], -5.0, 12.0))  # 7 um .. 160 m: no overflow on a wild step
        ch = c if constraint == "resting" else x[6]
        centre = base + s * e1 + t * e2 + ch * n
        ax1 = np.cos(yaw) * e1 + np.sin(yaw) * e2
        ax2 = -np.sin(yaw) * e1 + np.cos(yaw) * e2
        return centre, np.array([a, b, c]), np.column_stack([ax1, ax2, n])

    def res(x):
        centre, r, A = unpack(x)
        d = p - centre
        q = (d @ A) / r
        nq = np.linalg.norm(q, axis=1)
        return (1.0 - 1.0 / np.maximum(nq, 1e-12)) * np.linalg.norm(d, axis=1)

    x0 = [m[0], m[1], yaw0, np.log(a0), np.log(b0), np.log(c0)] + ([c0] if constraint == "upright" else [])
    try:
        with np.errstate(all="ignore"):
            out = least_squares(res, np.array(x0, float), method="lm", x_scale="jac", max_nfev=600)
            if loss != "linear" and out.status > 0 and np.all(np.isfinite(out.x)):
                r0 = res(out.x)
                scale_mm = max(ROBUST_MIN_SCALE_MM,
                               ROBUST_SCALE_SIGMAS * 1.4826 * float(np.median(np.abs(r0 - np.median(r0)))))
                # lsmr: the exact solver's SVD of the points' Jacobian cost 3x the fit (diameters within 0.001 mm)
                rob = least_squares(res, out.x, method="trf", loss=loss, f_scale=scale_mm, x_scale="jac",
                                    tr_solver="lsmr", max_nfev=600)
                if rob.status > 0 and np.all(np.isfinite(rob.x)):
                    out = rob
    except (ValueError, np.linalg.LinAlgError) as exc:
        return EllipsoidFit(False, f"the fit failed ({exc})", n_points=len(p), constraint=constraint)
    if out.status <= 0 or not np.all(np.isfinite(out.x)):
        return EllipsoidFit(False, f"the fit did not converge ({out.message})", n_points=len(p), constraint=constraint)
    centre, r, A = unpack(out.x)
    if r[1] > r[0]:  # a >= b: swap the horizontal axes (keep a right-handed frame)
        r = r[[1, 0, 2]]
        A = np.column_stack([A[:, 1], -A[:, 0], A[:, 2]])
    if np.any(r > 1e3 * np.linalg.norm(np.ptp(p, axis=0))):
        return EllipsoidFit(False, "degenerate fit (an axis far longer than the points' extent)", n_points=len(p),
                            constraint=constraint)
    return EllipsoidFit(True, centre_mm=centre, radii_mm=r, axes=A, residuals_mm=res(out.x), n_points=len(p),
                        constraint=constraint)


def fit_sphere_ransac(points: np.ndarray, radius_mm: float, threshold_mm: float = 1.0, radius_tol: float = 0.1,
                      iterations: int = 300, min_points: int = MIN_POINTS_SPHERE,
                      rng: np.random.Generator | None = None) -> tuple[SphereFit, np.ndarray]:
    """A sphere of about ``radius_mm`` (within ``radius_tol``) among other points (a ball bar's rod, stray depth):
    spheres through 4 random points, the one with most points within ``threshold_mm`` of its surface, then
    ``fit_sphere`` on those. Returns (fit, inlier mask over the finite points)."""
    p = _finite_points(points)
    if len(p) < min_points:
        return SphereFit(False, f"too few points ({len(p)} < {min_points})", n_points=len(p)), np.zeros(len(p), bool)
    rng = rng or np.random.default_rng(0)
    best, best_n = None, -1
    idx = rng.integers(0, len(p), size=(iterations, 4))
    for s in idx:
        q = p[s]
        A = np.column_stack([2 * q, np.ones(4)])
        try:
            sol = np.linalg.solve(A, np.sum(q ** 2, axis=1))
        except np.linalg.LinAlgError:
            continue
        c, r2 = sol[:3], sol[3] + sol[:3] @ sol[:3]
        if r2 <= 0 or abs(np.sqrt(r2) - radius_mm) > radius_tol * radius_mm:
            continue
        inl = np.abs(np.linalg.norm(p - c, axis=1) - np.sqrt(r2)) < threshold_mm
        if inl.sum() > best_n:
            best, best_n = inl, int(inl.sum())
    if best is None:
        return SphereFit(False, f"no sphere of radius {radius_mm:g} mm +- {100 * radius_tol:g} % among the points",
                         n_points=len(p)), np.zeros(len(p), bool)
    return fit_sphere(p[best], min_points), best
