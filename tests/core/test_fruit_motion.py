"""The fruit motion's parameters and its sigma map (gtforge.core.alignment.fruit_motion,
gtforge.dataset.motion_compensation) against exact geometry: a sphere's depth map, moved analytically."""
import numpy as np

from gtforge.core.alignment.fruit_motion import FruitMotionEstimate, so3_exp
from gtforge.core.camera import PinholeCamera, RectifiedStereo, Rig
from gtforge.dataset.motion_compensation import motion_sigma_px


def _sphere_depth(cam: PinholeCamera, centre: np.ndarray, radius: float) -> np.ndarray:
    v, u = np.mgrid[0:cam.height_px, 0:cam.width_px]
    r = np.stack([(u - cam.cx_px) / cam.fx_px, (v - cam.cy_px) / cam.fy_px, np.ones(u.shape)], axis=2)
    a = np.einsum("hwi,hwi->hw", r, r)
    b = -2 * r @ centre
    c = centre @ centre - radius ** 2
    disc = b * b - 4 * a * c
    return np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.nan)  # z, as r has z = 1


def _estimate(centre, rotvec, t, cov):
    return FruitMotionEstimate(np.asarray(centre, float), np.asarray(rotvec, float), np.asarray(t, float),
                               np.asarray(cov, float), 0, 0, True, 0.0, None, np.zeros((0, 3)))


def test_motion_parameters_round_trip_and_mahalanobis():
    """A motion's 4x4 read back in an estimate's parameters about its centroid; the squared Mahalanobis distance of
    the estimate to itself is 0, to a motion off by one sigma along one axis 1."""
    c = np.array([10.0, -20.0, 600.0])
    cov = np.diag([1e-4, 4e-4, 9e-4, 0.01, 0.04, 0.09])
    e = _estimate(c, [0.01, -0.02, 0.03], [1.0, -0.5, 0.2], cov)
    np.testing.assert_allclose(e.params_from_T(e.T_zed_moved_from_zed), np.r_[e.rotvec_rad, e.translation_mm],
                               atol=1e-12)
    assert abs(e.mahalanobis_sq(e.T_zed_moved_from_zed)) < 1e-18
    T_zed_moved_from_zed_shifted = e.T_zed_moved_from_zed.copy()
    T_zed_moved_from_zed_shifted[:3, 3] += [0.0, 0.2, 0.0]  # one sigma of t_y
    assert abs(e.mahalanobis_sq(T_zed_moved_from_zed_shifted) - 1.0) < 1e-9
    R = so3_exp([0.0, 0.0, 0.03])  # one sigma of omega_z, a left perturbation about the moved centroid
    T_zed_turned_from_zed_moved = np.eye(4)
    T_zed_turned_from_zed_moved[:3, :3] = R
    cm = c + e.translation_mm
    T_zed_turned_from_zed_moved[:3, 3] = cm - R @ cm
    assert abs(e.mahalanobis_sq(T_zed_turned_from_zed_moved @ e.T_zed_moved_from_zed) - 1.0) < 1e-6


def test_motion_sigma_is_the_disparity_change_of_the_moved_surface():
    """motion_sigma_px on a sphere: the 1-sigma disparity change at each pixel equals J C J^T with J the finite
    differences of the exact moved sphere's disparity at that pixel (away from the silhouette, within 2 %)."""
    cam = PinholeCamera(width_px=160, height_px=120, fx_px=400.0, fy_px=400.0, cx_px=79.5, cy_px=59.5)
    zed = RectifiedStereo(left=cam, baseline_mm=63.0, doffs_px=0.0)
    rig = Rig(zed=zed, mech=cam, T_zed_from_mech=np.eye(4))
    centre, radius = np.array([5.0, -3.0, 500.0]), 60.0
    depth = _sphere_depth(cam, centre, radius).astype(np.float32)
    centroid = centre + [0.0, 0.0, -30.0]  # the fit's points lie on the cap towards the camera
    cov = np.diag([2e-5, 3e-5, 1e-5, 0.02, 0.01, 0.04])
    e = _estimate(centroid, np.zeros(3), np.zeros(3), cov)
    who = np.where(np.isfinite(depth), 1, 0)
    sig = motion_sigma_px(depth, who, {1: e}, rig)
    fB = zed.f_px * zed.baseline_mm
    J = []
    for i in range(6):
        h = 1e-4 if i < 3 else 1e-2
        d = np.zeros(6)
        d[i] = h
        R = so3_exp(d[:3])  # a left perturbation about the (moved) centroid: the sphere's centre moves
        c_new = R @ (centre - centroid) + centroid + d[3:]
        z = _sphere_depth(cam, c_new, radius)
        J.append((fB / z - fB / depth.astype(np.float64)) / h)
    J = np.stack(J, axis=2)
    expect = np.sqrt(np.einsum("hwi,ij,hwj->hw", J, cov, J))
    v, u = np.mgrid[0:cam.height_px, 0:cam.width_px]
    # the sphere's image: a circle of about 48 px radius; its inner part
    inner = np.hypot(u - (cam.cx_px + 400 * 5 / 500), v - (cam.cy_px - 400 * 3 / 500)) < 30
    assert inner.sum() > 2000 and np.all(sig[~np.isfinite(depth)] == 0)
    np.testing.assert_allclose(sig[inner], expect[inner], rtol=0.02)
