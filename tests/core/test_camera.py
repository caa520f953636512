import numpy as np
import pytest

from gtforge.core.camera import PinholeCamera, RectifiedStereo, Rig
from gtforge.core.geometry import T_from_rotvec, invert_T, transform_points
from gtforge.errors import InputError


def cam(dist=(0.0,) * 5):
    # non-square image, fx != fy, off-centre principal point
    return PinholeCamera(width_px=640, height_px=360, fx_px=500.0, fy_px=470.0, cx_px=301.7, cy_px=190.2,
                         dist_coeffs=list(dist))


@pytest.mark.parametrize("dist", [(0.0,) * 5, (-0.12, 0.09, 0.001, -0.0007, -0.02)])
def test_project_unproject_round_trip(dist):
    c = cam(dist)
    rng = np.random.default_rng(0)
    uv = np.stack([rng.uniform(0, 639, 500), rng.uniform(0, 359, 500)], axis=1)
    z = rng.uniform(300, 900, 500)
    pts = c.unproject(uv, z)
    np.testing.assert_allclose(pts[:, 2], z)
    np.testing.assert_allclose(c.project(pts), uv, atol=1e-6)


def test_projection_axes_and_pixel_centres():
    c = cam()
    # a point on the optical axis lands on the principal point; +x right, +y down
    np.testing.assert_allclose(c.project(np.array([[0, 0, 1000.0]])), [[301.7, 190.2]])
    uv = c.project(np.array([[10.0, 0, 1000.0], [0, 10.0, 1000.0]]))
    assert uv[0, 0] > 301.7 and abs(uv[0, 1] - 190.2) < 1e-9
    assert uv[1, 1] > 190.2 and abs(uv[1, 0] - 301.7) < 1e-9
    grid = c.ray_grid()
    assert grid.shape == (360, 640, 2)
    np.testing.assert_allclose(grid[5, 7], [(7 - 301.7) / 500.0, (5 - 190.2) / 470.0])


def test_scaled_keeps_pixel_centres_consistent():
    c = cam().scaled(0.5)
    assert (c.width_px, c.height_px) == (320, 180)
    # the image corner (-0.5, -0.5) maps to itself
    p = cam().unproject(np.array([[-0.5, -0.5]]), [1000.0])
    np.testing.assert_allclose(c.project(p), [[-0.5, -0.5]], atol=1e-9)


def test_stereo_depth_disparity_and_invalid():
    s = RectifiedStereo(left=cam(), baseline_mm=63.0, doffs_px=2.5)
    z = np.array([[500.0, np.nan, 0.0]])
    d = s.depth_to_disparity(z)
    assert d.dtype == np.float32
    np.testing.assert_allclose(d[0, 0], 500.0 * 63.0 / 500.0 - 2.5, rtol=1e-6)
    assert np.isnan(d[0, 1]) and np.isnan(d[0, 2])
    back = s.disparity_to_depth(np.array([d[0, 0], 0.0 - 2.5, -10.0]))
    np.testing.assert_allclose(back[0], 500.0, rtol=1e-6)
    assert np.isnan(back[1]) and np.isnan(back[2])  # never a huge depth from zero disparity


def test_rig_refuses_non_rigid_transform():
    T_zed_from_mech = T_from_rotvec([0.1, 0.0, 0.0], [1, 2, 3])
    s = RectifiedStereo(left=cam(), baseline_mm=63.0)
    Rig(zed=s, mech=cam(), T_zed_from_mech=T_zed_from_mech)
    bad = T_zed_from_mech.copy()
    bad[0, 0] = 2.0
    with pytest.raises(Exception, match="rigid"):
        Rig(zed=s, mech=cam(), T_zed_from_mech=bad)


def test_rig_file_round_trip_and_extra_field(tmp_path):
    T_zed_from_mech = T_from_rotvec([0.01, -0.1, 0.02], [115, 18, 4])
    r = Rig(zed=RectifiedStereo(left=cam(), baseline_mm=63.0), mech=cam((-0.1, 0.05, 0, 0, 0)),
            T_zed_from_mech=T_zed_from_mech)
    p = r.write(tmp_path / "rig.yaml")
    r2 = Rig.read(p)
    np.testing.assert_allclose(r2.T_zed_from_mech, T_zed_from_mech)
    np.testing.assert_allclose(transform_points(r2.T_mech_from_zed, transform_points(r2.T_zed_from_mech, [[1, 2, 3]])),
                               [[1, 2, 3]], atol=1e-9)
    p.write_text(p.read_text() + "unexpected_field: 1\n")
    with pytest.raises(InputError, match="unexpected_field"):
        Rig.read(p)


def test_invert_T():
    T_a_from_b = T_from_rotvec([0.3, -0.2, 0.1], [10, -20, 30])
    np.testing.assert_allclose(T_a_from_b @ invert_T(T_a_from_b), np.eye(4), atol=1e-12)
