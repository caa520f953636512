"""Curved-surface accuracy of the ground truth on gauge objects, in the sense of VDI/VDE 2634 Part 2.

A session's ``gauges/`` folder holds one capture per gauge object (captured like a scene: structured-light
texture + depth, ZED pair) and ``gauges/gauges.yaml`` naming each object's calibrated size (docs/capture-layout.md).
For each gauge the ground truth is built exactly as ``build-dataset`` builds a scene (``reproject_to_zed`` with the
calibration's rig), turned back into 3-D points in the ZED-left frame from the disparity the dataset ships
(``Z = f*B/(d + doffs)``), the object segmented (components above the RANSAC table plane, eroded), and fitted by
least squares (``gtforge.core.measure.shapefit``). The raw structured-light depth, mapped into the same frame, is fitted
too for comparison. Figures (docs/metrics.md, "Gauge objects"):

* sphere: size error ``PS = D_fit - D_cal`` (mm), form error ``PF`` = range of the radial residuals (mm) and their RMS;
* sphere pair: both spheres as above and the sphere-spacing error ``SD = L_fit - L_cal`` (mm);
* plane: flatness ``F`` = range of the signed distances to the fitted plane (mm) and their RMS.

Each with the number of points used, and the form figures predicted from the per-pixel sigma map
(``gtforge.core.ground_truth.uncertainty.disparity_sigma`` without the extrinsic term, which moves the whole object
rigidly and changes no form or size figure).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import ClassVar, Literal

import cv2
import numpy as np
from pydantic import ConfigDict, Field, field_validator, model_validator
from scipy.stats import norm

from gtforge.core.geometry import fit_plane_robust, transform_points
from gtforge.core.schema import GTModel, VersionedFile
from gtforge.core.measure.shapefit import PlaneFit, SphereFit, fit_plane_lsq, fit_sphere, fit_sphere_ransac
from gtforge.core.ground_truth.uncertainty import DepthNoiseModel
from gtforge.errors import InputError

log = logging.getLogger("gtforge.core.measure.gauges")

GAUGES_DIR = "gauges"
GAUGES_FILE = "gauges.yaml"
Status = Literal["PASS", "WARN", "FAIL", "NOT MEASURABLE"]


class GaugeSpec(GTModel):
    """One gauge object of ``gauges.yaml``: its capture folder (under ``gauges/``) and calibrated size."""

    # finite sizes: an infinite diameter passed ``gt=0``, was measured NOT MEASURABLE (exit 0) with a size error of
    # -inf, and gauges.json / validation.json were written with Infinity, which no JSON reader takes
    model_config = ConfigDict(allow_inf_nan=False)
    capture: str
    kind: Literal["sphere", "sphere_pair", "plane"]
    diameter_mm: float | None = Field(None, gt=0)  # sphere, sphere_pair (both spheres)
    centre_distance_mm: float | None = Field(None, gt=0)  # sphere_pair

    @field_validator("capture")
    @classmethod
    def _a_folder_of_gauges(cls, v: str) -> str:
        # a capture folder directly under gauges/: "../scenes/000" measured a scene as a gauge
        if not v or v in (".", "..") or "/" in v or "\\" in v:
            raise ValueError(f"a capture folder's name under gauges/ (such as sphere), not a path: {v!r}")
        return v

    @model_validator(mode="after")
    def _sizes(self):
        if self.kind in ("sphere", "sphere_pair") and self.diameter_mm is None:
            raise ValueError(f"gauge '{self.capture}' ({self.kind}) needs diameter_mm "
                             "(the calibrated diameter, mm > 0)")
        if self.kind == "sphere_pair":
            if self.centre_distance_mm is None:
                raise ValueError(f"gauge '{self.capture}' (sphere_pair) needs centre_distance_mm (mm > 0)")
            if self.centre_distance_mm <= self.diameter_mm:
                raise ValueError(f"gauge '{self.capture}': centre_distance_mm {self.centre_distance_mm:g} must exceed "
                                 f"diameter_mm {self.diameter_mm:g} (the spheres would overlap)")
        return self


class GaugeLimits(GTModel):
    """PASS up to ``*_pass_mm``, WARN up to ``*_warn_mm``, FAIL beyond (absolute values, mm). Defaults: about twice
    and six times a metrology-grade structured-light camera's rated figures at 0.5-1 m (docs/metrics.md)."""

    model_config = ConfigDict(allow_inf_nan=False)  # finite limits (an infinite one went into the JSON as Infinity)
    size_pass_mm: float = Field(0.1, gt=0)
    size_warn_mm: float = Field(0.3, gt=0)
    form_pass_mm: float = Field(0.3, gt=0)
    form_warn_mm: float = Field(0.6, gt=0)
    spacing_pass_mm: float = Field(0.2, gt=0)
    spacing_warn_mm: float = Field(0.5, gt=0)
    flatness_pass_mm: float = Field(0.3, gt=0)
    flatness_warn_mm: float = Field(0.6, gt=0)

    @model_validator(mode="after")
    def _pass_within_warn(self) -> "GaugeLimits":
        for q in ("size", "form", "spacing", "flatness"):
            p, w = getattr(self, f"{q}_pass_mm"), getattr(self, f"{q}_warn_mm")
            if p > w:  # an error between the two would pass while a smaller one warns
                raise ValueError(f"{q}_pass_mm {p:g} must not exceed {q}_warn_mm {w:g} (PASS up to the first, "
                                 "WARN up to the second, FAIL beyond)")
        return self


class GaugesFile(VersionedFile):
    """``gauges/gauges.yaml``."""

    KIND: ClassVar[str] = "gauges.yaml (gauge objects of a capture session)"
    gauges: list[GaugeSpec] = Field(min_length=1)
    limits: GaugeLimits = Field(default_factory=GaugeLimits)
    params: "GaugeParams | None" = None  # segmentation, fit and depth-noise settings (defaults: GaugeParams())

    @field_validator("gauges")
    @classmethod
    def _each_capture_once(cls, v: list[GaugeSpec]) -> list[GaugeSpec]:
        # (one capture twice was measured twice, its two results side by side in the report)
        seen = [g.capture for g in v]
        twice = sorted({c for c in seen if seen.count(c) > 1})
        if twice:
            raise ValueError(f"each capture once; {', '.join(twice)} is listed {seen.count(twice[0])} times")
        return v


class GaugeParams(GTModel):
    model_config = ConfigDict(allow_inf_nan=False)  # finite settings, as the sizes and limits
    min_height_mm: float = Field(10.0, gt=0)  # object points: this far above the table plane
    erosion_px: int = Field(3, ge=0)  # the object's image mask is eroded by this (mixed silhouette pixels out)
    max_incidence_deg: float = Field(70.0, gt=0, le=90)  # sphere points seen more obliquely than this are left out
    gate_mm: float = Field(10.0, gt=0)  # raw depth: points within this of the GT fit's surface are the object's
    depth_noise: DepthNoiseModel = Field(default_factory=DepthNoiseModel)  # for the predicted form figures
    min_points: int = Field(30, ge=10)
    inlier_mm: float = Field(1.0, gt=0)  # sphere points farther than this from a RANSAC sphere of the calibrated size
    # are not the sphere's (a ball bar's rod, stray depth)


# ---- results ----------------------------------------------------------------------------------
class SphereFigures(GTModel):
    n_points: int
    diameter_mm: float
    size_error_mm: float  # PS: fitted - calibrated diameter
    form_range_mm: float  # PF: range of the radial residuals
    form_rms_mm: float
    centre_mm: list[float]  # ZED-left frame
    form_rms_predicted_mm: float | None = None  # from the sigma map (GT) or the depth noise model (raw)
    form_range_predicted_mm: float | None = None  # expected range of n_points Gaussian residuals of that RMS
    # 1-sigma of the fitted diameter from the same per-point sigmas (independent points: a lower bound where
    # neighbouring GT pixels share depth pixels); the mesh's chord bias is not in it
    size_sigma_predicted_mm: float | None = None
    n_outliers: int = 0  # points left out beyond 4 robust sigmas of the first fit
    centre_cov_predicted_mm2: list[list[float]] | None = None


class SourceFigures(GTModel):
    """One gauge measured from one source: ``gt`` (the ground-truth disparity) or ``raw`` (the depth map)."""

    source: Literal["gt", "raw"]
    measurable: bool
    reason: str | None = None
    spheres: list[SphereFigures] = Field(default_factory=list)
    centre_distance_mm: float | None = None
    spacing_error_mm: float | None = None  # SD
    spacing_sigma_predicted_mm: float | None = None  # 1-sigma of the centre distance from both centres' covariances
    n_points: int | None = None  # plane
    flatness_mm: float | None = None  # F
    plane_rms_mm: float | None = None
    flatness_predicted_mm: float | None = None
    plane_rms_predicted_mm: float | None = None


class GaugeResult(GTModel):
    capture: str
    kind: str
    spec: GaugeSpec
    gt: SourceFigures
    raw: SourceFigures | None = None
    status: Status
    reasons: list[str] = Field(default_factory=list)


class GaugesResult(VersionedFile):
    KIND: ClassVar[str] = "gauge validation (gauges.json from gtforge validate)"
    session_dir: str
    calibration_path: str
    limits: GaugeLimits
    params: GaugeParams
    gauges: list[GaugeResult]
    status: Status
    time_s: float = 0.0


# ---- measuring ------------------------------------------------------------------------------------
def read_gauges_file(session_root: Path) -> GaugesFile:
    p = Path(session_root) / GAUGES_DIR / GAUGES_FILE
    if not p.is_file():
        raise InputError(p, None, "a gauges.yaml naming each gauge object (docs/capture-layout.md, 'Gauge objects')",
                         "no such file", "add gauges/gauges.yaml, or validate without --gauges-only")
    g = GaugesFile.read(p)
    for k, s in enumerate(g.gauges):
        if not (p.parent / s.capture).is_dir():
            raise InputError(p, f"gauges.{k}.capture", f"a capture folder gauges/{s.capture}/", "no such folder",
                             "name the folder the gauge was captured into")
    return g


def disparity_points(disp: np.ndarray, zed) -> np.ndarray:
    """``(H, W, 3)`` ZED-left points from a disparity map: ``Z = f*B/(d + doffs)`` (NaN where invalid)."""
    cam = zed.left
    d = disp.astype(np.float64) + zed.doffs_px
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(d > 0, cam.fx_px * zed.baseline_mm / d, np.nan)
    H, W = disp.shape
    u = (np.arange(W) - cam.cx_px) / cam.fx_px
    v = (np.arange(H) - cam.cy_px) / cam.fy_px
    return np.stack([u[None, :] * z, v[:, None] * z, z], axis=-1)


def depth_points_in_zed(depth_mm: np.ndarray, rig) -> np.ndarray:
    """``(H, W, 3)`` the depth map's points in the ZED-left frame (NaN where invalid)."""
    rays = rig.depth_camera.ray_grid()
    z = depth_mm.astype(np.float64)
    P = np.stack([rays[..., 0] * z, rays[..., 1] * z, z], axis=-1)
    return transform_points(rig.T_zed_from_depth, P.reshape(-1, 3)).reshape(P.shape)


def gauge_components(mask: np.ndarray, erosion_px: int) -> list[np.ndarray]:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    order = sorted(range(1, n), key=lambda k: -stats[k, cv2.CC_STAT_AREA])
    out = []
    kern = (cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * erosion_px + 1, 2 * erosion_px + 1)) if erosion_px
            else None)
    for k in order:
        m = (labels == k).astype(np.uint8)
        out.append((cv2.erode(m, kern) if kern is not None else m).astype(bool))
    return out


def _radial_sigma(pts: np.ndarray, normals: np.ndarray, sigma_along_axis_mm: np.ndarray, c_cam: np.ndarray,
                  axis: np.ndarray) -> np.ndarray:
    """A depth error of ``sigma`` along the camera's axis moves a point along its ray by ``sigma / (ray . axis)``;
    its part along the surface normal is what the fit's residuals see."""
    ray = pts - c_cam
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    return sigma_along_axis_mm * np.abs(np.sum(ray * normals, axis=1)) / np.abs(ray @ axis)


def expected_range(rms: float, n: int) -> float:
    """Expected range of ``n`` independent Gaussian residuals of standard deviation ``rms`` (Blom's approximation of
    the expected maximum, times 2)."""
    return float(2 * rms * norm.ppf((n - 0.375) / (n + 0.25))) if n > 1 else 0.0


def _sphere_figures(pts: np.ndarray, spec_d: float, c_cam: np.ndarray, axis: np.ndarray, sigma_axis: np.ndarray | None,
                    params: GaugeParams) -> tuple[SphereFit, SphereFigures | None, np.ndarray]:
    """Find the sphere of the calibrated size among the points (RANSAC), fit, drop the grazing points, refit. Returns
    (fit, figures, mask of the points kept)."""
    f, keep = fit_sphere_ransac(pts, spec_d / 2, params.inlier_mm, min_points=params.min_points)
    if f.ok:
        nrm = pts - f.centre_mm
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        to_cam = c_cam - pts
        to_cam /= np.linalg.norm(to_cam, axis=1, keepdims=True)
        keep &= np.sum(nrm * to_cam, axis=1) >= np.cos(np.radians(params.max_incidence_deg))
        f = fit_sphere(pts[keep], params.min_points)
    n_out = 0
    if f.ok:  # once: points beyond 4 robust sigmas (at least 0.05 mm) of the fit (a ball bar's junction, stray depth)
        r = f.residuals_mm
        gate = max(4 * 1.4826 * float(np.median(np.abs(r - np.median(r)))), 0.05)
        far = np.abs(r - np.median(r)) > gate
        if far.any():
            n_out = int(far.sum())
            idx = np.flatnonzero(keep)
            keep[idx[far]] = False
            f = fit_sphere(pts[keep], params.min_points)
    if not f.ok:
        return f, None, keep
    fig = SphereFigures(n_points=f.n_points, diameter_mm=f.diameter_mm, size_error_mm=f.diameter_mm - spec_d,
                        form_range_mm=f.form_range_mm, form_rms_mm=f.rms_mm, centre_mm=[float(x) for x in f.centre_mm],
                        n_outliers=n_out)
    if sigma_axis is not None:
        p = pts[keep]
        nrm = (p - f.centre_mm) / np.linalg.norm(p - f.centre_mm, axis=1, keepdims=True)
        s = _radial_sigma(p, nrm, sigma_axis[keep], c_cam, axis)
        s = s[np.isfinite(s)]
        ok = np.isfinite(s) & (s > 0)
        if ok.any():
            rms = float(np.sqrt(np.mean(s[ok] ** 2)))
            fig.form_rms_predicted_mm = rms
            fig.form_range_predicted_mm = expected_range(rms, f.n_points)
            # weighted least squares covariance of (centre, radius): (J^T W J)^-1, J_i = (-(p_i - c)^T / |p_i - c|, -1)
            J = np.column_stack([-nrm[ok], -np.ones(ok.sum())]) / s[ok, None]
            try:
                cov = np.linalg.inv(J.T @ J)
                fig.size_sigma_predicted_mm = float(2 * np.sqrt(cov[3, 3]))
                fig.centre_cov_predicted_mm2 = cov[:3, :3].tolist()
            except np.linalg.LinAlgError:
                pass
    return f, fig, keep


def measure_source(spec: GaugeSpec, P: np.ndarray, masks: list[np.ndarray], sigma_axis: np.ndarray | None,
                   c_cam: np.ndarray, axis: np.ndarray, params: GaugeParams, source: str
                   ) -> tuple[SourceFigures, np.ndarray]:
    """Figures of one gauge from a point image ``P`` (H, W, 3) and the object's masks (largest first). Also returns
    the signed residual map (H, W; NaN where no point was used)."""
    need = 2 if spec.kind == "sphere_pair" else 1
    res_map = np.full(P.shape[:2], np.nan)
    if need == 2 and len(masks) == 1:  # a ball bar: the bar joins the spheres; split the points in two
        masks = _split_in_two(masks[0], P, spec.centre_distance_mm) or masks
    if len(masks) < need:
        return SourceFigures(source=source, measurable=False,
                             reason=f"{len(masks)} object(s) found above the table, {need} expected"), res_map
    if spec.kind == "plane":
        m = masks[0] & np.all(np.isfinite(P), axis=-1)
        f: PlaneFit = fit_plane_lsq(P[m], params.min_points)
        if not f.ok:
            return SourceFigures(source=source, measurable=False, reason=f"plane: {f.reason}"), res_map
        res_map[m] = f.residuals_mm
        out = SourceFigures(source=source, measurable=True, n_points=f.n_points, flatness_mm=f.flatness_mm,
                            plane_rms_mm=f.rms_mm)
        if sigma_axis is not None:
            s = _radial_sigma(P[m], np.broadcast_to(f.normal, (m.sum(), 3)), sigma_axis[m], c_cam, axis)
            s = s[np.isfinite(s)]
            if s.size:
                out.plane_rms_predicted_mm = float(np.sqrt(np.mean(s ** 2)))
                out.flatness_predicted_mm = expected_range(out.plane_rms_predicted_mm, f.n_points)
        return out, res_map
    spheres, centres = [], []
    for k in range(need):
        m = masks[k] & np.all(np.isfinite(P), axis=-1)
        pts = P[m]
        f, fig, keep = _sphere_figures(pts, spec.diameter_mm, c_cam, axis,
                                       None if sigma_axis is None else sigma_axis[m], params)
        if fig is None:
            name = "sphere" if need == 1 else f"sphere {k + 1}"
            return SourceFigures(source=source, measurable=False, reason=f"{name}: {f.reason}"), res_map
        vv, uu = np.nonzero(m)
        res_map[vv[keep], uu[keep]] = f.residuals_mm
        spheres.append(fig)
        centres.append(f.centre_mm)
    out = SourceFigures(source=source, measurable=True, spheres=spheres)
    if need == 2:
        L = float(np.linalg.norm(centres[0] - centres[1]))
        out.centre_distance_mm, out.spacing_error_mm = L, L - spec.centre_distance_mm
        if all(s.centre_cov_predicted_mm2 is not None for s in spheres):
            u = (centres[0] - centres[1]) / L
            C = np.asarray(spheres[0].centre_cov_predicted_mm2) + np.asarray(spheres[1].centre_cov_predicted_mm2)
            out.spacing_sigma_predicted_mm = float(np.sqrt(u @ C @ u))
    return out, res_map


def _split_in_two(mask: np.ndarray, P: np.ndarray, centre_distance_mm: float) -> list[np.ndarray] | None:
    """One component holding both spheres of a pair (and the bar between them): its points in two 3-D clusters.
    None when the component is too small to hold both (its extent below 0.9 of the centre distance)."""
    from scipy.cluster.vq import kmeans2

    m = mask & np.all(np.isfinite(P), axis=-1)
    v, u = np.nonzero(m)
    if len(v) < 4:
        return None
    X = P[v, u]
    if np.linalg.norm(np.ptp(X, axis=0)) < 0.9 * centre_distance_mm:
        return None
    _, lab = kmeans2(X, 2, seed=0, minit="++")
    out = []
    for k in (0, 1):
        mk = np.zeros_like(mask)
        mk[v[lab == k], u[lab == k]] = True
        out.append(mk)
    return out


def _grade(value: float | None, ok: float, warn: float) -> Status:
    if value is None or not np.isfinite(value):
        return "NOT MEASURABLE"
    return "PASS" if abs(value) <= ok else ("WARN" if abs(value) <= warn else "FAIL")


ORDER = {"PASS": 0, "WARN": 1, "NOT MEASURABLE": 1, "FAIL": 2}


def gauge_status(spec: GaugeSpec, gt: SourceFigures, lim: GaugeLimits) -> tuple[Status, list[str]]:
    if not gt.measurable:
        return "NOT MEASURABLE", [gt.reason or "not measurable"]
    checks = []
    for k, s in enumerate(gt.spheres):
        name = "sphere" if len(gt.spheres) == 1 else f"sphere {k + 1}"
        checks.append((f"{name} size error", s.size_error_mm, lim.size_pass_mm, lim.size_warn_mm))
        checks.append((f"{name} form error", s.form_range_mm, lim.form_pass_mm, lim.form_warn_mm))
    if gt.spacing_error_mm is not None:
        checks.append(("sphere-spacing error", gt.spacing_error_mm, lim.spacing_pass_mm, lim.spacing_warn_mm))
    if gt.flatness_mm is not None:
        checks.append(("flatness", gt.flatness_mm, lim.flatness_pass_mm, lim.flatness_warn_mm))
    worst, reasons = "PASS", []
    for name, v, ok, warn in checks:
        st = _grade(v, ok, warn)
        if st != "PASS":
            reasons.append(f"{name} {v:+.3f} mm ({st}: limits {ok:g} / {warn:g} mm)")
        if ORDER[st] > ORDER[worst]:
            worst = st
    return worst, reasons


def measure_raw_depth(spec: GaugeSpec, gt: SourceFigures, depth_mm: np.ndarray, rig, P_gt: np.ndarray, fg: np.ndarray,
                 params: GaugeParams) -> SourceFigures:
    """The raw depth map's points in the ZED-left frame, the object's taken within ``gate_mm`` of the GT fit and
    ``min_height_mm`` above the GT's table, eroded on the depth image like the GT's."""
    Q = depth_points_in_zed(depth_mm, rig)
    bg = ~fg & np.all(np.isfinite(P_gt), axis=-1)
    bgp = P_gt[bg]
    if len(bgp) < 50:
        return SourceFigures(source="raw", measurable=False, reason="too little table around the gauge in the GT")
    bgp = bgp[np.linspace(0, len(bgp) - 1, min(len(bgp), 20000)).astype(int)]
    n, c, _ = fit_plane_robust(bgp, 3.0, iterations=200, rng=np.random.default_rng(0))
    if c > 0:
        n, c = -n, -c
    finite = np.all(np.isfinite(Q), axis=-1)
    with np.errstate(invalid="ignore"):
        above = finite & (Q @ n - c > params.min_height_mm)
    masks = []
    if gt.spheres:
        for s in gt.spheres:
            r = np.linalg.norm(Q - np.asarray(s.centre_mm), axis=-1)
            with np.errstate(invalid="ignore"):
                masks.append(above & (np.abs(r - s.diameter_mm / 2) < params.gate_mm))
    else:
        f = fit_plane_lsq(P_gt[gauge_components(fg, params.erosion_px)[0] & np.all(np.isfinite(P_gt), axis=-1)])
        with np.errstate(invalid="ignore"):
            masks.append(above & (np.abs(Q @ f.normal - f.offset_mm) < params.gate_mm))
    if params.erosion_px:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * params.erosion_px + 1,) * 2)
        masks = [cv2.erode(m.astype(np.uint8), k).astype(bool) for m in masks]
    T_zed_from_depth = rig.T_zed_from_depth
    sig = params.depth_noise.sigma_mm(depth_mm)
    out, _ = measure_source(spec, Q, masks, sig, T_zed_from_depth[:3, 3], T_zed_from_depth[:3, 2], params, "raw")
    return out


def summary_lines(rep: GaugesResult) -> list[str]:
    """Console lines: one per gauge and figure, with PASS/WARN/FAIL."""
    lines = [f"Gauge objects (VDI/VDE 2634-2, ground truth): {rep.status}"]
    for g in rep.gauges:
        if not g.gt.measurable:
            lines.append(f"  {g.capture} ({g.kind}): NOT MEASURABLE: {g.gt.reason}")
            continue
        head = f"  {g.capture} ({g.kind}): {g.status}"
        parts = []
        for k, s in enumerate(g.gt.spheres):
            raw = g.raw.spheres[k] if g.raw is not None and g.raw.measurable else None
            parts.append(f"size error {s.size_error_mm:+.3f} mm (raw depth {raw.size_error_mm:+.3f})" if raw else
                         f"size error {s.size_error_mm:+.3f} mm")
            pr = f" (predicted {s.form_range_predicted_mm:.3f})" if s.form_range_predicted_mm is not None else ""
            prms = f" (predicted {s.form_rms_predicted_mm:.3f})" if s.form_rms_predicted_mm is not None else ""
            parts.append(f"form {s.form_range_mm:.3f} mm range{pr}, {s.form_rms_mm:.3f} mm RMS{prms}, "
                         f"{s.n_points} points")
        if g.gt.spacing_error_mm is not None:
            raw = g.raw.spacing_error_mm if g.raw is not None and g.raw.measurable else None
            parts.append(f"spacing error {g.gt.spacing_error_mm:+.3f} mm"
                         + (f" (raw depth {raw:+.3f})" if raw is not None else ""))
        if g.gt.flatness_mm is not None:
            pr = f", predicted {g.gt.flatness_predicted_mm:.3f}" if g.gt.flatness_predicted_mm is not None else ""
            parts.append(f"flatness {g.gt.flatness_mm:.3f} mm{pr} (RMS {g.gt.plane_rms_mm:.3f}), "
                         f"{g.gt.n_points} points")
        lines.append(head + ": " + "; ".join(parts))
    return lines


GaugesFile.model_rebuild()
