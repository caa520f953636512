"""Whether calibrate-scale's 1-sigma is a 1-sigma: its terms' errors over many independent synthetic sessions.

Each session (its own seed: board poses, fruit, noise) carries the same scale errors ("combined" of
bench_scale_calibration.py: ZED baseline +0.3 %, right camera yawed 0.15 deg, depth scale -0.2 %, depth offset
+0.5 mm), is calibrated from the exact extrinsic (only the scale terms are off) and solved by calibrate-scale with its
board captures. Printed: each term's normalised error z = (estimate - truth) / sigma per session, then per term the RMS
of z (1 for a calibrated sigma; below 1: the sigma is larger than the errors it describes) and the share within 1 and 2
sigma (68 / 95 % for a Gaussian).

Renders are kept in WORKDIR and reused.

    python benchmarks/bench_scale_coverage.py [--sessions 12] [--scale 0.3] [--boards 5] [--scenes 3]
        [--image-noise 1] [--workdir /tmp/gtforge_bench_scale_coverage]
"""
from __future__ import annotations

import argparse
import math
import shutil
import time
from pathlib import Path

from bench_scale_calibration import CASES, known_calibration, outside

from gtforge.records.calibration import ScaleParams
from gtforge.scale_calibration import calibrate_scale
from gtforge.synthetic import generate_session

TRUTH = {"zed_baseline_frac": 0.003, "zed_right_yaw_deg": 0.15, "depth_scale_frac": -0.002, "depth_offset_mm": 0.5}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sessions", type=int, default=12)
    ap.add_argument("--scale", type=float, default=0.3)
    ap.add_argument("--boards", type=int, default=5)
    ap.add_argument("--scenes", type=int, default=3)
    ap.add_argument("--supersample", type=int, default=2)
    ap.add_argument("--image-noise", type=float, default=1.0, help="grey levels (0: noise-free images)")
    ap.add_argument("--workdir", default="/tmp/gtforge_bench_scale_coverage")
    a = ap.parse_args()
    work = Path(a.workdir)
    work.mkdir(parents=True, exist_ok=True)
    z: dict[str, list[float]] = {k: [] for k in TRUTH}
    for seed in range(a.sessions):
        sess = work / (f"seed{seed:02d}_{a.scale:g}_{a.boards}_{a.scenes}_{a.supersample}"
                       + ("" if a.image_noise == 1.0 else f"_noise{a.image_noise:g}"))
        if not (sess / "done").exists():
            shutil.rmtree(sess, ignore_errors=True)
            t = time.perf_counter()
            generate_session(sess, n_board=a.boards, n_scenes=a.scenes, scale=a.scale, seed=100 + seed,
                             depth_noise_mm=0.03, image_noise=a.image_noise, supersample=a.supersample,
                             **CASES["combined"])
            (sess / "done").write_text("")
            print(f"rendered seed {seed} in {time.perf_counter() - t:.0f} s", flush=True)
        start = known_calibration(sess)
        res = calibrate_scale(sess, start, outside(sess, "scaled.yaml"), ScaleParams(use_boards=True))
        line = []
        for k, term in res.scale_calibration.terms.items():
            if term.estimate is None or not term.sigma:
                line.append(f"{k} -")
                continue
            z[k].append((term.estimate - TRUTH[k]) / term.sigma)
            line.append(f"{k} {term.estimate:+.5f}+-{term.sigma:.5f} z {z[k][-1]:+.2f}")
        print(f"seed {seed}: " + "; ".join(line), flush=True)
    print()
    print("| term | sessions | RMS z | within 1 sigma | within 2 sigma |")
    print("|---|---|---|---|---|")
    for k, v in z.items():
        if v:
            rms = math.sqrt(sum(x * x for x in v) / len(v))
            print(f"| {k} | {len(v)} | {rms:.2f} | {100 * sum(abs(x) <= 1 for x in v) / len(v):.0f} % | "
                  f"{100 * sum(abs(x) <= 2 for x in v) / len(v):.0f} % |")


if __name__ == "__main__":
    main()
