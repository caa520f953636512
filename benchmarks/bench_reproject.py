"""Reprojection core speed at full resolution: Mech-Eye-like 1920x1200 depth (distorted lens) into the ZED 2K
left camera (2208x1242), gtforge splat / mesh against Open3D's tensor API on the same depth, in the same run.

Baseline (what a careful user writes): ``cv2.remap`` of the depth through the lens's undistortion maps
(nearest neighbour; maps computed once, outside the timing), then Open3D ``create_from_depth_image`` +
``project_to_depth_image``. Measured on the machine as it is ("quiet") and again with one core kept busy
by another process (a Python spin loop), methods interleaved round-robin, medians of --repeat.
gtforge runs with its defaults (numba's threads: with two, a mesh or a splat is drawn in two halves of the grid's rows,
``reproject.HALVES_MIN_THREADS``; the windowed path from reproject.MIN_PARALLEL_THREADS),
with one thread (what a build worker gets with --workers = cores) and with the windowed multi-thread path
forced. OMP_WAIT_POLICY=PASSIVE (set here unless given) keeps the two OpenMP runtimes in this process
(Open3D's, numba's) from spinning against each other. ``--write`` puts the table into benchmarks/RESULTS.md.

Open3D at its fastest runs on one core: its CPU ``project_to_depth_image`` updates the z-buffer for every point
inside ``#pragma omp critical``, so a second thread only adds lock contention (on the 2-core project VMs: 124-288 ms
on two cores against 55 ms pinned to one, and faster with the other core busy than idle). It sizes its loops by
``omp_get_num_procs()``, which ignores ``OMP_NUM_THREADS``; the last row therefore runs Open3D in a separate process
pinned to one core (``sched_setaffinity``, as ``taskset -c 0`` does), and the line under the table gives gtforge's
speed-ups against that too. "speed-up, CPU": the ratio of the CPU times (all threads), the figure that holds on a
machine other work keeps busy.

Before anything is timed, every gtforge method's output on the benchmark's scene is compared with the float64
reference of the same computation (``gtforge.core.ground_truth.reproject_reference``; mesh with ``span_mm`` too): each
prints "identical to the float64 reference: yes" or "no, N pixels differ", and the benchmark stops with exit code 1 if
any of the current code's methods is not identical (benchmarks/README.md: speed work never changes results).
``--check-only`` runs these checks and exits (no Open3D timing).

    python benchmarks/bench_reproject.py [--repeat 15] [--against e1dbf65] [--write] [--check-only]

``--against REV`` adds the kernels of ``src/gtforge/core/ground_truth/reproject.py`` at git revision REV (before/after);
their comparison with the reference is printed but does not stop the run (an old revision may predate a fix).
"""
from __future__ import annotations

import os

# Open3D's and numba's OpenMP runtimes live in this one process: with the default wait policy the threads of
# the one that ran last spin on the cores while the other runs (it made Open3D up to 2x slower here).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import datetime
import platform
import statistics
import subprocess
import sys
import time

import cv2
import numba
import numpy as np
import open3d as o3d

from gtforge.core.ground_truth import reproject
from gtforge.core.ground_truth.reproject import ReprojectParams, project_depth_to_camera
from gtforge.core.ground_truth.reproject_reference import project_depth_reference
from gtforge.synthetic import default_rig, lit_mask, random_fruit_scene, raycast_depth


def scene_depth(rig):
    rng = np.random.default_rng(0)
    scene = random_fruit_scene(rng, rig, 0)
    z, _, p = raycast_depth(scene, rig.mech, rig.T_mech_from_world)
    hit = np.isfinite(z)
    lit = np.zeros_like(hit)
    lit[hit] = lit_mask(scene, rig, p[hit])
    return np.where(hit & lit, z, np.nan).astype(np.float32)


def module_at_revision(rev: str):
    """gtforge/core/ground_truth/reproject.py as it was at git revision ``rev``, imported as a separate module (its
    file, in a temporary folder of its own: ``__file__``, where numba caches its kernels)."""
    import tempfile

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    src = subprocess.run(["git", "-C", root, "show", f"{rev}:src/gtforge/core/ground_truth/reproject.py"],
                         capture_output=True, text=True, check=True).stdout
    path = os.path.join(tempfile.mkdtemp(), f"reproject_{rev}.py")
    with open(path, "w") as f:
        f.write(src)
    return module_from_file(path)


def module_from_file(path: str):
    """The Python file ``path`` imported as a module of its own, named after the file."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(os.path.splitext(os.path.basename(path))[0], path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def cpu_model() -> str:
    """The processor's name as the kernel reports it (ratios against Open3D depend on the CPU), or the platform's."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def interleaved(methods: dict, repeat: int) -> dict:
    """Median wall ms and median process CPU ms (all threads) of each method, methods run round-robin."""
    for fn in methods.values():
        fn()  # warm-up (numba compile / cache load, Open3D first call)
    wall = {k: [] for k in methods}
    cpu = {k: [] for k in methods}
    for _ in range(repeat):
        for k, fn in methods.items():
            t, c = time.perf_counter(), time.process_time()
            fn()
            cpu[k].append(time.process_time() - c)
            wall[k].append(time.perf_counter() - t)
    return {k: (statistics.median(wall[k]) * 1e3, statistics.median(cpu[k]) * 1e3) for k in methods}


def differing_pixels(got: np.ndarray, ref: np.ndarray) -> int:
    """Pixels whose float32 value is not the reference's, bit for bit (NaN equals NaN); a shape or dtype mismatch
    counts every pixel."""
    if got.shape != ref.shape or got.dtype != ref.dtype:
        return ref.size
    return int(np.count_nonzero(~((got == ref) | (np.isnan(got) & np.isnan(ref)))))


def check_against_reference(checks: dict, reference: dict) -> bool:
    """Run each method of ``checks`` (name -> (function, mode, returns span)) once and compare its output with
    ``reference[mode]`` (depth, span); prints one line a method. True when every one is identical."""
    all_same = True
    for name, (fn, mode, with_span) in checks.items():
        got = fn()
        outputs = got if with_span else (got,)
        counts = [differing_pixels(g, r) for g, r in zip(outputs, reference[mode])]
        n = counts[0]
        verdict = "yes" if n == 0 else f"no, {n} pixels differ"
        if with_span:
            verdict = "yes" if sum(counts) == 0 else f"no, {n} depth and {counts[1]} span_mm pixels differ"
        print(f"{name}: identical to the float64 reference: {verdict}", flush=True)
        all_same &= sum(counts) == 0
    return all_same


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--write", action="store_true")
    ap.add_argument("--against", default=None, help="also time reproject.py at this git revision")
    ap.add_argument("--check-only", action="store_true",
                    help="only compare every gtforge method with the float64 reference, then exit")
    ap.add_argument("--open3d-only", action="store_true", help=argparse.SUPPRESS)  # the 1-thread Open3D child
    args = ap.parse_args()
    rig = default_rig(1.0)
    depth = scene_depth(rig)
    mech, cam, T_zed_from_mech = rig.mech, rig.zed.left, rig.T_zed_from_mech
    n_threads = numba.get_num_threads()

    map1, map2 = cv2.initUndistortRectifyMap(mech.K, mech.dist, None, mech.K, (mech.width_px, mech.height_px),
                                             cv2.CV_32FC1)
    K_m, K_z = o3d.core.Tensor(mech.K), o3d.core.Tensor(cam.K)
    I4, T_zed_from_mech_tensor = o3d.core.Tensor(np.eye(4)), o3d.core.Tensor(T_zed_from_mech)
    depth0 = np.nan_to_num(depth, nan=0.0)

    def o3d_project(d):
        pcd = o3d.t.geometry.PointCloud.create_from_depth_image(o3d.t.geometry.Image(d), K_m, I4, depth_scale=1.0,
                                                                depth_max=1e5)
        return pcd.project_to_depth_image(cam.width_px, cam.height_px, K_z, T_zed_from_mech_tensor, depth_scale=1.0,
                                          depth_max=1e5)

    def with_threads(n, fn):
        def run():
            before = numba.get_num_threads()
            numba.set_num_threads(n)
            try:
                return fn()
            finally:
                numba.set_num_threads(before)
        return run

    mesh, splat = ReprojectParams(mode="mesh"), ReprojectParams(mode="splat")
    base = "Open3D + cv2.remap undistortion (baseline)"
    methods = {
        "Open3D + cv2.remap undistortion (baseline)":
            lambda: o3d_project(cv2.remap(depth0, map1, map2, cv2.INTER_NEAREST)),
        "Open3D alone (no undistortion)": lambda: o3d_project(depth0),
        f"gtforge splat (default: {n_threads} numba threads)": lambda: project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, splat),
        f"gtforge mesh (default: {n_threads} numba threads)": lambda: project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, mesh),
        f"gtforge mesh + span_mm (default: {n_threads} numba threads)": lambda: project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, mesh, return_span=True),
        "gtforge splat (1 thread)": with_threads(1, lambda: project_depth_to_camera(depth, mech, T_zed_from_mech, cam,
                                                                                    splat)),
        "gtforge mesh (1 thread)": with_threads(1, lambda: project_depth_to_camera(depth, mech, T_zed_from_mech, cam,
                                                                                   mesh)),
    }
    if n_threads >= 2:  # the windowed multi-thread path, used from reproject.MIN_PARALLEL_THREADS threads on
        def windowed(params):
            def run():
                before = reproject.MIN_PARALLEL_THREADS
                reproject.MIN_PARALLEL_THREADS = 2
                try:
                    return project_depth_to_camera(depth, mech, T_zed_from_mech, cam, params)
                finally:
                    reproject.MIN_PARALLEL_THREADS = before
            return run
        methods[f"gtforge splat, windowed path ({n_threads} threads)"] = windowed(splat)
        methods[f"gtforge mesh, windowed path ({n_threads} threads)"] = windowed(mesh)
    if args.against:
        old = module_at_revision(args.against)
        methods[f"gtforge mesh @{args.against} ({n_threads} threads)"] = lambda: old.project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, old.ReprojectParams(mode="mesh"))
        methods[f"gtforge mesh @{args.against} (1 thread)"] = with_threads(1, lambda: old.project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, old.ReprojectParams(mode="mesh")))
        methods[f"gtforge splat @{args.against} ({n_threads} threads)"] = lambda: old.project_depth_to_camera(
            depth, mech, T_zed_from_mech, cam, old.ReprojectParams(mode="splat"))
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from fullres_session import pin_to_one_core, update_results

    if args.open3d_only:  # run by the parent pinned to one core (Open3D's OpenMP sizes its loops by the affinity)
        r = interleaved({"o": methods[base]}, args.repeat)["o"]
        print(f"{r[0]} {r[1]}")
        return

    # "identical output" means identical to the float64 reference of the same computation, not only to the
    # previous optimisation (issue #26: float32 ray planes passed a comparison with the float32 code before them)
    t0 = time.perf_counter()
    reference = {"mesh": project_depth_reference(depth, mech, T_zed_from_mech, cam, mesh, return_span=True),
                 "splat": (project_depth_reference(depth, mech, T_zed_from_mech, cam, splat),)}
    print(f"float64 reference (gtforge.core.ground_truth.reproject_reference) on the benchmark's scene: "
          f"{time.perf_counter() - t0:.1f} s", flush=True)

    def mode_of(name):
        return "splat" if "splat" in name else "mesh"

    current = {k: (fn, mode_of(k), "span_mm" in k) for k, fn in methods.items()
               if k.startswith("gtforge") and "@" not in k}
    older = {k: (fn, mode_of(k), False) for k, fn in methods.items() if k.startswith("gtforge") and "@" in k}
    identical = check_against_reference(current, reference)
    if older:
        check_against_reference(older, reference)  # reported only: an old revision may predate a fix
    if not identical:
        sys.exit("bench_reproject: a gtforge method's output differs from the float64 reference; speed work may not "
                 "change results (benchmarks/README.md). Nothing timed.")
    if args.check_only:
        return
    child = subprocess.run([sys.executable, __file__, "--open3d-only", "--repeat", str(args.repeat)],
                           preexec_fn=pin_to_one_core,
                           capture_output=True, text=True, check=True)
    o3d_1 = tuple(float(x) for x in child.stdout.split()[-2:])
    load_start = os.getloadavg()[0]
    results = {"quiet": interleaved(methods, args.repeat)}
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.5)
        results["one core busy"] = interleaved(methods, args.repeat)
    finally:
        busy.kill()
        busy.wait()
    o = o3d_project(cv2.remap(depth0, map1, map2, cv2.INTER_NEAREST)).as_tensor().numpy()[..., 0]
    s = project_depth_to_camera(depth, mech, T_zed_from_mech, cam, splat)
    m = project_depth_to_camera(depth, mech, T_zed_from_mech, cam, mesh)

    cmd = (f"python benchmarks/bench_reproject.py --repeat {args.repeat}"
           + (f" --against {args.against}" if args.against else ""))
    lines = [f"Measured {datetime.date.today()} with `{cmd}`: "
             f"{cpu_model()}, {len(os.sched_getaffinity(0))} cores, load average {load_start:.2f} at the start and "
             f"{os.getloadavg()[0]:.2f} at the end; "
             f"{mech.width_px}x{mech.height_px} depth ({np.isfinite(depth).mean() * 100:.1f} % valid) -> "
             f"{cam.width_px}x{cam.height_px}; medians of {args.repeat}, methods interleaved.",
             "",
             "| method | ms | CPU ms (all threads) | speed-up | speed-up, CPU | ms, one core busy "
             "| speed-up, one core busy |",
             "|---|---|---|---|---|---|---|"]
    q, b = results["quiet"], results["one core busy"]
    for k in methods:
        lines.append(f"| {k} | {q[k][0]:.1f} | {q[k][1]:.1f} | {q[base][0] / q[k][0]:.1f}x | "
                     f"{q[base][1] / q[k][1]:.1f}x | {b[k][0]:.1f} | {b[base][0] / b[k][0]:.1f}x |")
    lines.append(f"| Open3D + cv2.remap, pinned to one core (separate process, same repeats) | {o3d_1[0]:.1f} | "
                 f"{o3d_1[1]:.1f} | {q[base][0] / o3d_1[0]:.1f}x | {q[base][1] / o3d_1[1]:.1f}x | | |")
    lines.append("")
    one = [k for k in methods if k.startswith("gtforge") and k.endswith("(1 thread)")]
    lines.append(f"Against Open3D pinned to one core ({o3d_1[0]:.1f} ms, its fastest): "
                 + ", ".join(f"{k[len('gtforge '):-len(' (1 thread)')]} {o3d_1[0] / q[k][0]:.1f}x" for k in one)
                 + " (gtforge with one thread, quiet).")
    lines.append("")
    lines.append(f"Pixels with depth: Open3D {np.mean(o > 0) * 100:.1f} %, splat {np.isfinite(s).mean() * 100:.1f} %, "
                 f"mesh {np.isfinite(m).mean() * 100:.1f} %.")
    text = "\n".join(lines)
    print(text)
    if args.write:
        print("written to", update_results("bench_reproject", text))


if __name__ == "__main__":
    main()
