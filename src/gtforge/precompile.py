"""Compile the numba kernels a build uses into numba's on-disk cache, before the first real build; and those the other
stages of ``gtforge demo`` (calibrate, validate, calibrate-scale, refine, evaluate) would otherwise compile on first use
(the projection into one camera and refine's float32 spline samples: 5 s of a first validate and refine).

numba compiles a kernel on its first call after an install or a change of its source, and caches the machine code
beside the source (``__pycache__``; numba's own cache folder where that is read-only). With a cold cache, the first
``build-dataset`` pays for it in every worker process at once, each compiling the same kernels (benchmarks/RESULTS.md,
round 10). ``make setup`` (scripts/setup.sh) runs ``python -m gtforge.precompile`` once after installing; every later
process loads the kernels from the cache.

It also writes the package's bytecode (``compile_bytecode``): where Python does not write it on import (an editable
install run with ``PYTHONDONTWRITEBYTECODE``, as on CI, or a read-only checkout), every command, fork server and
worker would compile gtforge's source again (0.1-0.2 s of each command's start: benchmarks/RESULTS.md, "Round 6").

It builds one small synthetic scene (default options: verification, sigma map, right view) in this process, once
with one numba thread (the kernels a build worker runs when ``--workers`` = cores) and once with every core (the
parallel ones an in-process build runs), into a temporary folder it removes, and projects its depth into the ZED's
left camera with each thread count. After it, ``gtforge demo`` adds nothing to numba's cache (benchmarks/RESULTS.md,
"Round 10 (issue 39)").
"""
from __future__ import annotations

import compileall
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from gtforge.build_dataset import build_dataset
from gtforge.core.camera import Rig
from gtforge.core.ground_truth.reproject import ReprojectParams, project_depth_to_camera
from gtforge.infra.scheduling import cpu_count, limit_threads
from gtforge.io.captures import open_session
from gtforge.records.calibration import CalibrationFile
from gtforge.synthetic import SyntheticTruth, generate_session

# A kernel of each part of a build, by its full name: the reader, both ZED views' rasterisation, the occlusion test,
# the sigma map, the verification's render and cubic samples, the writers, the fork server's preload; and the
# projection into one camera, which validate, align-depth and the uncertainty's Monte Carlo run, not a build.
# tests/cli/test_precompile.py checks that each is in numba's cache after compile_kernels.
KERNELS = (
    "gtforge.io.captures._depth_mm", "gtforge.io.formats._png_unfilter",
    "gtforge.core.ground_truth.reproject._mesh_rows_stereo",
    "gtforge.core.ground_truth.reproject._disparity_nonoccluded", "gtforge.core.ground_truth.uncertainty._sigma_kernel",
    "gtforge.core.ground_truth.render._render_kernel", "gtforge.core.alignment.photometric._cubic_at",
    "gtforge.io.formats._pfm_invalid_to_inf",
    "gtforge.io.formats._kitti_png_rows", "gtforge.infra.pool_preload._first_compiled_call",
    "gtforge.core.lens._undistort_kernel_serial", "gtforge.core.bspline._resample_homography",
    "gtforge.core.bspline._samples", "gtforge.core.ground_truth.reproject._mesh_rows",
)


def compile_bytecode(package_dir: Path | None = None) -> int:
    """Write the bytecode (``__pycache__/*.pyc``) of every module under ``package_dir`` (default: gtforge's own folder)
    that lacks it or whose source changed. Returns how many modules then have a bytecode file; a folder this process
    may not write to is left as it is (Python compiles its source on import, as before)."""
    import importlib.util

    root = Path(package_dir) if package_dir is not None else Path(__file__).resolve().parent
    compileall.compile_dir(root, quiet=2)
    return sum(Path(importlib.util.cache_from_source(str(p))).is_file() for p in root.rglob("*.py"))


def compile_kernels(scale: float = 0.25) -> float:
    """Build one synthetic scene at ``scale`` (of the ZED Mini's 2208x1242) with one thread and with every core, so
    that numba compiles and caches each kernel the build runs. Returns the seconds it took."""
    import numba

    import gtforge.infra.pool_preload  # noqa: F401  (its kernel: what a local pool's fork server loads)
    from gtforge.core import lens

    t0 = time.perf_counter()
    # the one-thread undistortion: the fork server and the workers run it (NUMBA_NUM_THREADS = 1 in their environment),
    # this process, whose numba may run more, does not choose it by itself
    lens.undistort(np.zeros((1, 2)), [0.1, 0.0, 0.0, 0.0], serial=True)
    # the verification's kernels for a work factor of 2 (full-resolution ZED images), which the small scene below
    # (factor 1) does not run: the non-occlusion of 2x2 blocks and the window's disparity
    from gtforge.dataset.scene_verification import _all_of_2x2, _disparity_and_range

    _all_of_2x2(np.ones((4, 8), np.bool_), 0, 2, np.empty((2, 2), np.bool_))
    _disparity_and_range(np.ones((2, 2), np.float32), 1.0, 0.0, np.empty((2, 2), np.float32))
    # the right image's resampling, which a calibration that corrects the right camera (calibrate's
    # self-rectification, calibrate-scale's yaw) makes every scene run, and calibrate-scale's own samples
    from gtforge.core import bspline

    rgb = np.zeros((12, 16, 3), np.uint8)
    bspline.resample_homography(rgb, np.eye(3))
    bspline.resample(rgb, np.zeros(1), np.zeros(1), (1, 1))
    bspline.sample(bspline.coefficients(np.zeros((12, 16, 3), np.float32)), np.zeros(1), np.zeros(1))
    # refine's samples of the ZED image's float32 coefficients (the verification's, float64, come with the build)
    from gtforge.core.alignment.photometric import sample_spline

    sample_spline(np.zeros((12, 16), np.float32), np.zeros(1), np.zeros(1))
    with tempfile.TemporaryDirectory(prefix="gtforge-precompile-") as tmp:
        session_dir = generate_session(Path(tmp) / "session", n_board=0, n_scenes=1, scale=scale, supersample=1)
        session = open_session(session_dir)
        truth = SyntheticTruth.read(session_dir / "truth" / "rig_truth.yaml")
        rig = Rig(zed=session.zed, mech=session.mech, T_zed_from_mech=truth.T_zed_from_mech)
        calib_path = Path(tmp) / "calibration.yaml"
        CalibrationFile.known_extrinsic(rig, sigma_rot_deg=0.002, sigma_trans_mm=0.02).write(calib_path)
        threads, logger = numba.get_num_threads(), logging.getLogger("gtforge")
        level = logger.level
        logger.setLevel(logging.ERROR)  # one scene: the build warns that its val and test splits are empty
        try:
            depth_mm = session.load_capture(session.capture_dirs("scenes")[0], need_right=False,
                                            decode_images=False).depth_mm
            for n in sorted({1, min(cpu_count(), numba.config.NUMBA_NUM_THREADS)}):
                limit_threads(n)
                build_dataset(session_dir, calib_path, Path(tmp) / f"dataset_{n}", workers=1)
                for span in (False, True):  # (validate without the span, the uncertainty with it)
                    project_depth_to_camera(depth_mm, rig.depth_camera, rig.T_zed_from_depth, rig.zed.left,
                                            ReprojectParams(), return_span=span)
        finally:
            limit_threads(threads)
            logger.setLevel(level)
    return time.perf_counter() - t0


def main() -> int:
    compile_bytecode()
    print("gtforge: compiling the build's kernels into numba's cache (once after an install; under a minute)",
          flush=True)
    print(f"gtforge: kernels compiled and cached in {compile_kernels():.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
