import os

import numpy as np
import pytest

from gtforge.errors import InputError
from gtforge.io.atomic import atomic_path, atomic_write_text
from gtforge.io.formats import (read_image, read_kitti_disparity, read_pfm, read_ply_points, write_image,
                                write_kitti_disparity, write_pfm, write_ply, write_tiff_float)


def test_pfm_layout_and_invalid(tmp_path):
    d = np.array([[1.5, np.nan, 3.0], [4.0, 5.0, np.inf]], np.float32)
    p = write_pfm(tmp_path / "d.pfm", d)
    raw = p.read_bytes()
    assert raw.startswith(b"Pf\n3 2\n-1.0\n")  # negative scale = little-endian
    body = np.frombuffer(raw[len(b"Pf\n3 2\n-1.0\n"):], "<f4").reshape(2, 3)
    np.testing.assert_array_equal(body[0], [4.0, 5.0, np.inf])  # rows bottom-to-top
    assert body[1, 1] == np.inf  # NaN written as +inf
    back = read_pfm(p)
    np.testing.assert_array_equal(np.isnan(back), [[False, True, False], [False, False, True]])
    np.testing.assert_array_equal(back[0, [0, 2]], [1.5, 3.0])


def test_pfm_truncated(tmp_path):
    p = write_pfm(tmp_path / "d.pfm", np.ones((4, 5), np.float32))
    p.write_bytes(p.read_bytes()[:-7])
    with pytest.raises(InputError, match="truncated"):
        read_pfm(p)


def test_kitti_png_encoding(tmp_path):
    d = np.array([[0.0, 1.0 / 1024, 12.3456], [np.nan, -1.0, 200.0]], np.float32)
    p = write_kitti_disparity(tmp_path / "d.png", d)
    q = read_image(p, expect="uint16")
    np.testing.assert_array_equal(q, [[1, 1, round(12.3456 * 256)], [0, 0, 51200]])  # true 0 -> 1, invalid -> 0
    back = read_kitti_disparity(p)
    assert np.isnan(back[1, 0]) and np.isnan(back[1, 1])
    assert abs(back[0, 2] - 12.3456) <= 0.5 / 256


def test_tiff_and_ply(tmp_path):
    a = np.array([[1.0, np.nan], [3.5, 4.25]], np.float32)
    write_tiff_float(tmp_path / "a.tiff", a)
    import tifffile

    b = tifffile.imread(tmp_path / "a.tiff")
    assert b.dtype == np.float32 and np.isnan(b[0, 1]) and b[1, 1] == 4.25
    pts = np.array([[0, 1, 2], [3, 4, 5.5]])
    write_ply(tmp_path / "c.ply", pts, np.array([[1, 0, 0], [0, 0, 1.0]]))
    np.testing.assert_allclose(read_ply_points(tmp_path / "c.ply"), pts)


def test_image_round_trip_and_truncated(tmp_path):
    img = (np.arange(30 * 40 * 3) % 251).astype(np.uint8).reshape(30, 40, 3)
    p = write_image(tmp_path / "i.png", img)
    np.testing.assert_array_equal(read_image(p), img)  # RGB in memory
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    with pytest.raises(InputError) as e:
        read_image(p)
    assert "i.png" in str(e.value) and "\n" not in str(e.value)


def test_atomic_write_keeps_original_on_failure(tmp_path):
    target = tmp_path / "f.txt"
    atomic_write_text(target, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash mid-write")
    assert target.read_text() == "old"
    assert os.listdir(tmp_path) == ["f.txt"]
