"""The disparity-scale terms (gtforge calibrate-scale, issue #25) at full resolution (ZED 2K, Mech-Eye-like 1920x1200).

One session per error kind, alone and combined, at the issue's limits: ZED baseline +0.3 %, right camera turned
0.15 deg about its vertical axis, depth scale -0.2 %, depth offset +0.5 mm; all of them with the right camera also
turned 0.15 deg about x and z ("all combined": calibrate's self-rectification removes those first); a separate depth
camera turned (0.1, -0.15, 0.1) deg against session.yaml, alone and with all the others; and one without any error
(for the separate depth camera too: "depth camera exact"). Each is calibrated from the exact extrinsic (a perfect \
board calibration: only the scale terms are off)
with the board captures and without them. Printed per row: every term's estimate +- 1-sigma (status), the GT's mean \
EPE against
what the images show (the right image corrected for the applied yaw in the session's one resampling, as
build-dataset writes im1) before and after, and verify's stereo disparity bias (scene 000) before and after.

Targets (the issue): EPE <= 0.02 px after; with no error every term within 2 sigma of 0 and the GT unchanged within
0.002 px.

Renders (several minutes a session) are kept in WORKDIR and reused.

    python benchmarks/bench_scale_calibration.py [--scale 1.0] [--boards 6] [--scenes 3] [--supersample 3]
        [--cases none,combined] [--workdir /tmp/gtforge_bench_scale]
"""
from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import numpy as np

from gtforge.core.camera import Rig
from gtforge.core.zed.scale_corrections import shown_disparity_px
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.dataset.scene_verification import verify_scene
from gtforge.io.calibrated_session import open_with_calibration
from gtforge.io.captures import open_session
from gtforge.records.calibration import CalibrationFile, ScaleParams
from gtforge.records.dataset import BuildParams
from gtforge.scale_calibration import calibrate_scale
from gtforge.synthetic import SyntheticTruth, generate_session

CASES = {
    "none": {},
    "baseline +0.3 %": dict(zed_baseline_error_frac=0.003),
    "yaw 0.15 deg": dict(right_yaw_deg=0.15),
    "depth scale -0.2 %": dict(depth_scale_error_frac=-0.002),
    "depth offset +0.5 mm": dict(depth_offset_mm=0.5),
    "combined": dict(zed_baseline_error_frac=0.003, right_yaw_deg=0.15, depth_scale_error_frac=-0.002,
                     depth_offset_mm=0.5),
    # the same and the right camera turned 0.15 deg about x and z as well (the self-rectification's errors)
    "all combined": dict(zed_baseline_error_frac=0.003, right_yaw_deg=0.15, depth_scale_error_frac=-0.002,
                         depth_offset_mm=0.5, zed_right_rotation_error_rad=(0.0026179938779914945, 0.0,
                                                                            0.0026179938779914945)),
    # a unit with a separate depth camera (two_camera_rig) whose session.yaml pose is turned by (0.1, -0.15, 0.1) deg
    "depth camera exact": dict(two_camera=True),
    "depth camera turned": dict(two_camera=True, depth_pose_error_deg=(0.1, -0.15, 0.1)),
    "all combined and depth camera turned": dict(zed_baseline_error_frac=0.003, right_yaw_deg=0.15,
                                                 depth_scale_error_frac=-0.002, depth_offset_mm=0.5,
                                                 zed_right_rotation_error_rad=(0.0026179938779914945, 0.0,
                                                                               0.0026179938779914945),
                                                 two_camera=True, depth_pose_error_deg=(0.1, -0.15, 0.1)),
}


def session(workdir: Path, name: str, kw: dict, scale: float, boards: int, scenes: int, supersample: int) -> Path:
    d = workdir / name.replace(" ", "_").replace("%", "pct").replace("+", "p").replace("-", "m")
    if not (d / "done").exists():
        shutil.rmtree(d, ignore_errors=True)
        t = time.perf_counter()
        generate_session(d, n_board=boards, n_scenes=scenes, scale=scale, seed=5, depth_noise_mm=0.03,
                         image_noise=1.0, supersample=supersample, **kw)
        (d / "done").write_text("")
        print(f"rendered {name} in {time.perf_counter() - t:.0f} s")
    return d


def outside(sess: Path, name: str) -> Path:
    """A file of the benchmark's beside the session (no stage writes into a session's folder)."""
    return sess.parent / f"{sess.name}-{name}"


def known_calibration(sess: Path, self_rectify: bool = False) -> Path:
    """The exact extrinsic; with ``self_rectify`` (a right camera turned about x and z) the calibration ``gtforge
    calibrate`` writes, self-rectification included, with its extrinsic replaced by the exact one."""
    s = open_session(sess)
    tr = SyntheticTruth.read(sess / "truth" / "rig_truth.yaml")
    if self_rectify:
        from gtforge.calibrate import calibrate
        from gtforge.records.calibration import CalibrateParams

        cal = calibrate(sess, outside(sess, "board.yaml"), CalibrateParams(leave_one_out=False))
        print(cal.zed_self_rectification.summary_line())
        cal = cal.model_copy(update=dict(rig=cal.rig.with_extrinsic(np.array(tr.T_zed_from_mech))))
        return cal.write(outside(sess, "known.yaml"))
    rig = Rig(zed=s.zed, mech=s.mech, depth_cam=s.depth_cam, T_mech_from_depth=s.T_mech_from_depth,
              T_zed_from_mech=np.array(tr.T_zed_from_mech))
    return CalibrationFile.known_extrinsic(rig).write(outside(sess, "known.yaml"))


def figures(sess: Path, calib: CalibrationFile) -> tuple[float, float, float]:
    """(mean EPE against what the images show over the scenes, the largest scene's, scene 000's stereo bias)."""
    s = open_with_calibration(sess, calib)  # the right image corrected for calib's yaw, as build-dataset writes im1
    yaw_true = SyntheticTruth.read(sess / "truth" / "rig_truth.yaml").zed_right_yaw_deg
    epes, bias = [], float("nan")
    for d in s.select("scenes", None):
        cap = s.load_capture(d)
        sd, region, _ = build_scene_arrays(cap.depth_mm, calib.rig, BuildParams(), cap.fruit_mask)
        t = np.load(sess / "truth" / f"scene_{d.name}.npz")
        shown = shown_disparity_px(t["zed_disparity_px"], calib.rig, yaw_true)
        m = np.isfinite(sd.disparity_px) & np.isfinite(shown) & t["seen_by_mech"] & sd.nonoccluded
        epes.append(float(np.mean(np.abs(sd.disparity_px[m] - shown[m]))))
        if d.name == "000":
            ver, _ = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, cap.zed_left,
                                  cap.zed_right, cap.mech_texture, calib.rig)
            bias = ver.stereo["all"].disparity_bias_px
    return float(np.mean(epes)), float(np.max(epes)), bias


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--boards", type=int, default=6)
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--supersample", type=int, default=3, help="rays per pixel side when rendering")
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated case names")
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_scale")
    a = ap.parse_args()
    work = Path(a.workdir)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in a.cases.split(","):
        sess = session(work, name, CASES[name], a.scale, a.boards, a.scenes, a.supersample)
        start = known_calibration(sess, "zed_right_rotation_error_rad" in CASES[name])
        c0 = CalibrationFile.read(start)
        e0, e0max, b0 = figures(sess, c0)
        for boards in (True, False):
            t = time.perf_counter()
            res = calibrate_scale(sess, start, outside(sess, f"scaled_{int(boards)}.yaml"),
                                  ScaleParams(use_boards=boards))
            dt = time.perf_counter() - t
            e1, e1max, b1 = figures(sess, res)
            terms = "; ".join(f"{k.replace('zed_', '').replace('_frac', '')} "
                              + (f"{v.estimate:+.5f}+-{v.sigma:.5f}" if v.sigma is not None else "-")
                              + (f" applied {v.value:+.5f}" if v.status == "applied" else f" ({v.status})")
                              for k, v in res.scale_calibration.terms.items())
            rows.append((name, "yes" if boards else "no", e0, e1, e1max, b0, b1, dt, terms))
            print(rows[-1], flush=True)
    print()
    print("| errors | boards | EPE before (px) | EPE after (px, mean / worst scene) | stereo bias before -> after (px) "
          "| time (s) | terms (estimate +- sigma, status) |")
    print("|---|---|---|---|---|---|---|")
    for name, b, e0, e1, e1max, b0, b1, dt, terms in rows:
        print(f"| {name} | {b} | {e0:.4f} | {e1:.4f} / {e1max:.4f} | {b0:+.3f} -> {b1:+.3f} | {dt:.0f} | {terms} |")


if __name__ == "__main__":
    main()
