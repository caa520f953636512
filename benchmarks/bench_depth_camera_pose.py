"""What an error in a separate depth camera's pose (session.yaml's ``T_mech_from_depth``) does to the labels, and
how far calibrate-scale's estimate of its rotation removes it (issue #25; docs/design/accuracy.md).

Renders a two-camera session (``gtforge.synthetic.two_camera_rig``: the depth camera 45 mm beside the texture
camera) whose session.yaml gives the depth camera's pose turned by ``--error-deg`` (a rotation vector, deg), then
calibrates from the boards and runs the README's chain from there: refine alone (the old way), calibrate-scale, and
calibrate-scale then refine. Prints for each calibration the error of ``T_zed_from_depth`` against the truth and the
GT's mean |error| against the exact disparity per scene, and calibrate-scale's estimate of the rotation (the
correction is the inverse turn).

    python benchmarks/bench_depth_camera_pose.py [--scale 0.3] [--error-deg 0.1,-0.15,0.1] [--workdir DIR]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from gtforge.calibrate import calibrate
from gtforge.core.geometry import pose_difference
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.io.captures import open_session
from gtforge.records.calibration import CalibrateParams
from gtforge.records.dataset import BuildParams
from gtforge.refine import RefineParams, refine
from gtforge.scale_calibration import calibrate_scale
from gtforge.synthetic import SyntheticTruth, generate_session


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=0.3)
    ap.add_argument("--error-deg", default="0.1,-0.15,0.1")
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_depth_pose")
    a = ap.parse_args()
    err = tuple(float(x) for x in a.error_deg.split(","))
    work = Path(a.workdir)
    sess = work / f"session_{a.scale:g}_{a.error_deg}"
    if not (sess / "done").exists():
        t = time.perf_counter()
        generate_session(sess, n_board=6, n_scenes=4, scale=a.scale, seed=4, two_camera=True,
                         depth_pose_error_deg=err if any(err) else None, supersample=2)
        (sess / "done").write_text("")
        print(f"rendered in {time.perf_counter() - t:.0f} s")
    truth = SyntheticTruth.read(sess / "truth" / "rig_truth.yaml")
    T_zed_from_depth_true = np.array(truth.T_zed_from_mech) @ np.array(truth.T_mech_from_depth)
    board = calibrate(sess, work / "board.yaml", CalibrateParams())
    refined = refine(sess, work / "board.yaml", work / "refined.yaml", RefineParams(leave_one_out=False))
    t = time.perf_counter()
    scaled = calibrate_scale(sess, work / "board.yaml", work / "scaled.yaml")
    t_scale = time.perf_counter() - t
    scaled_refined = refine(sess, work / "scaled.yaml", work / "scaled_refined.yaml", RefineParams(leave_one_out=False))
    s = open_session(sess)
    print(f"depth camera pose error in session.yaml: {err} deg (rotation vector)")
    print(f"calibrate-scale ({t_scale:.0f} s; the correction should read {tuple(-e for e in err)}):")
    for name, term in scaled.scale_calibration.terms.items():
        est = "-" if term.estimate is None else f"{term.estimate:+.5f} +- {term.sigma:.5f}"
        print(f"  {name}: {est} [{term.status}] applied {term.value:+.5f}")
    print("| calibration | T_zed_from_depth vs truth (deg / mm) | GT mean abs error per scene (px) |")
    print("|---|---|---|")
    for name, c in (("board", board), ("board, refined", refined), ("board, calibrate-scale", scaled),
                    ("board, calibrate-scale, refined", scaled_refined)):
        rot, tr = pose_difference(c.rig.T_zed_from_depth, T_zed_from_depth_true)
        epes = []
        for d in s.select("scenes", None):
            cap = s.load_capture(d)
            sd, _, _ = build_scene_arrays(cap.depth_mm, c.rig, BuildParams(), cap.fruit_mask)
            t = np.load(sess / "truth" / f"scene_{d.name}.npz")
            m = np.isfinite(sd.disparity_px) & t["seen_by_mech"] & np.isfinite(t["zed_disparity_px"])
            epes.append(float(np.mean(np.abs(sd.disparity_px[m] - t["zed_disparity_px"][m]))))
        print(f"| {name} | {rot:.4f} / {tr:.3f} | {', '.join(f'{e:.4f}' for e in epes)} |")


if __name__ == "__main__":
    main()
