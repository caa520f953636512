"""Reprojection core speed at full resolution: Mech-Eye-like 1920x1200 depth into the ZED 2K left camera
(2208x1242), gtforge splat / mesh against Open3D's tensor API (create_from_depth_image +
project_to_depth_image) on the same inputs, in the same run. Prints ratios (baseline: Open3D).

    python benchmarks/bench_reproject.py [--repeat 7]

Open3D ignores lens distortion (it gets the same depth and K), so it does less work than gtforge.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import open3d as o3d

from gtforge.reproject import ReprojectParams, project_depth_to_camera
from gtforge.synthetic import default_rig, lit_mask, random_fruit_scene, raycast_depth


def timeit(fn, repeat):
    fn()  # warm-up (numba compile, caches)
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    rig = default_rig(1.0)
    rng = np.random.default_rng(0)
    scene = random_fruit_scene(rng, rig, 0)
    z, _, p = raycast_depth(scene, rig.mech, rig.T_mech_from_world)
    hit = np.isfinite(z)
    lit = np.zeros_like(hit)
    lit[hit] = lit_mask(scene, rig, p[hit])
    depth = np.where(hit & lit, z, np.nan).astype(np.float32)
    mech, cam, T = rig.mech, rig.zed.left, rig.T_zed_from_mech
    print(f"depth {mech.width_px}x{mech.height_px} ({np.isfinite(depth).mean() * 100:.1f} % valid) -> "
          f"{cam.width_px}x{cam.height_px}; median of {args.repeat}")

    # Open3D baseline (tensor API, CPU)
    d_o3d = o3d.t.geometry.Image(o3d.core.Tensor(np.nan_to_num(depth, nan=0.0)))
    K_m = o3d.core.Tensor(mech.K, dtype=o3d.core.float64)
    K_z = o3d.core.Tensor(cam.K, dtype=o3d.core.float64)
    I4 = o3d.core.Tensor(np.eye(4), dtype=o3d.core.float64)
    T_t = o3d.core.Tensor(T, dtype=o3d.core.float64)

    def run_o3d():
        pcd = o3d.t.geometry.PointCloud.create_from_depth_image(d_o3d, K_m, I4, depth_scale=1.0, depth_max=1e6)
        return pcd.project_to_depth_image(cam.width_px, cam.height_px, K_z, T_t, depth_scale=1.0, depth_max=1e6)

    t_o3d = timeit(run_o3d, args.repeat)
    rows = [("open3d (baseline)", t_o3d)]
    for mode in ("splat", "mesh"):
        prm = ReprojectParams(mode=mode)
        rows.append((f"gtforge {mode}", timeit(lambda: project_depth_to_camera(depth, mech, T, cam, prm), args.repeat)))
    print(f"{'method':<20}{'ms':>10}{'speed-up vs open3d':>22}")
    for name, t in rows:
        print(f"{name:<20}{t * 1000:>10.1f}{t_o3d / t:>21.2f}x")
    # coverage of the outputs, for the record
    o = np.asarray(run_o3d().as_tensor().numpy())[..., 0]
    s = project_depth_to_camera(depth, mech, T, cam, ReprojectParams(mode="splat"))
    m = project_depth_to_camera(depth, mech, T, cam, ReprojectParams(mode="mesh"))
    print(f"pixels with depth: open3d {np.mean(o > 0) * 100:.1f} %, splat {np.isfinite(s).mean() * 100:.1f} %, "
          f"mesh {np.isfinite(m).mean() * 100:.1f} %")


if __name__ == "__main__":
    main()
