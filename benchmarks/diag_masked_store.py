"""The mesh kernel where its work rows sit on pages the process (or thread) has not written: a fork-server child, whose
heap pages are shared copy-on-write with its parent, and numba's second thread, whose malloc arena is fresh.

The mesh kernel's vectorised quad pass keeps each quad's span (``S``) with an AVX-512 masked store whose mask is empty
when no span_mm is asked for. Such a store to a page that is not present and writable in this process needs a microcode
assist every time (nothing is written, so the page never becomes writable); with ``S`` from ``np.empty`` that made a
whole mesh call 2.7x slower in a forked child and on numba's worker thread (benchmarks/RESULTS.md, "The masked
store"). Each configuration runs in a fresh process, first call without span_mm, as validate and align-depth call it:

* ``1 thread``: the median time of a mesh call in the process, then in a child forked from it (``os.fork``; one numba
  thread, so no OpenMP runtime objects to the fork);
* ``2 threads``: the median time with two numba threads (a mesh's two halves, ``reproject.HALVES_MIN_THREADS``; at a
  revision without them, the one-thread path).

    python benchmarks/diag_masked_store.py [--against REV] [--repeat 15] [--rounds 2]

``--against REV`` adds ``src/gtforge/core/ground_truth/reproject.py`` at git revision REV (e.g. ``e9e84c0~2``, before
the fix); configurations alternate in each round.
"""
from __future__ import annotations

import argparse
import atexit
import json
import os
import shutil
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def child(module_path: str, repeat: int) -> None:
    """Time the mesh kernel (no span_mm) in this process and, with one numba thread, in a child forked from it."""
    import numba
    import numpy as np

    from gtforge.synthetic import default_rig

    sys.path.insert(0, HERE)
    from bench_reproject import module_from_file, scene_depth

    if module_path == "current":
        from gtforge.core.ground_truth import reproject as rp
    else:
        rp = module_from_file(module_path)
    rig = default_rig()
    depth = np.ascontiguousarray(scene_depth(rig), np.float32)
    params = rp.ReprojectParams()

    def median_ms() -> float:
        def once() -> float:
            t0 = time.perf_counter()
            rp.project_depth_to_camera(depth, rig.mech, rig.T_zed_from_mech, rig.zed.left, params)
            return time.perf_counter() - t0

        once()
        return round(1e3 * statistics.median(once() for _ in range(repeat)), 2)

    result = {"process_ms": median_ms(), "threads": numba.get_num_threads()}
    if numba.get_num_threads() == 1:
        read, write = os.pipe()
        pid = os.fork()
        if pid == 0:
            os.close(read)
            os.write(write, json.dumps(median_ms()).encode())
            os._exit(0)
        os.close(write)
        with os.fdopen(read) as f:
            result["forked_child_ms"] = json.loads(f.read())
        os.waitpid(pid, 0)
    print(json.dumps(result))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", default=None, help="also run reproject.py at this git revision")
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--child", nargs=2, metavar=("MODULE", "REPEAT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child[0], int(args.child[1]))
        return
    sources = {"current": "current"}
    if args.against:
        sys.path.insert(0, HERE)
        from bench_reproject import module_at_revision

        path = module_at_revision(args.against).__file__  # one file for every child: numba's cache beside it shared
        atexit.register(shutil.rmtree, os.path.dirname(path), ignore_errors=True)
        sources[f"@{args.against}"] = path
    configs = [(name, threads) for name in sources for threads in (1, 2)]
    results: dict = {c: [] for c in configs}
    for round_ in range(args.rounds + 1):  # round 0 compiles (numba's cache) and is not counted
        for name, threads in configs:
            env = {**os.environ, "NUMBA_NUM_THREADS": str(threads), "OMP_WAIT_POLICY": "PASSIVE"}
            r = subprocess.run([sys.executable, __file__, "--child", sources[name], str(args.repeat)], env=env,
                               capture_output=True, text=True)
            if r.returncode != 0:
                sys.exit(f"{name}, {threads} thread(s) failed:\n{r.stderr[-2000:]}")
            if round_:
                results[(name, threads)].append(json.loads(r.stdout.strip().splitlines()[-1]))
    load = os.getloadavg()[0]
    print(f"{os.cpu_count()} cores, load average {load:.2f} at the end; medians of {args.repeat} calls, "
          f"{args.rounds} fresh processes each (each figure: the median over them)\n")
    print("| reproject.py | numba threads | mesh ms, in the process | mesh ms, in a forked child |")
    print("|---|---|---|---|")
    for (name, threads), runs in results.items():
        process = statistics.median(r["process_ms"] for r in runs)
        forked = [r["forked_child_ms"] for r in runs if "forked_child_ms" in r]
        print(f"| {name} | {threads} | {process:.2f} | {statistics.median(forked):.2f} |" if forked
              else f"| {name} | {threads} | {process:.2f} | |")


if __name__ == "__main__":
    main()
