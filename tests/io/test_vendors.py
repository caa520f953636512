"""Vendor camera files: Azure Kinect calibration.json (checked against numbers the Azure Kinect SDK computed from the
same file), the Mech-Eye API intrinsics YAML, the one entry point and its wiring into open_session."""
import copy
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from gtforge.core.camera import CameraFile, PinholeCamera, RectifiedStereo, StereoCalibrationFile
from gtforge.core.geometry import T_from_rotvec, invert_T, transform_points
from gtforge.errors import InputError
from gtforge.io.captures import open_session
from gtforge.io.vendors import (
    KINECT_COLOR_MODES,
    KINECT_DEPTH_MODES,
    MechEyeIntrinsicsFile,
    kinect_calibration_from_dict,
    load_structured_light_cameras,
    read_kinect_calibration,
    read_mecheye_intrinsics,
)

ROOT = Path(__file__).parents[2]
KINECT_JSON = ROOT / "tests" / "data" / "azure-kinect-frame" / "calibration.json"
MECHEYE_EXAMPLE = ROOT / "docs" / "examples" / "mecheye_intrinsics.yaml"


def kinect_data() -> dict:
    return json.loads(KINECT_JSON.read_text())


def write_json(tmp_path: Path, data: dict, name: str = "calibration.json") -> Path:
    p = tmp_path / name
    p.write_text(json.dumps(data))
    return p


def camera_entry(data: dict, location: str) -> dict:
    return next(c for c in data["CalibrationInformation"]["Cameras"] if c["Location"] == location)


# ---- Azure Kinect ------------------------------------------------------------------------------
def test_kinect_matches_sdk_numbers():
    """pyk4a's unit tests (etiennedub/pyk4a tests/unit/test_calibration.py) call the Azure Kinect SDK on this very
    calibration.json (NFOV_UNBINNED + 720P); its float32 results must come out of gtforge's reading to 1e-4."""
    k = read_kinect_calibration(KINECT_JSON, "NFOV_UNBINNED", "720P")
    T_depth_from_color = invert_T(k.T_color_from_depth)
    # calibration.color_to_depth_3d / depth_to_color_3d: the extrinsic, its direction and metres -> mm
    p_color, p_depth = np.array([[1000.0, 1500.0, 2000.0]]), np.array([[1031.4664306640625, 1325.8529052734375,
                                                                         2117.6611328125]])
    np.testing.assert_allclose(transform_points(T_depth_from_color, p_color), p_depth, rtol=0, atol=1e-4)
    np.testing.assert_allclose(transform_points(k.T_color_from_depth, p_depth), p_color, rtol=0, atol=1e-4)
    # convert_2d_to_3d / convert_3d_to_2d in the colour camera: mode crop, half-pixel shift, lens model, p1/p2
    uv, z = np.array([[250.0, 300.0]]), [250.0]
    p3 = np.array([[-154.5365753173828, -26.12171173095703, 250.0]])
    np.testing.assert_allclose(k.color.unproject(uv, z), p3, rtol=0, atol=1e-4)
    np.testing.assert_allclose(k.color.project(p3), uv, rtol=0, atol=1e-4)
    # ... with the depth camera as target / source
    p3_depth = np.array([[-122.29087829589844, -45.17741394042969, 243.19528198242188]])
    np.testing.assert_allclose(transform_points(T_depth_from_color, k.color.unproject(uv, z)), p3_depth, atol=1e-4)
    np.testing.assert_allclose(k.color.project(transform_points(k.T_color_from_depth, p3_depth)), uv, atol=1e-4)
    # every mistake the reader could make is far outside that tolerance
    half = k.color.model_copy(update={"cx_px": k.color.cx_px + 0.5, "cy_px": k.color.cy_px + 0.5})
    assert np.abs(half.unproject(uv, z) - p3).max() > 0.1  # 0.19 mm
    d = list(k.color.dist_coeffs)
    swapped = k.color.model_copy(update={"dist_coeffs": d[:2] + [d[3], d[2]] + d[4:]})
    assert np.abs(swapped.project(p3) - uv).max() > 0.01  # 0.020 px
    assert np.abs(transform_points(k.T_color_from_depth, p_color) - p_depth).max() > 50.0  # inverse T
    # the colour camera has no lens-model limit inside the image; the depth camera's MetricRadius is kept
    assert k.depth_metric_radius == pytest.approx(1.74, abs=1e-6) and k.color_metric_radius == 1.7


def test_kinect_values_order_and_units(tmp_path):
    """Distinct numbers in every slot: cx cy fx fy k1..k6 codx cody p2 p1 (normalised), translation in metres."""
    data = kinect_data()
    d = camera_entry(data, "CALIBRATION_CameraLocationD0")
    c = camera_entry(data, "CALIBRATION_CameraLocationPV0")
    d["Intrinsics"]["ModelParameters"] = [0.51, 0.52, 0.49, 0.48, 0.11, 0.12, 0.13, 0.14, 0.15, 0.16, 0, 0,
                                          0.0021, 0.0031]
    c["Intrinsics"]["ModelParameters"] = [0.501, 0.502, 0.47, 0.63, 0.21, 0.22, 0.23, 0.24, 0.25, 0.26, 0, 0,
                                          -0.0022, -0.0032]
    c["Rt"]["Translation"] = [-0.032, 0.0015, 0.004]
    k = read_kinect_calibration(write_json(tmp_path, data), "NFOV_UNBINNED", "1536P")
    # depth, NFOV_UNBINNED: 1024x1024 normalised, crop (192, 180), then -0.5 px
    assert (k.depth.width_px, k.depth.height_px) == (640, 576)
    assert k.depth.fx_px == pytest.approx(0.49 * 1024) and k.depth.fy_px == pytest.approx(0.48 * 1024)
    assert k.depth.cx_px == pytest.approx(0.51 * 1024 - 192 - 0.5) and k.depth.cy_px == pytest.approx(
        0.52 * 1024 - 180 - 0.5)
    # OpenCV order k1 k2 p1 p2 k3 k4 k5 k6, with the file's p1 last and p2 before it
    np.testing.assert_allclose(k.depth.dist_coeffs, [0.11, 0.12, 0.0031, 0.0021, 0.13, 0.14, 0.15, 0.16])
    # colour, 1536P: the 4:3 calibration at 2048x1536, no crop
    assert (k.color.width_px, k.color.height_px) == (2048, 1536)
    assert k.color.fx_px == pytest.approx(0.47 * 2048) and k.color.fy_px == pytest.approx(0.63 * 1536)
    assert k.color.cx_px == pytest.approx(0.501 * 2048 - 0.5) and k.color.cy_px == pytest.approx(0.502 * 1536 - 0.5)
    np.testing.assert_allclose(k.color.dist_coeffs, [0.21, 0.22, -0.0032, -0.0022, 0.23, 0.24, 0.25, 0.26])
    np.testing.assert_allclose(k.T_color_from_depth[:3, 3], [-32.0, 1.5, 4.0])  # mm


def sdk_project(params: list[float], mode, pts: np.ndarray) -> np.ndarray:
    """The Azure Kinect SDK's transformation_project_internal (Brown-Conrady) after its mode-specific calibration
    (mode_specific_calibration.c), transcribed in numpy: an independent statement of the model and the order."""
    cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1 = params
    bw, bh = mode.calibration_image_binned_resolution
    ox, oy = mode.crop_offset
    cx, cy, fx, fy = cx * bw - ox - 0.5, cy * bh - oy - 0.5, fx * bw, fy * bh
    xp, yp = pts[:, 0] / pts[:, 2] - codx, pts[:, 1] / pts[:, 2] - cody
    rs = xp * xp + yp * yp
    d = (1 + k1 * rs + k2 * rs ** 2 + k3 * rs ** 3) / (1 + k4 * rs + k5 * rs ** 2 + k6 * rs ** 3)
    xp_d = xp * d + (rs + 2 * xp * xp) * p2 + 2 * xp * yp * p1
    yp_d = yp * d + (rs + 2 * yp * yp) * p1 + 2 * xp * yp * p2
    return np.stack([(xp_d + codx) * fx + cx, (yp_d + cody) * fy + cy], axis=1)


@pytest.mark.parametrize("depth_mode", list(KINECT_DEPTH_MODES))
@pytest.mark.parametrize("color_mode", ["720P", "1080P", "3072P"])
def test_kinect_projection_equals_sdk_formula(tmp_path, depth_mode, color_mode):
    data = kinect_data()
    # tangential terms large enough that a p1/p2 mix-up moves pixels by several px
    for loc, p in (("CALIBRATION_CameraLocationD0", (0.004, -0.006)),
                   ("CALIBRATION_CameraLocationPV0", (-0.003, 0.005))):
        e = camera_entry(data, loc)
        e["Intrinsics"]["ModelParameters"][12:14] = list(p)
    k = read_kinect_calibration(write_json(tmp_path, data), depth_mode, color_mode)
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-0.6, 0.6, 300), rng.uniform(-0.5, 0.5, 300), np.ones(300)]) * 1500.0
    for cam, loc, mode in ((k.depth, "CALIBRATION_CameraLocationD0", KINECT_DEPTH_MODES[depth_mode]),
                           (k.color, "CALIBRATION_CameraLocationPV0", KINECT_COLOR_MODES[color_mode])):
        ref = sdk_project(camera_entry(data, loc)["Intrinsics"]["ModelParameters"], mode, pts)
        np.testing.assert_allclose(cam.project(pts), ref, rtol=0, atol=1e-9)
        assert (cam.width_px, cam.height_px) == mode.output_image_resolution


def test_kinect_modes_are_one_sensor():
    """Geometry, not the formula: a point seen in two modes lands where cropping and 2x2 binning put it
    (pixel corners scale, pixel centres shift by the crop)."""
    ks = {(d, c): read_kinect_calibration(KINECT_JSON, d, c) for d in KINECT_DEPTH_MODES for c in ("720P", "1080P",
                                                                                                  "1536P", "3072P")}
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(-0.4, 0.4, 200), rng.uniform(-0.4, 0.4, 200), np.ones(200)]) * 2000.0
    depth = {d: ks[(d, "720P")].depth.project(pts) for d in KINECT_DEPTH_MODES}
    wfov = depth["WFOV_UNBINNED"]
    np.testing.assert_allclose(depth["NFOV_UNBINNED"], wfov - [192, 180], atol=1e-9)
    np.testing.assert_allclose(depth["WFOV_2X2BINNED"] + 0.5, (wfov + 0.5) / 2, atol=1e-9)
    np.testing.assert_allclose(depth["NFOV_2X2BINNED"], (wfov + 0.5) / 2 - 0.5 - [96, 90], atol=1e-9)
    color = {c: ks[("NFOV_UNBINNED", c)].color.project(pts) for c in ("720P", "1080P", "1536P", "3072P")}
    full = color["3072P"]  # the whole 4096x3072 sensor
    np.testing.assert_allclose(color["1536P"] + 0.5, (full + 0.5) / 2, atol=1e-9)
    np.testing.assert_allclose(color["720P"] + 0.5, (full + 0.5) * 1280 / 4096 - [0, 120], atol=1e-9)
    np.testing.assert_allclose(color["1080P"] + 0.5, (full + 0.5) * 1920 / 4096 - [0, 180], atol=1e-9)


def test_kinect_legacy_16_9_colour_calibration(tmp_path):
    """A 4096x2304 (16:9) colour calibration is the 4:3 one cropped by 384 rows: same cameras in every mode."""
    data = kinect_data()
    legacy = copy.deepcopy(data)
    c = camera_entry(legacy, "CALIBRATION_CameraLocationPV0")
    p = c["Intrinsics"]["ModelParameters"]
    p[1] = (p[1] * 3072 - 384) / 2304  # cy
    p[3] = p[3] * 3072 / 2304  # fy
    c["SensorHeight"] = 2304
    for mode in KINECT_COLOR_MODES:
        a = kinect_calibration_from_dict(data, "4x3.json", "NFOV_UNBINNED", mode).color
        b = kinect_calibration_from_dict(legacy, "16x9.json", "NFOV_UNBINNED", mode).color
        for f in ("fx_px", "fy_px", "cx_px", "cy_px"):
            assert getattr(b, f) == pytest.approx(getattr(a, f), abs=1e-9)
        assert (a.width_px, a.height_px) == (b.width_px, b.height_px)


def test_kinect_extrinsic_from_both_cameras(tmp_path):
    """Each camera's Rt is T_camera_from_world: T_color_from_depth = Rt_color @ inv(Rt_depth), rows first, metres."""
    data = kinect_data()
    T_depth_from_world = T_from_rotvec([0.02, -0.01, 0.03], [5.0, -3.0, 1.0])  # mm
    T_color_from_world = T_from_rotvec([-0.05, 0.08, 0.01], [-32.0, 2.0, 4.0])
    for loc, T_camera_from_world in (("CALIBRATION_CameraLocationD0", T_depth_from_world),
                                     ("CALIBRATION_CameraLocationPV0", T_color_from_world)):
        camera_entry(data, loc)["Rt"] = {"Rotation": T_camera_from_world[:3, :3].ravel().tolist(),
                                         "Translation": (T_camera_from_world[:3, 3] / 1000.0).tolist()}
    k = read_kinect_calibration(write_json(tmp_path, data), "WFOV_UNBINNED", "720P")
    p_world = np.array([[100.0, -50.0, 900.0], [-300.0, 200.0, 1500.0]])
    p_depth, p_color = transform_points(T_depth_from_world, p_world), transform_points(T_color_from_world, p_world)
    np.testing.assert_allclose(transform_points(k.T_color_from_depth, p_depth), p_color, atol=1e-9)


@pytest.mark.parametrize("change, field, expected", [
    (lambda d: d.pop("CalibrationInformation"), None, "CalibrationInformation"),
    (lambda d: d["CalibrationInformation"]["Cameras"].pop(0), "Cameras[].Location", "CameraLocationD0"),
    (lambda d: camera_entry(d, "CALIBRATION_CameraLocationPV0")["Intrinsics"].update(
        ModelType="CALIBRATION_LensDistortionModelRational6KT"), "Intrinsics.ModelType", "BrownConrady"),
    (lambda d: camera_entry(d, "CALIBRATION_CameraLocationD0")["Intrinsics"]["ModelParameters"].__setitem__(10, 0.01),
     "codx, cody", "0, 0"),
    (lambda d: camera_entry(d, "CALIBRATION_CameraLocationD0").update(SensorWidth=512, SensorHeight=512),
     "SensorWidth/SensorHeight", "1024 x 1024"),
    (lambda d: camera_entry(d, "CALIBRATION_CameraLocationPV0").update(SensorWidth=1000, SensorHeight=1000),
     "SensorWidth/SensorHeight", "4:3 or 16:9"),
    (lambda d: camera_entry(d, "CALIBRATION_CameraLocationD0")["Intrinsics"]["ModelParameters"].pop(),
     "ModelParameters", "at least 14 numbers"),
    (lambda d: camera_entry(d, "CALIBRATION_CameraLocationPV0")["Intrinsics"]["ModelParameters"].__setitem__(
        2, float("nan")), "ModelParameters", "finite"),
    (lambda d: camera_entry(d, "CALIBRATION_CameraLocationPV0")["Rt"]["Rotation"].__setitem__(0, 1.5),
     "Rt.Rotation", "rotation matrix"),
    (lambda d: camera_entry(d, "CALIBRATION_CameraLocationPV0")["Rt"].pop("Translation"), "Rt.Translation",
     "this key"),
])
def test_kinect_errors(tmp_path, change, field, expected):
    data = kinect_data()
    change(data)
    path = write_json(tmp_path, data)
    with pytest.raises(InputError) as e:
        read_kinect_calibration(path, "NFOV_UNBINNED", "720P")
    msg = str(e.value)
    assert "calibration.json" in msg and expected in msg and "\n" not in msg
    if field:
        assert field in (e.value.field or "")


def test_kinect_modes_and_broken_files(tmp_path):
    with pytest.raises(InputError, match=r"kinect_depth_mode.*one of NFOV_2X2BINNED.*'NFOV'"):
        read_kinect_calibration(KINECT_JSON, "NFOV", "720P")
    with pytest.raises(InputError, match=r"kinect_color_mode.*none given.*session.yaml"):
        read_kinect_calibration(KINECT_JSON, "NFOV_UNBINNED", None)
    (tmp_path / "cut.json").write_text(KINECT_JSON.read_text()[:500])
    with pytest.raises(InputError, match=r"cut.json.*valid JSON.*truncated"):
        read_kinect_calibration(tmp_path / "cut.json", "NFOV_UNBINNED", "720P")


# ---- Mech-Eye API intrinsics ------------------------------------------------------------------
def test_mecheye_example_file():
    texture, depth, T_mech_from_depth = read_mecheye_intrinsics(MECHEYE_EXAMPLE)
    raw = yaml.safe_load(MECHEYE_EXAMPLE.read_text())["camera_intrinsics"]
    assert (texture.width_px, texture.height_px, depth.width_px, depth.height_px) == (2048, 1536, 1920, 1200)
    m = raw["texture"]["camera_matrix"]
    assert (texture.fx_px, texture.fy_px, texture.cx_px, texture.cy_px) == (m["fx"], m["fy"], m["cx"], m["cy"])
    dd = raw["depth"]["camera_distortion"]
    assert depth.dist_coeffs == [dd["k1"], dd["k2"], dd["p1"], dd["p2"], dd["k3"]]  # OpenCV order, as the API's
    np.testing.assert_array_equal(T_mech_from_depth[:3, :3], raw["depth_to_texture"]["rotation"])
    np.testing.assert_array_equal(T_mech_from_depth[:3, 3], raw["depth_to_texture"]["translation"])  # mm, as the API's
    np.testing.assert_array_equal(T_mech_from_depth[3], [0, 0, 0, 1])


def test_mecheye_one_camera_and_errors(tmp_path):
    data = yaml.safe_load(MECHEYE_EXAMPLE.read_text())
    one = copy.deepcopy(data)
    one["camera_intrinsics"]["depth"] = one["camera_intrinsics"]["texture"]
    one["camera_intrinsics"]["depth_to_texture"] = {"rotation": np.eye(3).tolist(), "translation": [0, 0, 0]}
    one["camera_resolutions"]["depth"] = one["camera_resolutions"]["texture"]
    texture, depth, T_mech_from_depth = MechEyeIntrinsicsFile.from_dict(one, "one.yaml").cameras()
    assert depth is None and T_mech_from_depth is None and texture.width_px == 2048

    def refused(change, field, words):
        d = copy.deepcopy(data)
        change(d)
        p = tmp_path / "m.yaml"
        p.write_text(yaml.safe_dump(d))
        with pytest.raises(InputError) as e:
            read_mecheye_intrinsics(p)
        assert str(p) in str(e.value) and field in e.value.field and words in str(e.value)

    refused(lambda d: d["camera_intrinsics"]["texture"]["camera_matrix"].update(fx=-1.0),
            "camera_intrinsics.texture.camera_matrix.fx", "greater than 0")
    refused(lambda d: d["camera_intrinsics"]["depth"].pop("camera_distortion"),
            "camera_intrinsics.depth.camera_distortion", "Field required")
    refused(lambda d: d["camera_intrinsics"]["depth"]["camera_distortion"].update(k4=0.1),
            "camera_intrinsics.depth.camera_distortion.k4", "Extra inputs")
    refused(lambda d: d["camera_intrinsics"]["depth_to_texture"]["rotation"][0].__setitem__(0, 0.9),
            "camera_intrinsics.depth_to_texture.rotation", "not a rotation matrix")
    refused(lambda d: d["camera_intrinsics"]["depth_to_texture"].update(translation=[1.0, 2.0]),
            "camera_intrinsics.depth_to_texture.translation", "3 finite numbers")
    refused(lambda d: d.pop("camera_resolutions"), "camera_resolutions", "Field required")


# ---- the entry point and the session ------------------------------------------------------------
def test_load_structured_light_cameras_recognises_each_file(tmp_path):
    cams = load_structured_light_cameras(KINECT_JSON, depth_mode="NFOV_UNBINNED", color_mode="720P")
    k = read_kinect_calibration(KINECT_JSON, "NFOV_UNBINNED", "720P")
    assert cams.texture == k.color and cams.depth == k.depth
    np.testing.assert_array_equal(cams.T_mech_from_depth, k.T_color_from_depth)
    assert load_structured_light_cameras(MECHEYE_EXAMPLE).depth.width_px == 1920
    cam = PinholeCamera(width_px=640, height_px=480, fx_px=600.0, fy_px=590.0, cx_px=321.0, cy_px=238.5,
                        dist_coeffs=[0.1, -0.05, 0.001, 0.0, 0.0])
    CameraFile(camera=cam).write(tmp_path / "one.yaml")
    assert tuple(load_structured_light_cameras(tmp_path / "one.yaml")) == (cam, None, None)
    with pytest.raises(InputError, match=r"kinect_depth_mode.*none given"):
        load_structured_light_cameras(KINECT_JSON)
    with pytest.raises(InputError, match=r"one.yaml.*kinect_depth_mode/kinect_color_mode.*remove the kinect_"):
        load_structured_light_cameras(tmp_path / "one.yaml", depth_mode="NFOV_UNBINNED", color_mode="720P")
    (tmp_path / "other.json").write_text(json.dumps({"fx": 1.0}))
    with pytest.raises(InputError, match=r"other.json.*Azure Kinect calibration.json.*\['fx'\]"):
        load_structured_light_cameras(tmp_path / "other.json")
    with pytest.raises(InputError, match=r"missing.yaml.*no such file"):
        load_structured_light_cameras(tmp_path / "missing.yaml")


def kinect_session(tmp_path: Path, **extra) -> Path:
    root = tmp_path / "session"
    root.mkdir(parents=True)
    (root / "calibration.json").write_text(KINECT_JSON.read_text())
    zl = PinholeCamera(width_px=1280, height_px=720, fx_px=700.0, fy_px=700.0, cx_px=640.2, cy_px=359.7)
    StereoCalibrationFile(zed=RectifiedStereo(left=zl, baseline_mm=63.0)).write(root / "zed_calibration.yaml")
    cfg = {"schema_version": 1, "mech_intrinsics": "calibration.json", "kinect_depth_mode": "NFOV_UNBINNED",
           "kinect_color_mode": "720P", **extra}
    (root / "session.yaml").write_text(yaml.safe_dump(cfg))
    return root


def test_open_session_with_a_kinect_calibration(tmp_path):
    s = open_session(kinect_session(tmp_path))
    k = read_kinect_calibration(KINECT_JSON, "NFOV_UNBINNED", "720P")
    assert s.mech == k.color and s.depth_cam == k.depth and s.depth_camera == k.depth
    np.testing.assert_array_equal(s.T_mech_from_depth, k.T_color_from_depth)


def test_open_session_refuses_two_depth_cameras(tmp_path):
    root = kinect_session(tmp_path, depth_intrinsics="depth.yaml")
    with pytest.raises(InputError) as e:
        open_session(root)
    assert "session.yaml" in str(e.value) and "depth_intrinsics" in e.value.field and "\n" not in str(e.value)
    root2 = kinect_session(tmp_path / "b", kinect_depth_mode="NFOV")
    with pytest.raises(InputError, match=r"session.yaml.*kinect_depth_mode"):
        open_session(root2)
