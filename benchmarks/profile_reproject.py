"""Where the reprojection kernels' time goes: each stage of ``reproject.project_depth_to_camera`` (one thread, the
path a build worker takes) timed alone on the benchmark's scene (bench_reproject.scene_depth: 1920x1200 depth into the
2208x1242 ZED left), by running the kernel's own compiled pieces cumulatively (projection; + edge flags; + the quads'
vectorised pass; + the z-buffer) and taking differences, beside a plain memory-read floor of the same inputs.

Thread CPU time (``time.thread_time``), medians of --repeat, the variants interleaved round-robin, so that a loaded
machine slows them all alike.

    python benchmarks/profile_reproject.py [--repeat 40]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numba
import numpy as np

from gtforge.core.ground_truth import reproject as rp
from gtforge.core.ground_truth.reproject import ReprojectParams, project_depth_to_camera

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_reproject import scene_depth  # noqa: E402

from gtforge.synthetic import default_rig  # noqa: E402


@numba.njit(**rp._JIT)
def _read_floor(depth, rx, ry):
    """Read every input once (depth, both ray planes): the memory traffic any kernel pays."""
    s = 0.0
    for r in range(depth.shape[0]):
        for c in range(depth.shape[1]):
            s += np.float64(depth[r, c]) + rx[r, c] + ry[r, c]
    return s


@numba.njit(**rp._JIT)
def _splat_project_only(buf, depth, rx, ry, R, t, fx, fy, cx, cy):
    """``_splat_rows``' vectorised projection loop without the z-buffer scatter."""
    Hb, W = buf.shape
    Wm = depth.shape[1]
    idx = np.empty(Wm, np.int64)
    Z = np.empty(Wm, np.float32)
    acc = 0
    for r in range(depth.shape[0]):
        for c in range(Wm):
            z = np.float64(depth[r, c])
            x = rx[r, c] * z
            y = ry[r, c] * z
            Zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
            inv = 1.0 / Zc
            ui = np.floor(fx * (R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]) * inv + cx + 0.5)
            vi = np.floor(fy * (R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]) * inv + cy + 0.5)
            ok = (z > 0.0) & (z < np.inf) & (Zc > 0.0) & (ui >= 0.0) & (ui < W) & (vi >= 0.0) & (vi < Hb)
            idx[c] = np.int64(vi * W + ui) if ok else -1
            Z[c] = np.float32(Zc)
        acc += idx[Wm // 2]
    return acc


@numba.njit(**rp._JIT)
def _mesh_stages(buf, sbuf, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2, abs_tol, stage):
    """``_mesh_rows`` over the whole grid, stopping after ``stage``: 1 projection, 2 + edge flags, 3 + everything."""
    Hm, Wm = depth.shape
    H = buf.shape[0]
    P = np.empty((2, 3, Wm))
    Q = np.empty((5, Wm))
    S = np.empty(Wm)
    F = np.empty(Wm, np.uint8)
    cand = np.empty(Wm, np.int64)
    rp._project_row(depth, rx, ry, R, t, fx, fy, cx, cy, 0, P[0, 0], P[0, 1], P[0, 2])
    acc = 0.0
    for r in range(Hm - 1):
        a_ = r & 1
        b_ = 1 - a_
        rp._project_row(depth, rx, ry, R, t, fx, fy, cx, cy, r + 1, P[b_, 0], P[b_, 1], P[b_, 2])
        if stage >= 2:
            rp._quad_flags(depth[r], depth[r + 1], P[a_, 2], P[b_, 2], k1, k2, abs_tol, F)
        if stage >= 3:
            rp._raster_quads(buf, sbuf, False, 0, 0, H - 1, P[a_, 0], P[a_, 1], P[a_, 2], P[b_, 0], P[b_, 1],
                             P[b_, 2], F, Q, S, cand)
        acc += P[b_, 0, Wm // 2] + F[Wm // 2]
    return acc


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=40)
    args = ap.parse_args()
    numba.set_num_threads(1)
    rig = default_rig(1.0)
    depth = scene_depth(rig)
    mech, cam, T = rig.mech, rig.zed.left, rig.T_zed_from_mech
    R, t = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])
    rx, ry = rp._ray_planes(mech.model_dump_json())
    H, W = cam.height_px, cam.width_px
    fx, fy, cx, cy = cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px
    params = ReprojectParams()
    k1, k2 = rp._slant_bounds(mech, params)
    splat, mesh = ReprojectParams(mode="splat"), ReprojectParams(mode="mesh")
    out = np.full((H, W), np.nan, np.float32)
    span = np.empty((1, 1), np.float32)

    def full_nan():
        return np.full((H, W), np.nan, np.float32)

    def splat_kernel():
        out.fill(np.nan)
        rp._splat_rows(out, 0, depth, rx, ry, R, t, fx, fy, cx, cy, 0, depth.shape[0])

    def mesh_stage(k):
        def run():
            out.fill(np.nan)
            _mesh_stages(out, span, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2, params.abs_tol_mm, k)
        return run

    def wrapper_only():  # the Python work of project_depth_to_camera around the kernel
        np.ascontiguousarray(depth, dtype=np.float32)
        Ta = np.asarray(T, np.float64)
        np.ascontiguousarray(Ta[:3, :3]), np.ascontiguousarray(Ta[:3, 3])
        rp._ray_planes(mech.model_dump_json())
        rp._slant_bounds(mech, params)
        numba.get_num_threads()

    methods = {
        "read floor (depth + rx + ry, float64 sum)": lambda: _read_floor(depth, rx, ry),
        "output allocation np.full(NaN) 2208x1242 float32": full_nan,
        "output reset (fill NaN, reused buffer)": lambda: out.fill(np.nan),
        "Python wrapper (checks, ray-grid lookup, conversions)": wrapper_only,
        "splat: projection loop only": lambda: _splat_project_only(out, depth, rx, ry, R, t, fx, fy, cx, cy),
        "splat: kernel (reset + projection + scatter)": splat_kernel,
        "splat: project_depth_to_camera": lambda: project_depth_to_camera(depth, mech, T, cam, splat),
        "mesh: reset + projection": mesh_stage(1),
        "mesh: reset + projection + edge flags": mesh_stage(2),
        "mesh: reset + all (+ quad pass + z-buffer)": mesh_stage(3),
        "mesh: project_depth_to_camera": lambda: project_depth_to_camera(depth, mech, T, cam, mesh),
    }
    for fn in methods.values():
        fn()
    cpu = {k: [] for k in methods}
    for _ in range(args.repeat):
        for k, fn in methods.items():
            c = time.thread_time()
            fn()
            cpu[k].append(time.thread_time() - c)
    print(f"thread CPU ms, medians of {args.repeat} (interleaved), load average {os.getloadavg()[0]:.2f}; "
          f"{np.isfinite(depth).mean() * 100:.1f} % of the depth valid")
    for k in methods:
        print(f"| {k} | {statistics.median(cpu[k]) * 1e3:.2f} |")


if __name__ == "__main__":
    main()
