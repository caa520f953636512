"""Where the motion-compensated fruit's residual error comes from (issue #37 follow-up), on the full-resolution draws
of ``bench_motion_compensation.py`` (made there, or here when missing).

Per moved fruit, against the exact truth at the ZED's exposure: the ground truth rebuilt with the estimated motion and
with the true motion, each without and with the silhouette ring (``SILHOUETTE_RING_PX``), split into the fruit's
inner part (the truth's fruit mask eroded by 5 px) and its outer 5 px; and the estimate's own error: the motion's
error vs the truth and its effect on the fruit's disparity (the directions that change the ground truth), for the
fit as built (texture weight 1), the texture term weighted 0.3 / 0.1 / 0.03 against the stereo term (stereo
dominant), and each term alone started from the truth (its own optimum).

    python benchmarks/diag_motion_residual.py [--draws 3 8] [--scale 1.0] [--workdir DIR]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
from bench_motion_compensation import cpu_s, load_scene, scene

import gtforge.core.alignment.fruit_motion as fmod
from gtforge.core.alignment.fruit_motion import FruitMotionEstimate, MotionImages, estimate_fruit_motion
from gtforge.core.alignment.photometric import local_normalize, to_gray
from gtforge.core.camera import Rig
from gtforge.core.geometry import invert_T, transform_points
from gtforge.core.ground_truth.render import render_texture
from gtforge.dataset import motion_compensation as mcm
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.records.dataset import BuildParams

VARIANTS = (("fit (texture weight 1)", 1.0, {}), ("texture weight 0.3", 0.3, {}), ("texture weight 0.1", 0.1, {}),
            ("texture weight 0.03", 0.03, {}), ("stereo alone, from the truth", 1.0, {"use_texture": False}),
            ("texture alone, from the truth", 1.0, {"use_stereo": False}))


def disparity_effect(e: FruitMotionEstimate, err: np.ndarray, depth_truth: np.ndarray, rig: Rig) -> float:
    """Mean |disparity change| over the fruit's moved points of the motion error ``err`` (omega, t): the motion's
    sigma map (``motion_sigma_px``) with the covariance ``err err^T``."""
    H, W = depth_truth.shape
    uv = rig.zed.left.project(e.moved_points_mm)
    ui, vi = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    ok = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    who = np.zeros((H, W), np.int64)
    who[vi[ok], ui[ok]] = 1
    who[~np.isfinite(depth_truth)] = 0
    ee = FruitMotionEstimate(e.centre_mm, e.rotvec_rad, e.translation_mm, np.outer(err, err), 0, 0, True, 0.0, None,
                             e.points_mm)
    return float(np.mean(mcm.motion_sigma_px(depth_truth, who, {1: ee}, rig)[who > 0]))


def run(d: Path) -> None:
    rig, cap, z = load_scene(d)
    params = BuildParams()
    sd, region, fruit = build_scene_arrays(cap.depth_mm, rig, params, None)
    H, W = sd.depth_mm.shape
    n_cc, labels = cv2.connectedComponents(fruit.view(np.uint8), connectivity=8)
    rec, _ = mcm._compensate(cap.depth_mm, rig, params, sd, region, fruit, cap.zed_left, cap.zed_right,
                             cap.mech_texture, None)
    T_zed_moved_from_zed_true = z["fruit_T_zed_moved_from_zed"]
    before = np.array([transform_points(invert_T(T_zed_moved_from_zed), c[None])[0]
                       for T_zed_moved_from_zed, c in zip(T_zed_moved_from_zed_true, z["fruit_centre_zed_mm"])])
    est, tru = {}, {}
    for f in rec.fruit:
        if f.status not in ("moved", "no ground truth"):
            continue
        c = np.array(f.centre_zed_mm)
        j = int(np.argmin(np.linalg.norm(before - c, axis=1)))
        e = FruitMotionEstimate(c, np.radians(f.rotvec_deg), np.array(f.translation_mm), np.array(f.cov_rad_mm), 0, 0,
                                True, 0.0, None, np.zeros((0, 3)))
        est[f.component] = e
        p = e.params_from_T(T_zed_moved_from_zed_true[j])
        tru[f.component] = FruitMotionEstimate(c, p[:3], p[3:], np.eye(6) * 1e-12, 0, 0, True, 0.0, None,
                                               np.zeros((0, 3)))
    ring0 = mcm.SILHOUETTE_RING_PX
    rebuilt = {}
    for ring in (0, ring0):
        mcm.SILHOUETTE_RING_PX = ring
        for name, m in (("estimated", est), ("true", tru)):
            rebuilt[name, ring] = mcm.rebuild_with_motion(cap.depth_mm, rig, params, sd, labels, m)[0].disparity_px
    mcm.SILHOUETTE_RING_PX = ring0
    tr = z["zed_disparity_px"]
    fm = z["fruit_mask"]
    inner = cv2.erode(fm.view(np.uint8), np.ones((11, 11), np.uint8)).view(bool)
    v, u = np.nonzero(fm & np.isfinite(tr))
    P = rig.zed.left.unproject(np.stack([u, v], 1), rig.zed.disparity_to_depth(tr[v, u]))
    who = np.argmin(np.linalg.norm(P[:, None, :] - z["fruit_centre_zed_mm"][None], axis=2), axis=1)
    lost = np.isfinite(rebuilt["estimated", 0]) & ~np.isfinite(rebuilt["estimated", ring0])
    e_lost = np.abs(rebuilt["estimated", 0][lost] - tr[lost])
    print(f"{d.name}: ring of {ring0} px: {lost.sum()} pixels without ground truth "
          f"({lost.sum() / np.isfinite(rebuilt['estimated', 0]).sum():.3%}); {np.sum(e_lost > 1)} of them were off "
          f"by > 1 px, the rest median {np.median(e_lost[e_lost <= 1]):.4f} px")
    for j in range(len(T_zed_moved_from_zed_true)):
        line = []
        parts = (("all", who == j), ("inner", (who == j) & inner[v, u]), ("outer 5 px", (who == j) & ~inner[v, u]))
        for part, m in parts:
            vals = []
            for ring in (0, ring0):  # where both motions' ground truths have a value
                vm, um = v[m], u[m]
                ok = np.isfinite(rebuilt["estimated", ring][vm, um]) & np.isfinite(rebuilt["true", ring][vm, um])
                vv, uu = vm[ok], um[ok]
                for name in ("estimated", "true"):
                    err = np.abs(rebuilt[name, ring][vv, uu] - tr[vv, uu]).mean()
                    vals.append(f"{name} motion{' + ring' if ring else ''} {err:.4f} ({len(vv)} px)")
            line.append(f"{part}: " + ", ".join(vals))
        print(f"  truth fruit {j}: " + "; ".join(line), flush=True)
    # the estimate's own error, per term
    vp = params.verify
    sn = vp.norm_sigma_px
    rend, ok = render_texture(sd.depth_mm, rig, cap.mech_texture, vp.texture_occlusion_tol_mm)
    images = MotionImages(local_normalize(to_gray(cap.zed_left[:H]).astype(np.float32), None, sn),
                          local_normalize(to_gray(cap.zed_right[:H]).astype(np.float32), None, sn),
                          local_normalize(rend, ok, sn))
    margin = int(np.ceil(2 * sn)) + 2
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
    depth_truth = z["zed_depth_mm"].astype(np.float32)
    w0 = fmod.TEXTURE_WEIGHT
    for k in range(1, n_cc):
        use = cv2.erode((labels == k).view(np.uint8), kernel).view(bool) & sd.nonoccluded & np.isfinite(sd.depth_mm)
        vk, uk = np.nonzero(use)
        if len(vk) < 100:
            continue
        X = rig.zed.left.unproject(np.stack([uk, vk], axis=1), sd.depth_mm[vk, uk])
        j = int(np.argmin(np.linalg.norm(before - X.mean(0), axis=1)))
        if not np.any(z["fruit_motion_translation_mm"][j]):
            continue
        for name, w, kw in VARIANTS:
            fmod.TEXTURE_WEIGHT = w
            if "use_texture" in kw or "use_stereo" in kw:
                kw = {**kw, "initial_T": T_zed_moved_from_zed_true[j]}
            t0 = cpu_s()
            e = estimate_fruit_motion(X, (vk, uk), images, rig.zed, **kw)
            fmod.TEXTURE_WEIGHT = w0
            if e is None:
                print(f"  truth fruit {j}, {name}: no estimate")
                continue
            err = e.params_from_T(T_zed_moved_from_zed_true[j]) - np.r_[e.rotvec_rad, e.translation_mm]
            print(f"  truth fruit {j}, {name}: converged {e.converged} ({e.iterations} it.), error rotation "
                  f"{np.degrees(np.linalg.norm(err[:3])):.4f} deg, translation {np.linalg.norm(err[3:]) * 1e3:.1f} um "
                  f"(z {err[5] * 1e3:+.1f} um) -> mean |disparity change| "
                  f"{disparity_effect(e, err, depth_truth, rig):.4f} px; squared Mahalanobis "
                  f"{e.mahalanobis_sq(T_zed_moved_from_zed_true[j]):.1f}; {cpu_s() - t0:.1f} s CPU", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, nargs="+", default=[3, 8])
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--supersample", type=int, default=2)
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_motion")
    a = ap.parse_args()
    t, c = time.perf_counter(), cpu_s()
    for k in a.draws:
        run(scene(Path(a.workdir), k, a.scale, a.supersample))
    print(f"{time.perf_counter() - t:.0f} s wall, {cpu_s() - c:.0f} s CPU")


if __name__ == "__main__":
    main()
