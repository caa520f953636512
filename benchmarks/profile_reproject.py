"""Where the reprojection kernels' time goes: each stage of ``reproject.project_depth_to_camera`` (one thread, the
path a build worker takes) timed alone on the benchmark's scene (bench_reproject.scene_depth: 1920x1200 depth into the
2208x1242 ZED left), by running the kernels' passes cumulatively and taking differences (splat: projection; + pixel
index; + z-buffer. mesh: projection; + edge flags; + the quads' vectorised pass; + the z-buffer), beside a plain
memory-read floor of the same inputs, the output's allocation and fill, and the Python wrapper. A kernel's first passes
alone are compiled from its own source, cut where the next pass begins (``_kernel_prefix``), so they stay in step
with the kernels.

Thread CPU time (``time.thread_time``), medians of --repeat, the variants interleaved round-robin, so that a loaded
machine slows them all alike.

    python benchmarks/profile_reproject.py [--repeat 40] [--against REV]

``--against REV`` adds the public calls with the kernels of ``reproject.py`` at git revision REV, interleaved with the
rest (before/after in one process).
"""
from __future__ import annotations

import argparse
import inspect
import math
import os
import statistics
import sys
import time

import numba
import numpy as np

from gtforge.core.ground_truth import reproject as rp
from gtforge.core.ground_truth.reproject import ReprojectParams, project_depth_to_camera

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_reproject import module_at_revision, scene_depth  # noqa: E402

from gtforge.synthetic import default_rig  # noqa: E402


_NOCACHE = {"error_model": "numpy"}  # as the kernels' _JIT, without caching (the functions below are built at run time)


def _kernel_prefix(fn, stop: str, tail: str):
    """The kernel ``fn``'s own source up to the line starting with ``stop``, followed by ``tail`` (a return that keeps
    the work from being optimised away), compiled like the kernel: its first passes alone, always in step with it."""
    src = inspect.getsource(fn.py_func)
    src = src[src.index("def "):]
    src = src[:src.index(stop)] + tail
    ns = {"np": np, "math": math, "numba": numba, "_EPS": rp._EPS, "_edge_ok": rp._edge_ok,
          "_project_row": rp._project_row, "_init_rows": rp._init_rows, "_rows_reached": rp._rows_reached}
    exec(src, ns)
    return numba.njit(**_NOCACHE)(ns[fn.__name__])


_splat_projection = _kernel_prefix(rp._splat_rows, "        for c in range(Wm):\n            ui = ",
                                   "    return U[Wm // 2]\n")
_splat_index = _kernel_prefix(rp._splat_rows, "        last = -1", "    return idx[Wm // 2]\n")
_raster_vector_pass = _kernel_prefix(rp._raster_quads, "    flat, sflat = ", "    return Q[0, Wm // 2]\n")


@numba.njit(**_NOCACHE)
def _mesh_stages(buf, sbuf, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2, abs_tol, stage):
    """``_mesh_rows`` over the whole grid (no row initialisation), stopping after ``stage``: 1 the projection, 2 + the
    edge flags, 3 + the quads' vectorised pass, 4 + the z-buffer updates."""
    Hm, Wm = depth.shape
    H = buf.shape[0]
    P, Q, S, F, cand = rp._mesh_work_rows(Wm)
    rp._project_row(depth, rx, ry, R, t, fx, fy, cx, cy, 0, P[0, 0], P[0, 1], P[0, 2])
    acc = 0.0
    for r in range(Hm - 1):
        a_ = r & 1
        b_ = 1 - a_
        rp._project_row(depth, rx, ry, R, t, fx, fy, cx, cy, r + 1, P[b_, 0], P[b_, 1], P[b_, 2])
        if stage >= 2:
            rp._quad_flags(depth[r], depth[r + 1], P[a_, 2], P[b_, 2], k1, k2, abs_tol, F)
        if stage == 3:
            acc += _raster_vector_pass(buf, sbuf, False, 0, 0, H - 1, P[a_, 0], P[a_, 1], P[a_, 2], P[b_, 0],
                                       P[b_, 1], P[b_, 2], F, Q, S, cand)
        if stage >= 4:
            rp._raster_quads(buf, sbuf, False, 0, 0, H - 1, P[a_, 0], P[a_, 1], P[a_, 2], P[b_, 0], P[b_, 1],
                             P[b_, 2], F, Q, S, cand)
        acc += P[b_, 0, Wm // 2] + F[Wm // 2]
    return acc


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=40)
    ap.add_argument("--against", default=None,
                    help="also time the public calls of reproject.py at this git revision (before/after, same run)")
    args = ap.parse_args()
    numba.set_num_threads(1)
    rig = default_rig(1.0)
    depth = scene_depth(rig)
    mech, cam, T_zed_from_mech = rig.mech, rig.zed.left, rig.T_zed_from_mech
    R, t = np.ascontiguousarray(T_zed_from_mech[:3, :3]), np.ascontiguousarray(T_zed_from_mech[:3, 3])
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
        rp._splat_rows(out, 0, depth, rx, ry, R, t, fx, fy, cx, cy, 0, depth.shape[0])

    def splat_pass(fn):
        return lambda: fn(out, 0, depth, rx, ry, R, t, fx, fy, cx, cy, 0, depth.shape[0])

    def mesh_stage(k):
        return lambda: _mesh_stages(out, span, depth, rx, ry, R, t, fx, fy, cx, cy, k1, k2, params.abs_tol_mm, k)

    def wrapper_only():  # the Python work of project_depth_to_camera around the kernel
        np.ascontiguousarray(depth, dtype=np.float32)
        T_zed_from_mech_f64 = np.asarray(T_zed_from_mech, np.float64)
        np.ascontiguousarray(T_zed_from_mech_f64[:3, :3]), np.ascontiguousarray(T_zed_from_mech_f64[:3, 3])
        rp._ray_planes(mech.model_dump_json())
        rp._slant_bounds(mech, params)
        numba.get_num_threads()

    methods = {
        "read floor: numpy sums of depth, rx, ry": lambda: (depth.sum(), rx.sum(), ry.sum()),
        "output allocation np.full(NaN), 2208x1242 float32": full_nan,
        "output fill with NaN (a reused buffer)": lambda: out.fill(np.nan),
        "Python wrapper (checks, ray-grid lookup, conversions)": wrapper_only,
        "splat: projection pass": splat_pass(_splat_projection),
        "splat: + pixel-index pass": splat_pass(_splat_index),
        "splat: + row initialisation and z-buffer (the kernel)": splat_kernel,
        "splat: project_depth_to_camera": lambda: project_depth_to_camera(depth, mech, T_zed_from_mech, cam, splat),
        "mesh: projection (both rows' slots)": mesh_stage(1),
        "mesh: + edge flags (_quad_flags)": mesh_stage(2),
        "mesh: + the quads' vectorised pass": mesh_stage(3),
        "mesh: + compaction, z-buffer, general quads": mesh_stage(4),
        "mesh: project_depth_to_camera (+ row initialisation)": lambda: project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, mesh),
        "mesh + span_mm: project_depth_to_camera": lambda: project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, mesh, return_span=True),
        "build-dataset's call: both ZED views + the left span_mm in one pass (_project_depth_to_stereo)":
            lambda: rp._project_depth_to_stereo(depth, mech, T_zed_from_mech, rig.zed.T_zedr_from_zed @ T_zed_from_mech,
                                                rig.zed, mesh, True),
    }
    if args.against:  # the same calls with the kernels of another revision (bench_reproject.module_at_revision)
        old = module_at_revision(args.against)
        ms, ss = old.ReprojectParams(mode="mesh"), old.ReprojectParams(mode="splat")
        methods[f"@{args.against} splat: project_depth_to_camera"] = lambda: old.project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, ss)
        methods[f"@{args.against} mesh: project_depth_to_camera"] = lambda: old.project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, ms)
        methods[f"@{args.against} mesh + span_mm: project_depth_to_camera"] = lambda: old.project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, ms, return_span=True)
        methods[f"@{args.against} build-dataset's call (_project_depth_to_stereo)"] = \
            lambda: old._project_depth_to_stereo(depth, mech, T_zed_from_mech,
                                                 rig.zed.T_zedr_from_zed @ T_zed_from_mech, rig.zed, ms, True)
    for fn in methods.values():
        fn()
    cpu = {k: [] for k in methods}
    for _ in range(args.repeat):
        for k, fn in methods.items():
            c = time.thread_time()
            fn()
            cpu[k].append(time.thread_time() - c)
    print(f"thread CPU ms, medians and minima of {args.repeat} (interleaved), load average {os.getloadavg()[0]:.2f}; "
          f"{np.isfinite(depth).mean() * 100:.1f} % of the depth valid")
    print("| stage | CPU ms, median | CPU ms, min |\n|---|---|---|")
    for k in methods:
        print(f"| {k} | {statistics.median(cpu[k]) * 1e3:.2f} | {min(cpu[k]) * 1e3:.2f} |")


if __name__ == "__main__":
    main()
