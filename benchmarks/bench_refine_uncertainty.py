"""Is the refined extrinsic's covariance (``gtforge refine``, ``cov_extrinsic_rad_mm``) the size of its real error?

Synthetic sessions at 0.4x (depth noise 0.03 mm, image noise 1.5 grey levels, the shared rig): every scene solved
alone (its GT built with the exact extrinsic), and full refinements over disjoint groups of ``--k`` scenes started
about 0.05 deg / 0.5 mm off. For each, the normalised squared error ``e^T C^-1 e`` of the extrinsic against the truth
(6 on average when ``C`` is right) for several estimators of ``C``: the tile sandwich refine now stores (16 px
tiles; 1, 4 and 64 px for comparison), the plain Gauss-Newton ``s^2 H^-1`` and that times the normalisation window's
area (113 px; what refine stored first). With ``--loo`` the refinements also run the leave-one-scene-out jackknife.

    python benchmarks/bench_refine_uncertainty.py [--workdir /tmp/gtforge_bench_refine_sigma] [--pools 2] [--loo]
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from gtforge import refine as R
from gtforge.calibrate import calibrate
from gtforge.core.geometry import T_from_rotvec
from gtforge.io.captures import open_session
from gtforge.records.calibration import CalibrateParams, CalibrationFile
from gtforge.records.dataset import BuildParams
from gtforge.synthetic import SyntheticTruth, generate_session


def _err(T_zed_from_mech, T_zed_from_mech_true):
    return np.concatenate([Rotation.from_matrix(T_zed_from_mech[:3, :3] @ T_zed_from_mech_true[:3, :3].T).as_rotvec(),
                           T_zed_from_mech[:3, 3] - T_zed_from_mech_true[:3, 3]])


def _row(e, est):
    return {k: (float(e @ np.linalg.solve(C, e)), float(np.degrees(np.sqrt(np.trace(C[:3, :3])))),
                float(np.sqrt(np.trace(C[3:, 3:])))) for k, C in est.items()}


def _table(title, rows, errs):
    E = np.array(errs)
    print(f"\n{title}: {len(rows)} trials; actual error RMS {np.degrees(np.sqrt((E[:, :3] ** 2).sum(1).mean())):.5f} "
          f"deg / {np.sqrt((E[:, 3:] ** 2).sum(1).mean()):.4f} mm (the sigmas below are sqrt(trace), comparable)")
    print("| covariance | mean NEES | median NEES | mean sigma deg | mean sigma mm |\n|---|---|---|---|---|")
    for k in rows[0]:
        v = np.array([r[k] for r in rows])
        print(f"| {k} | {v[:, 0].mean():.3f} | {np.median(v[:, 0]):.3f} | {v[:, 1].mean():.5f} "
              f"| {v[:, 2].mean():.4f} |")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_refine_sigma")
    ap.add_argument("--pools", type=int, default=2, help="sessions of --per-pool scenes (seeds 201, 202, ...)")
    ap.add_argument("--per-pool", type=int, default=12)
    ap.add_argument("--k", type=int, default=4, help="scenes per refinement")
    ap.add_argument("--loo", action="store_true", help="refinements with the leave-one-scene-out jackknife")
    args = ap.parse_args()
    wd = Path(args.workdir)
    wd.mkdir(parents=True, exist_ok=True)
    print(f"{os.cpu_count()} cores; load average {os.getloadavg()[0]:.1f} at start")
    true_path = wd / "true_calib.yaml"
    if not true_path.exists():  # a calibration file for the shared 0.4x rig, its extrinsic set to the truth
        generate_session(wd / "board", n_board=7, n_scenes=0, scale=0.4, seed=11, depth_noise_mm=0.0, image_noise=1.0)
        calibrate(wd / "board", wd / "board_calib.yaml", CalibrateParams(use_depth=False))
        c = CalibrationFile.read(wd / "board_calib.yaml")
        T_zed_from_mech_true = SyntheticTruth.read(wd / "board" / "truth" / "rig_truth.yaml").T_zed_from_mech
        c.rig = c.rig.model_copy(update={"T_zed_from_mech": T_zed_from_mech_true})
        c.write(true_path)
    true = CalibrationFile.read(true_path)
    T_zed_from_mech_true = true.rig.T_zed_from_mech
    pools = []
    for i in range(args.pools):
        p = wd / f"pool{201 + i}"
        if not (p / "session.yaml").exists():
            generate_session(p, n_board=0, n_scenes=args.per_pool, scale=0.4, seed=201 + i, depth_noise_mm=0.03,
                             image_noise=1.5)
        pools.append(p)
    params = R.RefineParams(leave_one_out=args.loo)
    single, single_e, full, full_e, scales = [], [], [], [], []
    for p in pools:
        s = open_session(p)
        for d in s.select("scenes", None):
            sp, _ = R._scene_at(s.load_capture(d), true.rig, BuildParams(), params)
            T_zed_from_mech, _ = R.solve_extrinsic([sp], T_zed_from_mech_true, true.rig, params)
            e = _err(T_zed_from_mech, T_zed_from_mech_true)
            single.append(_row(e, R.covariance_estimates([sp], T_zed_from_mech, true.rig, params)))
            single_e.append(e)
    _table("each scene alone", single, single_e)
    rng = np.random.default_rng(5)
    for p in pools:
        names = sorted(x.name for x in (p / "scenes").iterdir())
        for j in range(0, len(names) - args.k + 1, args.k):
            c = CalibrationFile.read(true_path)
            c.rig = c.rig.with_extrinsic(T_from_rotvec(np.radians(rng.normal(0, 0.03, 3)), rng.normal(0, 0.3, 3))
                                         @ T_zed_from_mech_true)
            start = wd / f"start_{p.name}_{j}.yaml"
            c.write(start)
            res = R.refine(p, start, None, params, scenes=names[j:j + args.k])
            T_zed_from_mech = res.rig.T_zed_from_mech
            s = open_session(p)
            pts = [R._scene_at(s.load_capture(s.root / "scenes" / n), true.rig.with_extrinsic(T_zed_from_mech),
                               BuildParams(), params)[0] for n in res.refinement.scenes_used]
            est = R.covariance_estimates(pts, T_zed_from_mech, true.rig, params)
            est["as written"] = np.array(res.cov_extrinsic_rad_mm)
            e = _err(T_zed_from_mech, T_zed_from_mech_true)
            full.append(_row(e, est))
            full_e.append(e)
            scales.append(res.cov_jackknife_scale)
    _table(f"refinements over {args.k} scenes" + (" (leave-one-scene-out on)" if args.loo else ""), full, full_e)
    if args.loo:
        print(f"cov_jackknife_scale: {', '.join(f'{x:.2f}' if x else 'None' for x in scales)}")


if __name__ == "__main__":
    main()
