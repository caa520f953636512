"""Which of calibrate-scale's three measurements (scenes, boards in the ZED, boards in the depth map) has errors its
covariance does not describe: each measurement on its own, solved on the exact extrinsic, against the generator's
truth, over the sessions ``bench_scale_coverage.py`` rendered (its WORKDIR).

Printed per session and measurement: the estimate's error over its 1-sigma (z); then per measurement and term the RMS
of z over the sessions (1 for a calibrated covariance) and the mean z (a bias shows as a mean away from 0).

    python benchmarks/diag_scale_sources.py [--workdir /tmp/gtforge_bench_scale_coverage] [--glob 'seed*_0.5_*']
        [--exact-labels]

``--exact-labels``: the scenes solved a second time on the same pixels with labels from the generator's exact depth
read as the depth camera reads it (``read_labels``: its scale and offset errors along its own rays): a bias that stays
comes from the images and their matching, not from the depth map or its reprojection. Each scene solve also prints
its three errors' joint effect on a disparity at the scenes' median depth (px): the three are nearly collinear over a
scene's depth range.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

import numpy as np

from bench_scale_calibration import outside

from gtforge.records.calibration import CalibrationFile, ScaleParams
from gtforge.records.dataset import BuildParams
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.io.calibrated_session import open_calibrated_session
from gtforge.scale_calibration import (IB, IC, IK, IY, apply_scale, board_measurements, scene_images,
                                       scene_pixels, solve_scenes)

TRUTH = np.zeros(7)
TRUTH[IB], TRUTH[IY], TRUTH[IK], TRUTH[IC] = 0.003, math.radians(0.15), -0.002, 0.5
NAMES = {IB: "b", IY: "yaw", IK: "k", IC: "c"}


def read_labels(z_mm: np.ndarray, rig) -> np.ndarray:
    """Exact labels on the ZED-left grid for the generator's exact depth ``z_mm`` (ZED-left pixels) as the depth
    camera reads it: each surface point moved along its depth-camera ray to ``(1 + k) z + c`` (TRUTH's k, c), then
    labelled at the ZED pixel it now projects to. That pixel is a fraction of a pixel from the one it came from, so
    the moved points' disparities are carried back to the grid to first order (their gradient times the shift).

    Reading ``(1 + k) Z + c`` at the point's own pixel (this script before round 4's session 14) takes neither the
    depth camera's rays nor the shift into account: it put the built labels 0.0009 px below 'exact' ones, an offset
    that was the formula's; against these the built labels of a noise-free depth map agree to 4e-6 px on the table
    (the fruit: the mesh's chord, -0.00015 px median, as the sigma map's mesh term has it)."""
    zed = rig.zed
    T_zed_from_mech = np.asarray(rig.T_zed_from_mech, np.float64)
    T_mech_from_zed = np.linalg.inv(T_zed_from_mech)
    H, W = z_mm.shape
    vv, uu = np.mgrid[0:H, 0:W].astype(np.float64)
    p_zed = np.stack([(uu - zed.left.cx_px) / zed.left.fx_px, (vv - zed.left.cy_px) / zed.left.fy_px,
                      np.ones_like(uu)]) * z_mm.astype(np.float64)
    p_mech = np.einsum("ij,jhw->ihw", T_mech_from_zed[:3, :3], p_zed) + T_mech_from_zed[:3, 3, None, None]
    p_mech = p_mech * (((1 + TRUTH[IK]) * p_mech[2] + TRUTH[IC]) / p_mech[2])
    q_zed = np.einsum("ij,jhw->ihw", T_zed_from_mech[:3, :3], p_mech) + T_zed_from_mech[:3, 3, None, None]
    du = zed.left.fx_px * q_zed[0] / q_zed[2] + zed.left.cx_px - uu
    dv = zed.left.fy_px * q_zed[1] / q_zed[2] + zed.left.cy_px - vv
    d = zed.f_px * zed.baseline_mm / q_zed[2] - zed.doffs_px
    gv, gu = np.gradient(d)
    return d - gu * du - gv * dv


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_scale_coverage")
    ap.add_argument("--glob", default="seed*")
    ap.add_argument("--exact-labels", action="store_true",
                    help="also solve the scenes with the generator's exact labels at the same pixels")
    a = ap.parse_args()
    zs: dict[str, list[float]] = {}
    params = ScaleParams()
    for sess in sorted(Path(a.workdir).glob(a.glob)):
        known = outside(sess, "known.yaml")  # (bench_scale_coverage.py's)
        if not sess.is_dir() or not known.is_file():
            continue
        calib = CalibrationFile.read(known)
        session, _ = open_calibrated_session(sess, calib, known, None, "scaled.yaml")
        rig = apply_scale(calib.rig, calib.rig.zed.baseline_mm, np.zeros(7))
        line = [sess.name]
        boards = board_measurements(session, session.select("board", None), calib.rig, calib.board.spec(), params)
        for m in boards:
            kind = "boards-zed" if m.A[:, IB].any() else "boards-depth"
            for row, (yv, sv) in enumerate(zip(m.y, np.sqrt(np.diag(m.C)))):
                term = int(np.flatnonzero(m.A[row])[0])
                z = (yv - TRUTH[term]) / sv
                zs.setdefault(f"{kind} {NAMES[term]}", []).append(z)
                line.append(f"{kind} {NAMES[term]} z {z:+.2f}")
        pix, exact = [], []
        fb = rig.zed.f_px * rig.zed.baseline_mm
        for d in session.select("scenes", None):
            cap = session.load_capture(d)
            sd, _, _ = build_scene_arrays(cap.depth_mm, rig, BuildParams(), cap.fruit_mask)
            sp = scene_pixels(d.name, sd.depth_mm, sd.disparity_px, sd.nonoccluded,
                              scene_images(cap.zed_left, cap.zed_right, params), params, rig)
            if sp is None:
                continue
            pix.append(sp)
            # the same pixels labelled from the generator's exact depth, read as the depth camera would (its scale
            # and offset errors), without the depth map's noise or its sampling: what the images alone give
            d_read = read_labels(np.load(sess / "truth" / f"scene_{d.name}.npz")["zed_depth_mm"], rig)[sp.v, sp.u]
            exact.append(dataclasses.replace(sp, d_gt=d_read, z_mm=fb / (d_read + rig.zed.doffs_px)))
        # the scenes measure b + k (with the depth offset's scale), c and yaw
        truth_s = np.array([TRUTH[IB] + TRUTH[IK], TRUTH[IC], TRUTH[IY]])
        for label, sps in [("scenes", pix)] + ([("scenes, exact labels", exact)] if a.exact_labels else []):
            theta, C_s, _ = solve_scenes(sps, rig, params, 0.0)
            err = theta[:3] - truth_s
            for i, name in enumerate(("b+k", "c", "yaw")):
                z = err[i] / math.sqrt(C_s[i, i])
                zs.setdefault(f"{label} {name}", []).append(z)
                line.append(f"{label} {name} z {z:+.2f}")
            # what the three errors together do to a disparity at the scenes' median depth, at the image's centre
            z_med = float(np.median(np.concatenate([sp.z_mm for sp in sps])))
            effect = err[0] * fb / z_med + err[1] * fb / z_med ** 2 - err[2] * rig.zed.f_px
            zs.setdefault(f"{label}: px at the median depth", []).append(effect)
            line.append(f"{label} {effect:+.4f} px at {z_med:.0f} mm")
        print("; ".join(line), flush=True)
    print()
    print("| measurement, term | sessions | RMS z | mean z |")
    print("|---|---|---|---|")
    for k, v in zs.items():
        if k.endswith("median depth"):
            print(f"| {k} | {len(v)} | RMS {math.sqrt(np.mean(np.square(v))):.4f} | mean {np.mean(v):+.4f} |")
        else:
            print(f"| {k} | {len(v)} | {math.sqrt(np.mean(np.square(v))):.2f} | {np.mean(v):+.2f} |")


if __name__ == "__main__":
    main()
