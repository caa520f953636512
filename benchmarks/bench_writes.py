"""Writing a build's large files: through the page cache (the baseline) against past it (``io.unbuffered``).

Writes --files files of one full-resolution disparity map (2208x1242 float32, 11 MB) each, three ways, alternating:

* buffered, as build-dataset wrote them before ``io.unbuffered`` (``open(..., "wb").write``, then
  ``scheduling.release_written_pages`` per file, which starts the writeback and drops the pages two files later);
* buffered with no page-cache advice (what a plain script does);
* ``io.unbuffered.write_file`` (``O_DIRECT`` where the filesystem takes it).

Reports per file: wall, this process's CPU, and the whole machine's busy time (/proc/stat, writeback and interrupts
included: everything is synced and 2 s waited before the reading is taken). --dir must be on the disk a build writes
to (not tmpfs, where O_DIRECT is refused and the third way is the first).

    python benchmarks/bench_writes.py [--files 30] [--rounds 2] [--dir /tmp/gtforge_bench/writes]
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import time
from pathlib import Path

import numpy as np
from bench_build_dataset import machine_busy_s

from gtforge.infra import unbuffered
from gtforge.infra.scheduling import release_written_pages
from gtforge.infra.unbuffered import buffer_of, write_file


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--files", type=int, default=30)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--dir", default="/tmp/gtforge_bench/writes")
    args = ap.parse_args()
    d = Path(args.dir)
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    data = np.random.default_rng(0).random(2208 * 1242, np.float32).tobytes()
    buf = buffer_of(data)

    def buffered_released(p):
        with open(p, "wb") as f:
            f.write(data)
        release_written_pages([p])

    def buffered_plain(p):
        with open(p, "wb") as f:
            f.write(data)

    ways = {"buffered + release_written_pages (the baseline: the build before io.unbuffered)": buffered_released,
            "buffered, no page-cache advice": buffered_plain,
            "io.unbuffered.write_file (O_DIRECT)": lambda p: write_file(p, buf)}
    res = {k: [] for k in ways}
    for r in range(args.rounds):
        for name, fn in ways.items():
            os.sync()
            time.sleep(2)
            b0, t0, c0 = machine_busy_s(), time.perf_counter(), time.process_time()
            for i in range(args.files):
                fn(d / f"f{i}.bin")
            t1, c1 = time.perf_counter(), time.process_time()
            os.sync()
            time.sleep(2)
            b1 = machine_busy_s()
            res[name].append(((t1 - t0) / args.files, (c1 - c0) / args.files, (b1 - b0) / args.files))
            for i in range(args.files):
                (d / f"f{i}.bin").unlink()
    shutil.rmtree(d, ignore_errors=True)
    base = statistics.median(x[1] for x in res[next(iter(ways))])
    print(f"{args.files} files of {len(data) / 1e6:.1f} MB, {args.rounds} rounds (medians); O_DIRECT on this "
          f"platform: {bool(unbuffered._O_DIRECT)}; load average {os.getloadavg()[0]:.2f}")
    print("| way | wall ms a file | process CPU ms a file | machine busy ms a file | baseline's process CPU / this |")
    print("|---|---|---|---|---|")
    for name, v in res.items():
        w, c, b = (statistics.median(x[i] for x in v) * 1e3 for i in range(3))
        print(f"| {name} | {w:.1f} | {c:.1f} | {b:.1f} | {base * 1e3 / max(c, 1e-3):.1f}x |")


if __name__ == "__main__":
    main()
