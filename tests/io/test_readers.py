import subprocess
import sys

import cv2
import numpy as np
import pytest
import yaml

from gtforge.core.camera import CameraFile, PinholeCamera, RectifiedStereo, StereoCalibrationFile
from gtforge.errors import InputError, MissingFileError
from gtforge.io.cameras import load_camera, load_zed_rectified, read_zed_conf, write_zed_conf
from gtforge.io.captures import open_session, read_depth, read_video_frame, split_side_by_side
from gtforge.io.formats import write_image, write_png16, write_tiff_float

CONF = {
    "LEFT_CAM_2K": dict(fx=1066.1, fy=1065.8, cx=1112.4, cy=615.2, k1=-0.0412, k2=0.0101, p1=0.0003, p2=-0.0002,
                        k3=-0.0051),
    "RIGHT_CAM_2K": dict(fx=1067.0, fy=1066.9, cx=1104.9, cy=620.1, k1=-0.0405, k2=0.0098, p1=-0.0001, p2=0.0002,
                         k3=-0.0049),
    "LEFT_CAM_HD": dict(fx=533.0, fy=532.9, cx=640.2, cy=357.6, k1=-0.0412, k2=0.0101, p1=0.0003, p2=-0.0002,
                        k3=-0.0051),
    "RIGHT_CAM_HD": dict(fx=533.5, fy=533.4, cx=636.4, cy=360.1, k1=-0.0405, k2=0.0098, p1=-0.0001, p2=0.0002,
                         k3=-0.0049),
    # the vendor's layout: TY, TZ once; the rotation per resolution
    "STEREO": dict(Baseline=63.02, TY=0.31, TZ=-0.22, CV_2K=0.0021, RX_2K=-0.0013, RZ_2K=0.0007,
                   CV_HD=0.0021, RX_HD=-0.0013, RZ_HD=0.0007),
}


def test_zed_conf_rectification_gives_positive_disparity(tmp_path):
    p = write_zed_conf(tmp_path / "SN12345.conf", CONF)
    calib = read_zed_conf(p, 2208)
    assert calib.resolution == "2K" and calib.left.height_px == 1242
    assert calib.left.dist_coeffs[0] == pytest.approx(-0.0412)
    rect = calib.rectification()
    assert rect.stereo.baseline_mm == pytest.approx(63.02, rel=2e-3)
    assert rect.stereo.left.width_px == 2208
    # a point 800 mm in front of the raw left camera
    X = np.array([[40.0, -25.0, 800.0]])
    uvl = cv2.projectPoints(X, np.zeros(3), np.zeros(3), calib.left.K, calib.left.dist)[0]
    Xr = X @ calib.R_right_from_left.T - calib.R_right_from_left @ calib.t_right_in_left_mm
    uvr = cv2.projectPoints(Xr, np.zeros(3), np.zeros(3), calib.right.K, calib.right.dist)[0]
    ul = cv2.undistortPoints(uvl, calib.left.K, calib.left.dist, R=rect.R_rect_from_raw_left, P=rect.P_left).ravel()
    ur = cv2.undistortPoints(uvr, calib.right.K, calib.right.dist, R=rect.R_rect_from_raw_right, P=rect.P_right).ravel()
    assert ul[1] == pytest.approx(ur[1], abs=1e-6)  # rows aligned
    d = ul[0] - ur[0]
    assert d > 0
    # and it matches f*B/Z in the rectified frame
    Z = (rect.R_rect_from_raw_left @ X[0])[2]
    assert d == pytest.approx(rect.stereo.f_px * rect.stereo.baseline_mm / Z - rect.stereo.doffs_px, rel=1e-3)
    # the HD section is chosen from the eye width
    assert read_zed_conf(p, 1280).left.fx_px == pytest.approx(533.0)


def test_zed_conf_missing_key(tmp_path):
    bad = {k: dict(v) for k, v in CONF.items()}
    del bad["STEREO"]["TY"]
    p = write_zed_conf(tmp_path / "SN1.conf", bad)
    with pytest.raises(InputError) as e:
        read_zed_conf(p, 2208)
    msg = str(e.value)
    assert "SN1.conf" in msg and "[[STEREO] TY]" in msg and "missing" in msg and "\n" not in msg


def test_zed_conf_suffixed_translation_and_missing_k3(tmp_path):
    """Files written by other tools hold TY_<res>, TZ_<res>: those win over the plain keys. A section without k3
    reads it as 0 and says so."""
    conf = {k: dict(v) for k, v in CONF.items()}
    conf["STEREO"].update(TY_2K=0.52, TZ_2K=-0.61)
    del conf["LEFT_CAM_HD"]["k3"]
    p = write_zed_conf(tmp_path / "SN2.conf", conf)
    c2k, chd = read_zed_conf(p, 2208), read_zed_conf(p, 1280)
    assert (c2k.ty_mm, c2k.tz_mm) == (0.52, -0.61) and (chd.ty_mm, chd.tz_mm) == (0.31, -0.22)
    assert c2k.notes == () and chd.notes == ("[LEFT_CAM_HD] has no k3: read as 0",)
    assert chd.left.dist_coeffs[4] == 0.0 and chd.right.dist_coeffs[4] == pytest.approx(-0.0049)


def test_real_factory_conf(tmp_path):
    """A real unit's factory file (ZED Mini SN10027514, ../shared/data): TY/TZ once, HD and FHD sections."""
    from conftest import shared_data

    path = shared_data("zed-mini-raw-pair") / "SN10027514.conf"
    hd, fhd = read_zed_conf(path, 1280), read_zed_conf(path, 1920)
    assert (hd.resolution, fhd.resolution) == ("HD", "FHD")
    assert (hd.baseline_conf_mm, hd.ty_mm, hd.tz_mm) == (63.0226, 0.00302386, -0.0360835)
    np.testing.assert_array_equal(hd.rotvec_conf_rad, [0.00300136, 0.000189208, -0.000855091])
    assert (hd.left.fx_px, hd.left.cx_px, hd.right.cy_px, fhd.left.fx_px) == (700.21, 650.413, 350.501, 1400.42)
    rect = hd.rectification()
    assert rect.stereo.baseline_mm == pytest.approx(63.02, abs=0.01) and rect.stereo.left.width_px == 1280
    with pytest.raises(InputError, match="LEFT_CAM_2K.*missing"):
        read_zed_conf(path, 2208)


def test_zed_conf_unknown_resolution(tmp_path):
    p = write_zed_conf(tmp_path / "SN1.conf", {k: v for k, v in CONF.items() if not k.endswith("HD")})
    with pytest.raises(InputError, match=r"LEFT_CAM_HD.*missing"):
        read_zed_conf(p, 1280)
    with pytest.raises(InputError, match="ZED eye width"):
        read_zed_conf(p, 1000)


def test_zed_conf_nan(tmp_path):
    bad = {k: dict(v) for k, v in CONF.items()}
    bad["LEFT_CAM_2K"]["fx"] = "nan"
    p = write_zed_conf(tmp_path / "SN1.conf", bad)
    with pytest.raises(InputError, match=r"\[LEFT_CAM_2K\] fx.*finite"):
        read_zed_conf(p, 2208)


def test_ros_and_opencv_yaml(tmp_path):
    K = [700.0, 0, 319.5, 0, 705.0, 241.0, 0, 0, 1]
    D = [-0.1, 0.05, 0.001, -0.001, 0.0]
    ros = dict(image_width=640, image_height=480, camera_name="mech", camera_matrix=dict(rows=3, cols=3, data=K),
               distortion_model="plumb_bob", distortion_coefficients=dict(rows=1, cols=5, data=D),
               projection_matrix=dict(rows=3, cols=4, data=[700.0, 0, 319.5, 0, 0, 705.0, 241.0, 0, 0, 0, 1, 0]))
    (tmp_path / "ros.yaml").write_text(yaml.safe_dump(ros))
    c = load_camera(tmp_path / "ros.yaml")
    assert (c.width_px, c.fx_px, c.fy_px, c.cx_px) == (640, 700.0, 705.0, 319.5)
    assert c.dist_coeffs == D
    fs = cv2.FileStorage(str(tmp_path / "cv.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array(K).reshape(3, 3))
    fs.write("distortion_coefficients", np.array(D).reshape(1, 5))
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.release()
    assert load_camera(tmp_path / "cv.yaml") == c
    CameraFile(camera=c).write(tmp_path / "g.yaml")
    assert load_camera(tmp_path / "g.yaml") == c
    # NaN in intrinsics
    ros["camera_matrix"]["data"] = [float("nan")] + K[1:]
    (tmp_path / "nan.yaml").write_text(yaml.safe_dump(ros))
    with pytest.raises(InputError, match=r"nan\.yaml \[camera_matrix\].*finite"):
        load_camera(tmp_path / "nan.yaml")


def test_rectified_zed_from_ros_left_right(tmp_path):
    left = dict(width=1280, height=720, K=[530.0, 0, 640.0, 0, 530.0, 360.0, 0, 0, 1], D=[0.0] * 5,
                P=[530.0, 0, 640.0, 0, 0, 530.0, 360.0, 0, 0, 0, 1, 0])
    # metres, as ROS drivers write
    right = dict(left, P=[530.0, 0, 640.0, -530.0 * 0.063, 0, 530.0, 360.0, 0, 0, 0, 1, 0])
    (tmp_path / "l.yaml").write_text(yaml.safe_dump(left))
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(right))
    z = load_zed_rectified(tmp_path / "l.yaml", tmp_path / "r.yaml")
    assert z.baseline_mm == pytest.approx(63.0) and z.doffs_px == 0.0 and z.left.fx_px == 530.0
    swapped = dict(left, P=[530.0, 0, 640.0, 530.0 * 63, 0, 530.0, 360.0, 0, 0, 0, 1, 0])
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(swapped))
    with pytest.raises(InputError, match="swapped"):
        load_zed_rectified(tmp_path / "l.yaml", tmp_path / "s.yaml")
    with pytest.raises(InputError, match="baseline"):
        load_zed_rectified(tmp_path / "l.yaml")


def test_depth_readers(tmp_path):
    cam = PinholeCamera(width_px=5, height_px=4, fx_px=10.0, fy_px=10.0, cx_px=2.0, cy_px=1.5)
    d = np.full((4, 5), 650.0, np.float32)
    d[0, 0], d[1, 1] = np.nan, 0.0
    write_tiff_float(tmp_path / "DepthMap.tiff", d)
    out = read_depth(tmp_path / "DepthMap.tiff", camera=cam)
    assert out.dtype == np.float32 and np.isnan(out[0, 0]) and np.isnan(out[1, 1]) and out[2, 2] == 650.0
    # metres refused with a hint, converted on request
    write_tiff_float(tmp_path / "m.tiff", d / 1000.0)
    with pytest.raises(InputError, match="depth_unit: m. in the session.s session.yaml"):
        read_depth(tmp_path / "m.tiff")
    assert read_depth(tmp_path / "m.tiff", depth_unit="m")[2, 2] == pytest.approx(650.0)
    # the median of every 16th valid pixel, exactly: half of them at 5 mm, half at 14 (median 9.5: refused) or 15 (10)
    grid = np.full((8, 8), np.nan, np.float32)
    grid[::4, ::4] = [[5.0, 14.0], [14.0, 5.0]]
    grid[1, 1] = 3.0  # not on the sampled grid
    write_tiff_float(tmp_path / "half.tiff", grid)
    with pytest.raises(InputError, match="median 9.5"):
        read_depth(tmp_path / "half.tiff")
    grid[grid == 14.0] = 15.0
    write_tiff_float(tmp_path / "half.tiff", grid)
    assert read_depth(tmp_path / "half.tiff")[0, 4] == 15.0
    grid[0, 0] = 16.0  # one sampled value below 10 of four
    write_tiff_float(tmp_path / "half.tiff", grid)
    assert read_depth(tmp_path / "half.tiff")[0, 0] == 16.0
    # 16-bit PNG with a scale
    write_png16(tmp_path / "d.png", np.where(np.isfinite(d), d * 10, 0).astype(np.uint16))
    np.testing.assert_allclose(read_depth(tmp_path / "d.png", depth_scale_mm=0.1)[2, 2], 650.0)
    with pytest.raises(InputError, match="depth_scale_mm"):
        read_depth(tmp_path / "d.png")
    np.save(tmp_path / "d.npy", d)
    assert np.isnan(read_depth(tmp_path / "d.npy")[1, 1])
    # size mismatch with the intrinsics
    small = PinholeCamera(width_px=6, height_px=4, fx_px=10.0, fy_px=10.0, cx_px=2.0, cy_px=1.5)
    with pytest.raises(InputError, match=r"6x4 px.*5x4 px"):
        read_depth(tmp_path / "DepthMap.tiff", camera=small)


def test_tiff_bytes_read_as_tifffile_reads_them(tmp_path):
    """``_tiff_image``: a view of the file's bytes for one uncompressed page in native byte order (one strip or several
    in one run), tifffile's own array for everything else; the same values and dtype either way, and read_depth's
    result from the bytes is its result from the path."""
    import io

    import tifffile

    from gtforge.io.captures import _tiff_image

    d = np.arange(37 * 23, dtype=np.float32).reshape(37, 23) + 600.0
    d[3, 4] = np.nan
    u16 = np.arange(37 * 5, dtype=np.uint16).reshape(37, 5) + 700
    native = "<" if sys.byteorder == "little" else ">"
    cases = {  # name: (imwrite arguments, a view of the bytes)
        "float32": ({}, True), "uint16": ({"data": u16}, True),
        "strips": ({"rowsperstrip": 5}, True), "contiguous=False": ({"contiguous": False}, True),
        "swapped": ({"byteorder": "<" if native == ">" else ">"}, False), "zlib": ({"compression": "zlib"}, False),
        "tiled": ({"tile": (16, 16)}, False),
        "predictor": ({"data": u16, "compression": "zlib", "predictor": True}, False),
        "two pages": ({"data": np.stack([d, d + 1])}, False),
    }
    for name, (kwargs, view) in cases.items():
        f = io.BytesIO()
        tifffile.imwrite(f, kwargs.pop("data", d), **kwargs)
        data = f.getvalue()
        a, want = _tiff_image(data), tifffile.imread(io.BytesIO(data))
        assert a.dtype == want.dtype and a.shape == want.shape, name
        np.testing.assert_array_equal(a, want, err_msg=name)
        assert (not a.flags.owndata and not a.flags.writeable) == view, name
        if a.ndim == 2 and a.dtype == np.float32:
            (tmp_path / "DepthMap.tiff").write_bytes(data)
            np.testing.assert_array_equal(read_depth(tmp_path / "DepthMap.tiff", data=data),
                                          read_depth(tmp_path / "DepthMap.tiff"), err_msg=name)


def test_side_by_side_split():
    img = np.zeros((4, 10, 3), np.uint8)
    img[:, 5:] = 7
    l, r = split_side_by_side(img, 5)
    assert l.shape == (4, 5, 3) and r.min() == 7 and l.max() == 0
    with pytest.raises(InputError, match="2 x 6 eye width"):
        split_side_by_side(img, 6)


def test_video_frame(tmp_path):
    import imageio.v2 as iio

    frames = [np.full((64, 128, 3), 40 * k, np.uint8) for k in range(4)]
    w = iio.get_writer(tmp_path / "zed.mp4", fps=5, codec="libx264", quality=10, macro_block_size=16)
    for f in frames:
        w.append_data(f)
    w.close()
    f2 = read_video_frame(tmp_path / "zed.mp4", 2)
    assert f2.shape == (64, 128, 3) and abs(float(f2.mean()) - 80) < 6
    with pytest.raises(InputError, match=r"frame index in \[0, 4\)"):
        read_video_frame(tmp_path / "zed.mp4", 9)


def _mini_session(tmp_path, sbs=False, kind="scenes"):
    mech = PinholeCamera(width_px=16, height_px=12, fx_px=20.0, fy_px=20.0, cx_px=7.5, cy_px=5.5)
    zl = PinholeCamera(width_px=20, height_px=10, fx_px=20.0, fy_px=20.0, cx_px=9.5, cy_px=4.5)
    CameraFile(camera=mech).write(tmp_path / "mech_intrinsics.yaml")
    StereoCalibrationFile(zed=RectifiedStereo(left=zl, baseline_mm=63.0)).write(tmp_path / "zed_calibration.yaml")
    c = tmp_path / kind / "000"
    c.mkdir(parents=True)
    write_image(c / "2DImage.png", np.zeros((12, 16), np.uint8))
    write_tiff_float(c / "DepthMap.tiff", np.full((12, 16), 600.0, np.float32))
    if sbs:
        write_image(c / "zed_sbs.png", np.zeros((10, 40, 3), np.uint8))
    else:
        write_image(c / "left.png", np.zeros((10, 20, 3), np.uint8))
        write_image(c / "right.png", np.zeros((10, 20, 3), np.uint8))
    return c


def test_session_loads_side_by_side(tmp_path):
    c = _mini_session(tmp_path, sbs=True)
    cap = open_session(tmp_path).load_capture(c)
    assert cap.zed_left.shape == (10, 20, 3) and cap.zed_right.shape == (10, 20, 3)


def test_session_image_size_mismatch(tmp_path):
    c = _mini_session(tmp_path)
    write_image(c / "left.png", np.zeros((10, 22, 3), np.uint8))
    with pytest.raises(InputError, match=r"left\.png \[size\]: expected 20x10 px.*got 22x10 px"):
        open_session(tmp_path).load_capture(c)


def _truncate(p):
    p.write_bytes(p.read_bytes()[:60])


def test_capture_without_decoding_checks_the_headers(tmp_path):
    """decode_images=False (build-dataset --no-verify): complete PNGs of the right size and type are not decoded
    (arrays None, the ZED files marked for verbatim copying); every defect falls back to decoding, so the error is
    the one a decoding load gives."""
    c = _mini_session(tmp_path)
    s = open_session(tmp_path)
    cap = s.load_capture(c, decode_images=False)
    assert cap.mech_texture is None and cap.zed_left is None and cap.zed_right is None
    assert cap.zed_left_file == c / "left.png" and cap.zed_right_file == c / "right.png"
    assert cap.depth_mm.shape == (12, 16)
    full = s.load_capture(c)
    assert full.zed_left.shape == (10, 20, 3) and full.zed_left_file == c / "left.png"
    # a grey ZED PNG is decoded (and expanded to RGB), so it is not copied verbatim
    write_image(c / "right.png", np.zeros((10, 20), np.uint8))
    cap = s.load_capture(c, decode_images=False)
    assert cap.zed_right.shape == (10, 20, 3) and cap.zed_right_file is None
    write_image(c / "right.png", np.zeros((10, 20, 3), np.uint8))
    for name, defect, match in (
            ("left.png", "truncated", r"left\.png \[zed_left\]: expected a readable image"),
            ("right.png", "size", r"right\.png \[size\]: expected 20x10 px.*got 22x10 px"),
            ("2DImage.png", "truncated", r"2DImage\.png \[mech_texture\]: expected a readable image"),
            ("2DImage.png", "size", r"2DImage\.png \[size\]: expected 16x12 px")):
        good = (c / name).read_bytes()
        if defect == "truncated":
            _truncate(c / name)  # the image data cut off: the header still looks right
        else:
            write_image(c / name, np.zeros((10, 22, 3) if name != "2DImage.png" else (12, 17), np.uint8))
        for decode in (True, False):
            with pytest.raises(InputError, match=match):
                s.load_capture(c, decode_images=decode)
        (c / name).write_bytes(good)


def test_capture_records_the_hash_of_the_bytes_it_decoded(tmp_path):
    """load_capture hashes each file it reads whole as it reads it (Capture.read_records): the SHA-256 and size of
    exactly those bytes (BLAKE3), the mtime from just before. build-dataset's hash_inputs takes them instead of reading
    the files again, and hashes only the rest (here: the PNGs a --no-verify load left undecoded)."""
    import blake3

    from gtforge.dataset.layout import hash_inputs

    c = _mini_session(tmp_path)
    s = open_session(tmp_path)
    cap = s.load_capture(c)
    names = {p.name for p in cap.input_files}
    assert set(cap.read_records) == names == {"2DImage.png", "DepthMap.tiff", "left.png", "right.png"}
    for name, r in cap.read_records.items():
        data = (c / name).read_bytes()
        assert r.blake3 == blake3.blake3(data).hexdigest() and r.size_bytes == len(data)
        assert r.mtime_ns == (c / name).stat().st_mtime_ns and r.read_at_ns >= r.mtime_ns
    lean = s.load_capture(c, decode_images=False)
    assert set(lean.read_records) == {"DepthMap.tiff"}  # the PNGs passed the header checks: not read
    for caps in (cap, lean):
        hashes, stamps = hash_inputs(caps.input_files, caps.read_records)
        assert hashes == {p.name: blake3.blake3(p.read_bytes()).hexdigest() for p in caps.input_files}
        assert {k: v.size_bytes for k, v in stamps.items()} == {p.name: p.stat().st_size for p in caps.input_files}


def test_decoded_images_decode_what_load_capture_left_and_only_the_rows_asked(tmp_path):
    """A build loads a capture without decoding its images, then decodes them once the ground truth says how many ZED
    rows its verification reads (Session.decoded_images): the texture whole, the ZED images' first rows, with the
    bytes read recorded as load_capture records them."""
    import blake3

    c = _mini_session(tmp_path)
    s = open_session(tmp_path)
    full = s.load_capture(c)
    lean = s.load_capture(c, decode_images=False)
    assert lean.mech_texture is None and lean.zed_left is None and set(lean.read_records) == {"DepthMap.tiff"}
    tex, left, right = s.decoded_images(lean, zed_rows=4)
    np.testing.assert_array_equal(tex, full.mech_texture)
    assert left.shape == (4,) + full.zed_left.shape[1:] and right.shape == left.shape
    np.testing.assert_array_equal(left, full.zed_left[:4])
    np.testing.assert_array_equal(right, full.zed_right[:4])
    assert set(lean.read_records) == {"DepthMap.tiff", "2DImage.png", "left.png", "right.png"}
    assert lean.read_records["left.png"].blake3 == blake3.blake3((c / "left.png").read_bytes()).hexdigest()
    # the ZED PNGs' bytes kept, in page-aligned buffers, for im0/im1 (a capture decoded whole keeps none)
    assert set(lean.read_buffers) == {"left.png", "right.png"} and not full.read_buffers
    for name, buf in lean.read_buffers.items():
        assert buf.data.tobytes() == (c / name).read_bytes() and buf.padded.ctypes.data % 4096 == 0
    _, left, _ = s.decoded_images(lean)  # every row
    np.testing.assert_array_equal(left, full.zed_left)
    same = s.decoded_images(full, zed_rows=4)  # decoded already: given as they are
    assert all(a is b for a, b in zip(same, (full.mech_texture, full.zed_left, full.zed_right)))


def test_cli_bad_input_is_one_line_exit_2(tmp_path):
    c = _mini_session(tmp_path)
    write_tiff_float(c / "DepthMap.tiff", np.full((12, 16), 0.6, np.float32))  # metres
    (tmp_path / "cal.yaml").write_text("schema_version: 1\n")
    r = subprocess.run([sys.executable, "-m", "gtforge.cli", "calibrate", str(tmp_path / "nowhere")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    lines = [l for l in r.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and "nowhere" in lines[0] and "no such folder" in lines[0]


@pytest.mark.parametrize("defect, expect", [
    ("metres", "DepthMap.tiff [mech_depth]: expected depth in mm"),
    ("truncated", "2DImage.png [mech_texture]: expected a readable image"),
    ("size", "left.png [size]: expected 20x10 px"),
    ("nan_intrinsics", "mech_intrinsics.yaml [camera.fx_px]"),
])
def test_cli_one_line_errors(tmp_path, defect, expect):
    c = _mini_session(tmp_path, kind="board")
    if defect == "metres":
        write_tiff_float(c / "DepthMap.tiff", np.full((12, 16), 0.6, np.float32))
    elif defect == "truncated":
        _truncate(c / "2DImage.png")
    elif defect == "size":
        write_image(c / "left.png", np.zeros((10, 22, 3), np.uint8))
    else:
        t = (tmp_path / "mech_intrinsics.yaml").read_text()
        (tmp_path / "mech_intrinsics.yaml").write_text(t.replace("fx_px: 20.0", "fx_px: .nan"))
    out = tmp_path.parent / f"{tmp_path.name}-calib.yaml"  # (beside the session: never inside it)
    r = subprocess.run([sys.executable, "-m", "gtforge.cli", "calibrate", str(tmp_path), "-o", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    lines = [l for l in r.stderr.splitlines() if l.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert expect in lines[0], lines[0]
    assert not out.exists()


def test_session_with_raw_zed_images_and_factory_conf(tmp_path):
    conf = {k.replace("HD", "VGA"): dict(v) for k, v in CONF.items() if "HD" in k or k == "STEREO"}
    for side in ("LEFT_CAM_VGA", "RIGHT_CAM_VGA"):
        conf[side].update(fx=conf[side]["fx"] * 672 / 1280, fy=conf[side]["fy"] * 672 / 1280,
                          cx=335.6, cy=187.9)
    conf["STEREO"] = {k.replace("HD", "VGA"): v for k, v in CONF["STEREO"].items() if "2K" not in k}
    write_zed_conf(tmp_path / "SN42.conf", conf)
    c = _mini_session(tmp_path)
    (c / "left.png").unlink()
    (c / "right.png").unlink()
    raw = np.zeros((376, 1344, 3), np.uint8)
    raw[200:204, 100:104] = 255  # a bright dot in the raw left image
    write_image(c / "zed_sbs.png", raw)
    (tmp_path / "session.yaml").write_text("schema_version: 1\nzed_calibration: SN42.conf\nzed_rectified: false\n")
    s = open_session(tmp_path)
    assert s.zed.left.width_px == 672 and s.zed.baseline_mm == pytest.approx(63.02, rel=2e-3)
    cap = s.load_capture(c)
    assert cap.zed_left.shape == (376, 672, 3)
    calib = read_zed_conf(tmp_path / "SN42.conf", 672)
    rect = s.rectification
    expect = cv2.undistortPoints(np.array([[[101.5, 201.5]]]), calib.left.K, calib.left.dist,
                                 R=rect.R_rect_from_raw_left, P=rect.P_left).ravel()
    v, u = np.unravel_index(np.argmax(cap.zed_left[..., 0].astype(float)), cap.zed_left.shape[:2])
    assert abs(u - expect[0]) <= 2.5 and abs(v - expect[1]) <= 2.5


def test_session_reads_side_by_side_video(tmp_path):
    import imageio.v2 as iio

    c = _mini_session(tmp_path)
    (c / "left.png").unlink()
    (c / "right.png").unlink()
    w = iio.get_writer(c / "zed.mp4", fps=5, codec="libx264", quality=10, macro_block_size=1)
    for k in range(3):
        f = np.zeros((10, 40, 3), np.uint8)
        f[:, 20:] = 60 * (k + 1)
        w.append_data(f)
    w.close()
    (tmp_path / "session.yaml").write_text("schema_version: 1\nvideo_frame: 2\n")
    cap = open_session(tmp_path).load_capture(c)
    assert cap.zed_left.shape == (10, 20, 3) and abs(float(cap.zed_right.mean()) - 180) < 15


def test_ros_rational_polynomial_keeps_all_eight_coefficients(tmp_path):
    D = [0.41, -0.02, 0.0003, -0.0002, 0.003, 0.78, 0.09, -0.01]
    ros = dict(image_width=640, image_height=576, distortion_model="rational_polynomial",
               camera_matrix=dict(rows=3, cols=3, data=[504.1, 0, 321.2, 0, 504.3, 330.7, 0, 0, 1]),
               distortion_coefficients=dict(rows=1, cols=8, data=D))
    (tmp_path / "k.yaml").write_text(yaml.safe_dump(ros))
    cam = load_camera(tmp_path / "k.yaml")
    assert cam.dist_coeffs == D
    X = np.array([[0.31, -0.22, 1.0]])
    uv = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, np.array(D))[0].reshape(-1, 2)
    np.testing.assert_allclose(cam.project(X), uv, atol=1e-9)
    ros["distortion_coefficients"]["data"] = D[:6]
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(ros))
    with pytest.raises(InputError, match=r"distortion_coefficients.*got 6"):
        load_camera(tmp_path / "bad.yaml")


def test_a_missing_capture_file_is_told_apart_from_a_wrong_one(tmp_path):
    """The stages that read many captures skip one whose file is missing and stop on one whose file is wrong: the
    error's type says which, not its words."""
    from gtforge.io.captures import missing_capture_file
    from gtforge.io.formats import read_image

    with pytest.raises(MissingFileError) as missing:
        read_depth(tmp_path / "DepthMap.tiff")
    assert missing_capture_file(missing.value)
    assert str(missing.value) == (f"{tmp_path / 'DepthMap.tiff'} [depth]: expected a depth map file, got no such file "
                                  "(hint: check the capture folder / session.yaml)")
    with pytest.raises(MissingFileError) as missing:
        read_image(tmp_path / "left.png")
    assert missing_capture_file(missing.value) and "got no such file" in str(missing.value)
    (tmp_path / "DepthMap.bmp").write_bytes(b"BM")
    with pytest.raises(InputError) as wrong:
        read_depth(tmp_path / "DepthMap.bmp")
    assert not missing_capture_file(wrong.value) and "got '.bmp'" in str(wrong.value)


@pytest.mark.parametrize("size_change", [0, 3, -3])
def test_read_recorded_bytes_record_and_buffer(tmp_path, size_change):
    """``read_recorded`` with ``buffers``: the file's bytes, recorded (BLAKE3, size) and kept in an aligned buffer when
    the size read is the size ``stat`` gave; a file that grew or shrank in between is returned as it is, neither
    recorded nor kept."""
    import pathlib
    import types

    import blake3

    from gtforge.io.captures import read_recorded

    class Changed(type(pathlib.Path())):
        def stat(self, **kwargs):  # the size before the file changed
            st = super().stat(**kwargs)
            return types.SimpleNamespace(st_size=st.st_size - size_change, st_mtime_ns=st.st_mtime_ns)

    content = bytes(range(256)) * 40 + b"end"
    (tmp_path / "f.png").write_bytes(content)
    records, buffers = {}, {}
    data = read_recorded(Changed(tmp_path / "f.png"), records, buffers)
    assert bytes(data) == content
    if size_change:
        assert not records and not buffers
    else:
        assert records["f.png"].blake3 == blake3.blake3(content).hexdigest() and records["f.png"].size_bytes == 10243
        assert buffers["f.png"].data.tobytes() == content
    assert read_recorded(tmp_path / "missing.png", records) is None
    plain = read_recorded(tmp_path / "f.png", {})  # nothing kept: the bytes object (io.BytesIO shares it)
    assert type(plain) is bytes and plain == content


@pytest.mark.parametrize("text, got, hint", [
    ("a: 1\n\tb: 2\n", "a parse error at line 2, column 1: found a tab character",
     "indent with spaces, not tabs (line 2)"),
    ("rig: {zed: [1, 2\n", "a parse error at line 2, column 1: ", "the text ends before its YAML does: is the file "
     "truncated, or a bracket or quote left open?"),
    ("a:\n  b: 1\n c: 2\n", "a parse error at line 3, column 2: ", "fix the YAML at line 3 (an indent or a ':' out "
     "of place is the usual cause)"),
])
def test_a_yaml_that_does_not_parse_names_its_line_and_a_fitting_hint(tmp_path, text, got, hint):
    """A tab-indented line said only "a parse error (while scanning for the next token)" with the hint "is the file
    truncated?" (a newcomer's run-through, round 4): the line and column now, and a hint for what went wrong."""
    from gtforge.records.calibration import CalibrationFile

    p = tmp_path / "calibration.yaml"
    p.write_text(text)
    for read in (CalibrationFile.read, load_camera):
        with pytest.raises(InputError) as e:
            read(p)
        assert e.value.file == str(p) and e.value.actual.startswith(got), (read, e.value)
        assert e.value.hint.startswith(hint), (read, e.value.hint)


def test_a_baseline_in_another_unit_is_refused_where_it_is_read(session_dir, true_calibration, tmp_path):
    """A ZED baseline written in metres (0.063) was read as 0.063 mm: calibrate and validate passed, calibrate-scale
    "corrected" it by +190,000 % (a newcomer's run-through, round 4). The session refuses it, naming the file; a
    calibration whose baseline is not the session's (beyond calibrate-scale's corrections) is refused too."""
    import shutil

    from gtforge.io.calibrated_session import check_rig_matches_session
    from gtforge.records.calibration import CalibrationFile

    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess, ignore=shutil.ignore_patterns("scenes", "board", "gauges", "truth"))
    zpath = sess / "zed_calibration.yaml"
    good = zpath.read_text()
    assert "baseline_mm: 63.0" in good
    for value, unit in (("0.063", "metres"), ("63000.0", "micrometres")):
        zpath.write_text(good.replace("baseline_mm: 63.0", f"baseline_mm: {value}"))
        with pytest.raises(InputError) as e:
            open_session(sess)
        assert e.value.file == str(zpath) and e.value.field == "baseline", e.value
        assert e.value.actual == f"{float(value):g} mm" and unit in e.value.hint, e.value
    zpath.write_text(good)
    session = open_session(sess)
    calib = CalibrationFile.read(true_calibration)
    check_rig_matches_session(calib.rig, session, true_calibration)  # the session's own baseline
    for b_mm in (63.0 * 1.05, 63.0 * 0.95):  # calibrate-scale's largest corrections
        rig = calib.rig.model_copy(update={"zed": calib.rig.zed.model_copy(update={"baseline_mm": b_mm})})
        check_rig_matches_session(rig, session, true_calibration)
    rig = calib.rig.model_copy(update={"zed": calib.rig.zed.model_copy(update={"baseline_mm": 0.063})})
    with pytest.raises(InputError) as e:
        check_rig_matches_session(rig, session, true_calibration)
    assert e.value.field == "rig.zed.baseline_mm" and e.value.actual == "0.063 mm", e.value
    assert e.value.expected == "63 mm (the session's zed_calibration.yaml), within 10%", e.value
