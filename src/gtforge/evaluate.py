"""Stage 4: score a stereo model's disparities against the built ground truth, per region."""
from __future__ import annotations

import contextlib
import datetime
import hashlib
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np

import gtforge
from gtforge.core.schema import parse_error
from gtforge.core.measure.fruit_size import GradeBins, measure_scene, scene_truth, summarise
from gtforge.core.measure.metrics import (
    Accumulator,
    mean_of,
    metrics_from_errors,
    region_errors,
)
from gtforge.core.ground_truth.regions import region_masks
from gtforge.errors import InputError, MissingFileError, first_of
from gtforge.infra.atomic import atomic_write_bytes
from gtforge.io.formats import read_image, read_pfm, write_image, write_ply
from gtforge.io.middlebury import SceneCalib
from gtforge.io.outputs import require_new_or_empty_folder
from gtforge.predictors import PREDICTION_NAMES, Predictor, timed_predict
from gtforge.records.evaluation import (
    DEPTH_ERROR_MAP_PERCENTILE,
    DEPTH_REGIONS,
    DISP_ERROR_MAP_MAX_PX,
    REGIONS,
    EvalResult,
    SceneResult,
)
from gtforge.reports.evaluation import (
    comparison_warnings,
    error_map_images,
    preview_jpeg,
    row_labels,
    tables_markdown,
    write_comparison_html,
    write_eval_html,
    write_tables,
)
from gtforge.reports.fruit_size import write_fruit_csv
from gtforge.reports.html import nice_ceil

log = logging.getLogger("gtforge.evaluate")

SIGMA_FILE = "disp0GT_sigma.pfm"  # per-pixel ground-truth sigma (px, +inf = no GT), written by build-dataset


def list_scenes(dataset_dir: Path, split: str | None) -> list[str]:
    """Scene ids of a dataset (``scenes/``), or of one split list (``filenames/<split>.txt``)."""
    if split:
        lst = dataset_dir / "filenames" / f"{split}.txt"
        if not lst.is_file():
            raise InputError(lst, None, f"a '{split}' list", "no such file", "splits: train, val, test")
        ids = [l.split()[0].split("/")[1] for l in lst.read_text().splitlines() if l.strip()]
        if not ids:
            raise InputError(lst, None, f"at least one scene in the '{split}' split", "an empty list",
                             _empty_split_hint(dataset_dir, split))
        return ids
    sc = dataset_dir / "scenes"
    if not sc.is_dir():
        raise InputError(dataset_dir, "scenes/", "a dataset built by gtforge build-dataset", "no scenes/ folder",
                         "give the OUT folder of gtforge build-dataset (docs/dataset-format.md)")
    return sorted(p.name for p in sc.iterdir() if p.is_dir() and not p.name.startswith("."))


RESULT_TABLES = ("results.json", "results.md", "results.csv", "results.html", "fruit_size.csv")  # one model's
# the mark of an evaluation's folder whose tables were withdrawn and not yet written again (a stopped rewrite)
INCOMPLETE_MARK = ".evaluation-incomplete"


def _withdraw_tables(out: Path) -> None:
    """An earlier evaluation's tables go before this one's maps replace its maps; the folder stays one evaluate may
    write again (``INCOMPLETE_MARK`` until this run's tables are written)."""
    atomic_write_bytes(out / INCOMPLETE_MARK, b"an evaluation stopped before it wrote its tables: run it again\n")
    for name in RESULT_TABLES:
        (out / name).unlink(missing_ok=True)


def _manifest_fields(ds: Path) -> dict:
    """manifest.json as a mapping, for the checks that read a field of it (of any schema). A file that is no JSON
    mapping (cut short, overwritten) is refused: without it the session the dataset came from, its flagged and
    quarantined scenes and its content hash are unknown (it was read as {}: the scenes scored, exit 0, nothing said,
    no output check against the session, no hash for compare)."""
    p = ds / "manifest.json"
    try:
        man = json.loads(p.read_bytes().decode("utf-8-sig"))
        got = None if isinstance(man, dict) else f"a JSON {type(man).__name__}, not a mapping"
    except UnicodeDecodeError as exc:
        got = f"binary data (byte 0x{exc.object[exc.start]:02x} at offset {exc.start} is not UTF-8 text)"
    except ValueError as exc:
        got = parse_error(exc, "JSON")[0]
    except OSError as exc:
        got = exc.strerror or type(exc).__name__
    if got is not None:
        raise InputError(p, None, "the dataset's manifest (a JSON mapping, as build-dataset writes it)", got,
                         "run gtforge build-dataset with the dataset's session and calibration into this folder "
                         "again: it keeps the scenes built and writes manifest.json anew")
    return man


def _suspect_scenes(man: dict, ids: list[str]) -> dict[str, str]:
    """Scenes of ``ids`` that verify quarantined or flagged (their labels suspect), each with why (``EvalResult``'s
    ``suspect_scenes``); they are scored like the others when asked for, and said once, each kind."""
    quarantined = man.get("quarantined")
    quarantined = set(quarantined if isinstance(quarantined, list) else [])
    flagged = man.get("flagged")
    flagged = flagged if isinstance(flagged, dict) else {}

    def why(sid: str) -> str:
        reasons = flagged.get(sid)
        return "; ".join(map(str, reasons)) if isinstance(reasons, list) else ""

    suspect = {}
    hit = sorted(quarantined & set(ids))
    if hit:
        log.warning("scoring %d scene(s) that verify quarantined (their ground truth is suspect): %s; a split "
                    "(--split train|val|test) leaves them out", len(hit), first_of(hit))
        suspect.update({s: "quarantined" + (f": {why(s)}" if why(s) else "") for s in hit})
    hit = sorted(set(flagged) & set(ids) - quarantined)
    if hit:
        log.warning("scoring %d scene(s) that verification flagged (their ground truth may not match their images): "
                    "%s; see the dataset's verification.html (gtforge verify --quarantine takes them out of the "
                    "splits)", len(hit), first_of(hit))
        suspect.update({s: "flagged" + (f": {why(s)}" if why(s) else "") for s in hit})
    return suspect


def _refuse_output_in_session(out: Path, man: dict) -> None:
    """No output inside the session the dataset was built from (manifest.json's ``session_dir``): no stage writes
    into a capture session."""
    session = man.get("session_dir")
    if not isinstance(session, str) or not session:
        return
    o, root = Path(os.path.realpath(out)), Path(os.path.realpath(session))
    if o == root or root in o.parents:
        raise InputError(out, "--output", "a folder outside the capture session (no stage writes into it)",
                         f"a path inside {root} (the session the dataset was built from)",
                         "give a new folder beside it, e.g. ./evaluation")


def _refuse_output_in_dataset(out: Path, ds: Path) -> None:
    """Results go to a folder of their own: not the dataset folder itself (inside the folders build-dataset writes:
    ``outputs.refuse_inside_dataset_folders``, every stage's check; a new subfolder such as DATASET/evaluation is
    fine)."""
    if Path(os.path.realpath(out)) == Path(os.path.realpath(ds)):
        raise InputError(out, "--output", "a folder of its own (for example DATASET/evaluation or ./evaluation)",
                         "the dataset folder itself", "evaluate never writes into the dataset's own folders")


def _empty_split_hint(dataset_dir: Path, split: str) -> str:
    """Why a split list is empty, from what build-dataset recorded in manifest.json."""
    tail = "rebuild with other --split ratios or more scenes/fruit, or evaluate without --split"
    try:
        man = json.loads((dataset_dir / "manifest.json").read_text())
        splits, scenes = man["splits"], man["scenes"]
        fruit = {(m.get("fruit_id") or f"scene:{sid}") for sid, m in scenes.items()}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return f"build-dataset put no scene into '{split}'; {tail}"
    counts = ", ".join(f"{k} {len(v)}" for k, v in splits.items())
    return (f"build-dataset split {len(scenes)} scene(s) of {len(fruit)} fruit group(s) into {counts} (all scenes "
            f"of one fruit stay in one split, so a small dataset leaves some splits empty); {tail}")


def _manifest_sha256(dataset_dir: Path) -> str | None:
    p = dataset_dir / "manifest.json"
    return hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None


def _content_sha256(dataset_dir: Path) -> str | None:
    from gtforge.records.dataset import Manifest

    try:
        return Manifest.read(dataset_dir / "manifest.json").content_sha256()
    except InputError:  # another schema: compare falls back to the file's hash
        return None


def _check_sigma_maps(ds: Path, ids: list[str]) -> None:
    absent = [sid for sid in ids if not (ds / "scenes" / sid / SIGMA_FILE).is_file()]
    if absent:
        raise InputError(ds / "scenes" / absent[0] / SIGMA_FILE, None,
                         f"a ground-truth sigma map in every scene ({SIGMA_FILE}, float32 px)",
                         f"none in {len(absent)} of {len(ids)} scene(s)",
                         "rebuild the dataset with a gtforge whose build-dataset writes it "
                         "(build-dataset ... --overwrite), or drop --max-gt-sigma")


def evaluate(dataset_dir: str | Path, predictor: Predictor, out_dir: str | Path | None = None, split: str | None = None,
             max_disp_px: float | None = None, write_clouds: bool = False, params_count: int | None = None,
             progress: Callable[[str], None] | None = None, max_gt_sigma_px: float | None = None,
             grades: GradeBins | None = None, fruit_size: bool = True) -> EvalResult:
    """Evaluate ``predictor`` on every scene (or a split) of a built dataset.

    ``max_gt_sigma_px``: score only GT pixels whose ``disp0GT_sigma.pfm`` is below it (the others are counted
    in ``Metrics.n_gt_sigma_left_out``). Scenes without a prediction (a folder predictor) are reported before
    any scoring and listed in ``EvalResult.missing``. ``fruit_size``: also measure every fruit's diameter, height
    and volume from the GT and the prediction (``gtforge.core.measure.fruit_size``; ``grades``: bins for the grade
    confusion)."""
    # finite (inf, the same as no limit, was written into results.json as Infinity, which is no JSON; NaN fails both)
    if max_disp_px is not None and not 0 < max_disp_px < math.inf:
        raise InputError(None, "--max-disp", "a finite disparity limit > 0 px", str(max_disp_px),
                         "give a positive number of px, or leave --max-disp out to score every disparity")
    if max_gt_sigma_px is not None and not 0 < max_gt_sigma_px < math.inf:
        raise InputError(None, "--max-gt-sigma", "a finite sigma limit > 0 px", str(max_gt_sigma_px),
                         "give a positive sigma in px, or leave --max-gt-sigma out to score every label "
                         "(docs/metrics.md)")
    from gtforge.dataset.layout import require_dataset

    ds = require_dataset(dataset_dir, "evaluate the OUT folder of build-dataset, not a capture session")
    ids = list_scenes(ds, split)
    if not ids:
        raise InputError(ds, "scenes", "at least one scene", "none",
                         "run gtforge build-dataset into this folder again: it builds the scenes not there yet")
    man = _manifest_fields(ds)
    suspect = _suspect_scenes(man, ids)
    listed = man.get("scenes")
    unlisted = [s for s in ids if isinstance(listed, dict) and s not in listed]
    if unlisted:  # landed by a build stopped before it wrote the manifest, or no longer in the session since
        log.warning("%d of %d scene(s) are not in %s, so not verified nor in a split: %s; scored like the others. "
                    "Either a build stopped before it finished (run build-dataset again to finish it) or the session "
                    "no longer holds their captures (delete them from the dataset, or build into a new folder)",
                    len(unlisted), len(ids), ds / "manifest.json", first_of(unlisted))
    # a scene the manifest lists whose folder is gone is one not scored (exit 1, the rebuild named), as in a split
    # that lists it; an evaluation of every scene left it out, exit 0, nothing said
    gone = sorted({str(s) for s in listed} - set(ids)) if not split and isinstance(listed, dict) else []
    ids = sorted(ids + gone)
    if max_gt_sigma_px is not None:
        _check_sigma_maps(ds, [s for s in ids if s not in gone])
    out = None
    if out_dir:
        # a folder of its own: new, empty, or an earlier evaluation's (rewritten: maps of scenes not scored this time
        # are removed); never a folder of other files, such as the predictions being scored
        if hasattr(predictor, "folder"):
            o, f = Path(os.path.realpath(out_dir)), Path(os.path.realpath(predictor.folder))
            if o == f or f in o.parents:
                raise InputError(out_dir, "--output", "a folder of its own, outside the predictions",
                                 "the --predictions folder" + ("" if o == f else " (a folder inside it)"),
                                 "give a new folder for the results")
        _refuse_output_in_dataset(Path(out_dir), ds)
        _refuse_output_in_session(Path(out_dir), man)
        out = require_new_or_empty_folder(out_dir, "--output", "give a new folder for the results (an earlier "
                                          "evaluation's folder is rewritten)",
                                          reusable_if=("results.json", INCOMPLETE_MARK))
        if (out / "results.json").is_file():  # its maps are removed below: only an evaluation's own folder
            try:
                EvalResult.read(out / "results.json")
            except InputError:
                raise InputError(out, "--output", "a new or empty folder, or an earlier evaluation's",
                                 "a folder whose results.json is not gtforge evaluate's",
                                 "give a new folder for the results") from None
    pooled = {r: Accumulator() for r in REGIONS}
    per_scene, missing, times = [], {}, []
    from_files = hasattr(predictor, "find")  # a folder of predictions, not a network
    for sid in gone:
        missing[sid] = str(MissingFileError(ds / "scenes" / sid, None, "the scene's folder (manifest.json lists it)",
                                            "no such folder", "run gtforge build-dataset into this folder again: it "
                                            "builds the scenes a dataset lacks"))
    absent = [sid for sid in ids if sid not in missing and predictor.find(sid) is None] if from_files else []
    if absent:
        where = getattr(predictor, "folder", "")
        if len(absent) == len(ids) - len(gone):
            raise InputError(where, None, f"a prediction per scene named {PREDICTION_NAMES}",
                             f"none for the {len(absent)} scene(s) ({first_of(absent, 3)})",
                             "name each file after its scene id (docs/metrics.md, 'Predictions')")
        log.warning("no prediction for %d of %d scene(s) in %s (%s; expected %s): scoring the other %d, "
                    "and the command will exit with code 1", len(absent), len(ids), where, first_of(absent),
                    PREDICTION_NAMES, len(ids) - len(gone) - len(absent))
        for sid in absent:
            missing[sid] = f"no prediction file ({PREDICTION_NAMES.replace('<id>', sid)})"
    for sid in gone:
        log.error("scene %s: %s", sid, missing[sid])
    warmed = False
    fruit_records, fruit_ms = [], []
    written: list[Path] = []  # the error maps this run wrote

    def leave_out(sid: str, exc: InputError) -> None:  # a scene not scored: said now, listed in the results
        missing[sid] = str(exc)
        log.error("scene %s: %s", sid, exc)

    for k, sid in enumerate(ids):
        if sid in missing:
            continue
        if progress:
            progress(f"{predictor.name}: scene {sid} ({k + 1}/{len(ids)})")
        s = ds / "scenes" / sid
        try:
            left, right = read_image(s / "im0.png"), read_image(s / "im1.png")
            gt = read_pfm(s / "disp0GT.pfm")
            if gt.shape != left.shape[:2]:
                raise InputError(s / "disp0GT.pfm", "size", f"{left.shape[1]}x{left.shape[0]} px (im0.png)",
                                 f"{gt.shape[1]}x{gt.shape[0]} px", "the scene's files are not one build's")
            region = read_image(s / "region.png")
            masks = region_masks(region, read_image(s / "mask0nocc.png"))
            cal = SceneCalib(s / "calib.txt")
            sigma = None
            if max_gt_sigma_px is not None:
                sigma = read_pfm(s / SIGMA_FILE)
                if sigma.shape != gt.shape:
                    raise InputError(s / SIGMA_FILE, "size", f"{gt.shape[1]}x{gt.shape[0]} px (disp0GT.pfm)",
                                     f"{sigma.shape[1]}x{sigma.shape[0]} px", "the scene's files are not one "
                                     "build's: build-dataset --overwrite builds them again")
        except MissingFileError as exc:  # a dataset's file, not a capture's: the build's to write again
            leave_out(sid, InputError(exc.file, exc.field, exc.expected, exc.actual, "the scene is incomplete: run "
                                      "build-dataset again (it rebuilds a scene whose files are missing)"))
            continue
        except InputError as exc:
            leave_out(sid, exc)
            continue
        if not from_files and not warmed:
            # a network that fails on its first scene (its inputs' or output's shape or type) fails on every scene:
            # the error stops the run here, once, before anything is scored
            predictor.predict(sid, left, right, cal.ndisp, cal.vmin)  # warm-up (not timed)
            warmed = True
        try:
            pred, ms = timed_predict(predictor, sid, left, right, cal.ndisp, cal.vmin)
        except InputError as exc:  # a folder's file, or a network on a scene unlike the first
            leave_out(sid, exc)
            continue
        if pred.shape != gt.shape:  # (each predictor returns the image's size; the contract's last line of defence)
            leave_out(sid, InputError(getattr(predictor, "source", None), "prediction size",
                                      f"{gt.shape[1]}x{gt.shape[0]} px (scene {sid})",
                                      f"{pred.shape[1]}x{pred.shape[0]} px",
                                      "a prediction has the dataset image's size (after its --crop): "
                                      "docs/metrics.md 'Predictions', 'Models'"))
            continue
        times.append(ms)
        res = {}
        for r, m in masks.items():
            re_ = region_errors(pred, gt, m, max_disp_px, cal.depth if r in DEPTH_REGIONS else None, sigma,
                                max_gt_sigma_px)
            res[r] = metrics_from_errors(*re_)
            pooled[r].add(*re_)
        scene = SceneResult(scene=sid, time_ms=ms, metrics=res)
        if fruit_size:  # per-fruit diameter, height, volume and grade (gtforge.core.measure.fruit_size)
            t0 = time.perf_counter()
            fruit_records += measure_scene(sid, region, cal, gt, pred, scene_truth(ds, sid), grades)
            fruit_ms.append((time.perf_counter() - t0) * 1000.0)
        if out is not None:
            if not written:  # an earlier evaluation's tables and maps go before this one's first map: never
                _withdraw_tables(out)  # one model's tables or maps beside another's (a Ctrl-C now leaves this
                _remove_earlier_outputs(out, [])  # run's maps alone, no tables)
            written += _write_error_maps(out, sid, scene, pred, gt, masks, cal, sigma, max_gt_sigma_px, max_disp_px,
                                         write_clouds)
        per_scene.append(scene)
    if not per_scene:  # (each scene's reason was said as it came: the line says where to look, once)
        where = getattr(predictor, "folder", None)
        counts = [f"{n} {what}" for n, what in ((len(absent), "without a prediction file"),
                                                (len(missing) - len(absent), "refused")) if n]
        raise InputError(where if where is not None else ds, "--predictions" if where is not None else "scenes",
                         "at least one scene scored", f"none of {len(ids)} ({', '.join(counts)}, each said "
                         "above)", "fix the predictions (their files, size or type: docs/metrics.md, "
                         "'Predictions')" if where is not None else "see each scene's error above")

    rep = EvalResult(model=predictor.name, provider=getattr(predictor, "provider", ""), dataset_dir=str(ds.resolve()),
                     scenes=[s.scene for s in per_scene], missing=missing,
                     suspect_scenes={s.scene: suspect[s.scene] for s in per_scene if s.scene in suspect},
                     max_disp_px=max_disp_px,
                     model_source=getattr(predictor, "source", ""), gtforge_version=gtforge.__version__,
                     created=datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
                     dataset_manifest_sha256=_manifest_sha256(ds),
                     dataset_content_sha256=_content_sha256(ds), split=split, max_gt_sigma_px=max_gt_sigma_px,
                     time_ms_median=float(np.median(times)) if times else None, params_count=params_count,
                     pooled={r: a.result() for r, a in pooled.items()},
                     per_image_mean={r: mean_of([s.metrics[r] for s in per_scene]) for r in REGIONS},
                     per_scene=per_scene)
    if fruit_size:
        rep.fruit_size = summarise(fruit_records, grades,
                                   time_ms_per_scene=float(np.median(fruit_ms)) if fruit_ms else None)
    if out is not None:
        write_tables([rep], out)
        if rep.fruit_size is not None:
            write_fruit_csv(rep, out / "fruit_size.csv")
            written.append(out / "fruit_size.csv")
        rep.write(out / "results.json")
        write_eval_html(rep, out)
        _remove_earlier_outputs(out, written)
        (out / INCOMPLETE_MARK).unlink(missing_ok=True)  # its tables are there: a whole evaluation again
    return rep


# what an evaluation writes besides its tables, by folder (``_write_error_maps``), and its fruit table
_MAP_FOLDERS = {"heatmaps": ("_disp_error.png", "_depth_error.png"),
                "heatmaps/preview": ("_disp_error.jpg", "_depth_error.jpg"), "clouds": ("_depth_error.ply",)}


def _remove_earlier_outputs(out: Path, written: list[Path]) -> None:
    """In a folder an earlier evaluation wrote: remove its maps, clouds and fruit table that this one did not write
    again (scenes not scored now, a fruit without depth error, --no-clouds, --no-fruit-size), so that every file in
    the folder is this evaluation's."""
    keep = set(written)
    stale = [out / "fruit_size.csv"] if (out / "fruit_size.csv") not in keep else []
    for folder, suffixes in _MAP_FOLDERS.items():
        if (out / folder).is_dir():
            stale += [f for f in (out / folder).iterdir() if f.name.endswith(suffixes) and f not in keep]
    for f in stale:
        f.unlink(missing_ok=True)
    for folder in sorted(_MAP_FOLDERS, reverse=True):  # a folder left empty goes too (clouds/ after --no-clouds)
        with contextlib.suppress(OSError):  # not empty (a user's file, this run's maps) or not there: stays
            (out / folder).rmdir()


def _write_error_maps(out: Path, sid: str, scene: SceneResult, pred: np.ndarray, gt: np.ndarray,
                      masks: dict[str, np.ndarray], cal: SceneCalib, sigma: np.ndarray | None,
                      max_gt_sigma_px: float | None, max_disp_px: float | None, write_clouds: bool) -> list[Path]:
    """``heatmaps/<id>_{disp,depth}_error.png`` (full size, colour bar below) + small previews for results.html,
    and with ``write_clouds`` the fruit points coloured by depth error. Only scored pixels are coloured. Returns the
    files written."""

    scored = masks["all"] & np.isfinite(gt)
    if max_disp_px is not None:
        scored &= gt < max_disp_px
    if sigma is not None:
        with np.errstate(invalid="ignore"):
            scored &= sigma < max_gt_sigma_px
    err = np.where(scored, np.abs(pred - gt), np.nan)
    scene.disp_error_map_max_px = DISP_ERROR_MAP_MAX_PX
    full, preview = error_map_images(err, DISP_ERROR_MAP_MAX_PX, "|disparity error| (px)")
    written = [out / "heatmaps" / f"{sid}_disp_error.png", out / "heatmaps" / "preview" / f"{sid}_disp_error.jpg"]
    write_image(written[0], full)
    atomic_write_bytes(written[1], preview_jpeg(preview))
    fruit = scored & masks["fruit"]
    with np.errstate(invalid="ignore"):
        zerr = np.where(fruit, np.abs(cal.depth(pred) - cal.depth(gt)), np.nan)
    finite = zerr[np.isfinite(zerr)]
    if finite.size == 0:
        return written
    zmax = nice_ceil(float(np.percentile(finite, DEPTH_ERROR_MAP_PERCENTILE)))
    scene.depth_error_map_max_mm = zmax
    full, preview = error_map_images(zerr, zmax, "|depth error| (mm)")
    written += [out / "heatmaps" / f"{sid}_depth_error.png", out / "heatmaps" / "preview" / f"{sid}_depth_error.jpg"]
    write_image(written[-2], full)
    atomic_write_bytes(written[-1], preview_jpeg(preview))
    if write_clouds:
        v, u = np.nonzero(np.isfinite(zerr))
        zp = cal.depth(pred[v, u])
        pts = np.stack([(u - cal.cx_px) / cal.f_px * zp, (v - cal.cy_px) / cal.f_px * zp, zp], axis=1)
        e = np.clip(zerr[v, u] / zmax, 0, 1.0)  # blue 0 mm -> red at the map's scale top
        written.append(out / "clouds" / f"{sid}_depth_error.ply")
        write_ply(written[-1], pts, np.stack([e, np.zeros_like(e), 1 - e], axis=1))
    return written


def compare(result_files: list[str | Path], out_dir: str | Path) -> tuple[str, list[str]]:
    """Several ``results.json`` (or the evaluation folders holding them) side by side (``comparison.md``/``.csv``/
    ``.html``).

    Returns the Markdown table and the warnings: results from different datasets, scene sets or scoring
    limits, and model names used by more than one result (their rows are then labelled with the folder)."""

    # an evaluation's folder stands for its results.json (what evaluate's -o named)
    files = [Path(p) / "results.json" if Path(p).is_dir() and (Path(p) / "results.json").is_file() else Path(p)
             for p in result_files]
    for f in files:
        if f.is_dir() and (f / INCOMPLETE_MARK).is_file():  # a rewrite stopped before its tables: no results yet
            raise InputError(f, "RESULTS", "an evaluation's results.json", f"an evaluation folder without one "
                             f"({INCOMPLETE_MARK}: evaluate was stopped before it wrote its tables)",
                             "run that evaluate again")
    seen: dict[str, Path] = {}
    for f in files:
        key = os.path.realpath(f)
        if key in seen:
            raise InputError(f, "RESULTS", "each evaluation once", f"the same file as {seen[key]}",
                             "drop the repeated one")
        seen[key] = f
    out = require_new_or_empty_folder(out_dir, "--output", "give a new folder for the comparison (an earlier "
                                      "comparison's folder is rewritten)", reusable_if="comparison.md")
    reports = [EvalResult.read(p) for p in files]
    warnings = comparison_warnings(reports, files)
    for w in warnings:
        log.warning(w)
    labels = row_labels(reports, files)
    write_tables(reports, out, "comparison", labels=labels, warnings=warnings)
    write_comparison_html(reports, files, labels, warnings, out / "comparison.html")
    return tables_markdown(reports, labels=labels, warnings=warnings), warnings
