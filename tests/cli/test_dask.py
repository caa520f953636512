"""build-dataset on a Dask cluster (gtforge[dask]): a LocalCluster of 2 worker processes on 127.0.0.1.

Byte-identical to a local build; a worker killed mid-build loses nothing; a scene whose workers keep dying
is listed as failed; Ctrl-C cancels; bad --scheduler values are one-line input errors.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from gtforge.build_dataset import build_dataset
from gtforge.errors import InputError
from gtforge.infra.scheduling import run_tasks
from gtforge.records.dataset import Manifest

pytest.importorskip("distributed")  # the 'dask' extra (part of the 'test' extra)
from distributed.diagnostics.plugin import SchedulerPlugin, WorkerPlugin  # noqa: E402

ALLOWED_FAILURES = 1  # the test scheduler gives up on a task after 2 worker deaths (Dask's default: 3 -> 4)


@pytest.fixture(scope="module")
def cluster():
    import cloudpickle
    import dask
    from distributed import Client, LocalCluster

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the worker plugin below, on the workers
    with dask.config.set({"distributed.scheduler.allowed-failures": ALLOWED_FAILURES}):
        lc = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None,
                          scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})  # its HTTP server: any free port
    client = Client(lc.scheduler_address, set_as_default=False)
    yield lc, client
    client.close()
    lc.close()
    cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


class TaskLog(SchedulerPlugin):
    """Keys of the tasks that finished on the cluster (runs inside the LocalCluster's scheduler, in this process)."""

    def __init__(self):
        self.keys: list[str] = []

    def transition(self, key, start, finish, *args, **kwargs):
        if finish == "memory" and str(key).startswith("gtforge-build_one_scene-"):
            self.keys.append(str(key))


def _ready(client, n=2):
    client.wait_for_workers(n, timeout=180)  # a killed worker's nanny starts a new one (slow on a busy machine)
    return client


def _files(scene: Path) -> set[str]:
    return {f.name for f in scene.iterdir()}


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _comparable(name: str, data: bytes, out: Path):
    """A file's bytes, except for what says when and where it was written: in the JSON files and the HTML
    report, the output folder's path, the report's date, durations (``time_*``) and clock readings (``*_at_ns``)."""
    if not name.endswith((".json", ".html")):
        return data
    text = data.decode().replace(str(out.resolve()), "<OUT>")
    if name.endswith(".html"):
        return re.sub(r"\d{4}-\d{2}-\d{2} \d{2}:\d{2}(:\d{2})?", "<DATE>", text)

    def strip(x):
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if not (k.startswith("time_") or k.endswith("_at_ns"))}
        return [strip(v) for v in x] if isinstance(x, list) else x

    return strip(json.loads(text))


def _session_of(session_dir: Path, dst: Path, copies: int) -> Path:
    """The 3 synthetic scenes, then the same inputs again (hard links) as scenes 003, 004, ..."""
    shutil.copytree(session_dir, dst, ignore=shutil.ignore_patterns("board", "truth"))
    for k in range(3, 3 * copies):
        d = dst / "scenes" / f"{k:03d}"
        d.mkdir()
        for f in (dst / "scenes" / f"{k % 3:03d}").iterdir():
            os.link(f, d / f.name)
    return dst


def _assert_complete(out: Path, ids: list[str], reference: Path) -> None:
    """Every scene once, with its full file set, its disparity equal to the local build's; nothing hidden."""
    scenes = out / "scenes"
    assert sorted(p.name for p in scenes.iterdir()) == ids  # no .tmp-*/.old-* left, no extra scene
    for sid in ids:
        assert _files(scenes / sid) == _files(reference / "scenes" / "000")
        ref = reference / "scenes" / f"{int(sid) % 3:03d}" / "disp0GT.pfm"
        assert (scenes / sid / "disp0GT.pfm").read_bytes() == ref.read_bytes()
    m = Manifest.read(out / "manifest.json")
    assert sorted(m.scenes) == ids and m.failures == {}
    listed = sorted(line.split()[0].split("/")[1] for split in ("train", "val", "test")
                    for line in (out / "filenames" / f"{split}.txt").read_text().splitlines())
    assert listed == ids  # each scene in exactly one list, once


@pytest.mark.slow
def test_dask_build_is_byte_identical_to_local(session_dir, true_calibration, cluster, tmp_path):
    from typer.testing import CliRunner

    from gtforge.cli.commands import app

    lc, client = cluster
    _ready(client)
    out = tmp_path / "ds"
    finished = TaskLog()
    lc.scheduler.add_plugin(finished, name="task-log")
    try:
        r = CliRunner().invoke(app, ["build-dataset", str(session_dir), "-c", str(true_calibration), "-o", str(out),
                                     "--scheduler", lc.scheduler_address])
    finally:
        lc.scheduler.remove_plugin(name="task-log")
    assert r.exit_code == 0, r.output
    assert "built 3, unchanged 0, failed 0" in r.output
    assert sorted(k.split("-")[2] for k in finished.keys) == ["0", "1", "2"]  # the cluster's workers built them
    # the local build, in a fresh process with single-threaded BLAS as on a Dask worker (its nanny sets these):
    # verification's correlation sums with a BLAS dot product whose last bits depend on BLAS's thread count
    ref = tmp_path / "local"
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    done = subprocess.run([sys.executable, "-m", "gtforge.cli", "build-dataset", str(session_dir), "-c",
                           str(true_calibration), "-o", str(ref), "--workers", "1"], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    local, remote = _tree(ref), _tree(out)
    assert sorted(remote) == sorted(local) and len(local) > 40  # the same files, hidden ones included
    for name in local:
        assert _comparable(name, remote[name], out) == _comparable(name, local[name], ref), name
    assert sum(not n.endswith((".json", ".html")) for n in local) > 40  # compared byte for byte


@pytest.mark.slow
def test_worker_killed_mid_build_loses_nothing(session_dir, true_calibration, dataset, cluster, tmp_path):
    lc, client = cluster
    _ready(client)
    sess = _session_of(session_dir, tmp_path / "sess", copies=2)
    ids = [f"{k:03d}" for k in range(6)]
    out = tmp_path / "ds"
    first: dict = {}

    def build():
        try:
            first["summary"] = build_dataset(sess, true_calibration, out, scheduler=lc.scheduler_address)
        except BaseException as exc:  # reported by the assertions below
            first["error"] = exc

    t = threading.Thread(target=build)
    t.start()
    deadline = time.time() + 120
    while time.time() < deadline and not list((out / "scenes").glob("*/meta.json")):
        time.sleep(0.02)
    busy: dict = {}
    while time.time() < deadline and not busy:  # a worker between two scenes holds none: wait for one that does
        busy = {w: keys for w, keys in client.processing().items() if keys}
        time.sleep(0.01)
    assert busy, "no worker was building a scene after the first one landed"
    victim = sorted(busy)[0]
    pid = client.run(os.getpid, workers=[victim])[victim]
    os.kill(pid, signal.SIGKILL)  # the worker process, mid-scene; its nanny starts a new one
    t.join(300)
    assert not t.is_alive() and "error" not in first, first.get("error")
    s1 = first["summary"]
    assert s1.built == ids and s1.failures == {}  # the killed worker's scene was run again elsewhere
    assert busy[victim]  # a scene was being built on it when it died
    _assert_complete(out, ids, dataset[0])
    s2 = build_dataset(sess, true_calibration, out, scheduler=lc.scheduler_address)  # the rerun
    assert s2.built == [] and s2.skipped_unchanged == ids and s2.failures == {}
    _assert_complete(out, ids, dataset[0])


class KillOnScene(WorkerPlugin):
    """Worker plugin: the worker process dies when it starts task number ``index`` of a run (every attempt)."""

    idempotent = True

    def __init__(self, index: int):
        self.index = index

    def setup(self, worker):
        pass

    def teardown(self, worker):
        pass

    def transition(self, key, start, finish, **kwargs):
        if finish == "executing" and str(key).startswith(f"gtforge-build_one_scene-{self.index}-"):
            os.kill(os.getpid(), signal.SIGKILL)


@pytest.mark.slow
def test_scene_that_keeps_killing_workers_is_listed_as_failed(session_dir, true_calibration, dataset, cluster,
                                                              tmp_path):
    from typer.testing import CliRunner

    from gtforge.cli.commands import app

    lc, client = cluster
    _ready(client)
    out = tmp_path / "ds"
    client.register_plugin(KillOnScene(1), name="kill-scene-1")  # scenes are dispatched in order: 001
    try:
        r = CliRunner().invoke(app, ["build-dataset", str(session_dir), "-c", str(true_calibration), "-o", str(out),
                                     "--scheduler", lc.scheduler_address])
    finally:
        client.unregister_worker_plugin("kill-scene-1")
    assert r.exit_code == 1, r.output  # a failed scene, not a crash
    assert "built 2, unchanged 0, failed 1 (001;" in r.output
    m = Manifest.read(out / "manifest.json")
    assert sorted(m.scenes) == ["000", "002"] and list(m.failures) == ["001"]
    assert "KilledWorker" in m.failures["001"] and f"{ALLOWED_FAILURES + 1} time(s)" in m.failures["001"]
    assert sorted(p.name for p in (out / "scenes").iterdir()) == ["000", "002"]
    _ready(client)
    s = build_dataset(session_dir, true_calibration, out, scheduler=lc.scheduler_address)  # the rerun
    assert s.built == ["001"] and s.skipped_unchanged == ["000", "002"] and s.failures == {}
    _assert_complete(out, ["000", "001", "002"], dataset[0])


@pytest.mark.slow
def test_ctrl_c_cancels_the_cluster_tasks(session_dir, true_calibration, dataset, cluster, tmp_path):
    lc, client = cluster
    _ready(client)
    sess = _session_of(session_dir, tmp_path / "sess", copies=2)
    ids = [f"{k:03d}" for k in range(6)]
    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "gtforge.cli", "build-dataset", str(sess), "-c", str(true_calibration), "-o", str(out),
           "--scheduler", lc.scheduler_address]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and not list((out / "scenes").glob("*/meta.json")):
        time.sleep(0.02)
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=120)
    assert p.returncode == 130, stderr
    assert "interrupted:" in stderr and "rerun the same command to resume" in stderr
    # queued scenes were cancelled: the scheduler forgets every task of that run (running ones finish first)
    deadline = time.time() + 30
    while time.time() < deadline and lc.scheduler.tasks:
        time.sleep(0.1)
    assert not lc.scheduler.tasks
    landed = [d.name for d in (out / "scenes").iterdir() if not d.name.startswith(".")]
    assert 1 <= len(landed) < len(ids)
    for sid in landed:  # whatever landed is complete
        assert _files(out / "scenes" / sid) == _files(dataset[0] / "scenes" / "000")
    s = build_dataset(sess, true_calibration, out, scheduler=lc.scheduler_address)
    assert sorted(s.built + s.skipped_unchanged) == ids and set(landed) <= set(s.skipped_unchanged)
    _assert_complete(out, ids, dataset[0])


@pytest.mark.slow
@pytest.mark.slow
def test_run_builds_and_verifies_on_the_cluster(session_dir, true_calibration, cluster, tmp_path):
    """gtforge run --scheduler: build-dataset's and verify's scenes on the cluster's workers (run had no --scheduler;
    a run-through), the labels those of the calibration it built with; a rerun redoes nothing; --workers with it, or
    an address without a port, is refused before any stage runs."""
    from gtforge.io.formats import read_pfm
    from gtforge.run import RunOptions, run_session

    lc, client = cluster
    _ready(client)
    sess = _session_of(session_dir, tmp_path / "s", 1)  # the 3 scenes, no boards: validate does not apply
    finished = TaskLog()
    lc.scheduler.add_plugin(finished, name="task-log")
    opts = RunOptions(calibration=str(true_calibration), loo=False, refine=False, scheduler=lc.scheduler_address)
    try:
        said: list[str] = []
        res = run_session(sess, tmp_path / "run", opts, say=said.append)
    finally:
        lc.scheduler.remove_plugin(name="task-log")
    assert res.redone == ["calibrate-scale", "build-dataset", "verify"], said
    assert sorted(k.split("-")[2] for k in finished.keys) == ["0", "1", "2"]  # the cluster's workers built them
    ds = tmp_path / "run" / "dataset"
    local = build_dataset(sess, tmp_path / "run" / "scaled.yaml", tmp_path / "local", workers=1)
    assert local.built == ["000", "001", "002"]
    for sid in local.built:
        assert (ds / "scenes" / sid / "disp0GT.pfm").read_bytes() == \
            (tmp_path / "local" / "scenes" / sid / "disp0GT.pfm").read_bytes()
        assert read_pfm(ds / "scenes" / sid / "disp0GT.pfm").shape[0] > 0
    said = []
    assert run_session(sess, tmp_path / "run", opts, say=said.append).redone == [], said
    for bad, words in ((opts.model_copy(update={"workers": 2}), "--workers"),
                       (opts.model_copy(update={"scheduler": "tcp://127.0.0.1"}), "the port is required")):
        with pytest.raises(InputError, match=words):
            run_session(sess, tmp_path / "run2", bad, say=said.append)
        assert not (tmp_path / "run2").exists()


def test_scheduler_errors_are_one_line(session_dir, true_calibration, tmp_path, monkeypatch):
    import socket

    with socket.socket() as sock:  # a port nothing listens on
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT="1s")
    r = subprocess.run([sys.executable, "-m", "gtforge.cli", "build-dataset", str(session_dir), "-c",
                        str(true_calibration), "-o", str(tmp_path / "ds"), "--scheduler", address],
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and address in r.stderr and "within 1 s" in r.stderr
    assert "dask scheduler" in r.stderr  # the hint
    assert not (tmp_path / "ds").exists()  # the output folder the build made for it is gone again (it stayed empty)
    with pytest.raises(InputError, match="expected a Dask scheduler address"):
        run_tasks(len, [("a",)], print, scheduler="no-port-here")
    with pytest.raises(InputError, match="--workers"):
        build_dataset(session_dir, true_calibration, tmp_path / "ds", workers=2, scheduler=address)
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if gtforge[dask] were not installed
    with pytest.raises(InputError, match=r"pip install 'gtforge\[dask\]'"):
        run_tasks(len, [("a",)], print, scheduler=address)
    results = []
    run_tasks(len, [("ab",), ("abc",)], results.append, workers=1)  # the local path needs no dask
    assert results == [2, 3]


def test_stale_cleanup_spares_a_live_writer(tmp_path):
    """A scene folder still being written (a Dask task cancelled by Ctrl-C runs to its end) is not removed
    under its writer; a dead writer's folders and locks are."""
    from gtforge.dataset.scene_folder import lock_writer, remove_stale_entries, unlock_writer

    scenes = tmp_path / "scenes"
    fd = lock_writer(scenes, "007", "abc")  # a live writer (flock: another open file, even in this process)
    (scenes / ".tmp-007-abc").mkdir()
    (scenes / ".tmp-007-abc" / "im0.png").write_bytes(b"partial")
    (scenes / ".tmp-008-def").mkdir()  # no lock: its writer is gone
    (scenes / ".lock-009-ghi").touch()  # a lock nobody holds (its writer was killed)
    remove_stale_entries(tmp_path)
    assert sorted(p.name for p in scenes.iterdir()) == [".lock-007-abc", ".tmp-007-abc"]
    assert (scenes / ".tmp-007-abc" / "im0.png").read_bytes() == b"partial"
    unlock_writer(scenes, "007", "abc", fd)
    remove_stale_entries(tmp_path)
    assert list(scenes.iterdir()) == []


def test_a_scheduler_stopped_mid_run_is_one_line(tmp_path):
    """The scheduler stopped while tasks were on it: the run ended in a traceback of Dask's internals
    (CommClosedError from client.nthreads(), exit 1), build-dataset writing no manifest and leaving its scenes' locks.
    Now one line (SchedulerLost, an InputError: exit 2) naming the scheduler, and the results that came back stand."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT="3s")
    dask_cli = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    sched = subprocess.Popen([*dask_cli, "--host", "127.0.0.1", "--port", str(port), "--dashboard-address",
                              "127.0.0.1:0"], env=env, cwd=tmp_path, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)
    worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1",
                               "--no-nanny", "--no-dashboard"], env=env, cwd=tmp_path, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    results = []

    def on_result(res):
        results.append(res)
        if len(results) == 1:  # the scheduler goes with tasks still queued
            sched.kill()
            sched.wait()

    import logging

    import dask

    class Seen(logging.Handler):  # what Dask's client logs, as the user's terminal would get it
        records: list = []

        def emit(self, record):
            self.records.append(record)

    seen = Seen()
    logging.getLogger("distributed.client").addHandler(seen)
    try:
        with dask.config.set({"distributed.comm.timeouts.connect": "30s"}):  # (the worker starts within it)
            from gtforge.infra.scheduling import connect_scheduler

            connect_scheduler(address).close()
        with dask.config.set({"distributed.comm.timeouts.connect": "3s"}):
            with pytest.raises(InputError) as err:
                run_tasks(time.sleep, [(0.3,)] * 20, on_result, scheduler=address)
    finally:
        logging.getLogger("distributed.client").removeHandler(seen)
        for p in (worker, sched):
            p.kill()
            p.wait()
    # Dask's own "Failed to reconnect to scheduler after 3.00 seconds" and its shutdown's tracebacks (CancelledError)
    # went to the terminal beside the one line below, which says it
    said = [r.getMessage() for r in seen.records if r.levelno >= logging.WARNING]
    assert not [m for m in said if "reconnect" in m] and not [r for r in seen.records if r.exc_info], said
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"--scheduler: expected the Dask scheduler at {address} for the whole run, got the "
                          "connection lost (")
    assert msg.endswith("(hint: restart the scheduler and its workers (docs/cluster.md) and rerun the same command: "
                        "it resumes with the work not done)")
    assert results == [None]
