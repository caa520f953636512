"""gtforge.precompile (run by scripts/setup.sh): afterwards a build finds every kernel it runs in numba's cache."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

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
    index = {p.name.split("-")[0] for p in cache.rglob("*.nbi")}
    # a kernel of each part of a build: the reader, both ZED views' rasterisation, the occlusion test, the sigma map,
    # the verification's render and cubic samples, the writers, the fork server's preload
    for kernel in ("captures._depth_mm", "formats._png_unfilter", "reproject._mesh_rows_stereo",
                   "reproject._disparity_nonoccluded", "uncertainty._sigma_kernel", "verify._render_kernel",
                   "verify._cubic_at", "formats._pfm_rows", "formats._kitti_png_rows", "pool_preload._first_compiled_call"):
        assert kernel in index, kernel
    before = _cache_state(cache)
    # a default build with two local workers (one numba thread each), on another session than precompile's (another
    # resolution, texture and fruit): numba would add an index entry for any new kernel or argument types
    r = subprocess.run([sys.executable, "-m", "gtforge.cli", "build-dataset", str(session_dir), "-c",
                        str(true_calibration), "-o", str(tmp_path / "dataset"), "--workers", "2"], env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "failed 0" in r.stdout
    assert _cache_state(cache) == before
