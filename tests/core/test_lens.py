"""gtforge.core.lens against OpenCV: the forward model equals cv2.projectPoints for every coefficient count; the inverse
round-trips to 1e-9 (normalised) where OpenCV's fixed-point undistortion does not, and is NaN where no inverse
exists."""
import cv2
import numpy as np
import pytest

from gtforge.core import lens
from gtforge.core.camera import PinholeCamera

# non-trivial coefficients of every OpenCV model (k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 tau_x tau_y), tilt in rad
COEFFS_14 = [-0.21, 0.08, 0.0012, -0.0009, -0.015, 0.11, -0.02, 0.004, 0.0021, -0.0007, -0.0016, 0.0004,
             0.021, -0.017]
# the real Azure Kinect depth camera of tests/data/azure-kinect-frame (rational: k1..k6 strong, p1 p2 tiny)
KINECT_DEPTH = [0.5479397773742676, -0.020971370860934258, 2.0557534298859537e-05, -7.210415787994862e-05,
                -0.002652231603860855, 0.8896790742874146, 0.08613020926713943, -0.013910384848713875]
STRONG_RATIONAL = [2.0, 0.5, 0.001, -0.002, 0.01, 2.6, 1.5, 0.2]


def cam(n: int, coeffs=COEFFS_14, **kw) -> PinholeCamera:
    # non-square image, fx != fy, off-centre principal point
    args = {"width_px": 640, "height_px": 360, "fx_px": 420.0, "fy_px": 395.0, "cx_px": 331.7, "cy_px": 171.2}
    args.update(kw)
    return PinholeCamera(dist_coeffs=list(coeffs[:n]), **args)


def kinect_depth_nfov() -> PinholeCamera:
    # NFOV_UNBINNED intrinsics from the normalised calibration (1024x1024, crop (192, 180), half-pixel shift)
    return PinholeCamera(width_px=640, height_px=576, fx_px=0.4927808940410614 * 1024, fy_px=0.49290284514427185 * 1024,
                         cx_px=0.5129697918891907 * 1024 - 192 - 0.5, cy_px=0.5169235467910767 * 1024 - 180 - 0.5,
                         dist_coeffs=KINECT_DEPTH)


def image_points(c: PinholeCamera, n: int = 400, seed: int = 0) -> np.ndarray:
    """Random pixels plus the four corners and the edge midpoints of the image."""
    rng = np.random.default_rng(seed)
    w, h = c.width_px - 1, c.height_px - 1
    uv = np.stack([rng.uniform(0, w, n), rng.uniform(0, h, n)], axis=1)
    border = np.array([[0, 0], [w, 0], [0, h], [w, h], [w / 2, 0], [w / 2, h], [0, h / 2], [w, h / 2]], float)
    return np.concatenate([border, uv])


@pytest.mark.parametrize("n", [4, 5, 8, 12, 14])
def test_forward_equals_opencv(n):
    c = cam(n)
    rng = np.random.default_rng(n)
    # points in front of the camera, out to the image corners and a bit beyond
    xy = np.stack([rng.uniform(-0.9, 0.9, 500), rng.uniform(-0.55, 0.55, 500)], axis=1)
    z = rng.uniform(200, 3000, 500)
    pts = np.column_stack([xy * z[:, None], z])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), c.K, c.dist)
    ours = c.project(pts)
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), rtol=0, atol=1e-6)
    # the model is not trivial: the distortion moves points by many pixels
    plain = np.column_stack([c.fx_px * xy[:, 0] + c.cx_px, c.fy_px * xy[:, 1] + c.cy_px])
    assert np.abs(ours - plain).max() > 10.0


@pytest.mark.parametrize("n", [4, 5, 8, 12, 14])
def test_inverse_round_trips(n):
    c = cam(n)
    # pixels -> rays -> pixels, corners included
    uv = image_points(c)
    xy = c.undistort_to_normalized(uv)
    assert np.isfinite(xy).all()
    np.testing.assert_allclose(c.project(np.column_stack([xy, np.ones(len(xy))])), uv, rtol=0, atol=1e-9 * c.fx_px)
    # rays -> distorted -> rays: 1e-9 normalised
    back = lens.undistort(lens.distort(xy, c.dist_coeffs), c.dist_coeffs)
    np.testing.assert_allclose(back, xy, rtol=0, atol=1e-9)
    # an independent inverse: OpenCV's iteration, run to convergence, agrees on this mild lens (tilt included)
    ref = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), c.K, c.dist, None, None,
                                  (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)).reshape(-1, 2)
    np.testing.assert_allclose(xy, ref, rtol=0, atol=1e-9)


def test_kinect_depth_corners_where_opencv_default_undistort_is_off():
    """The real Azure Kinect depth lens: cv2.undistortPoints (its default few fixed-point iterations) is off by
    up to ~10 px at the NFOV image corners; gtforge's inverse reprojects to 1e-9 px."""
    c = kinect_depth_nfov()
    corners = np.array([[0, 0], [639, 0], [0, 575], [639, 575]], float)
    xy = c.undistort_to_normalized(corners)
    back = c.project(np.column_stack([xy, np.ones(4)]))
    np.testing.assert_allclose(back, corners, rtol=0, atol=1e-9)
    cv_default = cv2.undistortPoints(corners.reshape(-1, 1, 2), c.K, c.dist).reshape(-1, 2)
    err_px = np.abs(cv_default - xy).max(axis=1) * c.fx_px
    assert err_px.max() > 5.0  # measured 9.96 px at the top-left corner (0.0197 normalised)
    assert err_px.min() > 0.3  # every corner is off (measured 0.48 px at the best one)


def strong_rational() -> PinholeCamera:
    # image corners at 1.4-1.6 normalised radius, close to where this lens folds (1.74; 0.24 px inside at (639, 0))
    return PinholeCamera(width_px=640, height_px=480, fx_px=557.0, fy_px=540.29, cx_px=323.4, cy_px=236.8,
                         dist_coeffs=STRONG_RATIONAL)


def test_strong_rational_corners_where_opencv_iteration_fails():
    """A strong rational lens whose image corners lie near the end of its monotonic branch: cv2.undistortPoints
    is off by 50-130 px there, and OpenCV's fixed-point iteration converges so slowly that 200 iterations still
    miss; gtforge's damped Newton is exact."""
    c = strong_rational()
    corners = np.array([[0, 0], [639, 0], [0, 479], [639, 479]], float)
    xy = c.undistort_to_normalized(corners)
    assert np.isfinite(xy).all()
    assert (np.linalg.norm(xy, axis=1) < lens.valid_radius(c.dist_coeffs)).all()
    np.testing.assert_allclose(c.project(np.column_stack([xy, np.ones(4)])), corners, rtol=0, atol=1e-9)
    cv_default = cv2.undistortPoints(corners.reshape(-1, 1, 2), c.K, c.dist).reshape(-1, 2)
    assert (np.abs(cv_default - xy).max(axis=1) > 0.09).all()  # measured 0.10-0.24 normalised (55-130 px)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    cv_iter = cv2.undistortPointsIter(corners.reshape(-1, 1, 2), c.K, c.dist, None, None, crit).reshape(-1, 2)
    assert np.abs(cv_iter - xy).max() > 1e-6  # measured 6.4e-6 at (639, 0) after 200 iterations


@pytest.mark.parametrize("which", ["kinect", "strong"])
def test_ray_grid_of_a_full_image(which):
    c = kinect_depth_nfov() if which == "kinect" else strong_rational()
    grid = c.ray_grid()
    assert grid.shape == (c.height_px, c.width_px, 2) and grid.dtype == np.float64
    assert np.isfinite(grid).all()
    v, u = np.mgrid[0:c.height_px, 0:c.width_px]
    uv = c.project(np.column_stack([grid.reshape(-1, 2), np.ones(grid.shape[0] * grid.shape[1])]))
    np.testing.assert_allclose(uv, np.column_stack([u.ravel(), v.ravel()]), rtol=0, atol=1e-9)
    # rays go the right way: x grows with u, y with v, everywhere
    assert (np.diff(grid[..., 0], axis=1) > 0).all() and (np.diff(grid[..., 1], axis=0) > 0).all()
    assert c.ray_grid() is grid  # cached per camera


def test_nan_where_no_inverse_exists():
    """Barrel k1 = -0.5: r_d = r - 0.5 r^3 rises to 0.5443 at r = 0.8165 and folds back. Below the fold the
    inverse is the root on the monotonic branch (not the second pre-image beyond the fold); above it, NaN."""
    dist = [-0.5, 0.0, 0.0, 0.0, 0.0]
    r_fold = 1 / np.sqrt(1.5)
    assert lens.valid_radius(dist) == pytest.approx(r_fold, abs=1e-12)
    ang = np.deg2rad(np.array([0.0, 33.0, 141.0, 250.0]))
    rd_max = r_fold - 0.5 * r_fold ** 3
    for rd in (0.1, 0.4, 0.5, 0.99 * rd_max):
        xd = np.column_stack([rd * np.cos(ang), rd * np.sin(ang)])
        xy = lens.undistort(xd, dist)
        roots = np.roots([-0.5, 0.0, 1.0, -rd]).real
        main = roots[(roots > 0) & (roots < r_fold)].min()
        np.testing.assert_allclose(np.linalg.norm(xy, axis=1), main, rtol=0, atol=1e-9)
        np.testing.assert_allclose(lens.distort(xy, dist), xd, rtol=0, atol=1e-12)
    for rd in (1.01 * rd_max, 0.8, 3.0, 50.0):
        xd = np.column_stack([rd * np.cos(ang), rd * np.sin(ang)])
        assert np.isnan(lens.undistort(xd, dist)).all()
        # OpenCV returns finite numbers there, which do not map back to the pixel
        cv = cv2.undistortPoints(xd.reshape(-1, 1, 2), np.eye(3), np.array(dist)).reshape(-1, 2)
        assert np.isfinite(cv).all() and np.abs(lens.distort(cv, dist) - xd).max() > 1e-3
    # through the camera: pixels outside the field of this lens are NaN, the rest finite
    c = cam(5, coeffs=dist, fx_px=250.0, fy_px=240.0)
    grid = c.ray_grid()
    rd_px = np.hypot((np.arange(640)[None, :] - c.cx_px) / c.fx_px, (np.arange(360)[:, None] - c.cy_px) / c.fy_px)
    assert np.isnan(grid[rd_px > rd_max + 1e-9]).all() and np.isfinite(grid[rd_px < rd_max - 1e-9]).all()
    assert (rd_px > rd_max).sum() > 1000  # the case is exercised


def test_nan_input_zero_distortion_and_valid_radius():
    xy = np.array([[0.1, -0.2], [np.nan, 0.3], [0.0, 0.0]])
    out = lens.undistort(xy, COEFFS_14)
    assert np.isnan(out[1]).all() and np.isfinite(out[[0, 2]]).all()
    np.testing.assert_allclose(out[2], [0.0, 0.0], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(lens.undistort(xy, [0.0] * 5), xy)
    assert lens.valid_radius([]) == np.inf
    assert lens.valid_radius([0.1, 0.01, 0.0, 0.0, 0.001]) == np.inf  # pincushion never folds
    # rational with a pole: 1 + k4 r^2 = 0 at r = sqrt(2)
    assert lens.valid_radius([0, 0, 0, 0, 0, -0.5, 0, 0]) == pytest.approx(np.sqrt(2.0), abs=1e-9)
    # the real Kinect depth lens folds at r = 3.21 (72.7 deg off-axis), far outside its 640x576 NFOV image
    assert 3.0 < lens.valid_radius(KINECT_DEPTH) < 3.3


@pytest.mark.parametrize("coeffs", [COEFFS_14, KINECT_DEPTH, STRONG_RATIONAL], ids=["tilted-14", "kinect", "strong"])
def test_one_thread_undistortion_is_the_parallel_one_bit_for_bit(coeffs, monkeypatch):
    """With one numba thread (a build worker, the pool's fork server) ``undistort`` runs the serial compilation of its
    kernel, which starts no OpenMP runtime: the same values to the bit, NaN where no inverse exists included."""
    c = cam(len(coeffs), coeffs)
    rng = np.random.default_rng(3)
    # the image's pixels and points far outside it (where the Newton starts fail and the fallback or NaN decides)
    xy = np.concatenate([c.ray_grid().reshape(-1, 2), rng.uniform(-3.0, 3.0, (20000, 2))])
    xy_d = lens.distort(xy, coeffs)
    xy_d[::997] = np.nan
    parallel = lens.undistort(xy_d, coeffs, serial=False)
    serial = lens.undistort(xy_d, coeffs, serial=True)
    assert np.isnan(parallel).any() and np.isfinite(parallel).sum() > 200000
    assert serial.tobytes() == parallel.tobytes()
    # two kernels, each with its own cache files (one name would make them share, and overwrite, one cache entry)
    assert lens._undistort_kernel_serial.py_func.__qualname__ == "_undistort_kernel_serial"
    assert not lens._undistort_kernel_serial.targetoptions.get("parallel")
    assert lens._undistort_kernel.targetoptions.get("parallel")
    # the default: serial where numba may run one thread only (the pool's workers and fork server)
    calls = []
    for name in ("_undistort_kernel", "_undistort_kernel_serial"):
        kernel = getattr(lens, name)
        monkeypatch.setattr(lens, name, lambda *a, _k=kernel, _n=name: calls.append(_n) or _k(*a))
    for n in (1, 2):
        monkeypatch.setattr(lens.numba.config, "NUMBA_NUM_THREADS", n)
        lens.undistort(xy_d[:10], coeffs)
    assert calls == ["_undistort_kernel_serial", "_undistort_kernel"]
