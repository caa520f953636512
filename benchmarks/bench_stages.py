"""Each stage's time per capture on one synthetic session, the baseline tree and this one in the same run (issue 39).

Stages: calibrate (board captures; its self-rectification matches every capture, boards and scenes), validate
(boards and gauges), calibrate-scale, refine, verify (one process, ``--workers 1``: the stage's own time, not a
pool's start) and evaluate (OpenCV SGBM, fruit sizes); and calibrate, validate and calibrate-scale in one process,
as ``gtforge run`` runs them (a board image's detection is remembered from one stage to the next). Each run is a
process of its own, as a lab's command is (imports included), the two trees in turn on the same inputs; per run it
takes the wall time and the CPU time of the process and its threads (``resource.getrusage``). Printed per stage: the
median wall and CPU seconds per capture of each tree and the ratios baseline / this tree, and whether the two trees'
outputs are the same (``scripts/compare_outputs.py``: every file byte for byte, JSON/YAML/HTML without the fields
that record time).

The baseline is the tree at ``--baseline`` (default ``cb56d33``: before issue 39's stage work), its ``src/`` extracted
with ``git archive`` into WORKDIR and imported from there. A first, untimed round of every stage fills both trees'
numba caches. The session is rendered once (``gtforge.synthetic.generate_session``, with gauges; a few minutes) and
kept in WORKDIR.

    python benchmarks/bench_stages.py [--scale 0.5] [--boards 8] [--scenes 5] [--repeats 3] [--baseline REV]
        [--stages calibrate,validate,calibrate-scale,refine,verify,evaluate,calibrate+validate+scale]
        [--workdir /tmp/gtforge_bench_stages] [--baseline-threads N] [--write]
"""
from __future__ import annotations

import argparse
import importlib.util
import io
import json
import os
import shutil
import statistics
import subprocess
import sys
import tarfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from fullres_session import machine_line, update_results  # noqa: E402

STAGES = ("calibrate", "validate", "calibrate-scale", "refine", "verify", "evaluate", "calibrate+validate+scale")

# One stage in a fresh process; its inputs are the outputs of this tree's run of the stage before (the same bytes in
# both trees: each pair is compared). Prints its wall and CPU seconds as JSON on the last line.
RUNNER = r"""
import json, resource, sys, time
t0 = time.perf_counter()
stage, session, inp, out = sys.argv[1:5]
if __name__ == "__main__":
    if sys.argv[5:]:  # --baseline-threads: this many capture threads (gtforge.infra.threads)
        import gtforge.infra.threads as threads
        threads.capture_threads = lambda: int(sys.argv[5])
    if stage == "calibrate":
        from gtforge.calibrate import calibrate
        calibrate(session, out + "/calibration.yaml")
    elif stage == "validate":
        from gtforge.validate import validate
        validate(session, inp + "/calibration.yaml", out + "/validation")
    elif stage == "calibrate-scale":
        from gtforge.scale_calibration import calibrate_scale
        calibrate_scale(session, inp + "/calibration.yaml", out + "/scaled.yaml")
    elif stage == "refine":
        from gtforge.refine import RefineParams, refine
        refine(session, inp + "/scaled.yaml", out + "/refined.yaml", RefineParams(leave_one_out=False))
    elif stage == "verify":
        from gtforge.verify import verify_dataset
        verify_dataset(out + "/dataset", workers=1)
    elif stage == "calibrate+validate+scale":  # in one process, as `gtforge run` runs them
        from gtforge.calibrate import calibrate
        from gtforge.scale_calibration import calibrate_scale
        from gtforge.validate import validate
        calibrate(session, out + "/calibration.yaml")
        validate(session, out + "/calibration.yaml", out + "/validation")
        calibrate_scale(session, out + "/calibration.yaml", out + "/scaled.yaml")
    elif stage == "evaluate":
        from gtforge.evaluate import evaluate
        from gtforge.predictors import SGBM
        evaluate(inp + "/dataset", SGBM(), out + "/evaluation")
    wall = time.perf_counter() - t0
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime
    print(json.dumps({"wall_s": wall, "cpu_s": cpu}))
"""


def baseline_tree(workdir: Path, rev: str) -> Path:
    """``src/`` of ``rev`` (git archive), extracted once into ``workdir/baseline-<rev>/src``."""
    rev = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", rev], check=True, capture_output=True,
                         text=True).stdout.strip()  # HEAD moves; a commit does not
    root = workdir / f"baseline-{rev}"
    if not (root / "src" / "gtforge").is_dir():
        shutil.rmtree(root, ignore_errors=True)
        data = subprocess.run(["git", "-C", str(REPO), "archive", "--format=tar", rev, "src"], check=True,
                              capture_output=True).stdout
        with tarfile.open(fileobj=io.BytesIO(data)) as tar:
            tar.extractall(root, filter="data")
    return root / "src"


def make_session(workdir: Path, scale: float, boards: int, scenes: int) -> Path:
    """The demo's kind of session (a ZED baseline 0.25 % long, the right camera yawed 0.04 deg, the last fruit rolled
    0.6 mm), with gauges; rendered once."""
    from gtforge.synthetic import generate_gauges, generate_session

    sess = workdir / f"session-{scale:g}x-{boards}b-{scenes}s"
    if not (sess / "done").exists():
        shutil.rmtree(sess, ignore_errors=True)
        t0 = time.perf_counter()
        generate_session(sess, n_board=boards, n_scenes=scenes, scale=scale, seed=0,
                         fruit_motion_mm={scenes - 1: (0.6, 0.2, 0.0)} if scenes >= 4 else None,
                         zed_baseline_error_frac=0.0025, right_yaw_deg=0.04)
        generate_gauges(sess, scale=scale, seed=0, depth_noise_mm=0.03)  # as `gtforge synth --gauges`
        (sess / "done").write_text("")
        print(f"rendered {sess} in {time.perf_counter() - t0:.0f} s", flush=True)
    return sess


def run_stage(src: Path, stage: str, session: Path, inp: Path, out: Path, threads: int | None = None) -> dict:
    env = dict(os.environ, PYTHONPATH=str(src), OPENBLAS_NUM_THREADS="1", OMP_WAIT_POLICY="passive")
    extra = [] if threads is None else [str(threads)]
    p = subprocess.run([sys.executable, "-c", RUNNER, stage, str(session), str(inp), str(out), *extra], env=env,
                       capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"{stage} failed under {src}:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def prepare(stage: str, inp: Path, out: Path) -> None:
    """A fresh output folder; verify writes into the dataset, so it gets its own copy of the one it checks."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    if stage == "verify":
        shutil.copytree(inp / "dataset", out / "dataset")


def load_compare():
    spec = importlib.util.spec_from_file_location("compare_outputs", REPO / "scripts" / "compare_outputs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.compare


def _chain_is_current(chain: Path) -> bool:
    """Whether ``chain`` holds a dataset this tree reads (one built before a schema change is built again)."""
    from gtforge.records.dataset import Manifest

    try:
        manifest = json.loads((chain / "dataset" / "manifest.json").read_text())
    except (OSError, ValueError):
        return False
    return manifest.get("schema_version") == Manifest.SCHEMA_VERSION


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--boards", type=int, default=8)
    ap.add_argument("--scenes", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline", default="cb56d33")
    ap.add_argument("--baseline-threads", type=int, default=None,
                    help="run the baseline with this many capture threads (a tree with gtforge.infra.threads: "
                    "--baseline HEAD --baseline-threads 1 measures what the threads alone give)")
    ap.add_argument("--stages", default=",".join(STAGES))
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_stages")
    ap.add_argument("--write", action="store_true", help="put the table into RESULTS.md")
    args = ap.parse_args(argv)
    stages = [s for s in STAGES if s in args.stages.split(",")]
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    trees = {"baseline": baseline_tree(work, args.baseline), "this tree": REPO / "src"}
    session = make_session(work, args.scale, args.boards, args.scenes)
    n_gauges = len([d for d in (session / "gauges").iterdir() if d.is_dir()]) if (session / "gauges").is_dir() else 0
    per = {"calibrate": args.boards + args.scenes, "validate": args.boards + n_gauges,
           "calibrate-scale": args.boards + args.scenes, "refine": args.scenes, "verify": args.scenes,
           "evaluate": args.scenes, "calibrate+validate+scale": 2 * args.boards + 2 * args.scenes + n_gauges}
    what = {"calibrate": "boards + scenes", "validate": "boards + gauges", "calibrate-scale": "boards + scenes",
            "refine": "scenes", "verify": "scenes", "evaluate": "scenes",
            "calibrate+validate+scale": "the three stages' captures, one process"}
    # inputs: calibrate's output feeds validate and calibrate-scale, scaled.yaml refine; verify and evaluate need a
    # dataset, built once from refined.yaml by this tree (build-dataset is not timed here)
    chain = work / "chain"
    if not _chain_is_current(chain):
        shutil.rmtree(chain, ignore_errors=True)
        chain.mkdir()
        for stage in ("calibrate", "calibrate-scale", "refine"):
            run_stage(trees["this tree"], stage, session, chain, chain)
        env = dict(os.environ, PYTHONPATH=str(trees["this tree"]))
        # (exit status 1 when a scene is flagged: the demo's rolled fruit is)
        subprocess.run([sys.executable, "-m", "gtforge.cli", "build-dataset", str(session), "-c",
                        str(chain / "refined.yaml"), "-o", str(chain / "dataset")], env=env, capture_output=True)
        if not (chain / "dataset" / "manifest.json").exists():
            raise SystemExit("build-dataset wrote no dataset")
    compare = load_compare()
    print(machine_line(), flush=True)
    base = args.baseline + ("" if args.baseline_threads is None else f" with {args.baseline_threads} capture thread(s)")
    print(f"session {session.name}: {args.boards} boards, {args.scenes} scenes, {n_gauges} gauges; baseline "
          f"{base}; {args.repeats} timed runs a tree after an untimed one", flush=True)
    rows = []
    for stage in stages:
        times: dict[str, list[dict]] = {t: [] for t in trees}
        for k in range(args.repeats + 1):
            for name, src in trees.items():
                out = work / "runs" / stage / name.replace(" ", "_")
                prepare(stage, chain, out)
                r = run_stage(src, stage, session, chain, out, args.baseline_threads if name == "baseline" else None)
                if k:  # the first run of each tree compiles what numba had not cached
                    times[name].append(r)
        diffs = compare(work / "runs" / stage / "baseline", work / "runs" / stage / "this_tree")
        n = per[stage]
        med = {t: {q: statistics.median(r[q] for r in rs) / n for q in ("wall_s", "cpu_s")} for t, rs in times.items()}
        b, a = med["baseline"], med["this tree"]
        row = (stage, f"{n} ({what[stage]})", b["wall_s"], a["wall_s"], b["wall_s"] / a["wall_s"], b["cpu_s"],
               a["cpu_s"], b["cpu_s"] / a["cpu_s"], "identical" if not diffs else f"{len(diffs)} differ")
        rows.append(row)
        print(f"{stage:16s} per capture: wall {b['wall_s']:.3f} -> {a['wall_s']:.3f} s ({row[4]:.2f}x), CPU "
              f"{b['cpu_s']:.3f} -> {a['cpu_s']:.3f} s ({row[7]:.2f}x); outputs {row[8]}", flush=True)
        for d in diffs[:10]:
            print("   ", d)
    table = ["| stage | captures (what) | wall s/capture, baseline | wall s/capture, this tree | wall ratio | "
             "CPU s/capture, baseline | CPU s/capture, this tree | CPU ratio | outputs |",
             "|---|---|---|---|---|---|---|---|---|"]
    table += [f"| {r[0]} | {r[1]} | {r[2]:.3f} | {r[3]:.3f} | {r[4]:.2f}x | {r[5]:.3f} | {r[6]:.3f} | {r[7]:.2f}x | "
              f"{r[8]} |" for r in rows]
    print("\n".join(table))
    if args.write:
        cmd = "python benchmarks/bench_stages.py " + " ".join(argv if argv is not None else sys.argv[1:])
        section = "bench_stages" if args.baseline_threads is None else "bench_stages_threads"
        update_results(section, f"`{cmd.strip()}`, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; "
                       f"{machine_line()}; session {session.name}; baseline {base}; medians of {args.repeats} runs a "
                       "tree\n\n" + "\n".join(table))
    return 0 if all(r[8] == "identical" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
