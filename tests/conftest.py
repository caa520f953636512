"""Shared fixtures: the synthetic sessions (exact truth beside them) and the shared calibration, made once per test run
for every pytest-xdist worker (tests/made_once.py). The tests that need none of them run first, while a background
process makes those the collected tests need, in the order they will be needed."""
from __future__ import annotations

import hashlib
import os
import pickle
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from made_once import SPECS, make_calibration, make_session, session_spec

from gtforge.synthetic import SyntheticTruth

SHARED = session_spec("session_dir", "session", n_board=7, n_scenes=3, scale=0.4, seed=11, depth_noise_mm=0.0,
                      image_noise=1.0)


def made_once_root(config) -> Path:
    """Where this run's shared folders are made (``made_once``): beside the workers' own temporary folders."""
    base = config._tmp_path_factory.getbasetemp()
    return (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "made-once"


def synthetic_session(request, spec: tuple[str, dict]) -> Path:
    """The synthetic session ``spec`` (``session_spec``) declares, made once per test run."""
    return make_session(made_once_root(request.config), *spec)


@pytest.fixture(scope="session")
def session_dir(request):
    """7 board poses + 3 fruit scenes at 0.4x resolution, noise-free depth (ZED 883x497, mech 768x480)."""
    return synthetic_session(request, SHARED)


@pytest.fixture(scope="session")
def T_zed_from_mech_true(session_dir):
    return np.array(SyntheticTruth.read(session_dir / "truth" / "rig_truth.yaml").T_zed_from_mech)


@pytest.fixture(scope="session")
def calibration(session_dir, request):
    """The shared session calibrated (its file, and the result as ``calibrate`` returned it), once per test run."""
    folder = make_calibration(made_once_root(request.config), session_dir)
    return folder / "calibration.yaml", pickle.loads((folder / "result.pickle").read_bytes())


@pytest.fixture(scope="session")
def true_calibration(session_dir, calibration, T_zed_from_mech_true, tmp_path_factory):
    """The calibration file with the exact extrinsic (isolates the later stages from calibration error)."""
    from gtforge.records.calibration import CalibrationFile

    c = CalibrationFile.read(calibration[0])
    c.rig = c.rig.with_extrinsic(T_zed_from_mech_true)
    path = tmp_path_factory.mktemp("calib_true") / "calibration.yaml"
    c.write(path)
    return path


@pytest.fixture(scope="session")
def dataset(session_dir, true_calibration, tmp_path_factory):
    from gtforge.build_dataset import build_dataset

    out = tmp_path_factory.mktemp("dataset")
    summary = build_dataset(session_dir, true_calibration, out, workers=1)
    return out, summary


SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def shared_data(name: str) -> Path:
    """A folder of real sensor data in ``../shared/data`` (beside the clone, as CI lays it out); the test skips,
    naming the folder, where it is absent."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"real data {path} is absent (CI lays ../shared/data beside the clone)")
    return path


# The real command as a user runs it, and what its tests check about the run (tests/cli/, tests/core/test_targets.py)
def gtforge(*args, umask=None, timeout=600):
    """Run the real command (``main()``: exit codes and one-line errors as a user sees them)."""
    def pre():
        if umask is not None:
            os.umask(umask)
    return subprocess.run([sys.executable, "-m", "gtforge.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, preexec_fn=pre)


def tree_digest(root):
    h = {}
    for dirpath, _, files in os.walk(root):
        for f in files:
            p = os.path.join(dirpath, f)
            h[os.path.relpath(p, root)] = hashlib.sha256(open(p, "rb").read()).hexdigest()
    return h


def one_line_error(r):
    lines = [l for l in r.stderr.splitlines() if l.strip()]
    return len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in r.stderr


@pytest.hookimpl(trylast=True)  # after pytest's tmp_path plugin has set up the run's temporary folder
def pytest_configure(config):
    """gtforge's disk cache (``infra.disk_cache``) in this run's temporary folder, not the user's ``~/.cache``: tests
    start from an empty cache and leave nothing behind (child processes inherit it)."""
    from gtforge.infra.disk_cache import CACHE_ENV

    os.environ[CACHE_ENV] = str(config._tmp_path_factory.getbasetemp() / "disk-cache")
    # The commands the tests start and then Ctrl-C must start with Ctrl-C in effect, as from a terminal; a suite started
    # in the background of a script (`make test &`) has it ignored, which they would inherit and keep (gtforge.cli.main)
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


PREFETCH = "calibration"  # besides SPECS' fixtures: the shared session's calibration


@pytest.hookimpl(trylast=True)  # after -m / -k have deselected
def pytest_collection_modifyitems(session, config, items):
    """Light tests first, then the tests of each shared folder together, in the order a background process (started
    once per run) makes the folders."""
    order: list[str] = []
    for item in items:
        for f in item.fixturenames:
            if (f in SPECS or f == PREFETCH) and f not in order:
                order.append(f)

    def first_heavy(item) -> int:
        used = [order.index(f) for f in item.fixturenames if f in order]
        return min(used) if used else -1

    items.sort(key=first_heavy)
    if not order or config.option.collectonly or os.environ.get("PYTEST_XDIST_WORKER", "gw0") != "gw0":
        return
    root = made_once_root(config)
    jobs = [(str(root), "calib", SPECS["session_dir"]) if f == PREFETCH else (str(root), *SPECS[f]) for f in order]
    proc = subprocess.Popen([sys.executable, str(Path(__file__).with_name("made_once.py"))], stdin=subprocess.PIPE)
    proc.stdin.write(pickle.dumps(jobs))
    proc.stdin.close()
    config._gtforge_prefetch = proc


def pytest_sessionfinish(session, exitstatus):
    proc = getattr(session.config, "_gtforge_prefetch", None)
    if proc is not None and proc.poll() is None:  # the run ended first (a failure with -x, Ctrl-C)
        proc.terminate()
        proc.wait()
