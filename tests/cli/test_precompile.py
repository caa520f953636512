"""gtforge.precompile (run by scripts/setup.sh): afterwards a build finds every kernel it runs in numba's cache."""
from __future__ import annotations

import importlib
import importlib.util
import os
import subprocess
import sys

import pytest

from gtforge.precompile import KERNELS

pytestmark = pytest.mark.slow  # compiles every kernel into a cold cache, then builds the shared session


def _cache_state(cache):
    return {p.relative_to(cache): p.stat().st_mtime_ns for p in cache.rglob("*") if p.is_file()}


def test_after_precompile_a_build_compiles_nothing(tmp_path, session_dir, true_calibration):
    cache = tmp_path / "numba_cache"  # a cache of its own: cold, whatever this checkout's __pycache__ holds
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    r = subprocess.run([sys.executable, "-m", "gtforge.precompile"], env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "kernels compiled and cached in" in r.stdout and r.stderr == ""  # (no split warning for its one scene)
    index = {p.name.split("-")[0] for p in cache.rglob("*.nbi")}  # numba names them <file stem>.<function>-...
    for kernel in KERNELS:
        module, name = kernel.rsplit(".", 1)
        assert callable(getattr(importlib.import_module(module), name)), kernel  # the list names real kernels
        assert f"{module.rsplit('.', 1)[1]}.{name}" in index, kernel
    before = _cache_state(cache)
    # a default build with two local workers (one numba thread each), on another session than precompile's (another
    # resolution, texture and fruit): numba would add an index entry for any new kernel or argument types
    r = subprocess.run([sys.executable, "-m", "gtforge.cli", "build-dataset", str(session_dir), "-c",
                        str(true_calibration), "-o", str(tmp_path / "dataset"), "--workers", "2"], env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "failed 0" in r.stdout
    assert _cache_state(cache) == before
    # and with a calibration that corrects the right camera (calibrate-scale's yaw), as a user's: the right image
    # resampled in every scene (gtforge.core.bspline)
    from gtforge.core.camera import ScaleCorrections
    from gtforge.records.calibration import CalibrationFile

    c = CalibrationFile.read(true_calibration)
    c.rig = c.rig.model_copy(update={"scale_corrections": ScaleCorrections(zed_right_yaw_deg=0.0005)})
    c.write(tmp_path / "corrected.yaml")
    r = subprocess.run([sys.executable, "-m", "gtforge.cli", "build-dataset", str(session_dir), "-c",
                        str(tmp_path / "corrected.yaml"), "-o", str(tmp_path / "dataset_corrected"), "--workers", "2"],
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "failed 0" in r.stdout
    assert _cache_state(cache) == before



def test_compile_bytecode_writes_what_import_would_not(tmp_path):
    from gtforge.precompile import compile_bytecode

    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    for rel, src in (("__init__.py", "A_MM = 1\n"), ("sub/__init__.py", ""), ("sub/mod.py", "B_PX = 2.5\n")):
        (pkg / rel).write_text(src)
    pyc = [importlib.util.cache_from_source(str(pkg / rel)) for rel in ("__init__.py", "sub/__init__.py", "sub/mod.py")]
    assert compile_bytecode(pkg) == 3
    assert all(os.path.isfile(p) for p in pyc)
    # a changed source gets fresh bytecode (its header records the source's mtime); an unchanged one keeps its file
    kept = os.stat(pyc[0]).st_mtime_ns
    (pkg / "sub" / "mod.py").write_text("B_PX = 3.5  # changed\n")
    new_s = int(os.stat(pyc[2]).st_mtime) + 5
    os.utime(pkg / "sub" / "mod.py", (new_s, new_s))
    assert compile_bytecode(pkg) == 3
    assert os.stat(pyc[0]).st_mtime_ns == kept
    with open(pyc[2], "rb") as f:
        assert int.from_bytes(f.read(12)[8:12], "little") == new_s
