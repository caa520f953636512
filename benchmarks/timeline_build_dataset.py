"""build-dataset's critical path on a shared machine: each run's wall time, when its first scene landed, and the CPU
of the whole process tree (the command, the pool's fork server, its workers), alternating configurations in one run.

A configuration is ``SRC`` or ``SRC:ARGS``: the folder put on PYTHONPATH (``src`` of this checkout, or another
checkout's, for before/after) and extra build-dataset arguments separated by commas (``--workers,1``). This process
makes itself the child subreaper (Linux ``PR_SET_CHILD_SUBREAPER``), so the fork server and its workers, which the
command does not wait for, are reaped and counted here. CPU time moves less with other users' load than wall time; the
first scene's landing (its ``meta.json``'s time) is the fixed cost's critical path.

Each configuration's ``gtforge`` gets its bytecode first (``gtforge.precompile.compile_bytecode``, as ``make setup``
gives the checkout's): a copy made with ``git archive`` has none, and where Python does not write it
(``PYTHONDONTWRITEBYTECODE``) every process of its builds compiled the source again, 0.13-0.15 s of a 6-scene build's
wall time that the checkout did not pay (benchmarks/RESULTS.md, round 16).

    python benchmarks/timeline_build_dataset.py [--scenes 6] [--repeat 4] [--idle-s 0] [CONFIG ...]
    python benchmarks/timeline_build_dataset.py --scenes 6 /path/to/before/src src src:--workers,1
"""
from __future__ import annotations

import argparse
import ctypes
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from fullres_session import machine_line, make_session

from gtforge.precompile import compile_bytecode

PR_SET_CHILD_SUBREAPER = 36


def reap() -> None:
    """Wait for every orphaned descendant (the fork server exits once the command has)."""
    while True:
        try:
            os.waitpid(-1, 0)
        except ChildProcessError:
            return


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("configs", nargs="*", default=[str(Path(__file__).resolve().parents[1] / "src")])
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--repeat", type=int, default=4)
    ap.add_argument("--workdir", default="/tmp/gtforge_bench")
    ap.add_argument("--idle-s", type=float, default=0.0,
                    help="wait this long before each run, as bench_build_dataset's settle does: on a VM that returns "
                         "free memory to its host, a process started after the machine idled touches every new page "
                         "at a higher cost (benchmarks/RESULTS.md, round 9)")
    args = ap.parse_args()
    if ctypes.CDLL(None).prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        sys.exit("prctl(PR_SET_CHILD_SUBREAPER) failed: Linux only")
    sess, calib = make_session(Path(args.workdir), args.scenes, min(args.scenes, 4))
    out = Path(args.workdir) / "out_timeline"
    exe = Path(sys.executable).with_name("gtforge")
    print(machine_line(), flush=True)
    for src in {c.partition(":")[0] for c in args.configs}:
        compile_bytecode(Path(src).resolve() / "gtforge")
    res: dict[str, list[tuple[float, float, float]]] = {}
    for _ in range(args.repeat):
        for config in args.configs:
            src, _, extra = config.partition(":")
            shutil.rmtree(out, ignore_errors=True)
            os.sync()
            time.sleep(args.idle_s)
            env = {**os.environ, "PYTHONPATH": str(Path(src).resolve())}
            c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.time()
            r = subprocess.run([str(exe), "build-dataset", str(sess), "-c", str(calib), "-o", str(out),
                                *[a for a in extra.split(",") if a]], capture_output=True, text=True, env=env)
            wall = time.time() - t0
            reap()
            c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            if r.returncode not in (0, 1):
                sys.exit(f"failed ({r.returncode}): {config}\n{r.stderr[-2000:]}")
            first = min(p.stat().st_mtime for p in out.glob("scenes/*/meta.json")) - t0
            cpu = c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime
            res.setdefault(config, []).append((wall, first, cpu))
            print(f"{config}: wall {wall:.2f} s, first scene {first:.2f} s, CPU {cpu:.2f} s, "
                  f"load {os.getloadavg()[0]:.1f}", flush=True)
    for config, runs in res.items():
        w, f, c = (statistics.median(x) for x in zip(*runs))
        print(f"median {config}: wall {w:.2f} s, first scene {f:.2f} s, CPU {c:.2f} s")


if __name__ == "__main__":
    main()
