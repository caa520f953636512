"""build-dataset end to end against the plain Open3D script a user would write, on the same scenes, in one run.

Renders a few distinct full-resolution fruit scenes (ZED 2K 2208x1242, 1920x1200 depth; benchmarks/
fullres_session.py), hard-links them to N scene folders, then runs, each as its own process from a cold
start (imports included), one after the other:

* baseline: ``benchmarks/baseline_open3d_script.py`` (tifffile + OpenCV + Open3D, one process; writes
  im0/im1, PFM, KITTI PNG);
* ``gtforge build-dataset`` with the default options and ``--workers`` = cores (mesh, occlusion mask,
  regions, weights, depth TIFF, KITTI + ETH3D views, verification, hashes for resume, atomic writes);
* the baseline again, pinned to one core (Open3D's projection runs fastest on one: see bench_reproject.py);
* ``gtforge build-dataset --no-verify`` (the same without the per-scene verification);
* ``gtforge build-dataset --no-right-gt`` (verification on, no right-view ground truth);
* ``gtforge build-dataset`` with a calibration that corrects the right camera (calibrate-scale's yaw; 0.0005 deg, too
  small for the verification to see, as the renders have none): what a user's builds run after ``gtforge calibrate``
  and ``calibrate-scale``, the right image resampled once (cubic B-spline) and written again;
* a resume of the default build (nothing to rebuild: the inputs' size + mtime checks).

``--repeat N`` runs the baseline and the default build N times, alternating, and reports each pair's ratio (the
machine's speed drifts by several per cent between runs; the table then holds the runs with the median wall time).

Before every timed run the earlier runs' outputs are deleted, everything is written to disk, and the run waits until
``--settle-s`` (65) seconds have passed since the deletion (``settle``): each run starts from the same state,
whichever ran before it.

Prints scenes/s, the ratio to the baseline, and the projected time for 808 scenes at the measured rate.
``--write`` puts the table into benchmarks/RESULTS.md (section ``bench_build_dataset``).

    python benchmarks/bench_build_dataset.py [--scenes 100] [--distinct 4] [--repeat 1] [--write] [--workdir ...]

Several scene counts (``--scenes 6,24,48``): for each count, the baseline and the default build only, ``--repeat``
times alternating, each a fresh process after ``settle``; prints one row per count (medians) with each repeat's ratio,
the fixed cost and the marginal cost per scene of both tools (a line fitted through the counts' median wall times),
and with ``--write`` puts that table into RESULTS.md (section ``bench_build_dataset_sweep``). What the issue's "6 / 24
/ 48 scenes" table measures: the start-up (imports, worker pool, session, reports) weighs most at 6 scenes.

    python benchmarks/bench_build_dataset.py --scenes 6,24,48 --repeat 3 [--settle-s 65] [--write]
"""
from __future__ import annotations

import argparse
import datetime
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from fullres_session import corrected_calibration, machine_line, make_session, pin_to_one_core, update_results

HERE = Path(__file__).resolve().parent
TARGET_SCENES = 808


def machine_busy_s() -> float | None:
    """CPU seconds the whole machine has been busy (user, nice, system, irq, softirq of every core; /proc/stat), or
    None where there is no /proc/stat."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:8]
    except OSError:
        return None
    user, nice, system, _idle, _iowait, irq, softirq = (int(x) for x in fields)
    return (user + nice + system + irq + softirq) / os.sysconf("SC_CLK_TCK")


def timed(cmd: list[str], expect: str | None = None, one_core: bool = False) -> tuple[float, float]:
    """(wall s, CPU s). The CPU is the whole machine's busy time during the run (``machine_busy_s``; the machine is
    otherwise idle): gtforge's workers are children of its fork server, which the command's own resource usage does not
    count, and the kernel's writeback threads work for both tools. Without /proc/stat: the command and the children it
    waited for. ``expect``: a text its output must hold (such as ``built 240,``: no scene failed). ``one_core``: the
    command runs pinned to one core (``sched_setaffinity``, as ``taskset -c`` does)."""
    c0, b0 = resource.getrusage(resource.RUSAGE_CHILDREN), machine_busy_s()
    t = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, preexec_fn=pin_to_one_core if one_core else None)
    dt = time.perf_counter() - t
    c1, b1 = resource.getrusage(resource.RUSAGE_CHILDREN), machine_busy_s()
    if r.returncode not in (0, 1) or (expect and expect not in r.stdout):  # 1: a scene failed or was flagged
        sys.exit(f"failed ({r.returncode}): {' '.join(cmd)}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
    if b0 is not None and b1 is not None:
        return dt, b1 - b0
    return dt, (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)


_LAST_DELETION: list[float] = []  # perf_counter time of settle's last deletion


def settle(*delete: Path, wait_s: float = 65.0) -> None:
    """Before each timed run: delete ``delete`` (earlier runs' outputs: 6-13 GB), write everything to disk, and wait
    until ``wait_s`` have passed since the last deletion, so that every run, baseline or gtforge, starts from the same
    state whichever ran before it.

    The run right after a deletion pays for it otherwise: ext4 without a journal (the project VM's) skips, for every
    new file, the inodes deleted in the last 60 s (``recently_deleted`` in its inode allocator); after deleting an
    earlier build's 13 GB, 1.3 % of the next build's CPU samples were there and its wall time was 2-3 % longer.
    Dropping the page cache instead (as root) removes that but makes the next run read the filesystem's block bitmaps
    back from disk: 4.7 s of I/O wait in a 31 s build."""
    for d in delete:
        if d.exists():
            shutil.rmtree(d)
            _LAST_DELETION[:] = [time.perf_counter()]
    os.sync()
    if _LAST_DELETION:
        time.sleep(max(0.0, wait_s - (time.perf_counter() - _LAST_DELETION[0])))


def baseline_command(session: Path, calib: Path, out: Path) -> list[str]:
    """The plain Open3D script (the baseline) on ``session``, writing into ``out``."""
    return [sys.executable, str(HERE / "baseline_open3d_script.py"), str(session), str(calib), str(out)]


def warm_up(workdir: Path, n_distinct: int, calib: Path, gtforge_cli: list[str], workers: int) -> str:
    """Before the timed runs: build the distinct renders twice and run the baseline on them once, untimed in the
    table. numba compiles gtforge's kernels on their first call after an install or a change of their source and
    caches them (``__pycache__``); that one-time cost belongs to no repeat (the first repeat of a fresh clone's run
    took 46.7 s against 28.3-32.3 s for the others). Returns a line with both builds' times: the first one's extra is
    what a first build after installing pays once (``make setup`` compiles the kernels, so after it both are alike)."""
    small, _ = make_session(workdir, n_distinct, n_distinct, log=lambda *_: None)
    out = workdir / "out_warmup"
    times = []
    for _ in range(2):
        settle(out, wait_s=0.0)
        times.append(timed(gtforge_cli + ["build-dataset", str(small), "-c", str(calib), "--workers", str(workers),
                                          "-o", str(out)], f"built {n_distinct}, unchanged 0, failed 0")[0])
    settle(out, wait_s=0.0)
    timed(baseline_command(small, calib, out), f"{n_distinct} scenes in")
    settle(out, wait_s=0.0)
    return (f"Warm-up before the timed runs (not in the table): two builds of the {n_distinct} distinct scenes, "
            f"{times[0]:.1f} s then {times[1]:.1f} s (the first includes numba compiling any kernel it had not "
            f"cached), and one baseline run on them.")


def line_fit(xs: list[float], ys: list[float]) -> tuple[float, float]:
    """Least-squares line ``y = a + b x``: (a, b)."""
    mx, my = statistics.fmean(xs), statistics.fmean(ys)
    b = sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)
    return my - b * mx, b


def sweep(counts: list[int], args, gtforge_cli: list[str], workers: int) -> None:
    """The baseline and the default build at every scene count in ``counts`` (see the module's docstring)."""
    wd = Path(args.workdir)
    machine = machine_line()
    sessions = {n: make_session(wd, n, args.distinct) for n in counts}
    calib = sessions[counts[0]][1]
    outs = {k: wd / f"out_{k}" for k in ("baseline", "gtforge")}
    wait = {"wait_s": args.settle_s}
    warmup = warm_up(wd, args.distinct, calib, gtforge_cli, workers)
    print(warmup, flush=True)
    rows = {}
    for n in counts:
        sess, _ = sessions[n]
        pairs = []
        for i in range(max(1, args.repeat)):
            settle(*outs.values(), **wait)
            b = timed(baseline_command(sess, calib, outs["baseline"]), f"{n} scenes in")
            settle(outs["baseline"], **wait)
            g = timed(gtforge_cli + ["build-dataset", str(sess), "-c", str(calib), "--workers", str(workers), "-o",
                                     str(outs["gtforge"])], f"built {n}, unchanged 0, failed 0")
            pairs.append((b, g))
            print(f"{n} scenes, repeat {i + 1}: user script {b[0]:.2f} s, gtforge {g[0]:.2f} s ({b[0] / g[0]:.2f}x); "
                  f"machine CPU {b[1]:.1f} / {g[1]:.1f} s", flush=True)
        rows[n] = pairs
    settle(*outs.values(), wait_s=0.0)

    def med(ts):
        return statistics.median(t[0] for t in ts), statistics.median(t[1] for t in ts)

    rep = f" --repeat {args.repeat}" if args.repeat > 1 else ""
    lines = [f"Measured {datetime.date.today()} with `python benchmarks/bench_build_dataset.py --scenes "
             f"{','.join(map(str, counts))} --distinct {args.distinct}{rep} --settle-s {args.settle_s:g}`: {machine}; "
             f"full-resolution scenes ({args.distinct} distinct renders hard-linked), each run a fresh process "
             f"(imports included), the user script (`baseline_open3d_script.py`) and `gtforge build-dataset --workers "
             f"{workers}` (default options: verification on) alternating, each after the earlier outputs were deleted "
             f"and synced (`settle`, {args.settle_s:g} s); medians of {max(1, args.repeat)}. Machine CPU: the whole "
             "machine's busy time during the run (/proc/stat), other users' processes included.",
             "",
             "| scenes | user script s | gtforge s | ratio (median) | ratio, each repeat "
             "| machine CPU s, script / gtforge |",
             "|---|---|---|---|---|---|"]
    for n, pairs in rows.items():
        b, g = med([p[0] for p in pairs]), med([p[1] for p in pairs])
        each = ", ".join(f"{p[0][0] / p[1][0]:.2f}x" for p in pairs)
        lines.append(f"| {n} | {b[0]:.2f} | {g[0]:.2f} | {b[0] / g[0]:.2f}x | {each} | {b[1]:.1f} / {g[1]:.1f} |")
    if len(counts) > 1:
        xs = [float(n) for n in rows]
        fb = line_fit(xs, [med([p[0] for p in rows[n]])[0] for n in rows])
        fg = line_fit(xs, [med([p[1] for p in rows[n]])[0] for n in rows])
        lines += ["", f"A line through the median wall times: user script {fb[0]:.2f} s + {fb[1]:.3f} s a scene, "
                  f"gtforge {fg[0]:.2f} s + {fg[1]:.3f} s a scene (its fixed cost: start-up, worker pool, session, "
                  f"reports; the marginal cost on {workers} workers)."]
    lines += ["", warmup]
    text = "\n".join(lines)
    print(text)
    if args.write:
        print("written to", update_results("bench_build_dataset_sweep", text))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default="100",
                    help="scene count, or several separated by commas (6,24,48: the baseline and the default build at "
                         "each)")
    ap.add_argument("--distinct", type=int, default=4)
    ap.add_argument("--workers", type=int, default=None, help="gtforge --workers (default: cores)")
    ap.add_argument("--workdir", default="/tmp/gtforge_bench")
    ap.add_argument("--repeat", type=int, default=1,
                    help="run the baseline and the default build this many times, alternating (the table: medians)")
    ap.add_argument("--write", action="store_true", help="write the table into benchmarks/RESULTS.md")
    ap.add_argument("--settle-s", type=float, default=65.0,
                    help="seconds between deleting an earlier output and the next timed run (see settle)")
    args = ap.parse_args()
    from gtforge.infra.scheduling import cpu_count

    workers = args.workers or cpu_count()
    try:
        counts = [int(x) for x in args.scenes.split(",")]
    except ValueError:
        ap.error(f"--scenes: a count or counts separated by commas such as 6,24,48, not {args.scenes!r}")
    exe = Path(sys.executable).with_name("gtforge")  # the console script beside this interpreter
    gtforge_cli = [str(exe)] if exe.exists() else [sys.executable, "-c", "from gtforge.cli import main; main()"]
    if len(counts) > 1:
        return sweep(counts, args, gtforge_cli, workers)
    n = counts[0]
    wd = Path(args.workdir)
    sess, calib = make_session(wd, n, args.distinct)
    machine = machine_line()
    outs = {k: wd / f"out_{k}" for k in ("baseline", "gtforge", "noverify")}
    built = f"built {n}, unchanged 0, failed 0"  # what a complete build prints
    runs = []
    build = gtforge_cli + ["build-dataset", str(sess), "-c", str(calib), "--workers", str(workers)]
    pairs = []  # (baseline, default) of each repeat: (wall s, CPU s)
    wait = {"wait_s": args.settle_s}
    warmup = warm_up(wd, args.distinct, calib, gtforge_cli, workers)
    print(warmup, flush=True)
    for i in range(max(1, args.repeat)):
        # outputs take 20-56 MB a scene: only the one the resume row needs is kept
        settle(*outs.values(), **wait)
        b = timed(baseline_command(sess, calib, outs["baseline"]), f"{n} scenes in")
        settle(outs["baseline"], **wait)
        pairs.append((b, timed(build + ["-o", str(outs["gtforge"])], built)))
        print(f"repeat {i + 1}: baseline {b[0]:.1f} s, default build {pairs[-1][1][0]:.1f} s "
              f"({b[0] / pairs[-1][1][0]:.2f}x)", flush=True)

    def median(ts):  # (wall, CPU) of the run with the median wall time (the faster middle one of an even count)
        return sorted(ts)[(len(ts) - 1) // 2]

    runs.append(("baseline: plain Open3D script (one process)", *median([p[0] for p in pairs])))
    runs.append((f"gtforge build-dataset --workers {workers} (default: verification on)",
                 *median([p[1] for p in pairs])))
    settle(**wait)
    pinned = timed(baseline_command(sess, calib, outs["baseline"]), f"{n} scenes in", one_core=True)
    runs.append(("the same script pinned to one core (Open3D's projection at its fastest)", *pinned))
    settle(outs["baseline"], **wait)
    t = timed(build + ["-o", str(outs["noverify"]), "--no-verify"], built)
    runs.append((f"gtforge build-dataset --workers {workers} --no-verify", *t))
    settle(outs["noverify"], **wait)
    t = timed(build + ["-o", str(outs["noverify"]), "--no-right-gt"], built)
    runs.append((f"gtforge build-dataset --workers {workers} --no-right-gt (verification on)", *t))
    settle(outs["noverify"], **wait)
    t = timed(gtforge_cli + ["build-dataset", str(sess), "-c", str(corrected_calibration(calib)), "--workers",
                             str(workers), "-o", str(outs["noverify"])], built)
    runs.append((f"gtforge build-dataset --workers {workers}, a calibration that corrects the right camera "
                 "(calibrate-scale's yaw: the right image resampled)", *t))
    settle(outs["noverify"], **wait)
    t_resume, _ = timed(build + ["-o", str(outs["gtforge"])], f"unchanged {n},")
    base_rate = n / runs[0][1]
    rep = f" --repeat {args.repeat}" if args.repeat > 1 else ""
    lines = [f"Measured {datetime.date.today()} with `python benchmarks/bench_build_dataset.py --scenes {n} "
             f"--distinct {args.distinct}{rep}`: {machine}; {n} full-resolution scenes "
             f"({args.distinct} distinct renders "
             f"hard-linked), each run a fresh process (imports included), one after the other, each after the "
             f"earlier runs' outputs were deleted, everything written to disk and {args.settle_s:.0f} s since the "
             f"deletion (`settle`)"
             + (f"; the baseline and the default build ran {args.repeat} times, alternating (their rows: the run "
                "with the median wall time)." if args.repeat > 1 else ".")
             + " Machine CPU: the whole machine's busy time during the run (/proc/stat; kernel threads included).",
             "",
             f"| run | wall s | scenes/s | vs baseline | {TARGET_SCENES} scenes at this rate "
             "| machine CPU s per scene |",
             "|---|---|---|---|---|---|"]
    for name, t, cpu in runs:
        rate = n / t
        lines.append(f"| {name} | {t:.1f} | {rate:.2f} | {rate / base_rate:.2f}x | "
                     f"{TARGET_SCENES / rate / 60:.1f} min | {cpu / n:.3f} |")
    lines.append(f"| resume of the default build (nothing to rebuild) | {t_resume:.1f} | | | | |")
    if len(pairs) > 1:
        ratios = sorted(b[0] / g[0] for b, g in pairs)
        lines += ["", "Each repeat, baseline / default build (s): " + ", ".join(
            f"{b[0]:.1f} / {g[0]:.1f} ({b[0] / g[0]:.2f}x)" for b, g in pairs)
            + f"; the default build's ratio {ratios[0]:.2f}-{ratios[-1]:.2f}x, median "
              f"{statistics.median(ratios):.2f}x."]
    lines += ["", f"Against the script pinned to one core ({pinned[0]:.1f} s: Open3D's `project_to_depth_image` "
              "serialises its z-buffer updates in an OpenMP critical section, so its second thread only adds lock "
              f"contention): the default build (median run) {pinned[0] / runs[1][1]:.2f}x, each repeat "
              + ", ".join(f"{pinned[0] / g[0]:.2f}x" for _, g in pairs) + "."]
    lines += ["", warmup]
    text = "\n".join(lines)
    print(text)
    if args.write:
        print("written to", update_results("bench_build_dataset", text))


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
