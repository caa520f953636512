"""Extrinsic accuracy per calibration target, and what ChArUco partial views add (docs/targets.md).

For each target (the 12x9 checkerboard for reference, ChArUco, symmetric and asymmetric circle grids) renders
``--poses`` whole-board poses with ``gtforge.core.targets.models.render_board_views`` (the generator's rig at
``--scale``, 2x2 supersampling, image noise 1 grey level) and calibrates with the default parameters (leave-one-out on):
error of ``T_zed_from_mech`` against the truth, the reported 1-sigma, RMS. For ChArUco it then replaces the last
``--partial`` whole-board poses by as many poses cut by the texture camera's image border near its corners (same
pose count) and calibrates again.

    python benchmarks/bench_targets.py [--scale 1.0] [--poses 12] [--partial 4] [--seed 5] [--only charuco,...]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from gtforge.calibrate import calibrate_observations, detect_pose
from gtforge.core.targets.board import BoardSpec
from gtforge.core.geometry import pose_difference
from gtforge.core.targets.models import CharucoSpec, CircleGridSpec, board_model_of
from gtforge.records.calibration import CalibrateParams
from gtforge.synthetic import default_rig, random_board_pose, random_partial_board_pose, render_board_views

TARGETS = {
    "checkerboard": BoardSpec(12, 9, 20.0),
    "charuco": CharucoSpec(12, 9, 20.0, 15.0, "DICT_5X5_100"),
    "circles_symmetric": CircleGridSpec(11, 8, 20.0, 10.0, False),
    "circles_asymmetric": CircleGridSpec(4, 11, 20.0, 14.0, True),
}


def calibrate_views(views, rig, spec):
    obs, reps = [], []
    for v in views:
        o, r = detect_pose(v.name, v.mech_texture, v.depth_mm, v.zed_left, rig.mech, rig.zed, spec, 4.0)
        reps.append(r)
        if o is not None:
            obs.append(o)
    res = calibrate_observations(obs, reps, rig.mech, rig.zed, CalibrateParams(board=board_model_of(spec)))
    rot, tr = pose_difference(res.rig.T_zed_from_mech, rig.T_zed_from_mech)
    return res, rot, tr, len(obs)


def line(name, res, rot, tr, n):
    return (f"| {name} | {n} | {rot:.4f} | {tr:.3f} | {res.sigma_rot_deg:.4f} | {res.sigma_trans_mm:.3f} | "
            f"{res.rms_px:.3f} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--poses", type=int, default=12)
    ap.add_argument("--partial", type=int, default=4)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--only", default=",".join(TARGETS))
    a = ap.parse_args()
    rig = default_rig(a.scale)
    print(f"scale {a.scale} (ZED {rig.zed.left.width_px}x{rig.zed.left.height_px}, texture "
          f"{rig.mech.width_px}x{rig.mech.height_px}), {a.poses} poses, seed {a.seed}")
    print("| target | poses used | rotation error (deg) | translation error (mm) | 1-sigma rot (deg) | "
          "1-sigma trans (mm) | RMS (px) |")
    print("|---|---|---|---|---|---|---|")
    for name in a.only.split(","):
        spec = TARGETS[name]
        rng = np.random.default_rng(a.seed)
        t0 = time.perf_counter()
        views = [render_board_views(f"{i:03d}", rig, spec, random_board_pose(rng, rig, spec), rng, i)
                 for i in range(a.poses)]
        print(line(name, *calibrate_views(views, rig, spec)), flush=True)
        if name == "charuco" and a.partial:
            part = [render_board_views(f"p{k}", rig, spec, random_partial_board_pose(rng, rig, spec, k % 4), rng,
                                       100 + k)
                    for k in range(a.partial)]
            mixed = views[:a.poses - a.partial] + part
            print(line(f"charuco, {a.poses - a.partial} whole + {a.partial} cut by the texture image's border",
                       *calibrate_views(mixed, rig, spec)), flush=True)
            print(line(f"charuco, the {a.poses - a.partial} whole ones only",
                       *calibrate_views(views[:a.poses - a.partial], rig, spec)), flush=True)
        print(f"<!-- {name}: {time.perf_counter() - t0:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
