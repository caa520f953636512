"""build-dataset on a local Dask cluster (1 and 2 worker processes) against the local process pool, same scenes,
one run, full resolution (ZED 2K 2208x1242, 1920x1200 depth; benchmarks/fullres_session.py).

Each configuration builds the same N scenes into its own folder with the default options:

* local ``workers=1`` (the baseline: one process, numba on every core) and local ``workers=2`` (process pool);
* ``scheduler=`` a ``LocalCluster`` on 127.0.0.1 with 1 worker, then with 2 workers (processes, 1 thread each;
  gtforge gives each task cores / task threads on the host numba threads). The cluster is started, and warmed
  with one scene (imports, numba cache), before the clock starts: a cluster outlives many builds.

Prints scenes/s and the ratio to the baseline. Needs gtforge[dask].

    python benchmarks/bench_dask.py [--scenes 8] [--distinct 4] [--workdir /tmp/gtforge_bench]
"""
from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

from fullres_session import machine_line, make_session

from gtforge.build_dataset import build_dataset


def timed_build(sess: Path, calib: Path, out: Path, **kw) -> tuple[float, int]:
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    s = build_dataset(sess, calib, out, **kw)
    dt = time.perf_counter() - t
    if s.failures:
        raise SystemExit(f"failures in {out}: {s.failures}")
    return dt, len(s.built)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--distinct", type=int, default=4)
    ap.add_argument("--workdir", default="/tmp/gtforge_bench")
    args = ap.parse_args()
    from distributed import LocalCluster

    wd = Path(args.workdir)
    sess, calib = make_session(wd, args.scenes, args.distinct)
    print(machine_line())
    rows = []
    for workers in (1, 2):
        dt, n = timed_build(sess, calib, wd / f"ds_local{workers}", workers=workers)
        rows.append((f"local --workers {workers}", n / dt, dt, n))
    for n_workers in (1, 2):
        with LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address=None, scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as lc:
            timed_build(sess, calib, wd / "ds_warmup", scheduler=lc.scheduler_address, scenes=[f"{0:04d}"])
            dt, n = timed_build(sess, calib, wd / f"ds_dask{n_workers}", scheduler=lc.scheduler_address)
        rows.append((f"Dask, {n_workers} local worker(s)", n / dt, dt, n))
    base = rows[0][1]
    for name, rate, dt, n in rows:
        print(f"{name:28s} {rate:6.3f} scenes/s  ({n} scenes in {dt:6.1f} s)  {rate / base:5.2f}x the baseline")


if __name__ == "__main__":
    main()
