"""Per-pixel ground-truth uncertainty: a 1-sigma disparity error bar for every GT pixel (``disp0GT_sigma.pfm``).

A GT disparity at ZED-left pixel ``u`` is the disparity of the surface point the reprojection put there. An error
moves that point: by ``delta_X`` in the ZED frame. The label at ``u`` then changes by the point's own disparity change
minus the GT's slope times the point's image motion::

    delta_d(u) = (dd/dX - grad_d(u) . du/dX) . delta_X        (d = f*B/Z - doffs, du/dX: the pinhole Jacobian)

so surfaces steep in disparity (silhouettes, grazing table) react to lateral errors and flat ones do not. Sources,
independent, added in quadrature (docs/dataset-format.md, "disp0GT_sigma.pfm"):

1. **Extrinsic**: ``delta_X = -[X - t]x omega + delta_t`` for the calibration's left perturbation
   ``T_zed_from_mech = [exp(omega) R | t + delta_t]``; ``sigma^2 = J C J^T`` with each pixel's own 1x6 Jacobian and the
   calibration's 6x6 covariance ``cov_extrinsic_rad_mm``.
2. **Depth noise**: the structured-light depth along the depth camera's ray, ``sigma_z = a + b * Z_m^2`` (mm, Z in m;
   ``DepthNoiseModel``), ``delta_X = (X - c_depth) / z_depth * delta_z``; the mesh interpolates three noisy samples,
   which divides the noise by sqrt(2) in the mean square over a triangle.
3. **Mesh interpolation**: the pixel lies inside a triangle of the depth grid whose vertices span ``span_mm`` in depth;
   a triangle interpolates linearly, and on a surface curved with radius ``R`` (``curvature_radius_mm``, 50 mm: half a
   melon's) the chord misses the surface by about ``span^2 / (8 R)``: ``sigma = f*B/Z^2 * span^2 / (8 R)``. Negligible
   on the fruit's top, it grows where triangles are steep: silhouettes and grazing surfaces.
4. **Verification** (optional): a scene whose texture is off by ``s`` px gets ``|grad_d| * s`` of lateral uncertainty.
"""
from __future__ import annotations

import math

import numba
import numpy as np
from pydantic import ConfigDict, Field

from gtforge.core.camera import Rig
from gtforge.core.geometry import finite_box, perturb_left
from gtforge.core.ground_truth.reproject import ReprojectParams, project_depth_to_camera
from gtforge.core.schema import GTModel


class DepthNoiseModel(GTModel):
    """1-sigma structured-light depth noise along the depth camera's z: ``a_mm + b_mm_per_m2 * (Z / 1000 mm)^2``.

    Default: Mech-Eye PRO S, rated 0.05 mm at 1 m (Mech-Mind's data sheet, Z repeatability), growing with Z^2 as
    triangulation noise does. Set it for your camera (``--depth-noise-a-mm``, ``--depth-noise-b-mm-per-m2``)."""

    model_config = ConfigDict(allow_inf_nan=False)  # finite (gauges.yaml's depth_noise: .inf went into the JSON)

    a_mm: float = Field(0.0, ge=0)
    b_mm_per_m2: float = Field(0.05, ge=0)

    def sigma_mm(self, z_mm: np.ndarray) -> np.ndarray:
        return self.a_mm + self.b_mm_per_m2 * (np.asarray(z_mm, np.float64) / 1000.0) ** 2


class UncertaintyParams(GTModel):
    depth_noise: DepthNoiseModel = Field(default_factory=DepthNoiseModel)
    # a triangle of the depth grid interpolates its surface linearly; on a surface curved with radius R the chord is off
    # by about L^2 / (8 R) (L: the triangle's 3-D extent, dominated by its depth span where the surface is steep)
    curvature_radius_mm: float = Field(50.0, gt=0)
    use_verification: bool = True  # add the scene's measured texture shift as lateral uncertainty


@numba.njit(inline="always", cache=True)
def _finite(x):
    return abs(x) < np.inf  # (NaN compares false)


@numba.njit(inline="always", cache=True)
def _slope(before, here, after):
    """Slope of three neighbouring samples: central difference where both neighbours are finite, else one-sided,
    else 0 (selects, no branches: the row loop vectorises)."""
    fb, fa = _finite(before), _finite(after)
    one_sided = (after - here) if fa else ((here - before) if fb else 0.0)
    return 0.5 * (after - before) if (fb and fa) else one_sided


@numba.njit(inline="always", cache=True, error_model="numpy")
def _sigma_px(d, left, right, above, below, Z, sp, X_over_Z, y_over_z, has_cov, cc, fx, fy, fb, t, c_depth,
              axis_depth, a_mm, b_mm, radius_mm, shift_px):
    """The 1-sigma of one pixel: GT disparity ``d`` and its four neighbours (NaN: none), depth ``Z``, the winning
    triangle's span ``sp`` (NaN: no mesh term); +inf where there is no GT. Every term is computed and an invalid pixel
    replaced at the end, with selects for branches: a row of calls vectorises (the same arithmetic, the same values).
    ``t``, ``c_depth``, ``axis_depth``: 3-tuples (arrays here would be reference-counted at every pixel)."""
    c00, c01, c02, c03, c04, c05, c11, c12, c13, c14, c15, c22, c23, c24, c25, c33, c34, c35, c44, c45, c55 = cc
    d = np.float64(d)
    Z = np.float64(Z)
    ok = _finite(d) & _finite(Z) & (Z > 0)
    # GT slope (px/px): central difference where both neighbours exist, else one-sided
    gx = _slope(np.float64(left), d, np.float64(right))
    gy = _slope(np.float64(above), d, np.float64(below))
    X = X_over_Z * Z
    Y = y_over_z * Z
    iz = 1.0 / Z
    # a = dd/dX - g . du/dX  (row vector)
    ax = -gx * fx * iz
    ay = -gy * fy * iz
    az = (-fb + gx * fx * X + gy * fy * Y) * iz * iz
    var = 0.0
    if has_cov:  # (the same for every pixel: taken out of the loop by the compiler)
        # extrinsic: dX/domega = -[P]x with P = X - t, dX/ddt = I  ->  J = [P x a, a]
        px, py, pz = X - t[0], Y - t[1], Z - t[2]
        J0 = py * az - pz * ay
        J1 = pz * ax - px * az
        J2 = px * ay - py * ax
        var = (J0 * (c00 * J0 + c01 * J1 + c02 * J2 + c03 * ax + c04 * ay + c05 * az)
               + J1 * (c11 * J1 + c12 * J2 + c13 * ax + c14 * ay + c15 * az)
               + J2 * (c22 * J2 + c23 * ax + c24 * ay + c25 * az)
               + ax * (c33 * ax + c34 * ay + c35 * az) + ay * (c44 * ay + c45 * az) + az * (c55 * az))
    # depth noise along the depth camera's ray: dX/dz_d = (X - c) / z_d, z_d = the point's depth-camera z
    rx, ry, rz = X - c_depth[0], Y - c_depth[1], Z - c_depth[2]
    zd = rx * axis_depth[0] + ry * axis_depth[1] + rz * axis_depth[2]
    # the mesh interpolates three noisy vertices: sqrt(sum w_i^2) of the noise, 1/sqrt(2) in the mean square
    # over a triangle (uniform barycentric weights: E[sum w_i^2] = 1/2)
    zd_m = zd * 0.001
    sz = (a_mm + b_mm * (zd_m * zd_m)) * 0.7071067811865476
    dn_ = (ax * rx + ay * ry + az * rz) / zd * sz
    var += dn_ * dn_
    # mesh interpolation: the chord of a surface curved with radius R, over the triangle's depth span
    sp = np.float64(sp)
    m = fb * iz * iz * sp * sp / (8.0 * radius_mm)
    var += m * m if _finite(sp) else 0.0
    # verification: the measured texture shift as lateral uncertainty
    var += shift_px * shift_px * (gx * gx + gy * gy)
    return math.sqrt(var) if ok else np.inf


@numba.njit(cache=True, error_model="numpy")
def _sigma_row(above, row, below, z_row, span_row, has_cov, cc, x_over_z, y_over_z, fx, fy, fb, t, c_depth,
               axis_depth, a_mm, b_mm, radius_mm, shift_px, x0, x1, out):
    """``_sigma_px`` on columns ``x0:x1`` of one row (``above``/``below``: the neighbouring rows, NaN beyond the
    image; ``span_row`` NaN: no mesh term). The image's first and last columns apart, so that the loop's loads are all
    in bounds and it vectorises."""
    W = row.shape[0]
    nan = np.nan
    t, c_depth, axis_depth = (t[0], t[1], t[2]), (c_depth[0], c_depth[1], c_depth[2]), \
        (axis_depth[0], axis_depth[1], axis_depth[2])
    lo, hi = max(x0, 1), max(min(x1, W - 1), 1)
    # the loop over slices from index 0: plain loads (indices that could be negative would make them gathers)
    here, left, right, up, down = row[lo:hi], row[lo - 1:hi - 1], row[lo + 1:hi + 1], above[lo:hi], below[lo:hi]
    z, sp, xz, o = z_row[lo:hi], span_row[lo:hi], x_over_z[lo:hi], out[lo:hi]
    for i in range(hi - lo):
        o[i] = _sigma_px(here[i], left[i], right[i], up[i], down[i], z[i], sp[i], xz[i], y_over_z, has_cov, cc, fx, fy,
                         fb, t, c_depth, axis_depth, a_mm, b_mm, radius_mm, shift_px)
    for u in (0, W - 1):
        if x0 <= u < x1:
            out[u] = _sigma_px(row[u], row[u - 1] if u > 0 else nan, row[u + 1] if u < W - 1 else nan, above[u],
                               below[u], z_row[u], span_row[u], x_over_z[u], y_over_z, has_cov, cc, fx, fy, fb, t,
                               c_depth, axis_depth, a_mm, b_mm, radius_mm, shift_px)


@numba.njit(cache=True)
def _sigma_kernel(disp, depth, span, fx, fy, cx, cy, B, cov, t, c_depth, axis_depth, a_mm, b_mm, radius_mm, shift_px,
                  out):
    """``out[v, u]``: the 1-sigma of pixel ``(v, u)``, +inf where there is no GT. The maps are read as they come
    (float32 or float64), every sample widened to float64 before any arithmetic; ``span`` of shape ``(0, 0)``: no mesh
    term; ``cov`` None: no extrinsic term (the same sigma a zero covariance gives). Computed on the GT's bounding box
    only (``finite_box``), +inf around it."""
    H, W = disp.shape
    use_span = span.shape == disp.shape
    has_cov = cov is not None
    C = np.zeros((6, 6)) if cov is None else cov
    # J C J^T of a symmetric C written out over its upper triangle, off-diagonal terms doubled (21 products, no loop)
    cc = (C[0, 0], 2 * C[0, 1], 2 * C[0, 2], 2 * C[0, 3], 2 * C[0, 4], 2 * C[0, 5],
          C[1, 1], 2 * C[1, 2], 2 * C[1, 3], 2 * C[1, 4], 2 * C[1, 5],
          C[2, 2], 2 * C[2, 3], 2 * C[2, 4], 2 * C[2, 5],
          C[3, 3], 2 * C[3, 4], 2 * C[3, 5],
          C[4, 4], 2 * C[4, 5],
          C[5, 5])
    fb = fx * B
    x_over_z = np.empty(W)  # (u - cx) / fx of each column, divided once, not once a pixel (the same value)
    for u in range(W):
        x_over_z[u] = (u - cx) / fx
    y0, y1, x0, x1 = finite_box(disp)  # no GT outside it
    out[:y0] = np.inf
    out[y1:] = np.inf
    nan_row = np.full(W, np.nan, disp.dtype)
    no_span = np.full(W, np.nan, span.dtype)
    for v in range(y0, y1):
        out[v, :x0] = np.inf
        out[v, x1:] = np.inf
        _sigma_row(disp[v - 1] if v > 0 else nan_row, disp[v], disp[v + 1] if v < H - 1 else nan_row, depth[v],
                   span[v] if use_span else no_span, has_cov, cc, x_over_z, (v - cy) / fy, fx, fy, fb, t,
                   c_depth, axis_depth, a_mm, b_mm, radius_mm, shift_px, x0, x1, out[v])


def _float_map(a) -> np.ndarray:
    """A C-contiguous float32 or float64 array (float32 maps as built are not copied; other types become float64)."""
    a = np.asarray(a)
    return np.ascontiguousarray(a, a.dtype if a.dtype in (np.float32, np.float64) else np.float64)


def disparity_sigma(disparity_px: np.ndarray, depth_mm: np.ndarray, rig: Rig, cov_extrinsic_rad_mm,
                    params: UncertaintyParams | None = None, span_mm: np.ndarray | None = None,
                    texture_shift_px: float | None = None) -> np.ndarray:
    """``(H, W)`` float32 1-sigma disparity uncertainty (px) of a GT disparity map, +inf where there is no GT.

    ``disparity_px``/``depth_mm``: the ZED-left GT (uncropped, ``(H, W)``). ``cov_extrinsic_rad_mm``: the calibration's
    6x6 covariance (None: the extrinsic is taken as exact). ``span_mm``: the winning triangle's depth span per pixel
    (``reproject.project_depth_to_camera(..., return_span=True)``; None: no mesh term). ``texture_shift_px``: the
    scene's measured texture shift (verification), added as lateral uncertainty."""
    params = params or UncertaintyParams()
    cam = rig.zed.left
    disp, depth = _float_map(disparity_px), _float_map(depth_mm)
    if disp.shape != depth.shape:
        raise ValueError(f"{disp.shape=} but expected {depth.shape} (the depth's shape)")
    cov = None
    if cov_extrinsic_rad_mm is not None:
        cov = np.asarray(cov_extrinsic_rad_mm, np.float64)
        if cov.shape != (6, 6):
            raise ValueError(f"{cov.shape=} but expected (6, 6)")
    span = np.zeros((0, 0), np.float32) if span_mm is None else _float_map(span_mm)  # (0, 0): no mesh term
    if span_mm is not None and span.shape != disp.shape:
        raise ValueError(f"{span.shape=} but expected {disp.shape} (the disparity's shape)")
    T_zed_from_depth = rig.T_zed_from_depth
    # the depth camera's centre and optical axis in the ZED frame
    c_depth, axis_depth = T_zed_from_depth[:3, 3], T_zed_from_depth[:3, 2]
    shift = float(texture_shift_px) if (params.use_verification and texture_shift_px is not None
                                        and math.isfinite(texture_shift_px)) else 0.0
    out = np.empty(disp.shape, np.float32)  # each sigma computed in float64, rounded once on storing
    _sigma_kernel(disp, depth, span, cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px, rig.zed.baseline_mm, cov,
                  np.ascontiguousarray(rig.T_zed_from_mech[:3, 3]), np.ascontiguousarray(c_depth),
                  np.ascontiguousarray(axis_depth),
                  params.depth_noise.a_mm,
                  params.depth_noise.b_mm_per_m2, params.curvature_radius_mm, shift, out)
    return out


class SigmaStats(GTModel):
    median_px: float | None
    p95_px: float | None
    over_0_1_px_pct: float | None  # share of GT pixels with sigma above 0.1 px


_LOG_EDGES = np.linspace(-6.0, 2.0, 1601)  # log10(sigma px): 1e-6 .. 100 px, 1.2 % bins


def sigma_stats_by_label(sigma_px: np.ndarray, labels: np.ndarray, groups: dict[str, tuple[int, ...]]
                         ) -> dict[str, "SigmaStats"]:
    """Per group of integer labels: median, 95th percentile (from a log-spaced histogram, 1.2 % bins, interpolated
    within the bin) and the exact share above 0.1 px of the finite sigma values: numpy's log10 and one compiled pass
    over the values' bounding box."""
    s = np.asarray(sigma_px, np.float32)
    labels = np.asarray(labels)
    if labels.shape != s.shape:
        raise ValueError(f"{labels.shape=} but expected {s.shape} (the sigma map's)")
    # numpy's log10 of the values' bounding box (none outside it), copied contiguous: numpy's float32 log10 gives every
    # element of a contiguous array the same value wherever it lies, so each finite positive value gets the log10 it
    # gets alone; then one compiled pass counts them (no compacted copy of the values)
    y0, y1, x0, x1 = finite_box(s)
    box = np.ascontiguousarray(s[y0:y1, x0:x1])
    lab = labels[y0:y1, x0:x1]
    lab = lab.view(np.uint8) if lab.dtype == bool else lab
    # a row for every label in the box: a label no counted value has gets an empty row, which no statistic reads
    n_labels = int(lab.max()) + 1 if lab.size else 1
    nb = len(_LOG_EDGES) - 1
    step = (_LOG_EDGES[-1] - _LOG_EDGES[0]) / nb
    with np.errstate(divide="ignore", invalid="ignore"):  # (NaN, zero and negative values: not counted)
        lg = np.log10(box)
    hist, over = _log_histogram(lg, box, lab, np.float32(_LOG_EDGES[0]), np.float32(step), nb, n_labels,
                                np.float32(0.1))
    out = {}
    for name, labs in groups.items():
        labs = [k for k in labs if k < n_labels]
        h = hist[labs].sum(axis=0) if labs else np.zeros(nb)
        n = int(h.sum())
        if not n:
            out[name] = SigmaStats(median_px=None, p95_px=None, over_0_1_px_pct=None)
            continue
        cdf = np.cumsum(h) / n

        def q(p):
            i = int(np.searchsorted(cdf, p))
            lo = cdf[i - 1] if i else 0.0
            t = (p - lo) / max(cdf[i] - lo, 1e-12)
            return float(10 ** (_LOG_EDGES[i] + t * (_LOG_EDGES[i + 1] - _LOG_EDGES[i])))

        out[name] = SigmaStats(median_px=q(0.5), p95_px=q(0.95),
                               over_0_1_px_pct=float(100.0 * over[labs].sum() / n))
    return out


@numba.njit(cache=True)
def _log_histogram(lg, s, labels, e0, step, nb, n_labels, over):
    """Per label: counts of the finite positive values of ``s`` (2-D, with their ``lg`` = log10 and ``labels``) in
    ``nb`` bins of ``step`` from ``e0`` (float32 arithmetic, truncated and clipped as numpy's ``astype(int64)`` and
    ``clip`` do), and the count of those ``> over`` (float32, as numpy compares)."""
    hist = np.zeros((n_labels, nb), np.int64)
    n_over = np.zeros(n_labels, np.int64)
    for i in range(s.shape[0]):
        for j in range(s.shape[1]):
            x = s[i, j]
            if x > 0 and x < np.inf:  # (NaN fails both)
                b = int((lg[i, j] - e0) / step)
                lab = labels[i, j]
                hist[lab, min(max(b, 0), nb - 1)] += 1
                if x > over:
                    n_over[lab] += 1
    return hist, n_over


def sigma_stats(sigma_px: np.ndarray, mask: np.ndarray) -> "SigmaStats":
    """The statistics of the sigma values under ``mask`` (see ``sigma_stats_by_label``)."""
    return sigma_stats_by_label(sigma_px, np.asarray(mask, bool), {"in": (1,)})["in"]


def draw_ground_truth(depth_mech_mm: np.ndarray, rig: Rig, cov_extrinsic_rad_mm, depth_noise_mm: float,
                      rng: np.random.Generator, params: UncertaintyParams | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """One draw of the errors the sigma map describes: the extrinsic perturbed by a sample of its covariance, the
    depth map by Gaussian noise; the ground truth built from them (mesh) and its sigma map. ``(disparity, sigma)``
    ZED-left arrays, for checking coverage against exact truth (tests, benchmarks)."""

    C = np.asarray(cov_extrinsic_rad_mm, np.float64)
    drawn = rig.with_extrinsic(perturb_left(rig.T_zed_from_mech, np.linalg.cholesky(C) @ rng.standard_normal(6)))
    noisy = depth_mech_mm + rng.normal(0, depth_noise_mm, depth_mech_mm.shape).astype(np.float32)
    depth, span = project_depth_to_camera(noisy, drawn.depth_camera, drawn.T_zed_from_depth, drawn.zed.left,
                                          ReprojectParams(), return_span=True)
    disp = drawn.zed.depth_to_disparity(depth)
    return disp, disparity_sigma(disp, depth, drawn, C, params, span)
