"""gtforge.core.bspline: the compiled cubic B-spline resampling gives SciPy's values to the last bit (the
coefficients of ``spline_filter``, the samples of ``map_coordinates``, the rounded image of the
resampling gtforge did with SciPy), on random images of every shape and type it takes and on real camera images."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import shared_data
from scipy import ndimage

from gtforge.core import bspline
from gtforge.core.zed.scale_corrections import apply_homography, right_yaw_homography


def _channels(img):
    return [img] if img.ndim == 2 else [img[..., k] for k in range(img.shape[2])]


def _reference_coefficients(img):
    return [ndimage.spline_filter(np.asarray(a, np.float64), order=3, mode="mirror") for a in _channels(img)]


def _reference_resample(img, us, vs, out_hw):
    """The resampling as gtforge did it with SciPy: its coefficients and samples, black outside, np.round, np.clip,
    the type."""
    h, w = img.shape[:2]
    out = np.stack([ndimage.map_coordinates(c, [vs, us], order=3, prefilter=False, mode="mirror")
                    for c in _reference_coefficients(img)])
    inside = (us >= 0) & (us <= w - 1) & (vs >= 0) & (vs <= h - 1)
    out = np.clip(np.round(np.where(inside[None], out, 0.0)), 0, np.iinfo(img.dtype).max).astype(img.dtype)
    out = out.reshape((-1, *out_hw))
    return out[0] if img.ndim == 2 else np.moveaxis(out, 0, 2)


def _bits(a):
    return np.ascontiguousarray(a, np.float64).view(np.uint64)


@pytest.mark.parametrize("shape,dtype", [((7, 5), np.uint8), ((1, 9), np.uint8), ((9, 1, 3), np.uint8),
                                         ((2, 2), np.uint16), ((37, 61, 3), np.uint8), ((300, 520), np.uint16),
                                         ((64, 48, 2), np.float32)])
def test_coefficients_and_samples_are_scipys_to_the_last_bit(shape, dtype):
    rng = np.random.default_rng(sum(shape))
    img = (rng.integers(0, np.iinfo(dtype).max, shape, endpoint=True) if dtype != np.float32
           else rng.normal(0, 50, shape)).astype(dtype)
    coef = bspline.coefficients(img)
    h, w = shape[:2]
    assert coef.shape == (h, w, 1 if img.ndim == 2 else shape[2])
    ref = _reference_coefficients(img)
    for k, c in enumerate(ref):
        assert np.array_equal(_bits(coef[..., k]), _bits(c))
    # inside, on every edge and corner, just past them, and far outside (mirrored into the image)
    n = 4000
    us = np.concatenate([rng.uniform(0, w - 1, n), [0, w - 1, 0, w - 1, 0.5, w - 1.5, -1e-9, w - 1 + 1e-9],
                         rng.uniform(-3 * w, 4 * w, n)])
    vs = np.concatenate([rng.uniform(0, h - 1, n), [0, 0, h - 1, h - 1, h - 1.0, 0.25, 0, 0],
                         rng.uniform(-3 * h, 4 * h, n)])
    got = bspline.sample(coef, us, vs)
    for k, c in enumerate(ref):
        want = ndimage.map_coordinates(c, [vs, us], order=3, prefilter=False, mode="mirror")
        assert np.array_equal(_bits(got[:, k]), _bits(want))


@pytest.mark.parametrize("dtype,channels", [(np.uint8, 3), (np.uint16, 0)])
def test_resample_is_the_scipy_pipelines_image(dtype, channels):
    """Including values that overshoot the type's range (a spline rings past 0 and the top at sharp edges: clipped)
    and points outside the image (black)."""
    rng = np.random.default_rng(3)
    top = np.iinfo(dtype).max
    shape = (90, 130, channels) if channels else (90, 130)
    img = np.where(rng.random(shape) < 0.5, 0, top).astype(dtype)  # a black/white pattern: maximal ringing
    h, w = shape[:2]
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    H = right_yaw_homography(np.array([[120.0, 0, 65], [0, 120.0, 45], [0, 0, 1]]), np.radians(3.0))
    H[1, 2] += 0.5
    us, vs = apply_homography(H, uu.ravel(), vv.ravel())
    got = bspline.resample(img, us, vs, (h, w))
    want = _reference_resample(img, us, vs, (h, w))
    assert got.dtype == dtype and got.shape == want.shape
    assert np.array_equal(got, want)
    assert np.array_equal(bspline.resample_homography(img, H), want)  # the grid's positions computed in the kernel
    assert (got == 0).any() and (got == top).any() and (us > w - 1).any()  # both clips and the outside occurred


def test_a_homography_through_the_horizon_leaves_those_pixels_black():
    """A pixel whose homogeneous coordinate is zero (the map's horizon crosses the image) has no position: black, as a
    pixel mapped outside the image, and every other pixel as ``resample`` of ``apply_homography``'s positions (the
    kernel divided by zero with Python's error model, a ZeroDivisionError out of a build, before it had numpy's)."""
    rng = np.random.default_rng(7)
    img = rng.integers(0, 256, (6, 9, 3), dtype=np.uint8)
    H = np.array([[1.0, 0.0, 0.25], [0.0, 1.0, 0.0], [-0.25, 0.0, 1.0]])  # w = 1 - u / 4: zero at column 4
    uu, vv = np.meshgrid(np.arange(9.0), np.arange(6.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        us, vs = apply_homography(H, uu.ravel(), vv.ravel())
    assert not np.isfinite(us.reshape(6, 9)[:, 4]).any()
    got = bspline.resample_homography(img, H)
    assert np.array_equal(got, bspline.resample(img, us, vs, (6, 9)))
    assert (got[:, 4] == 0).all() and (got[:, :3] != 0).any()


def test_resample_refuses_a_float_image():
    with pytest.raises(TypeError, match="8- or 16-bit"):
        bspline.resample(np.zeros((4, 4), np.float32), np.zeros(16), np.zeros(16), (4, 4))


@pytest.mark.parametrize("name,files", [("zed-mini-raw-pair", ("right_raw.png", "left_raw.png")),
                                        ("middlebury2014-motorcycle-Q", ("im1.png",))])
def test_real_images_resample_to_the_same_pixels(name, files):
    """Real camera images (a ZED Mini's raw pair, Middlebury 2014 Motorcycle), resampled as a session corrects a
    right camera: a small yaw, a row shift and a shear (the self-rectification's kind of correction)."""
    import cv2

    folder = shared_data(name)
    for f in files:
        img = cv2.imread(str(folder / f), cv2.IMREAD_UNCHANGED)
        h, w = img.shape[:2]
        K = np.array([[0.8 * w, 0, w / 2], [0, 0.8 * w, h / 2], [0, 0, 1]])
        H = right_yaw_homography(K, np.radians(0.04))
        H[1, 2] += 0.37
        H[0, 1] += 1e-4
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
        us, vs = apply_homography(H, uu.ravel(), vv.ravel())
        want = _reference_resample(img, us, vs, (h, w))
        assert np.array_equal(bspline.resample(img, us, vs, (h, w)), want), f
        assert np.array_equal(bspline.resample_homography(img, H), want), f


def test_long_black_lines_and_non_finite_values_are_scipys_to_the_last_bit():
    """Lines longer than about 566 samples, where the causal initialisation's ``z^i`` underflows to zero and the
    prefilter stops summing: a black image whose content starts only past that point along both axes (sums that are
    signed zeros when the stop comes, which the remaining zero terms can still turn from -0 to +0), and float images
    with an infinity or a NaN far down a line (whose remaining terms are not zeros: no early stop)."""
    rng = np.random.default_rng(566)
    img = np.zeros((700, 1300, 3), np.uint8)
    img[620:] = rng.integers(0, 256, (80, 1300, 3))
    img[:, 1200:] = rng.integers(0, 256, (700, 100, 3))
    coef = bspline.coefficients(img)
    assert (np.signbit(coef) & (coef == 0)).any() and ((coef == 0) & ~np.signbit(coef)).any()  # both zeros occur
    for k, c in enumerate(_reference_coefficients(img)):
        assert np.array_equal(_bits(coef[..., k]), _bits(c))
    for bad in (np.inf, np.nan):
        f = rng.normal(0, 50, (600, 640)).astype(np.float32)
        f[590, 630] = bad
        got, (want,) = bspline.coefficients(f)[..., 0], _reference_coefficients(f)
        assert np.array_equal(got, want, equal_nan=True) and np.isnan(got).any()
        fin = np.isfinite(want)
        assert np.array_equal(_bits(got[fin]), _bits(want[fin]))


def test_a_line_whose_sum_is_minus_zero_when_the_initialisation_stops():
    """The one case where the prefilter's early stop must still add the remaining (zero) terms: a line whose first 566
    values are zeros signed so that every term of the causal sum is -0, and whose values past 733 are positive, so that
    a later zero term is +0 and turns the sum into +0 (as SciPy's full sum does)."""
    line = np.zeros((1, 1300), np.float64)
    line[0, 0:566:2] = -0.0  # even taps: -0 (z^i > 0), odd taps: +0 (z^i < 0): every term z^i * x_i is -0
    line[0, 734:] = np.arange(1, 567)
    coef = bspline.coefficients(line)[..., 0]
    (want,) = _reference_coefficients(line)
    assert np.array_equal(_bits(coef), _bits(want))
