"""The disk cache of arrays (``infra.disk_cache``) and the ray grids kept in it (``camera.PinholeCamera.ray_grid``):
a cached array is bit-identical to the computed one, or it is not used."""
from __future__ import annotations

import os
import stat

import numpy as np
import pytest
from tests.conftest import shared_data

from gtforge.core import camera
from gtforge.core.camera import PinholeCamera
from gtforge.infra import disk_cache
from gtforge.infra.disk_cache import CACHE_ENV


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_round_trip_is_exact_and_read_only(cache):
    a = np.random.default_rng(3).normal(size=(7, 5, 2))
    assert disk_cache.load_array("k", "key1") is None
    disk_cache.store_array("k", "key1", a)
    b = disk_cache.load_array("k", "key1")
    assert b.dtype == a.dtype and b.shape == a.shape and b.tobytes() == a.tobytes()
    assert not b.flags.writeable
    assert disk_cache.load_array("k", "key2") is None  # another key
    (f,) = (cache / "k").iterdir()
    assert stat.S_IMODE(f.stat().st_mode) == 0o666 & ~_umask()  # a normal file: the umask, not mkstemp's 0600
    assert not [p for p in (cache / "k").iterdir() if p.name.startswith(".")]  # no temporary file left


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def test_a_corrupted_or_truncated_file_is_dropped(cache):
    a = np.arange(1000, dtype=np.float64)
    disk_cache.store_array("k", "key", a)
    (f,) = (cache / "k").iterdir()
    data = bytearray(f.read_bytes())
    data[-8] ^= 1  # one bit of the last value
    f.write_bytes(bytes(data))
    assert disk_cache.load_array("k", "key") is None and not f.exists()
    disk_cache.store_array("k", "key", a)
    (f,) = (cache / "k").iterdir()
    f.write_bytes(f.read_bytes()[:-100])
    assert disk_cache.load_array("k", "key") is None and not f.exists()


def test_a_dead_writers_temporary_file_goes_once_stale(cache):
    """A process killed while it stored an array (the unused fork server killed at exit) leaves its hidden temporary
    file; the next store removes it once no writer can still be using it (an hour old), and never a fresh one."""
    disk_cache.store_array("k", "key", np.ones(4))
    (cache / "k" / ".key-abc.x1.tmp.npy").write_bytes(b"half")  # as atomic_path names them
    (cache / "k" / ".key-abc.x2.tmp.npy").write_bytes(b"writing")
    os.utime(cache / "k" / ".key-abc.x1.tmp.npy", (1000.0, 1000.0))
    disk_cache.store_array("k", "key2", np.zeros(4))
    names = sorted(p.name for p in (cache / "k").iterdir())
    assert ".key-abc.x1.tmp.npy" not in names and ".key-abc.x2.tmp.npy" in names and len(names) == 3


def test_least_recently_used_files_go_and_empty_setting_disables(cache, monkeypatch):
    for k in range(disk_cache.KEEP_FILES + 2):
        disk_cache.store_array("k", f"key{k}", np.full(3, float(k)))
        os.utime(next((cache / "k").glob(f"key{k}-*")), (1000.0 + k, 1000.0 + k))  # distinct times, oldest first
    assert len(list((cache / "k").iterdir())) == disk_cache.KEEP_FILES
    assert disk_cache.load_array("k", "key0") is None and disk_cache.load_array("k", "key1") is None
    assert disk_cache.load_array("k", f"key{disk_cache.KEEP_FILES + 1}")[0] == disk_cache.KEEP_FILES + 1
    monkeypatch.setenv(CACHE_ENV, "")
    assert disk_cache.cache_dir() is None
    disk_cache.store_array("k2", "key", np.ones(2))
    assert not (cache / "k2").exists() and disk_cache.load_array("k", "key5") is None
    monkeypatch.delenv(CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache.parent / "xdg"))
    assert disk_cache.cache_dir() == cache.parent / "xdg" / "gtforge"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/xdg")  # invalid: ignored
    monkeypatch.setenv("HOME", str(cache.parent / "home"))
    assert disk_cache.cache_dir() == cache.parent / "home" / ".cache" / "gtforge"


def test_an_unwritable_cache_costs_only_the_computation(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(CACHE_ENV, str(blocker / "cache"))
    disk_cache.store_array("k", "key", np.ones(2))  # no exception
    assert disk_cache.load_array("k", "key") is None


def _clear_memory_caches() -> None:
    camera._ray_planes_cached.cache_clear()
    camera._ray_grid_cached.cache_clear()


def _ray_grid_twice(cam: PinholeCamera, cache) -> tuple[np.ndarray, np.ndarray]:
    _clear_memory_caches()
    computed = cam.ray_grid()
    assert len(list((cache / "ray_grid").iterdir())) == 1
    _clear_memory_caches()
    return computed, cam.ray_grid()


def test_ray_grid_from_the_disk_cache_is_the_computed_one(cache, monkeypatch):
    monkeypatch.setattr(camera, "RAY_GRID_DISK_CACHE_MIN_PX", 0)  # (at the default, only full-resolution grids)
    cam = PinholeCamera(width_px=320, height_px=200, fx_px=260.0, fy_px=255.0, cx_px=161.3, cy_px=98.7,
                        dist_coeffs=[-0.12, 0.09, 0.001, -0.0007, -0.02])
    computed, cached = _ray_grid_twice(cam, cache)
    assert cached.tobytes() == computed.tobytes() and cached.shape == (200, 320, 2) and not cached.flags.writeable
    # the exact grid, not merely a stored one: every pixel centre distorts back onto itself
    uv = cam.project(np.concatenate([cached.reshape(-1, 2), np.ones((64000, 1))], axis=1))
    vv, uu = np.mgrid[0:200, 0:320]
    assert np.abs(uv - np.stack([uu.ravel(), vv.ravel()], axis=1)).max() < 1e-9
    other = cam.model_copy(update={"cx_px": 161.4})  # another camera: another entry
    _clear_memory_caches()
    assert other.ray_grid()[0, 0, 0] != cached[0, 0, 0]
    assert len(list((cache / "ray_grid").iterdir())) == 2
    assert not PinholeCamera(width_px=8, height_px=4, fx_px=5.0, fy_px=5.0, cx_px=3.5, cy_px=1.5).has_distortion


def test_ray_planes_are_the_grid_split_and_stored_as_planes(cache, monkeypatch):
    """The reprojection reads the grid as two C-contiguous planes, which the disk cache keeps as they are (read back
    without a split): the grid's own values, from a fresh computation and from the disk."""
    monkeypatch.setattr(camera, "RAY_GRID_DISK_CACHE_MIN_PX", 0)
    cam = PinholeCamera(width_px=96, height_px=64, fx_px=80.0, fy_px=81.0, cx_px=47.2, cy_px=31.9,
                        dist_coeffs=[0.08, -0.05, 0.0004, 0.0002, 0.01])
    _clear_memory_caches()
    planes = cam.ray_planes()
    (stored,) = (cache / "ray_grid").iterdir()
    assert np.load(stored).shape == (2, 64, 96)  # the planes, not the (H, W, 2) grid
    _clear_memory_caches()
    grid = cam.ray_grid()  # from the disk this time
    read = cam.ray_planes()
    for p in (planes, read):
        assert p.shape == (2, 64, 96) and p.dtype == np.float64 and p.flags.c_contiguous and not p.flags.writeable
        assert p[0].tobytes() == grid[..., 0].tobytes() and p[1].tobytes() == grid[..., 1].tobytes()
    assert grid.flags.c_contiguous and not grid.flags.writeable
    assert np.ptp(grid[..., 0]) > 1.0 and np.ptp(grid[..., 1]) > 0.7  # a real grid, not zeros


def test_real_azure_kinect_ray_grid_from_the_disk_cache(cache):
    """The real Azure Kinect depth camera (640x576, OpenCV's rational model), at the default size threshold scaled
    2x (1280x1152: above it), computed then read back: the same bytes."""
    from gtforge.io.vendors import read_kinect_calibration

    k = read_kinect_calibration(shared_data("azure-kinect-frame") / "calibration.json", "NFOV_UNBINNED", "720P")
    cam = k.depth.scaled(2.0)
    assert cam.has_distortion and cam.width_px * cam.height_px >= camera.RAY_GRID_DISK_CACHE_MIN_PX
    computed, cached = _ray_grid_twice(cam, cache)
    assert cached.tobytes() == computed.tobytes()
    assert np.isfinite(computed).mean() > 0.9
