"""Stage 4: score a stereo model's disparities against the built ground truth, per region."""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Callable

import numpy as np
from pydantic import Field

from gtforge.errors import InputError
from gtforge.io.formats import read_image, read_pfm, write_image, write_ply
from gtforge.metrics import Accumulator, Metrics, mean_of, metrics_from_errors, region_errors
from gtforge.schema import VersionedFile
from gtforge.predictors import Predictor, timed_predict

log = logging.getLogger("gtforge.evaluate")

REGIONS = ("all", "nonoccluded", "fruit", "fruit_edge", "fruit_centre", "background")
TABLE_REGIONS = ("all", "fruit", "fruit_edge", "fruit_centre")


class SceneCalib:
    def __init__(self, path: Path):
        if not path.is_file():
            raise InputError(path, None, "a Middlebury calib.txt", "no such file")
        kv = dict(re.findall(r"^(\w+)=(.*)$", path.read_text(), flags=re.M))
        try:
            cam0 = [float(x) for x in re.split(r"[\s;]+", kv["cam0"].strip("[] "))]
            self.f_px = cam0[0]
            self.cx_px, self.cy_px = cam0[2], cam0[5]
            self.doffs_px = float(kv["doffs"])
            self.baseline_mm = float(kv["baseline"])
            self.ndisp = int(float(kv.get("ndisp", 192)))
            self.vmin = int(float(kv.get("vmin", 0)))
        except (KeyError, ValueError, IndexError) as exc:
            raise InputError(path, str(exc).strip("'"), "Middlebury keys cam0, doffs, baseline", "missing/invalid") from None

    def depth(self, disp: np.ndarray) -> np.ndarray:
        d = np.asarray(disp, np.float64) + self.doffs_px
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(d > 0, self.f_px * self.baseline_mm / d, np.nan)


def region_masks(region: np.ndarray, nocc: np.ndarray) -> dict[str, np.ndarray]:
    return {"all": nocc > 0, "nonoccluded": nocc == 255, "fruit": (region == 2) | (region == 3),
            "fruit_edge": region == 3, "fruit_centre": region == 2, "background": region == 1}


class SceneResult(VersionedFile):
    scene: str
    time_ms: float
    metrics: dict[str, Metrics]


class EvalReport(VersionedFile):
    model: str
    provider: str
    dataset_dir: str
    scenes: list[str]
    missing: dict[str, str] = Field(default_factory=dict)
    max_disp_px: float | None = None
    time_ms_median: float | None = None
    params_count: int | None = None
    pooled: dict[str, Metrics]
    per_image_mean: dict[str, Metrics]
    per_scene: list[SceneResult]


def list_scenes(dataset_dir: Path, split: str | None) -> list[str]:
    if split:
        lst = dataset_dir / "filenames" / f"{split}.txt"
        if not lst.is_file():
            raise InputError(lst, None, f"a '{split}' list", "no such file", "splits: train, val, test")
        return [l.split()[0].split("/")[1] for l in lst.read_text().splitlines() if l.strip()]
    sc = dataset_dir / "scenes"
    if not sc.is_dir():
        raise InputError(dataset_dir, "scenes/", "a dataset built by gtforge build-dataset", "no scenes/ folder")
    return sorted(p.name for p in sc.iterdir() if p.is_dir() and not p.name.startswith("."))


def _heatmap(err: np.ndarray, vmax: float) -> np.ndarray:
    import matplotlib

    cmap = matplotlib.colormaps["turbo"]
    rgb = (cmap(np.clip(np.nan_to_num(err, nan=0) / vmax, 0, 1))[..., :3] * 255).astype(np.uint8)
    rgb[~np.isfinite(err)] = 0
    return rgb


def evaluate(dataset_dir: str | Path, predictor: Predictor, out_dir: str | Path | None = None, split: str | None = None,
             max_disp_px: float | None = None, write_clouds: bool = True, params_count: int | None = None,
             progress: Callable[[str], None] | None = None) -> EvalReport:
    """Evaluate ``predictor`` on every scene (or a split) of a built dataset."""
    ds = Path(dataset_dir)
    ids = list_scenes(ds, split)
    if not ids:
        raise InputError(ds, "scenes", "at least one scene", "none")
    out = Path(out_dir) if out_dir else None
    pooled = {r: Accumulator() for r in REGIONS}
    per_scene, missing, times = [], {}, []
    warmed = False
    for k, sid in enumerate(ids):
        if progress:
            progress(f"{predictor.name}: scene {sid} ({k + 1}/{len(ids)})")
        s = ds / "scenes" / sid
        try:
            left, right = read_image(s / "im0.png"), read_image(s / "im1.png")
            gt = read_pfm(s / "disp0GT.pfm")
            masks = region_masks(read_image(s / "region.png"), read_image(s / "mask0nocc.png"))
            cal = SceneCalib(s / "calib.txt")
            if not warmed and not hasattr(predictor, "find"):
                predictor.predict(sid, left, right, cal.ndisp, cal.vmin)  # warm-up (not timed)
                warmed = True
            pred, ms = timed_predict(predictor, sid, left, right, cal.ndisp, cal.vmin)
            if pred.shape != gt.shape:
                raise InputError(sid, "prediction size", f"{gt.shape[1]}x{gt.shape[0]}", f"{pred.shape[1]}x{pred.shape[0]}")
        except InputError as exc:
            missing[sid] = str(exc)
            log.error("scene %s: %s", sid, exc)
            continue
        times.append(ms)
        res = {}
        for r, m in masks.items():
            err, n_gt, derr = region_errors(pred, gt, m, max_disp_px, cal.depth if r.startswith("fruit") else None)
            res[r] = metrics_from_errors(err, n_gt, derr)
            pooled[r].add(err, n_gt, derr)
        per_scene.append(SceneResult(scene=sid, time_ms=ms, metrics=res))
        if out is not None:
            err = np.where(masks["all"] & np.isfinite(gt), np.abs(pred - gt), np.nan)
            write_image(out / "heatmaps" / f"{sid}_disp_error.png", _heatmap(err, 2.0))
            zerr = np.where(masks["fruit"], np.abs(cal.depth(pred) - cal.depth(gt)), np.nan)
            write_image(out / "heatmaps" / f"{sid}_depth_error.png", _heatmap(zerr, 1.0))
            if write_clouds:
                v, u = np.nonzero(masks["fruit"] & np.isfinite(gt) & np.isfinite(pred))
                if len(v):
                    zp = cal.depth(pred[v, u])
                    pts = np.stack([(u - cal.cx_px) / cal.f_px * zp, (v - cal.cy_px) / cal.f_px * zp, zp], axis=1)
                    e = np.clip(np.abs(zp - cal.depth(gt[v, u])), 0, 1.0)  # blue 0 mm -> red >= 1 mm
                    write_ply(out / "clouds" / f"{sid}_depth_error.ply", pts, np.stack([e, np.zeros_like(e), 1 - e], axis=1))
    if not per_scene:
        raise InputError(ds, "scenes", "at least one scene with a prediction", "none",
                         "; ".join(f"{k}: {v}" for k, v in list(missing.items())[:3]))
    rep = EvalReport(model=predictor.name, provider=getattr(predictor, "provider", ""), dataset_dir=str(ds),
                     scenes=[s.scene for s in per_scene], missing=missing, max_disp_px=max_disp_px,
                     time_ms_median=float(np.median(times)) if times else None, params_count=params_count,
                     pooled={r: a.result() for r, a in pooled.items()},
                     per_image_mean={r: mean_of([s.metrics[r] for s in per_scene]) for r in REGIONS},
                     per_scene=per_scene)
    if out is not None:
        from gtforge.reports.evaluation import write_eval_html, write_tables

        write_tables([rep], out)
        rep.write(out / "results.json")
        write_eval_html(rep, out)
    return rep


def compare(result_files: list[str | Path], out_dir: str | Path) -> str:
    """Several ``results.json`` side by side in one table (``comparison.md``/``.csv``)."""
    from gtforge.reports.evaluation import tables_markdown, write_tables

    reports = [EvalReport.read(p) for p in result_files]
    write_tables(reports, Path(out_dir), "comparison")
    return tables_markdown(reports)
