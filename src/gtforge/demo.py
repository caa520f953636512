"""``gtforge demo``: the whole chain on a freshly generated synthetic session, checked against truth."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np

from gtforge.build_dataset import BuildParams, build_dataset
from gtforge.calibrate import CalibrateParams, calibrate
from gtforge.evaluate import evaluate
from gtforge.geometry import pose_difference
from gtforge.io.formats import read_pfm
from gtforge.predictors import SGBM
from gtforge.synthetic import SyntheticTruth, generate_session
from gtforge.reports.calibration import write_calibration_report
from gtforge.reports.evaluation import tables_markdown
from gtforge.validate import validate


def run_demo(directory: str | Path, scale: float = 0.5, n_board: int = 8, n_scenes: int = 4, seed: int = 0,
             holdout: int = 2, say: Callable[[str], None] = print, status: Callable[[str], None] = print) -> dict:
    d = Path(directory)
    t0 = time.perf_counter()
    session = d / "session"
    say(f"[1/5] rendering a synthetic session ({n_board} board poses, {n_scenes} fruit scenes, scale {scale}) -> {session}")
    generate_session(session, n_board=n_board, n_scenes=n_scenes, scale=scale, seed=seed, progress=status)
    truth = SyntheticTruth.read(session / "truth" / "rig_truth.yaml")
    T_true = np.array(truth.T_zed_from_mech)

    boards = sorted(p.name for p in (session / "board").iterdir())
    held = boards[-holdout:] if holdout else []
    say(f"[2/5] calibrate on {len(boards) - len(held)} poses (holding out {', '.join(held) or 'none'})")
    calib_path = d / "calibration.yaml"
    cal = calibrate(session, calib_path, CalibrateParams(use_depth=True), exclude=held, progress=status)
    write_calibration_report(cal, d / "calibration_report")
    rot_err, tr_err = pose_difference(cal.rig.T, T_true)
    say(f"      RMS {cal.rms_px:.3f} px; sigma {cal.sigma_rot_deg:.4f} deg / {cal.sigma_trans_mm:.3f} mm; "
        f"vs truth: {rot_err:.4f} deg / {tr_err:.3f} mm")

    say("[3/5] validate on the held-out poses")
    val = validate(session, calib_path, d / "validation", captures=held or None, progress=status)
    say(f"      XY {val.xy_mean_px:.3f} px (published 0.56), Z {val.z_error_mean_pct:.4f} % (published 0.08) -> "
        f"{'PASS' if val.passed else 'FAIL'}")

    say("[4/5] build the dataset")
    ds = d / "dataset"
    summ = build_dataset(session, calib_path, ds, BuildParams(ply=True), progress=True)
    epes = []
    for sid in summ.built + summ.skipped_unchanged:
        tr = np.load(session / "truth" / f"scene_{sid}.npz")
        gt = read_pfm(ds / "scenes" / sid / "disp0GT.pfm")
        seen = tr["seen_by_mech"] & np.isfinite(gt)
        epes.append(float(np.mean(np.abs(gt[seen] - tr["zed_disparity_px"][seen]))))
    say(f"      {len(summ.built)} scenes built; ground-truth disparity vs exact truth: EPE {np.mean(epes):.4f} px")

    say("[5/5] evaluate the SGBM baseline against the ground truth")
    ev = evaluate(ds, SGBM(), d / "evaluation", progress=status)
    say(tables_markdown([ev]))
    say(f"done in {time.perf_counter() - t0:.0f} s. Open:\n"
        f"  {d / 'calibration_report' / 'calibration_report.html'}\n  {d / 'validation' / 'validation.html'}\n"
        f"  {ds / 'manifest.json'}  (dataset: {ds})\n  {d / 'evaluation' / 'results.html'} (and results.md/.csv/.json)")
    return {"rot_err_deg": rot_err, "trans_err_mm": tr_err, "xy_px": val.xy_mean_px, "z_pct": val.z_error_mean_pct,
            "gt_epe_px": float(np.mean(epes)), "sgbm_epe_px": ev.pooled["all"].epe_px}
