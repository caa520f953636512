"""Where build-dataset's fixed cost goes: what runs before a build's first scene lands, each part in a fresh process.

1. ``import gtforge.build_dataset`` (what the command imports before it plans the scenes), wall and CPU.
2. The local pool's fork server, step by step, with ``NUMBA_NUM_THREADS=1`` as it starts when ``--workers`` = cores: the
   command's module (its ``__main__``), numba, ``gtforge.build_dataset``, numba's registries (``infra.pool_preload``),
   then the warm-up (``build_dataset.warm_worker``): the calibration, the session, the depth camera's ray grid; run
   twice on an empty disk cache (``infra.disk_cache``, a temporary folder): computed and stored, then read back (a
   rerun of the same calibration).
3. One build worker's scenes: ``build_one_scene`` on ``--scenes`` full-resolution scenes in a process forked as the
   pool forks its workers (after the server's imports; its heap reserved as a pool worker's: ``reserve_heap``, not
   counted in the first scene), once without the warm-up (each worker's first scene computes
   the calibration, session and ray grid itself) and once from a warmed server; CPU of each scene.

Prints one table (CPU s of this machine's processes: the machine may be shared, and CPU time moves less with other
users' load than wall time). ``--write`` puts it into benchmarks/RESULTS.md (section ``profile_startup``).

    python benchmarks/profile_startup.py [--scenes 4] [--workdir /tmp/gtforge_bench] [--write]
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from fullres_session import machine_line, make_session, update_results

from gtforge.cli import OPENBLAS_SPIN_ENV
from gtforge.infra.disk_cache import CACHE_ENV

IMPORT = """
import json, resource, time
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF); return r.ru_utime + r.ru_stime
t = time.perf_counter(); import gtforge.build_dataset
print(json.dumps({"wall": time.perf_counter() - t, "cpu": cpu()}))
"""

SERVER = """
import json, resource, sys, time
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF); return r.ru_utime + r.ru_stime
steps, last = [], [time.perf_counter(), cpu()]
def mark(what):
    t, c = time.perf_counter(), cpu(); steps.append((what, t - last[0], c - last[1])); last[:] = [t, c]
import gtforge.cli; mark("the command's module (the server's __main__: gtforge.cli)")
import numba; mark("numba")
import gtforge.build_dataset; mark("gtforge.build_dataset (the task's module)")
import gtforge.infra.pool_preload; mark("numba's registries (infra.pool_preload.load_registries)")
from gtforge.dataset.worker_cache import cached_calibration, cached_session
from gtforge.infra.digest import sha256_file
from gtforge.core.ground_truth.reproject import prepare_rays
session, calib_path = sys.argv[1:3]
calib = cached_calibration(calib_path, sha256_file(calib_path)); mark("warm-up: the calibration")
cached_session(session, calib); mark("warm-up: the session")
prepare_rays(calib.rig.depth_camera); mark("warm-up: the depth camera's ray grid")
print(json.dumps(steps))
"""

WORKER = """
import json, os, resource, shutil, sys, time
from pathlib import Path
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF); return r.ru_utime + r.ru_stime
import gtforge.build_dataset as bd
import gtforge.infra.pool_preload  # noqa: F401 (as the fork server)
from gtforge.dataset.worker_cache import scene_heap_bytes
from gtforge.infra.digest import sha256_file
from gtforge.infra.scheduling import limit_threads, reserve_heap, reuse_freed_memory
from gtforge.records.calibration import CalibrationFile
from gtforge.records.dataset import BuildParams
session, calib_path, out, n, warm = sys.argv[1], sys.argv[2], Path(sys.argv[3]), int(sys.argv[4]), sys.argv[5] == "1"
zed = CalibrationFile.read(calib_path).rig.zed.left
t = time.perf_counter(); c = cpu()
if warm:
    bd.warm_worker(session, calib_path)
warm_cpu = cpu() - c
r, w = os.pipe()
pid = os.fork()  # a worker, as the pool forks it from its server
if pid == 0:
    os.close(r)
    limit_threads(1); reuse_freed_memory()
    c0 = cpu()
    reserve_heap(scene_heap_bytes(zed))  # as the pool's workers start
    reserve_cpu = cpu() - c0
    shutil.rmtree(out, ignore_errors=True); (out / "scenes").mkdir(parents=True)
    sha, pj = sha256_file(calib_path), BuildParams().model_dump_json()
    scenes, res = sorted((Path(session) / "scenes").iterdir())[:n], []
    for d in scenes:
        c0 = cpu()
        assert bd.build_one_scene(session, str(d), d.name, calib_path, sha, str(out), pj)[1] is None
        res.append(cpu() - c0)
    os.write(w, json.dumps([reserve_cpu, res]).encode()); os._exit(0)
os.close(w)
data = b""
while chunk := os.read(r, 65536):
    data += chunk
os.waitpid(pid, 0)
reserve_cpu, res = json.loads(data)
print(json.dumps({"warm_up_cpu": warm_cpu, "reserve_cpu": reserve_cpu, "scenes": res}))
"""


def run(code: str, *args: str, env: dict | None = None):
    r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                       env={**os.environ, **(env or {})}, timeout=900)
    if r.returncode != 0:
        sys.exit(f"failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=4, help="scenes a worker builds (first + steady state)")
    ap.add_argument("--workdir", default="/tmp/gtforge_bench")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    machine = machine_line()
    sess, calib = make_session(Path(args.workdir), args.scenes, min(args.scenes, 4))
    sess, calib = str(sess.resolve()), str(calib.resolve())
    # every process as the gtforge command starts it: OpenBLAS's idle threads spin briefly (gtforge.cli.main)
    spin = dict(OPENBLAS_SPIN_ENV)
    one = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", **spin}
    imp = run(IMPORT, env=spin)
    with tempfile.TemporaryDirectory() as cache:
        server = run(SERVER, sess, calib, env={**one, CACHE_ENV: cache})
        rerun = run(SERVER, sess, calib, env={**one, CACHE_ENV: cache})
        out = str(Path(args.workdir) / "out_profile_startup")
        cold = run(WORKER, sess, calib, out, str(args.scenes), "0", env={**one, CACHE_ENV: cache})
        warm = run(WORKER, sess, calib, out, str(args.scenes), "1", env={**one, CACHE_ENV: cache})
    lines = [f"Measured {datetime.date.today()} with `python benchmarks/profile_startup.py --scenes {args.scenes}`: "
             f"{machine}; each part in a fresh process; CPU s of that process.", "",
             "| part | step | wall s | CPU s |", "|---|---|---|---|",
             f"| the command | `import gtforge.build_dataset` | {imp['wall']:.3f} | {imp['cpu']:.3f} |"]
    lines += [f"| fork server (NUMBA_NUM_THREADS=1) | {w} | {t:.3f} | {c:.3f} |" for w, t, c in server]
    lines.append(f"| fork server | **its whole start, warm-up included** | {sum(s[1] for s in server):.3f} | "
                 f"**{sum(s[2] for s in server):.3f}** |")
    lines.append(f"| fork server, a rerun | warm-up: the ray grid, from the disk cache | {rerun[-1][1]:.3f} | "
                 f"{rerun[-1][2]:.3f} |")
    lines.append(f"| fork server, a rerun | **its whole start, warm-up included** | {sum(s[1] for s in rerun):.3f} | "
                 f"**{sum(s[2] for s in rerun):.3f}** |")
    for name, r in (("worker forked without the warm-up", cold), ("worker forked from a warmed server", warm)):
        s = r["scenes"]
        steady = sorted(s[1:])[len(s[1:]) // 2] if len(s) > 1 else float("nan")
        lines.append(f"| {name} | its heap reserved (before the first scene) | | {r['reserve_cpu']:.3f} |")
        lines.append(f"| {name} | first scene / median of the next {len(s) - 1} | | **{s[0]:.3f}** / {steady:.3f} |")
    text = "\n".join(lines)
    print(text)
    if args.write:
        print("written to", update_results("profile_startup", text))


if __name__ == "__main__":
    main()
