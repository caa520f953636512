"""align-depth on the synthetic two-camera rig with each choice of edges: the depth silhouettes alone, the depth
camera's own image (IR.png) alone, and both; how far the pose lands from the truth, each rotation's sigma, and the
labels' mean error against the exact disparity.

The session is tests/stages/test_align_depth.py's: the depth camera 45 mm beside the texture camera, 0.3x, one board
and three scenes, session.yaml's depth camera pose turned by (0.6, -0.7, 0.3) deg; the calibration has the exact
extrinsic and that factory pose. Figures, not timings (each line's seconds are for orientation only).

    python benchmarks/bench_align_depth_edges.py [--workdir /tmp/gtforge_bench_align_depth]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from gtforge.align_depth import align_depth
from gtforge.core.alignment.edge_alignment import EdgeAlignmentParams
from gtforge.core.camera import Rig
from gtforge.core.geometry import pose_difference
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.io.captures import open_session
from gtforge.records.calibration import CalibrationFile
from gtforge.records.dataset import BuildParams
from gtforge.synthetic import SyntheticTruth, generate_session

POSE_ERROR_DEG = (0.6, -0.7, 0.3)


def labels_epe_px(session: Path, rig: Rig) -> float:
    """Mean |GT - exact disparity| over the scenes' pixels the depth camera saw (every scene)."""
    s = open_session(session)
    errs = []
    for d in s.select("scenes", None):
        cap = s.load_capture(d)
        sd, _, _ = build_scene_arrays(cap.depth_mm, rig, BuildParams(), cap.fruit_mask)
        t = np.load(session / "truth" / f"scene_{d.name}.npz")
        m = np.isfinite(sd.disparity_px) & np.isfinite(t["zed_disparity_px"]) & t["seen_by_mech"] & sd.nonoccluded
        errs.append(np.abs(sd.disparity_px[m] - t["zed_disparity_px"][m]))
    return float(np.mean(np.concatenate(errs)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_align_depth")
    a = ap.parse_args()
    work = Path(a.workdir)
    session = work / "session"
    if not session.is_dir():
        generate_session(session, n_board=1, n_scenes=3, scale=0.3, seed=5, supersample=1, two_camera=True,
                         depth_pose_error_deg=POSE_ERROR_DEG)
    s = open_session(session)
    truth = SyntheticTruth.read(session / "truth" / "rig_truth.yaml")
    T_mech_from_depth_true = np.array(truth.T_mech_from_depth)
    rig = Rig(zed=s.zed, mech=s.mech, depth_cam=s.depth_cam, T_mech_from_depth=s.T_mech_from_depth,
              T_zed_from_mech=np.array(truth.T_zed_from_mech))
    start = CalibrationFile.known_extrinsic(rig).write(work / "start.yaml")
    exact = rig.model_copy(update={"T_mech_from_depth": T_mech_from_depth_true})
    print(f"labels' mean error: factory pose {labels_epe_px(session, rig):.4f} px, exact pose "
          f"{labels_epe_px(session, exact):.4f} px")
    print("| edges | from the true pose (deg) | omega (deg) | sigma (deg) | offset after (px) "
          "| labels' mean error (px) | s |")
    print("|---|---|---|---|---|---|---|")
    for edges in ("silhouettes", "texture", "both"):
        t0 = time.perf_counter()
        cal = align_depth(session, start, None, EdgeAlignmentParams(edges=edges))
        dt = time.perf_counter() - t0
        r = cal.depth_alignment.result
        off_deg, _ = pose_difference(np.array(cal.rig.T_mech_from_depth), T_mech_from_depth_true)
        print(f"| {edges} | {off_deg:.4f} | {', '.join(f'{x:+.4f}' for x in r.omega_deg)} | "
              f"{', '.join(f'{x:.4f}' for x in r.sigma_omega_deg)} | ({r.offset_after_px[0]:+.3f}, "
              f"{r.offset_after_px[1]:+.3f}) | {labels_epe_px(session, cal.rig):.4f} | {dt:.1f} |", flush=True)


if __name__ == "__main__":
    main()
