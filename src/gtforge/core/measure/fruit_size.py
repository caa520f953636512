"""Per-fruit size, volume and grade from disparity maps: what a grading line measures (docs/metrics.md,
"Fruit size, volume and grade").

For each fruit instance (a connected component of ``region.png``'s fruit labels, 2 and 3) the pixels' disparities
are turned into 3-D points in the ZED-left frame (``Z = f*B/(d + doffs)``), the table is fitted to the same
source's background pixels around the fruit, and an ellipsoid resting on the table with one axis along its
normal is fitted to the visible surface (``gtforge.core.measure.shapefit.fit_resting_ellipsoid``). The same pixels are
used for the ground truth and for the model's prediction, each with its own table; the generator's exact ellipsoids
(synthetic sessions, ``truth/scene_<id>.npz``) score the ground truth itself.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import Field, field_validator

from gtforge.core.geometry import fit_plane_robust
from gtforge.core.ground_truth.regions import REGION_BG, REGION_CENTRE, REGION_EDGE
from gtforge.core.schema import GTModel
from gtforge.core.measure.shapefit import EllipsoidFit, fit_resting_ellipsoid
from gtforge.errors import InputError

MIN_FRUIT_PX = 200  # smaller fruit components are not measured (specks of a mislabelled region)
MAX_FIT_POINTS = 4000  # the ellipsoid is fitted to at most this many of a fruit's pixels (an even subsample)
TABLE_THRESHOLD_MM = 3.0  # RANSAC inlier distance of the table plane
TABLE_RING = 0.5  # the table is fitted to background pixels within this share of the fruit's box size around it
REGION_FRUIT = (REGION_CENTRE, REGION_EDGE)
REGION_BACKGROUND = REGION_BG


# ---- grades -----------------------------------------------------------------------------------------
class GradeBins(GTModel):
    """Grade bins on one measured quantity: grade ``k`` is ``edges[k-1] <= value < edges[k]`` (0 below the first
    edge, ``len(edges)`` from the last one up)."""

    quantity: Literal["diameter_mm", "volume_ml"]
    edges: list[float] = Field(min_length=1)

    @field_validator("edges")
    @classmethod
    def _increasing(cls, v):
        if any(not np.isfinite(x) or x <= 0 for x in v) or any(b <= a for a, b in zip(v, v[1:])):
            raise ValueError("edges must be positive and strictly increasing")
        return v

    def grade(self, value: float | None) -> int | None:
        if value is None or not np.isfinite(value):
            return None
        return int(np.searchsorted(np.asarray(self.edges), value, side="right"))

    def labels(self) -> list[str]:
        e = [f"{x:g}" for x in self.edges]
        return [f"<{e[0]}"] + [f"{a}-{b}" for a, b in zip(e, e[1:])] + [f">={e[-1]}"]


def parse_grades(text: str) -> GradeBins:
    """``diameter_mm:180,200,220`` or ``volume_ml:2500,4000`` -> ``GradeBins``; a one-line error otherwise."""
    m = re.fullmatch(r"\s*(diameter_mm|volume_ml)\s*:\s*([0-9.eE+\-,\s]+)", text or "")
    hint = "for example --grades diameter_mm:180,200,220 or --grades volume_ml:2500,4000"
    if not m:
        raise InputError(None, "--grades", "QUANTITY:EDGE,EDGE,... with QUANTITY diameter_mm or volume_ml", repr(text),
                         hint)
    try:
        edges = [float(x) for x in m.group(2).split(",") if x.strip()]
        return GradeBins(quantity=m.group(1), edges=edges)
    except ValueError:
        raise InputError(None, "--grades", "positive, strictly increasing bin edges", repr(m.group(2)), hint) from None


# ---- results ------------------------------------------------------------------------------------------
class FruitSize(GTModel):
    """One fruit measured from one source (ground truth, prediction or the generator's exact shape)."""

    ok: bool
    reason: str | None = None  # why not measurable
    n_points: int = 0
    diameter_mm: float | None = None  # equatorial: 2 sqrt(a b), a >= b the horizontal semi-axes
    length_mm: float | None = None  # 2 a
    width_mm: float | None = None  # 2 b
    height_mm: float | None = None  # 2 c (along the table normal)
    volume_ml: float | None = None  # 4/3 pi a b c
    centre_mm: list[float] | None = None  # ZED-left frame
    fit_rms_mm: float | None = None

    @classmethod
    def from_fit(cls, f: EllipsoidFit) -> "FruitSize":
        if not f.ok:
            return cls(ok=False, reason=f.reason, n_points=f.n_points)
        return cls(ok=True, n_points=f.n_points, diameter_mm=f.diameter_mm, length_mm=f.length_mm, width_mm=f.width_mm,
                   height_mm=f.height_mm, volume_ml=f.volume_ml, centre_mm=[float(x) for x in f.centre_mm],
                   fit_rms_mm=f.rms_mm)

    @classmethod
    def from_radii(cls, radii_mm, centre_mm) -> "FruitSize":
        """The exact size of an ellipsoid whose third semi-axis is the vertical one."""
        a, b = sorted([float(radii_mm[0]), float(radii_mm[1])], reverse=True)
        c = float(radii_mm[2])
        return cls(ok=True, diameter_mm=2 * np.sqrt(a * b), length_mm=2 * a, width_mm=2 * b, height_mm=2 * c,
                   volume_ml=4 / 3 * np.pi * a * b * c / 1000.0, centre_mm=[float(x) for x in centre_mm])


class FruitRecord(GTModel):
    scene: str
    fruit: int  # component number in the scene (1, 2, ... by area, largest first)
    n_pixels: int
    centroid_uv: list[float]
    gt: FruitSize
    pred: FruitSize | None = None
    truth: FruitSize | None = None  # the generator's exact ellipsoid (synthetic sessions)
    diameter_error_mm: float | None = None  # prediction - GT
    volume_error_pct: float | None = None  # (prediction - GT) / GT * 100
    gt_diameter_error_mm: float | None = None  # GT - truth
    gt_volume_error_pct: float | None = None
    grade_gt: int | None = None
    grade_pred: int | None = None
    grade_truth: int | None = None


class DiameterErrors(GTModel):
    n: int
    mean_mm: float | None  # signed
    mae_mm: float | None
    max_abs_mm: float | None


class VolumeErrors(GTModel):
    n: int
    mean_pct: float | None  # signed
    mape_pct: float | None
    max_abs_pct: float | None


class GradeAgreement(GTModel):
    bins: GradeBins
    labels: list[str]
    confusion: list[list[int]]  # rows: reference grade, columns: compared grade
    n: int
    changed_pct: float | None  # share of fruit whose grade differs


class FruitSizeResult(GTModel):
    """``results.json`` ``fruit_size``: per fruit and pooled."""

    constraint: str = "resting"
    fruit: list[FruitRecord] = Field(default_factory=list)
    n_not_measurable_gt: int = 0
    n_not_measurable_pred: int = 0
    diameter_model_vs_gt: DiameterErrors | None = None
    volume_model_vs_gt: VolumeErrors | None = None
    diameter_gt_vs_truth: DiameterErrors | None = None
    volume_gt_vs_truth: VolumeErrors | None = None
    grades_model_vs_gt: GradeAgreement | None = None
    grades_gt_vs_truth: GradeAgreement | None = None
    time_ms_per_scene: float | None = None  # what measuring the fruit added to evaluate (median per scene)


# ---- measuring ------------------------------------------------------------------------------------------
def _components(region: np.ndarray, min_pixels: int) -> tuple[np.ndarray, list[tuple[int, tuple[int, int, int, int]]]]:
    """(labels, [(label, (y0, y1, x0, x1) box), ...]) of the fruit components, largest first."""
    fruit = ((region == REGION_FRUIT[0]) | (region == REGION_FRUIT[1])).view(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(fruit, connectivity=8)
    order = sorted(range(1, n), key=lambda k: -stats[k, cv2.CC_STAT_AREA])
    boxes = []
    for k in order:
        x, y, w, h, area = stats[k]
        if area >= min_pixels:
            boxes.append((k, (int(y), int(y + h), int(x), int(x + w))))
    return labels, boxes


def fruit_instances(region: np.ndarray, min_pixels: int = MIN_FRUIT_PX) -> list[np.ndarray]:
    """Boolean masks of the fruit components (8-connected region 2/3 pixels), largest first."""
    labels, boxes = _components(region, min_pixels)
    return [labels == k for k, _ in boxes]


class _Window:
    """A calibration seen through an image window starting at pixel (x0, y0) (the principal point moves)."""

    def __init__(self, calib, x0: int, y0: int):
        self.f_px, self.fy_px = calib.f_px, getattr(calib, "fy_px", calib.f_px)
        self.cx_px, self.cy_px = calib.cx_px - x0, calib.cy_px - y0
        self.baseline_mm, self.doffs_px = calib.baseline_mm, calib.doffs_px


def points_from_disparity(disp: np.ndarray, calib, mask: np.ndarray, step: int = 1) -> np.ndarray:
    """``(N, 3)`` ZED-left points (mm) of the masked pixels with a finite, positive ``d + doffs``; ``calib``: a
    ``gtforge.io.middlebury.SceneCalib`` (f, fy, cx, cy, baseline, doffs). ``step``: every ``step``-th row and column
    only, unless that grid meets far fewer valid disparities than the mask holds (a prediction invalid on every other
    row: the grid would land on its holes only); then every pixel."""
    v, u = np.nonzero(mask[::step, ::step])
    v, u = v * step, u * step
    d = disp[v, u].astype(np.float64) + calib.doffs_px
    ok = np.isfinite(d) & (d > 0)
    if step > 1 and ok.size:
        d_all = disp[mask].astype(np.float64) + calib.doffs_px
        if ok.mean() < 0.5 * np.mean(np.isfinite(d_all) & (d_all > 0)):
            return points_from_disparity(disp, calib, mask, 1)
    v, u, d = v[ok], u[ok], d[ok]
    z = calib.f_px * calib.baseline_mm / d
    fy = getattr(calib, "fy_px", calib.f_px)
    return np.column_stack([(u - calib.cx_px) / calib.f_px * z, (v - calib.cy_px) / fy * z, z])


def _subsample(n: int, max_n: int) -> np.ndarray:
    return np.arange(n) if n <= max_n else np.linspace(0, n - 1, max_n).round().astype(int)


def _step(n_pixels: int) -> int:
    """A grid step that still leaves at least ``MAX_FIT_POINTS`` of ``n_pixels`` (fewer pixels to turn into points)."""
    return max(1, int(np.sqrt(n_pixels / (2.0 * MAX_FIT_POINTS))))


def table_plane(disp: np.ndarray, calib, background: np.ndarray, fruit: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The table ``n . p = c`` (``n`` towards the camera) from the background pixels around ``fruit``; None when
    fewer than 50 background points remain."""
    v, u = np.nonzero(fruit)
    h, w = np.ptp(v) + 1, np.ptp(u) + 1
    r = int(np.ceil(TABLE_RING * max(h, w)))
    y0, y1 = max(v.min() - r, 0), min(v.max() + r + 1, disp.shape[0])
    x0, x1 = max(u.min() - r, 0), min(u.max() + r + 1, disp.shape[1])
    ring = np.zeros(disp.shape, bool)
    ring[y0:y1, x0:x1] = background[y0:y1, x0:x1]
    pts = points_from_disparity(disp, calib, ring, _step((y1 - y0) * (x1 - x0)))
    if len(pts) < 50:
        return None
    pts = pts[_subsample(len(pts), MAX_FIT_POINTS)]
    n, c, _ = fit_plane_robust(pts, TABLE_THRESHOLD_MM, iterations=200, rng=np.random.default_rng(0))
    if c > 0:  # towards the camera (the origin): the table lies at n . p = c < 0
        n, c = -n, -c
    return n, float(c)


def measure_fruit(disp: np.ndarray, calib, fruit: np.ndarray, background: np.ndarray,
                  constraint: str = "resting") -> FruitSize:
    """Fit one fruit's visible surface in ``disp`` (ground truth or a prediction)."""
    plane = table_plane(disp, calib, background, fruit)
    if plane is None:
        return FruitSize(ok=False, reason="too few table pixels around the fruit to fit the support plane")
    pts = points_from_disparity(disp, calib, fruit, _step(int(np.count_nonzero(fruit))))
    pts = pts[_subsample(len(pts), MAX_FIT_POINTS)]
    return FruitSize.from_fit(fit_resting_ellipsoid(pts, plane[0], plane[1], constraint))


def scene_truth(dataset_dir: Path, sid: str) -> dict | None:
    """The generator's fruit ellipsoids for scene ``sid`` (from the manifest's session ``truth/``), or None."""
    import json

    try:
        session = Path(json.loads((dataset_dir / "manifest.json").read_text())["session_dir"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    p = session / "truth" / f"scene_{sid}.npz"
    if not p.is_file():
        return None
    with np.load(p) as z:
        if "fruit_radii_mm" not in z.files:
            return None
        return {k: z[k] for k in ("fruit_centre_zed_mm", "fruit_radii_mm")}


def _match_truth(mask: np.ndarray, truth: dict, calib) -> int | None:
    c = truth["fruit_centre_zed_mm"]
    if len(c) == 0:
        return None
    fy = getattr(calib, "fy_px", calib.f_px)
    uv = np.column_stack([calib.f_px * c[:, 0] / c[:, 2] + calib.cx_px, fy * c[:, 1] / c[:, 2] + calib.cy_px])
    v, u = np.nonzero(mask)
    cen = np.array([u.mean(), v.mean()])
    H, W = mask.shape
    for k in np.argsort(np.linalg.norm(uv - cen, axis=1)):
        iu, iv = int(round(uv[k, 0])), int(round(uv[k, 1]))
        if 0 <= iv < H and 0 <= iu < W and mask[iv, iu]:
            return int(k)
    k = int(np.argmin(np.linalg.norm(uv - cen, axis=1)))
    return k if np.linalg.norm(uv[k] - cen) < 0.5 * np.sqrt(mask.sum()) else None


def _pct(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or not b else (a - b) / b * 100.0


def _diff(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a - b


def measure_scene(sid: str, region: np.ndarray, calib, gt: np.ndarray, pred: np.ndarray | None = None,
                  truth: dict | None = None, grades: GradeBins | None = None,
                  constraint: str = "resting") -> list[FruitRecord]:
    """Every fruit of one scene: sizes from the GT and (given) the prediction on the same pixels, and the
    generator's truth where it exists."""
    labels, boxes = _components(region, MIN_FRUIT_PX)
    H, W = region.shape
    out = []
    for k, (lab, (y0, y1, x0, x1)) in enumerate(boxes, start=1):
        # everything on the fruit's box plus the table ring around it (the same result as on the whole image)
        r = int(np.ceil(TABLE_RING * max(y1 - y0, x1 - x0)))
        wy0, wy1, wx0, wx1 = max(y0 - r, 0), min(y1 + r, H), max(x0 - r, 0), min(x1 + r, W)
        win = (slice(wy0, wy1), slice(wx0, wx1))
        m = labels[win] == lab
        bg = region[win] == REGION_BACKGROUND
        cal = _Window(calib, wx0, wy0)
        v, u = np.nonzero(m)
        g = measure_fruit(gt[win], cal, m, bg, constraint)
        p = measure_fruit(pred[win], cal, m, bg, constraint) if pred is not None else None
        v, u = v + wy0, u + wx0
        t = None
        if truth is not None:
            j = _match_truth(m, truth, cal)
            if j is not None:
                t = FruitSize.from_radii(truth["fruit_radii_mm"][j], truth["fruit_centre_zed_mm"][j])
        q = grades.quantity if grades else None

        def grade(s):
            return grades.grade(getattr(s, q)) if grades and s is not None and s.ok else None

        out.append(FruitRecord(
            scene=sid, fruit=k, n_pixels=int(m.sum()), centroid_uv=[float(u.mean()), float(v.mean())], gt=g, pred=p,
            truth=t, diameter_error_mm=_diff(p.diameter_mm, g.diameter_mm) if p else None,
            volume_error_pct=_pct(p.volume_ml, g.volume_ml) if p else None,
            gt_diameter_error_mm=_diff(g.diameter_mm, t.diameter_mm) if t else None,
            gt_volume_error_pct=_pct(g.volume_ml, t.volume_ml) if t else None,
            grade_gt=grade(g), grade_pred=grade(p), grade_truth=grade(t)))
    return out


def _diameter_errors(e: list[float | None]) -> DiameterErrors:
    a = np.array([x for x in e if x is not None], float)
    if not a.size:
        return DiameterErrors(n=0, mean_mm=None, mae_mm=None, max_abs_mm=None)
    return DiameterErrors(n=a.size, mean_mm=float(a.mean()), mae_mm=float(np.abs(a).mean()),
                          max_abs_mm=float(np.abs(a).max()))


def _volume_errors(e: list[float | None]) -> VolumeErrors:
    a = np.array([x for x in e if x is not None], float)
    if not a.size:
        return VolumeErrors(n=0, mean_pct=None, mape_pct=None, max_abs_pct=None)
    return VolumeErrors(n=a.size, mean_pct=float(a.mean()), mape_pct=float(np.abs(a).mean()),
                        max_abs_pct=float(np.abs(a).max()))


def grade_agreement(bins: GradeBins, ref: list[int | None], other: list[int | None]) -> GradeAgreement:
    k = len(bins.edges) + 1
    cm = np.zeros((k, k), int)
    pairs = [(a, b) for a, b in zip(ref, other) if a is not None and b is not None]
    for a, b in pairs:
        cm[a, b] += 1
    changed = sum(a != b for a, b in pairs)
    return GradeAgreement(bins=bins, labels=bins.labels(), confusion=cm.tolist(), n=len(pairs),
                          changed_pct=100.0 * changed / len(pairs) if pairs else None)


def summarise(records: list[FruitRecord], grades: GradeBins | None = None, constraint: str = "resting",
              time_ms_per_scene: float | None = None) -> FruitSizeResult:
    has_truth = any(r.truth is not None for r in records)
    rep = FruitSizeResult(
        constraint=constraint, fruit=records,
        n_not_measurable_gt=sum(not r.gt.ok for r in records),
        n_not_measurable_pred=sum(r.pred is not None and not r.pred.ok for r in records),
        diameter_model_vs_gt=_diameter_errors([r.diameter_error_mm for r in records]),
        volume_model_vs_gt=_volume_errors([r.volume_error_pct for r in records]),
        diameter_gt_vs_truth=_diameter_errors([r.gt_diameter_error_mm for r in records]) if has_truth else None,
        volume_gt_vs_truth=_volume_errors([r.gt_volume_error_pct for r in records]) if has_truth else None,
        time_ms_per_scene=time_ms_per_scene)
    if grades is not None:
        rep.grades_model_vs_gt = grade_agreement(grades, [r.grade_gt for r in records], [r.grade_pred for r in records])
        if has_truth:
            rep.grades_gt_vs_truth = grade_agreement(grades, [r.grade_truth for r in records],
                                                     [r.grade_gt for r in records])
    return rep
