"""Shared fixtures: the synthetic sessions rendered once per test run, whichever pytest-xdist worker asks first
(``made_once``), with exact truth beside them."""
from __future__ import annotations

import fcntl
import hashlib
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

import gtforge.synthetic
from gtforge.synthetic import SyntheticTruth, generate_session

# the generator's version: its source (a change to it renders every cached session again)
GENERATOR_VERSION = hashlib.sha256(Path(gtforge.synthetic.__file__).read_bytes()).hexdigest()[:12]


def made_once(tmp_path_factory, name: str, make: Callable[[Path], object], **key) -> Path:
    """The folder ``make(folder)`` fills, made once per test run and shared by every worker of the run (pytest-xdist
    workers wait for the first to finish; a worker's own files go elsewhere). The folder name carries the generator's
    version and ``key`` (the arguments it was made with). Tests must not write into it: they copy it first."""
    base = tmp_path_factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "made-once"
    root.mkdir(exist_ok=True)
    digest = hashlib.sha256(repr((GENERATOR_VERSION, sorted(key.items()))).encode()).hexdigest()[:12]
    out = root / f"{name}-{digest}"
    with open(root / f"{name}-{digest}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / f"{name}-{digest}.done").exists():
            shutil.rmtree(out, ignore_errors=True)
            make(out)
            (root / f"{name}-{digest}.done").touch()
    return out


def synthetic_session(tmp_path_factory, name: str, **kwargs) -> Path:
    """``generate_session(folder, **kwargs)``, once per test run (``made_once``)."""
    return made_once(tmp_path_factory, name, lambda d: generate_session(d, **kwargs), **kwargs)


@pytest.fixture(scope="session")
def session_dir(tmp_path_factory):
    """7 board poses + 3 fruit scenes at 0.4x resolution, noise-free depth (ZED 883x497, mech 768x480)."""
    return synthetic_session(tmp_path_factory, "session", n_board=7, n_scenes=3, scale=0.4, seed=11,
                             depth_noise_mm=0.0, image_noise=1.0)


@pytest.fixture(scope="session")
def T_true(session_dir):
    return np.array(SyntheticTruth.read(session_dir / "truth" / "rig_truth.yaml").T_zed_from_mech)


@pytest.fixture(scope="session")
def calibration(session_dir, tmp_path_factory):
    from gtforge.calibrate import calibrate
    from gtforge.records.calibration import CalibrateParams

    def make(d):
        res = calibrate(session_dir, d / "calibration.yaml", CalibrateParams(use_depth=False))
        (d / "result.pickle").write_bytes(pickle.dumps(res))  # as calibrate returned it (report inputs included)

    folder = made_once(tmp_path_factory, "calib", make, session=str(session_dir))
    return folder / "calibration.yaml", pickle.loads((folder / "result.pickle").read_bytes())


@pytest.fixture(scope="session")
def true_calibration(session_dir, calibration, T_true, tmp_path_factory):
    """The calibration file with the exact extrinsic (isolates the later stages from calibration error)."""
    from gtforge.records.calibration import CalibrationFile

    c = CalibrationFile.read(calibration[0])
    c.rig = c.rig.with_extrinsic(T_true)
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
