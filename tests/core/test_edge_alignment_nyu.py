"""Edge alignment on a second real sensor of another kind: a Kinect v1 (PrimeSense structured light) raw frame of NYU
Depth V2 with the NYU toolbox's calibration (tests/data/nyu-kinect-frame; docs/cameras.md has the table).

The calibration as the toolbox applies it leaves the depth edges (-0.74, +0.16) px off the colour edges: the frame
determines no rotation to 0.3 px, and the factory pose is kept, said so. Two misreadings of the same file (the
translation's sign flipped; the rotation not inverted) put them 8.4 px and (4.4, 3.9) px off, diagonally: both are
found (the search widens, all rotations start together) and brought within 0.1 px (0.10, 0.05); the second's
rotation error, known exactly, is recovered within 2 sigma on every axis.
"""
from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from gtforge.core.camera import PinholeCamera
from gtforge.core.alignment.edge_alignment import align_color_to_depth
from gtforge.core.geometry import make_T

pytestmark = pytest.mark.slow  # three fits of a 640x480 frame, 1-2 s each

DATA = Path(__file__).parents[1] / "data" / "nyu-kinect-frame"


@functools.lru_cache(maxsize=1)
def frame():
    """(depth mm float32 NaN invalid, colour RGB, depth camera, colour camera, A, t_mm) as the toolbox reads them."""
    if not (DATA / "calibration.yaml").is_file():
        pytest.skip(f"{DATA} is absent")
    c = yaml.safe_load((DATA / "calibration.yaml").read_text())
    raw = cv2.imread(str(DATA / "depth_raw.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    depth = np.where(raw < 2047, 1000.0 * c["depth_param1"] / (c["depth_param2"] - raw), np.nan).astype(np.float32)
    color = cv2.cvtColor(cv2.imread(str(DATA / "color.jpg")), cv2.COLOR_BGR2RGB)

    def cam(k):  # MATLAB's 1-based pixel coordinates -> gtforge's (pixel centres at integers from 0)
        return PinholeCamera(width_px=640, height_px=480, fx_px=k["fx"], fy_px=k["fy"], cx_px=k["cx"] - 1,
                             cy_px=k["cy"] - 1, dist_coeffs=k["dist"])

    return depth, color, cam(c["depth"]), cam(c["rgb"]), np.array(c["r"]).reshape(3, 3), 1000.0 * np.array(c["t_m"])


def _rotvec_deg(R_a, R_b) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return np.degrees(Rotation.from_matrix(R_a @ R_b.T).as_rotvec())


def test_the_toolbox_calibration_is_kept_and_said_so():
    depth, color, dcam, ccam, A, t = frame()
    T_color_from_depth = make_T(np.linalg.inv(A), -t)
    res = align_color_to_depth(depth, dcam, color, ccam, T_color_from_depth)
    # measured: offset (-0.74, +0.16) px, 56 structures, no rotation to 0.3 px from this one frame
    assert np.hypot(*res.offset_before_px) < 1.0 and res.search_px == 6
    assert res.decision == "not determined" and "structures" in res.reason
    np.testing.assert_array_equal(np.array(res.T_color_from_depth), T_color_from_depth)


@pytest.mark.parametrize("reading", ["translation sign flipped", "rotation not inverted"])
def test_misread_calibrations_are_found(reading):
    depth, color, dcam, ccam, A, t = frame()
    R_true, t_true = np.linalg.inv(A), -t
    R, t_read = (R_true, t) if reading == "translation sign flipped" else (A, t_true)
    res = align_color_to_depth(depth, dcam, color, ccam, make_T(R, t_read))
    assert res.decision == "applied" and res.search_interior
    assert np.hypot(*res.offset_before_px) > 5 and np.hypot(*res.offset_after_px) < 0.2  # measured 0.05, 0.10
    if reading == "rotation not inverted":
        # measured (-4.36, +3.86) px before; (-0.472, -0.568, +0.771) +- (0.047, 0.075, 0.159) deg against the exact
        # (-0.421, -0.494, +0.578) deg
        truth = _rotvec_deg(R_true, R)
        assert np.all(np.abs(np.array(res.omega_deg) - truth) <= 2 * np.array(res.sigma_omega_deg))
    else:
        # measured (-8.42, -0.01) px before: 50 mm at 3.3 m, taken up by omega_y -0.888 +- 0.050 deg
        assert res.search_px == 12 and abs(res.omega_deg[1] + 50 / 3300 * 180 / np.pi) < 0.15
