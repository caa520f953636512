"""Per-scene verification and scene-based refinement at full resolution (ZED 2K, Mech-Eye-like 1920x1200).

1. Shift precision: with the exact extrinsic, the texture shift each scene measures (it should be 0) for depth noise
   0 / 0.03 / 0.1 mm and ZED image noise 0.5 / 1.5 / 4 grey levels (the baseline: the issue's 0.05 px target).
2. Sensitivity: a fruit rolled 0.5 mm between the captures, and a 0.05 deg extrinsic error against its predicted
   shift.
3. Refinement: start 0.05 deg / 0.5 mm off the truth; error after refining over 3, 6 and all scenes (baseline: the
   starting error, and the issue's 0.005 deg / 0.05 mm target).

Renders (about a minute a scene at 3x3 supersampling) are kept in WORKDIR and reused.

    python benchmarks/bench_verify_refine.py [--scenes 8] [--workdir /tmp/gtforge_bench_verify]
"""
from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

import numpy as np

from gtforge.core.camera import Rig
from gtforge.core.geometry import T_from_rotvec, pose_difference
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.dataset.scene_verification import predicted_shift, verify_scene
from gtforge.io.captures import open_session
from gtforge.records.calibration import CalibrationFile
from gtforge.records.dataset import BuildParams
from gtforge.refine import RefineParams, refine
from gtforge.synthetic import SyntheticTruth, generate_session


def session(workdir: Path, n: int) -> Path:
    d = workdir / f"fullres_{n}"
    if not (d / "done").exists():
        shutil.rmtree(d, ignore_errors=True)
        t = time.perf_counter()
        generate_session(d, n_board=0, n_scenes=n + 1, scale=1.0, seed=5, depth_noise_mm=0.0, image_noise=0.5,
                         fruit_motion_mm={n: (0.5, 0.0, 0.0)},
                         progress=lambda m: print(f"  rendered {m} ({time.perf_counter() - t:.0f} s)", flush=True))
        (d / "done").write_text("")
    return d


def calib_file(d: Path, T_zed_from_mech: np.ndarray, path: Path) -> Path:
    s = open_session(d)
    CalibrationFile.known_extrinsic(Rig(zed=s.zed, mech=s.mech, T_zed_from_mech=T_zed_from_mech)).write(path)
    return path


def verify(cap, rig, depth=None, left=None):
    sd, region, _ = build_scene_arrays(cap.depth_mm if depth is None else depth, rig, BuildParams())
    ver, _ = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region,
                          cap.zed_left if left is None else left, cap.zed_right, cap.mech_texture, rig)
    return ver, sd


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_verify")
    args = ap.parse_args()
    wd = Path(args.workdir)
    wd.mkdir(parents=True, exist_ok=True)
    print(f"{os.cpu_count()} cores; load average {os.getloadavg()[0]:.1f} at start")
    d = session(wd, args.scenes)
    T_zed_from_mech_true = np.array(SyntheticTruth.read(d / "truth" / "rig_truth.yaml").T_zed_from_mech)
    rig = CalibrationFile.read(calib_file(d, T_zed_from_mech_true, wd / "exact.yaml")).rig
    s = open_session(d)
    ids = [f"{i:03d}" for i in range(args.scenes)]
    caps = {sid: s.load_capture(s.root / "scenes" / sid) for sid in ids}
    rng = np.random.default_rng(0)

    print("\n## 1. texture shift with the exact extrinsic (px; 0 is right; target |shift| <= 0.05)")
    print("| depth noise (mm) | image noise (grey) | mean |shift| all | max |shift| all | max |shift| fruit "
          "| max |stereo bias| |")
    print("|---|---|---|---|---|---|")
    for dn in (0.0, 0.03, 0.1):
        for im in (0.5, 1.5, 4.0):
            sh, sf, sb = [], [], []
            for sid in ids:
                cap = caps[sid]
                depth = cap.depth_mm + rng.normal(0, dn, cap.depth_mm.shape).astype(np.float32) if dn else None
                extra = np.sqrt(max(im ** 2 - 0.5 ** 2, 0.0))  # the renders carry 0.5 already
                left = np.clip(cap.zed_left + rng.normal(0, extra, cap.zed_left.shape), 0, 255).astype(np.uint8) \
                    if extra else None
                ver, _ = verify(cap, rig, depth, left)
                sh.append(ver.texture_all.magnitude_px)
                sf.append(ver.texture_fruit.magnitude_px)
                sb.append(max(abs(e.disparity_bias_px) for e in ver.stereo.values() if e.disparity_bias_px is not None))
            print(f"| {dn} | {im} | {np.mean(sh):.4f} | {np.max(sh):.4f} | {np.max(sf):.4f} | {np.max(sb):.4f} |",
                  flush=True)

    print("\n## 2. sensitivity")
    moved = s.load_capture(s.root / "scenes" / f"{args.scenes:03d}")
    ver, _ = verify(moved, rig)
    print(f"fruit rolled 0.5 mm: fruit shift {ver.texture_fruit.magnitude_px:.3f} px, whole area "
          f"{ver.texture_all.magnitude_px:.3f} px -> {ver.status}")
    for axis in ([0, 0.05, 0], [0.05, 0, 0]):
        T_zed_from_mech_wrong = T_from_rotvec(np.radians(axis), [0, 0, 0]) @ T_zed_from_mech_true
        rw = rig.with_extrinsic(T_zed_from_mech_wrong)
        ver, sd = verify(caps[ids[0]], rw)
        pred = predicted_shift(sd.depth_mm, rw, T_zed_from_mech_true)
        got = np.array([ver.texture_all.dx_px, ver.texture_all.dy_px])
        print(f"0.05 deg about {'xyz'[int(np.argmax(axis))]}: predicted ({pred[0]:+.3f}, {pred[1]:+.3f}) px, measured "
              f"({got[0]:+.3f}, {got[1]:+.3f}) px, difference {np.linalg.norm(got - pred):.4f} px (target <= 0.05)")

    print("\n## 3. refinement from 0.05 deg / 0.5 mm off (target: 0.005 deg / 0.05 mm with 6+ scenes)")
    print("| scenes | start deg / mm | refined deg / mm | scenes left out | time (s) |")
    print("|---|---|---|---|---|")
    T_zed_from_mech_init = T_from_rotvec(np.radians([0.03, -0.03, 0.025]), [0.3, -0.3, 0.25]) @ T_zed_from_mech_true
    start = calib_file(d, T_zed_from_mech_init, wd / "start.yaml")
    r0, t0 = pose_difference(T_zed_from_mech_init, T_zed_from_mech_true)
    for n in sorted({3, 6, args.scenes}):
        if n > args.scenes:
            continue
        use = ids[:n] + [f"{args.scenes:03d}"]  # plus the rolled fruit, which refinement must leave out
        t = time.perf_counter()
        res = refine(d, start, None, RefineParams(leave_one_out=False), scenes=use)
        r, tr = pose_difference(res.rig.T_zed_from_mech, T_zed_from_mech_true)
        print(f"| {n} (+1 rolled) | {r0:.4f} / {t0:.3f} | {r:.4f} / {tr:.3f} | "
              f"{', '.join(res.refinement.scenes_excluded) or 'none'} | {time.perf_counter() - t:.0f} |", flush=True)
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
