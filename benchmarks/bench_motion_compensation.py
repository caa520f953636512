"""Motion-compensated ground truth (issue #37) at full resolution (ZED 2K, Mech-Eye-like 1920x1200) over random draws.

Each draw renders one scene of four melon-sized fruit (``gtforge.synthetic.several_fruit_scene``): two moved by a
random rigid motion of the draw's size (translation ``t`` mm in a random direction, rotation ``2/3 t`` deg about a
random axis through the fruit's centre, capped at 2 deg), one left still, and one partly out of the depth camera's
view moved like the first two. The largest size (20 mm, 5 deg) is beyond the limits and must stay flagged. For each
draw: verification and compensation (``verify_and_compensate``) on the ground truth built from the depth capture, with
the exact extrinsic; against the exact truth at the ZED's exposure, the fruit's EPE before and after (the scenes
compensated, every fruit pixel both have), the estimated motions' squared Mahalanobis distance to the truth (chi-square
with 6 degrees of freedom when the covariance is honest: 95 % under 12.59), and the time. The baseline: the same
scene's plain build (``build_scene_arrays`` + ``verify_scene``) in the same run.

    python benchmarks/bench_motion_compensation.py [--draws 12] [--scale 1.0] [--workdir DIR] [--write]
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import time
from pathlib import Path

import numpy as np

from gtforge.core.alignment.fruit_motion import FruitMotionEstimate
from gtforge.core.camera import Rig
from gtforge.core.geometry import invert_T, transform_points
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.dataset.motion_compensation import verify_and_compensate
from gtforge.dataset.scene_verification import verify_scene
from gtforge.io.captures import open_session
from gtforge.records.dataset import BuildParams
from gtforge.synthetic import SyntheticTruth, generate_session

CHI2_6_95 = 12.59
SIZES_MM = (0.5, 1.0, 2.0, 3.0, 20.0)  # the last: beyond the limits (must stay flagged)


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def draw_motions(rng: np.random.Generator, size_mm: float) -> list:
    def one():
        d = rng.normal(size=3)
        d[2] *= 0.5  # mostly along the table (rolling), some settling
        a = rng.normal(size=3)
        rot = min(2.0, 2.0 / 3.0 * size_mm) if size_mm <= 3.0 else 5.0
        return tuple(size_mm * d / np.linalg.norm(d)), tuple(rot * a / np.linalg.norm(a))
    return [one(), ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), one(), one()]


def scene(workdir: Path, k: int, scale: float, supersample: int) -> Path:
    size = SIZES_MM[k % len(SIZES_MM)]
    d = workdir / f"draw_{k:03d}_{scale:g}"
    if not (d / "done").exists():
        shutil.rmtree(d, ignore_errors=True)
        rng = np.random.default_rng(1000 + k)
        generate_session(d, n_board=0, n_scenes=1, scale=scale, seed=300 + k, supersample=supersample,
                         fruit_rigid_motion={0: draw_motions(rng, size)})
        (d / "done").write_text(f"{size}")
    return d


def load_scene(d: Path):
    """A generated one-scene session's rig (with the true extrinsic), its capture and its exact truth."""
    s = open_session(d)
    truth = SyntheticTruth.read(d / "truth" / "rig_truth.yaml")
    rig = Rig(zed=s.zed, mech=s.mech, T_zed_from_mech=truth.T_zed_from_mech)
    return rig, s.load_capture(s.root / "scenes" / "000"), np.load(d / "truth" / "scene_000.npz")


def measure(d: Path):
    rig, cap, z = load_scene(d)
    params = BuildParams()
    t, c = time.perf_counter(), cpu_s()
    sd, region, fruit = build_scene_arrays(cap.depth_mm, rig, params, None)
    verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, cap.zed_left, cap.zed_right, cap.mech_texture,
                 rig, params.verify)
    base_wall, base_cpu = time.perf_counter() - t, cpu_s() - c
    t, c = time.perf_counter(), cpu_s()
    sd, region, fruit = build_scene_arrays(cap.depth_mm, rig, params, None)
    ch = verify_and_compensate(cap.depth_mm, rig, params, sd, region, fruit, cap.zed_left, cap.zed_right,
                               cap.mech_texture)
    wall, cpu = time.perf_counter() - t, cpu_s() - c
    tr = z["zed_disparity_px"]
    T_zed_moved_from_zed_true = z["fruit_T_zed_moved_from_zed"]
    centres_before = np.array([transform_points(invert_T(T_zed_moved_from_zed), c[None])[0]
                               for T_zed_moved_from_zed, c in zip(T_zed_moved_from_zed_true, z["fruit_centre_zed_mm"])])
    moved_truth = np.any(z["fruit_motion_translation_mm"] != 0, axis=1) | np.any(z["fruit_motion_rotvec_deg"] != 0,
                                                                                 axis=1)

    def epe(disp, mask):
        m = mask & np.isfinite(disp) & np.isfinite(tr)
        return float(np.abs(disp[m] - tr[m]).mean()) if m.any() else float("nan")

    # per truth fruit: its pixels at the ZED exposure (truth mask), split by which fruit is nearest; before: where the
    # first ground truth has a value, after: where both have one (a fruit too uncertain to compensate has none: nan)
    fruit_truth = z["fruit_mask"]
    both = fruit_truth & np.isfinite(sd.disparity_px) & np.isfinite(tr)
    v, u = np.nonzero(both)
    P = rig.zed.left.unproject(np.stack([u, v], 1), rig.zed.disparity_to_depth(tr[v, u]))
    after_centres = z["fruit_centre_zed_mm"]
    who = np.argmin(np.linalg.norm(P[:, None, :] - after_centres[None], axis=2), axis=1)
    per_fruit, lost = [], []
    for j in range(len(T_zed_moved_from_zed_true)):
        m = np.zeros_like(both)
        m[v[who == j], u[who == j]] = True
        per_fruit.append((epe(sd.disparity_px, m), epe(ch.sd.disparity_px, m), int(m.sum())))
        # pixels of the compensated fruit without ground truth (the silhouette ring, holes)
        lost.append(int((m & ~np.isfinite(ch.sd.disparity_px)).sum()))
    mc = ch.verification.motion_compensation
    maha = []
    if mc is not None:
        for f in mc.fruit:
            if f.cov_rad_mm is None:
                continue
            c = np.array(f.centre_zed_mm)
            j = int(np.argmin(np.linalg.norm(centres_before - c, axis=1)))
            e = FruitMotionEstimate(c, np.radians(f.rotvec_deg), np.array(f.translation_mm), np.array(f.cov_rad_mm),
                                    f.n_pixels, 0, True, 0.0, None, np.zeros((0, 3)))
            maha.append((j, bool(moved_truth[j]), e.mahalanobis_sq(T_zed_moved_from_zed_true[j]), f.status,
                         f.disparity_sigma_px))
    return dict(status=ch.verification.status, compensated=ch.verification.compensated,
                reasons=mc.reasons if mc is not None else ch.verification.reasons, per_fruit=per_fruit, maha=maha,
                lost=lost, wall=wall, cpu=cpu, base_wall=base_wall, base_cpu=base_cpu)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--draws", type=int, default=15, help="draws (sizes in turn: 0.5, 1, 2, 3, 20 mm)")
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--supersample", type=int, default=2)
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_motion")
    ap.add_argument("--write", action="store_true", help="put the table into benchmarks/RESULTS.md")
    a = ap.parse_args()
    work = Path(a.workdir)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for k in range(a.draws):
        d = scene(work, k, a.scale, a.supersample)
        r = measure(d)
        r["size"] = SIZES_MM[k % len(SIZES_MM)]
        rows.append(r)
        pf = " ".join(f"{b:.3f}->{c:.3f}(-{n_lost}/{n} px)" for (b, c, n), n_lost in zip(r["per_fruit"], r["lost"]))
        mh = " ".join(f"{j}:{m:.1f}{'' if moved else '(still)'}:{st}:sigma{sg:.4f}"
                      for j, moved, m, st, sg in r["maha"])
        print(f"draw {k:2d} {r['size']:4.1f} mm: {r['status']:8s} compensated={r['compensated']!s:5s} EPE per fruit "
              f"{pf}; chi2 {mh}; {r['wall']:.1f} s wall ({r['cpu']:.1f} s CPU) vs plain {r['base_wall']:.1f} s; "
              f"{'; '.join(r['reasons'])[:200]}", flush=True)
    lines = ["| motion (mm / deg) | draws | compensated | moved fruit EPE before (px, mean / worst) | moved fruit EPE "
             "after (px, mean / worst; compensated scenes; fruit too uncertain: holes) | still fruit EPE (the GT's own "
             "floor, px) | time per scene "
             "(s wall / CPU; CPU x plain build+verify) |", "|---|---|---|---|---|---|---|"]
    for size in sorted({r["size"] for r in rows}):
        rs = [r for r in rows if r["size"] == size]
        comp = [r for r in rs if r["compensated"]]
        before = [b for r in rs for j, (b, c, n) in enumerate(r["per_fruit"]) if j != 1 and np.isfinite(b)]
        after = [c for r in comp for j, (b, c, n) in enumerate(r["per_fruit"]) if j != 1 and np.isfinite(c)]
        holes = sum(x[3] == "no ground truth" for r in comp for x in r["maha"])
        still = [c for r in rs for j, (b, c, n) in enumerate(r["per_fruit"]) if j == 1 and np.isfinite(c)]
        rot = min(2.0, 2.0 / 3.0 * size) if size <= 3.0 else 5.0
        wall, cpu = np.mean([r["wall"] for r in rs]), np.mean([r["cpu"] for r in rs])
        ratio = np.mean([r["cpu"] / r["base_cpu"] for r in rs])
        lines.append(f"| {size:g} / {rot:.2g} | {len(rs)} | {len(comp)} | "
                     f"{np.mean(before):.3f} / {np.max(before):.3f} | "
                     + (f"{np.mean(after):.4f} / {np.max(after):.4f} ({sum(a <= 0.01 for a in after)} of {len(after)} "
                        f"<= 0.01; {holes} without ground truth)" if after else "-")
                     + f" | {np.mean(still):.4f} | {wall:.1f} / {cpu:.1f} (x{ratio:.1f}) |")
    m = [x for r in rows if r["size"] <= 3.0 for x in r["maha"] if x[1]]
    inside = np.mean([x[2] <= CHI2_6_95 for x in m]) if m else float("nan")
    still = [x for r in rows for x in r["maha"] if not x[1]]
    lines.append("")
    lines.append(f"Moved fruit (motions up to 3 mm / 2 deg), estimated motion within chi-square(6) 95 % ({CHI2_6_95}) "
                 f"of the truth: {inside:.0%} of {len(m)} (median squared Mahalanobis distance "
                 f"{np.median([x[2] for x in m]):.1f}; 5.35 when honest). Still fruit judged still: "
                 f"{sum(x[3] == 'still' for x in still)} of {len(still)}. Scenes beyond the limits left flagged: "
                 f"{sum(not r['compensated'] for r in rows if r['size'] > 3.0)} of "
                 f"{sum(r['size'] > 3.0 for r in rows)}.")
    text = "\n".join(lines)
    print(text)
    if a.write:
        from fullres_session import update_results

        load = os.getloadavg()[0]
        update_results("motion_compensation", f"## Motion-compensated ground truth (issue #37)\n\n"
                       f"{time.strftime('%Y-%m-%d')}, `python benchmarks/bench_motion_compensation.py --draws "
                       f"{a.draws} --scale {a.scale:g} --write`, scale {a.scale:g}, supersample {a.supersample}; a "
                       f"2-core machine shared with other developers (load average {load:.1f}): times are noisy, the "
                       f"CPU time beside the wall time.\n\n{text}\n")


if __name__ == "__main__":
    main()
