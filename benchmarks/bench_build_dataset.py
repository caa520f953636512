"""End-to-end build-dataset throughput at full resolution (ZED 2K, Mech-Eye-like 1920x1200 depth).

Renders a few distinct fruit scenes once, replicates them (hard links) to N scene folders, then builds the
dataset with the default outputs (mesh, masks, regions, weights, KITTI + ETH3D views, lists, manifest).
Prints scenes/s with --workers 2 against --workers 1 on the same scenes (the baseline), and the share of
worker time spent reading inputs, computing, and writing outputs (from each scene's meta.json).

    python benchmarks/bench_build_dataset.py [--scenes 100] [--distinct 4] [--workdir /tmp/gtforge_bench]
"""
from __future__ import annotations

import argparse
import os
import shutil
import time
from pathlib import Path

import numpy as np

from gtforge.build_dataset import Manifest, build_dataset
from gtforge.calibrate import BoardModel, CalibrationFile
from gtforge.camera import CameraFile, Rig, StereoCalibrationFile
from gtforge.synthetic import default_rig, random_fruit_scene, render_capture, write_capture


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=100)
    ap.add_argument("--distinct", type=int, default=4)
    ap.add_argument("--baseline-scenes", type=int, default=20, help="scenes built with 1 worker for the ratio")
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_build")
    args = ap.parse_args()
    wd = Path(args.workdir)
    shutil.rmtree(wd, ignore_errors=True)
    sess = wd / "session"
    rig = default_rig(1.0)
    CameraFile(camera=rig.mech).write(sess / "mech_intrinsics.yaml")
    StereoCalibrationFile(zed=rig.zed).write(sess / "zed_calibration.yaml")
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    for i in range(args.distinct):
        cap = render_capture(f"{i:03d}", random_fruit_scene(rng, rig, i), rig, rng, kind="scene", supersample=1,
                             depth_noise_mm=0.05)
        write_capture(wd / "src" / cap.name, cap, wd / "truth")
        print(f"\rrendered {i + 1}/{args.distinct} distinct scenes ({time.perf_counter() - t0:.0f} s)", end="", flush=True)
    print()
    for k in range(args.scenes):
        src = wd / "src" / f"{k % args.distinct:03d}"
        dst = sess / "scenes" / f"{k:03d}"
        dst.mkdir(parents=True)
        for f in src.iterdir():
            os.link(f, dst / f.name)
    calib = CalibrationFile(rig=Rig(zed=rig.zed, mech=rig.mech, T_zed_from_mech=rig.T_zed_from_mech), board=BoardModel(),
                            captures_used=[], rms_px=0.0, max_px=0.0, sigma_rot_xyz_deg=[0, 0, 0],
                            sigma_trans_xyz_mm=[0, 0, 0], sigma_rot_deg=0.0, sigma_trans_mm=0.0, poses=[])
    calib.write(wd / "calibration.yaml")
    nb = min(args.baseline_scenes, args.scenes)
    base = build_dataset(sess, wd / "calibration.yaml", wd / "ds1", workers=1,
                         scenes=[f"{k:03d}" for k in range(nb)])
    rate1 = len(base.built) / base.time_s
    s = build_dataset(sess, wd / "calibration.yaml", wd / "ds2", workers=2, progress=True)
    rate2 = len(s.built) / s.time_s
    m = Manifest.read(wd / "ds2" / "manifest.json")
    rd = sum(x.time_read_s for x in m.scenes.values())
    cp = sum(x.time_compute_s for x in m.scenes.values())
    wr = sum(x.time_write_s for x in m.scenes.values())
    tot = rd + cp + wr
    print(f"scenes: {len(s.built)} built, {len(s.failures)} failed; {os.cpu_count()} cores")
    print(f"workers=1 (baseline): {rate1:.2f} scenes/s over {nb} scenes")
    print(f"workers=2           : {rate2:.2f} scenes/s over {len(s.built)} scenes  ({rate2 / rate1:.2f}x the baseline)")
    print(f"worker time: read inputs {rd / tot * 100:.0f} %, compute {cp / tot * 100:.0f} %, "
          f"write outputs (+hashing) {wr / tot * 100:.0f} %; views/lists/manifest in the main process: "
          f"{s.time_s - tot / 2:.1f} s of {s.time_s:.1f} s wall")


if __name__ == "__main__":
    main()
