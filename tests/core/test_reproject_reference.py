"""The fast reprojection kernels draw exactly what the slow float64 reference
(gtforge.core.ground_truth.reproject_reference) draws.

Bit for bit, NaN where NaN: on small synthetic scenes from the generator (a distorted depth camera denser than the
target, one sparser than it, noisy depth under a strict slant bound, an undistorted depth camera, both ZED views of the
one-pass stereo path) and on real data (Middlebury 2014 Motorcycle, as tests/core/test_real_reprojection.py uses it).
A speed change that moves any depth by one bit, or draws one pixel more or less, fails here (docs/pipeline.md,
"Speed work never changes results"). One numba thread throughout: the windowed multi-thread path is forced onto it
once here (its chunks, windows and merge), and tests/core/test_real_reprojection.py holds a real four-thread run to the
one-thread image. The two-thread path (two halves of the grid) is forced onto one thread here as well.
"""
from __future__ import annotations

import functools

import numba
import numpy as np
import pytest

from gtforge.core.camera import RectifiedStereo
from gtforge.core.ground_truth import reproject
from gtforge.core.ground_truth.reproject import ReprojectParams, project_depth_to_camera, reproject_to_zed
from gtforge.core.ground_truth.reproject_reference import project_depth_reference
from gtforge.synthetic import default_rig, lit_mask, random_fruit_scene, raycast_depth

MESH, SPLAT = ReprojectParams(mode="mesh"), ReprojectParams(mode="splat")


@pytest.fixture(autouse=True)
def one_thread():
    """One numba thread: the path a build worker takes (the windowed path is held to it elsewhere)."""
    previous = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(previous)


def assert_identical(fast: np.ndarray, ref: np.ndarray, what: str) -> None:
    assert fast.dtype == ref.dtype == np.float32 and fast.shape == ref.shape
    differ = ~((fast == ref) | (np.isnan(fast) & np.isnan(ref)))
    assert differ.sum() == 0, f"{what}: {differ.sum()} pixels differ from the float64 reference"
    np.testing.assert_array_equal(fast, ref)  # the same, with numpy's own NaN-aware comparison
    assert np.isfinite(ref).sum() > 1000  # a real comparison, not two empty images


@functools.lru_cache(maxsize=1)
def small_scene():
    """The benchmark's scene (bench_reproject.scene_depth) at 0.2x: a 384x240 distorted depth camera -> 442x248."""
    rig = default_rig(0.2)
    rng = np.random.default_rng(0)
    scene = random_fruit_scene(rng, rig, 0)
    z, _, p = raycast_depth(scene, rig.mech, rig.T_mech_from_world)
    hit = np.isfinite(z)
    lit = np.zeros_like(hit)
    lit[hit] = lit_mask(scene, rig, p[hit])
    return rig, np.where(hit & lit, z, np.nan).astype(np.float32)


def check_both_modes(depth, mech, T_cam_from_depth, cam, mesh=MESH, what=""):
    fast, fast_span = project_depth_to_camera(depth, mech, T_cam_from_depth, cam, mesh, return_span=True)
    ref, ref_span = project_depth_reference(depth, mech, T_cam_from_depth, cam, mesh, return_span=True)
    assert_identical(fast, ref, f"{what} mesh")
    assert_identical(fast_span, ref_span, f"{what} mesh span_mm")
    splat = ReprojectParams(mode="splat", max_slant_deg=mesh.max_slant_deg, abs_tol_mm=mesh.abs_tol_mm)
    assert_identical(project_depth_to_camera(depth, mech, T_cam_from_depth, cam, splat),
                     project_depth_reference(depth, mech, T_cam_from_depth, cam, splat), f"{what} splat")


def test_synthetic_distorted_depth_camera():
    rig, depth = small_scene()
    assert rig.mech.has_distortion
    check_both_modes(depth, rig.mech, rig.T_zed_from_mech, rig.zed.left, what="synthetic")


def test_synthetic_target_denser_than_the_depth_grid():
    """Most quads hold several pixel centres: the kernels' general triangle loop instead of the one-pixel path."""
    rig, depth = small_scene()
    check_both_modes(depth, rig.mech, rig.T_zed_from_mech, rig.zed.left.scaled(2.5), what="dense target")


def test_synthetic_noisy_depth_strict_slant_bound():
    """Noise puts many edges near the continuity bound, so the drawn/rejected decisions are exercised."""
    rig, depth = small_scene()
    noisy = (depth + np.random.default_rng(3).normal(0.0, 0.4, depth.shape)).astype(np.float32)
    noisy[::17, ::13] = -5.0  # invalid depths other than NaN: negative ...
    noisy[5::23, 7::19] = 0.0  # ... zero
    noisy[9::29, 3::31] = np.inf  # ... and infinite
    params = ReprojectParams(mode="mesh", max_slant_deg=70.0, abs_tol_mm=0.1)
    check_both_modes(noisy, rig.mech, rig.T_zed_from_mech, rig.zed.left, params, what="noisy")


def test_synthetic_undistorted_depth_camera():
    rig, depth = small_scene()
    mech = rig.mech.model_copy(update={"dist_coeffs": [0.0] * 5})
    assert not mech.has_distortion
    check_both_modes(depth, mech, rig.T_zed_from_mech, rig.zed.left, what="undistorted")


def test_stereo_one_pass_both_views():
    """reproject_to_zed's one-pass path (one thread, mesh) draws both ZED views as the reference does."""
    rig, depth = small_scene()
    zed = rig.zed.model_copy(update={"doffs_px": 3.25})
    sd = reproject_to_zed(depth, rig.mech, rig.T_zed_from_mech, zed, MESH, left_span=True)
    ref_l, ref_span = project_depth_reference(depth, rig.mech, rig.T_zed_from_mech, zed.left, MESH, return_span=True)
    ref_r = project_depth_reference(depth, rig.mech, zed.T_zedr_from_zed @ rig.T_zed_from_mech, zed.right, MESH)
    assert_identical(sd.depth_mm, ref_l, "stereo left")
    assert_identical(sd.span_mm, ref_span, "stereo left span_mm")
    assert_identical(sd.depth_right_mm, ref_r, "stereo right")


def motorcycle():
    from test_real_reprojection import motorcycle as load  # skips where ../shared/data is absent

    return load()


def test_middlebury_motorcycle():
    """Real depth, a rectified pair: nearly every pixel centre lies on a grid edge two quads share, so the z-buffer's
    tie rule (the first quad wins among equal depths) decides span_mm at 220,180 pixels."""
    z0, cam0, cam1, T_cam1_from_cam0, _, _ = motorcycle()
    check_both_modes(z0, cam0, T_cam1_from_cam0, cam1, what="Middlebury Motorcycle")


@pytest.mark.slow
def test_the_comparison_catches_float32_rays(monkeypatch):
    """The guard has teeth: the kernels fed float32-rounded ray planes (issue #26's speed change) differ from the
    reference on the real scene: measured 2026-12-02, mesh 18,173 pixels differ, 4,564 of them holes the reference
    fills (splat: 6 pixels)."""
    z0, cam0, cam1, T_cam1_from_cam0, _, _ = motorcycle()
    rx, ry = reproject._ray_planes(cam0.model_dump_json())
    rounded = (rx.astype(np.float32).astype(np.float64), ry.astype(np.float32).astype(np.float64))
    monkeypatch.setattr(reproject, "_ray_planes", lambda cam_json: rounded)
    fast = project_depth_to_camera(z0, cam0, T_cam1_from_cam0, cam1, MESH)
    ref = project_depth_reference(z0, cam0, T_cam1_from_cam0, cam1, MESH)
    differ = ~((fast == ref) | (np.isnan(fast) & np.isnan(ref)))
    assert differ.sum() > 1000 and np.isnan(fast).sum() > np.isnan(ref).sum()  # the float32 rays lost pixels


def test_windowed_path_on_one_thread(monkeypatch):
    """The windowed path (chunks of grid rows rasterised into windows of target rows, merged by a per-pixel minimum)
    forced on the one thread here: the same images as the reference, span_mm included (the merge keeps the first
    window's span among equal depths, as the reference keeps the first quad's)."""
    monkeypatch.setattr(reproject, "MIN_PARALLEL_THREADS", 1)
    rig, depth = small_scene()
    check_both_modes(depth, rig.mech, rig.T_zed_from_mech, rig.zed.left, what="windowed synthetic")
    z0, cam0, cam1, T_cam1_from_cam0, _, _ = motorcycle()
    check_both_modes(z0, cam0, T_cam1_from_cam0, cam1, what="windowed Middlebury Motorcycle")


def test_two_halves_path_on_one_thread(monkeypatch):
    """The two-thread path (the grid's rows in two halves, the second drawn into the rows of a second buffer it reaches
    and merged by a per-pixel minimum, the first half's on a tie; mesh and splat) forced on the one thread here: the
    same images as the reference, span_mm included; also upside down, where the second half's rows lie above the
    first's, and where the grid's second half holds no valid depth (nothing to merge)."""
    monkeypatch.setattr(reproject, "HALVES_MIN_THREADS", 1)
    rig, depth = small_scene()
    check_both_modes(depth, rig.mech, rig.T_zed_from_mech, rig.zed.left, what="halves synthetic")
    left = rig.zed.left
    flipped = left.model_copy(update={"cx_px": left.width_px - 1 - left.cx_px,
                                      "cy_px": left.height_px - 1 - left.cy_px})
    check_both_modes(depth, rig.mech, np.diag([-1.0, -1.0, 1.0, 1.0]) @ rig.T_zed_from_mech, flipped,
                     what="halves upside down")
    top_only = depth.copy()
    top_only[depth.shape[0] // 2:] = np.nan
    check_both_modes(top_only, rig.mech, rig.T_zed_from_mech, rig.zed.left, what="halves, second half empty")
    z0, cam0, cam1, T_cam1_from_cam0, _, _ = motorcycle()
    check_both_modes(z0, cam0, T_cam1_from_cam0, cam1, what="halves Middlebury Motorcycle")


@pytest.mark.parametrize("upside_down", [False, True])
def test_kernels_ignore_what_the_output_held(upside_down):
    """The kernels set each output row to NaN just before the first point or triangle reaches it (no full-image fill
    beforehand): buffers that start at 0 mm, a depth that would win every z-buffer test and show wherever a row was
    reached before it was reset or never reset at all, still give the reference's images. Upside down (the target
    camera rolled 180 degrees), the grid's first rows land on the image's last rows."""
    rig, depth = small_scene()
    mech, zed, T_zed_from_mech = rig.mech, rig.zed, rig.T_zed_from_mech
    if upside_down:
        T_zed_from_mech = np.diag([-1.0, -1.0, 1.0, 1.0]) @ T_zed_from_mech
        left = zed.left
        flipped = left.model_copy(update={"cx_px": left.width_px - 1 - left.cx_px,
                                          "cy_px": left.height_px - 1 - left.cy_px})
        zed = zed.model_copy(update={"left": flipped})
    cam = zed.left
    R, t = np.ascontiguousarray(T_zed_from_mech[:3, :3]), np.ascontiguousarray(T_zed_from_mech[:3, 3])
    rx, ry = reproject._ray_planes(mech.model_dump_json())
    k1, k2 = reproject._slant_bounds(mech, MESH)
    H, W, Hm = cam.height_px, cam.width_px, depth.shape[0]
    intrinsics = (cam.fx_px, cam.fy_px, cam.cx_px, cam.cy_px)
    splat = np.zeros((H, W), np.float32)
    reproject._splat_rows(splat, 0, depth, rx, ry, R, t, *intrinsics, 0, Hm)
    assert_identical(splat, project_depth_reference(depth, mech, T_zed_from_mech, cam, SPLAT), "splat into zeros")
    mesh, span = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)
    reproject._mesh_rows(mesh, span, True, 0, 0, H - 1, depth, rx, ry, R, t, *intrinsics, k1, k2, MESH.abs_tol_mm, 0,
                         Hm - 1)
    ref, ref_span = project_depth_reference(depth, mech, T_zed_from_mech, cam, MESH, return_span=True)
    assert_identical(mesh, ref, "mesh into zeros")
    assert_identical(span, ref_span, "mesh span_mm into zeros")
    # the two halves: the first into zeros, the second into a buffer of zeros of which only the rows it reaches are read
    halves, hspan = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)
    aux, saux, window = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32), np.zeros(2, np.int64)
    reproject._mesh_halves(halves, hspan, aux, saux, True, window, depth, rx, ry, R, t, *intrinsics, k1, k2,
                           MESH.abs_tol_mm, (Hm - 1) // 2)
    reproject._merge_window(halves, hspan, aux, saux, True, window[0], window[1])
    assert 0 < window[1] - window[0] < H  # (a window, not the whole image)
    assert_identical(halves, ref, "halves into zeros")
    assert_identical(hspan, ref_span, "halves span_mm into zeros")
    splat_halves, aux, window = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32), np.zeros(2, np.int64)
    reproject._splat_halves(splat_halves, aux, window, depth, rx, ry, R, t, *intrinsics, Hm // 2)
    one = np.zeros((1, 1), np.float32)
    reproject._merge_window(splat_halves, one, aux, one, False, window[0], window[1])
    assert 0 < window[1] - window[0] < H
    assert_identical(splat_halves, splat, "splat halves into zeros")
    if not upside_down:  # the one-pass stereo path (the right view differs from the left by a shift along x only)
        T_zedr_from_mech = zed.T_zedr_from_zed @ T_zed_from_mech
        left, right = np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)
        reproject._mesh_rows_stereo(left, np.zeros((1, 1), np.float32), False, right, depth, rx, ry, R, t,
                                    *intrinsics, np.ascontiguousarray(T_zedr_from_mech[:3, 3]), zed.right.cx_px, k1, k2,
                                    MESH.abs_tol_mm)
        assert_identical(left, ref, "stereo left into zeros")
        assert_identical(right, project_depth_reference(depth, mech, T_zedr_from_mech, zed.right, MESH),
                         "stereo right into zeros")


def test_middlebury_motorcycle_stereo_one_pass():
    """reproject_to_zed's one-pass path on real depth: view 0's depth into a rectified pair whose left camera is view 0
    itself (every grid point lands on a pixel centre: ties everywhere) and whose right camera is view 1."""
    from test_real_reprojection import BASELINE_MM, CX0_PX, CX1_PX

    z0, cam0, cam1, _, _, _ = motorcycle()
    zed = RectifiedStereo(left=cam0, baseline_mm=BASELINE_MM, doffs_px=CX1_PX - CX0_PX)
    assert zed.right == cam1
    sd = reproject_to_zed(z0, cam0, np.eye(4), zed, MESH, left_span=True)
    ref_l, ref_span = project_depth_reference(z0, cam0, np.eye(4), zed.left, MESH, return_span=True)
    assert_identical(sd.depth_mm, ref_l, "Middlebury stereo left")
    assert_identical(sd.span_mm, ref_span, "Middlebury stereo left span_mm")
    assert_identical(sd.depth_right_mm, project_depth_reference(z0, cam0, zed.T_zedr_from_zed, zed.right, MESH),
                     "Middlebury stereo right")


def test_a_child_forked_after_the_parallel_kernels_reprojects_as_its_parent(tmp_path):
    """A child forked from a process whose numba ran its OpenMP parallel loops (the two halves with two threads) was
    stopped by numba at its first parallel loop (SIGTERM: GNU OpenMP is not fork-safe), as in a ``multiprocessing``
    pool forked after the parent reprojected. Such a child now runs the one-thread kernels: the same images as its
    parent's, for the mesh, the splat and a depth camera with another lens (its undistortion's parallel loop)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    paths = [str(Path(__file__).parent), str(Path(__file__).parents[1])]
    script = f"""
import os, sys
sys.path[:0] = {paths!r}
import numba, numpy as np
import test_reproject_reference as t
from gtforge.core.ground_truth.reproject import project_depth_to_camera
assert numba.get_num_threads() == 2
rig, depth = t.small_scene()
other = rig.mech.model_copy(update={{"dist": [0.05, -0.02, 0.0, 0.0, 0.0]}})
def images():
    return [project_depth_to_camera(depth, cam, rig.T_zed_from_mech, rig.zed.left, p)
            for cam in (rig.mech, other) for p in (t.MESH, t.SPLAT)]
parent = images()[:2]  # (the parallel loops run here; the other lens is left for the child)
if numba.threading_layer() != "omp":
    sys.exit(3)
pid = os.fork()
if pid == 0:
    np.savez({str(tmp_path / "child.npz")!r}, *images())
    os._exit(0)
_, status = os.waitpid(pid, 0)
print("child", status)
np.savez({str(tmp_path / "parent.npz")!r}, *images())
"""
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                       env={**os.environ, "NUMBA_NUM_THREADS": "2"})
    if r.returncode == 3:
        pytest.skip("numba's OpenMP threading layer (the one that is not fork-safe) is not the one loaded here")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "child 0" in r.stdout, (r.stdout, r.stderr[-2000:])  # not stopped by a signal
    child, parent = np.load(tmp_path / "child.npz"), np.load(tmp_path / "parent.npz")
    assert len(child.files) == 4
    for name in child.files:
        np.testing.assert_array_equal(child[name], parent[name])
