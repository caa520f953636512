"""``gtforge run``'s dataset stages on full-resolution scenes, this tree against a baseline tree in the same run
(issue 39): build-dataset, then verify.

``gtforge run SESSION -o OUT -c CALIBRATION --no-refine`` on ``--scenes`` full-resolution scenes (``fullres_session``:
no board captures, so calibrate, validate and calibrate-scale do not apply) with a calibration that corrects the right
camera, as a run's own calibration does after calibrate-scale (its right image resampled in both stages). Each run is a
fresh process writing into an empty folder; the baseline (``--baseline REV``: its ``src/`` from ``git archive``, as
``bench_stages.py`` extracts it) and this tree alternate, after one untimed run each (numba's caches). Printed per
tree: the medians of the command's wall time and of each stage's time (``run_state.json``), the ratios baseline /
this tree, and whether the two trees' datasets hold the same files (``scripts/compare_outputs.py``: byte for byte,
JSON/YAML/HTML without the fields that record time).

    python benchmarks/bench_run.py [--scenes 24] [--repeats 3] [--baseline REV] [--workdir /tmp/gtforge_bench]
        [--write]
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bench_stages import baseline_tree, load_compare
from fullres_session import corrected_calibration, machine_line, make_session, update_results

from gtforge.precompile import compile_bytecode

STAGES = ("build-dataset", "verify")


def run_once(src: Path, session: Path, calib: Path, out: Path) -> dict[str, float]:
    """One ``gtforge run`` under ``src``: its wall time and each stage's ``time_s``."""
    shutil.rmtree(out, ignore_errors=True)
    os.sync()
    exe = Path(sys.executable).with_name("gtforge")
    t0 = time.perf_counter()
    p = subprocess.run([str(exe), "run", str(session), "-o", str(out), "-c", str(calib), "--no-refine"],
                       env={**os.environ, "PYTHONPATH": str(src)}, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"gtforge run failed under {src} ({p.returncode}):\n{p.stderr[-3000:]}")
    stages = json.loads((out / "run_state.json").read_text())["stages"]
    return {"wall": wall, **{s: stages[s]["time_s"] for s in STAGES}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline", default="ce9cae5")  # before run took the build's checks (round 22)
    ap.add_argument("--workdir", default="/tmp/gtforge_bench")
    ap.add_argument("--write", action="store_true", help="write the table into benchmarks/RESULTS.md")
    args = ap.parse_args(argv)
    work = Path(args.workdir)
    session, calib = make_session(work, args.scenes)
    calib = corrected_calibration(calib)
    trees = {"baseline": baseline_tree(work, args.baseline), "this tree": Path(__file__).resolve().parents[1] / "src"}
    for src in trees.values():
        compile_bytecode(src / "gtforge")
    outs = {name: work / "out_run" / name.replace(" ", "_") for name in trees}
    head = machine_line()
    print(head, flush=True)
    for name, src in trees.items():  # untimed: numba's caches filled, the files read once
        run_once(src, session, calib, outs[name])
    times: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
    for _ in range(args.repeats):
        for name, src in trees.items():
            times[name].append(run_once(src, session, calib, outs[name]))
            t = times[name][-1]
            print(f"{name}: wall {t['wall']:.2f} s, " + ", ".join(f"{s} {t[s]:.2f} s" for s in STAGES), flush=True)
    diffs = load_compare()(outs["baseline"] / "dataset", outs["this tree"] / "dataset")
    med = {name: {k: statistics.median(t[k] for t in runs) for k in ("wall", *STAGES)} for name, runs in times.items()}
    rows = [f"| {k} | {med['baseline'][k]:.2f} | {med['this tree'][k]:.2f} | "
            f"{med['baseline'][k] / max(med['this tree'][k], 1e-9):.2f}x |" for k in ("wall", *STAGES)]
    same = "the same files" if not diffs else f"{len(diffs)} difference(s), the first: {diffs[0]}"
    cmd = f"python benchmarks/bench_run.py --scenes {args.scenes} --repeats {args.repeats} --baseline {args.baseline}"
    text = "\n".join([
        f"`{cmd}`, {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; {head}; {args.scenes} "
        "full-resolution scenes, a calibration that corrects the right camera; medians of "
        f"{args.repeats} runs a tree, alternating",
        "",
        "| `gtforge run ... --no-refine` | baseline s | this tree s | ratio |",
        "|---|---|---|---|",
        *rows,
        "",
        f"Datasets of the two trees: {same}.",
    ])
    print(text)
    if args.write:
        print(f"written to {update_results('bench_run', text)}")
    return 0 if not diffs else 1


if __name__ == "__main__":
    sys.exit(main())
