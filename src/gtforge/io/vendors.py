"""Vendor calibration files of structured-light / RGB-D units with a depth camera beside the texture camera.

- Azure Kinect (and Orbbec's Azure-Kinect-compatible wrapper) ``calibration.json`` (``CalibrationInformation``):
  :func:`read_kinect_calibration`, for one depth mode and one colour mode.
- Mech-Eye API intrinsics (``Camera.get_camera_intrinsics`` + ``get_camera_resolutions``) written as YAML:
  :class:`MechEyeIntrinsicsFile`, :func:`read_mecheye_intrinsics`.
- :func:`load_structured_light_cameras`: the one entry point a session uses; it also takes the one-camera
  gtforge / ROS / OpenCV YAML of :func:`gtforge.io.cameras.load_camera`.

Frames (docs/cameras.md): ``mech`` is the texture camera (Kinect: the colour camera), ``depth`` the camera of the
depth map's pixel grid; ``T_mech_from_depth`` maps depth-camera points (mm) into the texture camera.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import numpy as np
import yaml
from pydantic import Field, field_validator

from gtforge.core.camera import PinholeCamera
from gtforge.core.geometry import invert_T, make_T
from gtforge.core.schema import GTModel, VersionedFile, load_yaml, parse_error
from gtforge.errors import InputError
from gtforge.io.cameras import load_camera


class StructuredLightCameras(NamedTuple):
    """What a session needs from a camera file: the texture camera and, when separate, the depth camera."""

    texture: PinholeCamera  # the ``mech`` frame: the camera of the 2D (texture / colour) image
    depth: PinholeCamera | None  # the camera of the depth map's pixel grid; None: the texture camera
    T_mech_from_depth: np.ndarray | None  # 4x4 float64, mm; None when ``depth`` is None


# ---- Azure Kinect / Orbbec calibration.json --------------------------------------------------------
@dataclass(frozen=True)
class KinectModeInfo:
    """One row of the Azure Kinect SDK's mode tables (``k4a_camera_calibration_mode_info_t``), in pixels."""

    calibration_image_binned_resolution: tuple[int, int]
    crop_offset: tuple[int, int]
    output_image_resolution: tuple[int, int]


# src/transformation/mode_specific_calibration.c, transformation_get_mode_specific_depth_camera_calibration
# (the raw depth calibration is for the 1024x1024 sensor image)
KINECT_DEPTH_MODES: dict[str, KinectModeInfo] = {
    "NFOV_2X2BINNED": KinectModeInfo((512, 512), (96, 90), (320, 288)),
    "NFOV_UNBINNED": KinectModeInfo((1024, 1024), (192, 180), (640, 576)),
    "WFOV_2X2BINNED": KinectModeInfo((512, 512), (0, 0), (512, 512)),
    "WFOV_UNBINNED": KinectModeInfo((1024, 1024), (0, 0), (1024, 1024)),
}
# ... transformation_get_mode_specific_color_camera_calibration (after converting to the 4:3 calibration)
KINECT_COLOR_MODES: dict[str, KinectModeInfo] = {
    "720P": KinectModeInfo((1280, 960), (0, 120), (1280, 720)),
    "1080P": KinectModeInfo((1920, 1440), (0, 180), (1920, 1080)),
    "1440P": KinectModeInfo((2560, 1920), (0, 240), (2560, 1440)),
    "1536P": KinectModeInfo((2048, 1536), (0, 0), (2048, 1536)),
    "2160P": KinectModeInfo((3840, 2880), (0, 360), (3840, 2160)),
    "3072P": KinectModeInfo((4096, 3072), (0, 0), (4096, 3072)),
}
# legacy 16:9 colour calibrations are first converted to 4:3, kept normalised (same function)
_KINECT_LEGACY_16_9 = KinectModeInfo((4096, 2304), (0, -384), (4096, 3072))
KINECT_DEPTH_LOCATION = "CALIBRATION_CameraLocationD0"
KINECT_COLOR_LOCATION = "CALIBRATION_CameraLocationPV0"
KINECT_MODEL_TYPE = "CALIBRATION_LensDistortionModelBrownConrady"


@dataclass(frozen=True)
class KinectCalibration:
    """Both cameras of an Azure Kinect calibration for one depth mode and one colour mode."""

    depth: PinholeCamera
    color: PinholeCamera
    T_color_from_depth: np.ndarray  # 4x4 float64, mm
    depth_metric_radius: float  # the SDK refuses projections beyond this normalised radius (not used by gtforge)
    color_metric_radius: float


def is_kinect_calibration(data: Any) -> bool:
    return isinstance(data, dict) and "CalibrationInformation" in data


def _mode(name: str | None, table: dict[str, KinectModeInfo], field: str, path: Path) -> KinectModeInfo:
    if name is None:
        raise InputError(path, field, f"a Kinect mode for this calibration.json ({', '.join(table)})", "none given",
                         f"set '{field}' in session.yaml (the mode the captures were recorded in)")
    if name not in table:
        raise InputError(path, field, f"one of {', '.join(table)}", repr(name), "the names of the Azure Kinect SDK's "
                         "k4a_depth_mode_t / k4a_color_resolution_t without the K4A_..._ prefix")
    return table[name]


def _numbers(v: Any, n: int, path: Path, field: str, at_least: bool = False) -> np.ndarray:
    ok = isinstance(v, list) and (len(v) >= n if at_least else len(v) == n) and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
    if not ok:
        got = f"a list of {len(v)}" if isinstance(v, list) else type(v).__name__
        raise InputError(path, field, f"{'at least ' if at_least else ''}{n} numbers", got,
                         "is the calibration.json complete (as k4a_device_get_raw_calibration writes it)?")
    a = np.asarray(v, np.float64)
    if not np.isfinite(a).all():
        raise InputError(path, field, "finite numbers", "NaN/inf", "the calibration export is broken")
    return a


def _get(d: Any, key: str, path: Path, where: str) -> Any:
    if not isinstance(d, dict) or key not in d:
        raise InputError(path, f"{where}.{key}" if where else key, "this key", "missing",
                         "is this the Azure Kinect calibration.json (CalibrationInformation)?")
    return d[key]


def _kinect_camera_entry(cameras: list, location: str, path: Path) -> tuple[dict, str]:
    for i, cam in enumerate(cameras):
        if isinstance(cam, dict) and cam.get("Location") == location:
            return cam, f"CalibrationInformation.Cameras[{i}]"
    have = [c.get("Location") for c in cameras if isinstance(c, dict)]
    raise InputError(path, "CalibrationInformation.Cameras[].Location", f"a camera at {location}",
                     f"only {have}", "the SDK needs the depth camera D0 and the colour camera PV0")


def _kinect_mode_camera(entry: dict, where: str, mode: KinectModeInfo, path: Path, is_depth: bool) -> PinholeCamera:
    intr = _get(entry, "Intrinsics", path, where)
    model = _get(intr, "ModelType", path, f"{where}.Intrinsics")
    if model != KINECT_MODEL_TYPE:
        hint = ("Rational6KT (early internal devices; deprecated in the SDK) has a tangential term OpenCV cannot "
                "express" if model == "CALIBRATION_LensDistortionModelRational6KT" else
                "the Azure Kinect SDK transforms only Brown-Conrady (= OpenCV's rational model) calibrations")
        raise InputError(path, f"{where}.Intrinsics.ModelType", KINECT_MODEL_TYPE, repr(model), hint)
    count = _get(intr, "ModelParameterCount", path, f"{where}.Intrinsics")
    if not isinstance(count, int) or count < 14:
        raise InputError(path, f"{where}.Intrinsics.ModelParameterCount", "14", repr(count),
                         "the SDK needs 14 parameters: cx cy fx fy k1..k6 codx cody p2 p1")
    p = _numbers(_get(intr, "ModelParameters", path, f"{where}.Intrinsics"), 14, path,
                 f"{where}.Intrinsics.ModelParameters", at_least=True)
    # k4a_calibration_intrinsic_parameters_t: cx cy fx fy k1 k2 k3 k4 k5 k6 codx cody p2 p1 (normalised cx..fy)
    cx, cy, fx, fy, k1, k2, k3, k4, k5, k6, codx, cody, p2, p1 = p[:14]
    if codx != 0.0 or cody != 0.0:
        raise InputError(path, f"{where}.Intrinsics.ModelParameters[10:12] (codx, cody)", "0, 0 (Brown-Conrady)",
                         f"{codx}, {cody}", "a centre of distortion off the principal point has no OpenCV equivalent")
    w_cal = _get(entry, "SensorWidth", path, where)
    h_cal = _get(entry, "SensorHeight", path, where)
    if not (isinstance(w_cal, int) and isinstance(h_cal, int) and w_cal > 0 and h_cal > 0):
        raise InputError(path, f"{where}.SensorWidth/SensorHeight", "positive integers", f"{w_cal!r}, {h_cal!r}",
                         "is the calibration.json complete (as k4a_device_get_raw_calibration writes it)?")
    if is_depth:
        if (w_cal, h_cal) != (1024, 1024):
            raise InputError(path, f"{where}.SensorWidth/SensorHeight", "1024 x 1024 (the depth sensor)",
                             f"{w_cal} x {h_cal}", "the Azure Kinect SDK's depth modes assume the 1024x1024 sensor")
    elif w_cal * 9 // 16 == h_cal:  # legacy 16:9 calibration -> 4:3, still normalised (SDK: integer arithmetic)
        L = _KINECT_LEGACY_16_9
        cx = (cx * L.calibration_image_binned_resolution[0] - L.crop_offset[0]) / L.output_image_resolution[0]
        cy = (cy * L.calibration_image_binned_resolution[1] - L.crop_offset[1]) / L.output_image_resolution[1]
        fx = fx * L.calibration_image_binned_resolution[0] / L.output_image_resolution[0]
        fy = fy * L.calibration_image_binned_resolution[1] / L.output_image_resolution[1]
    elif w_cal * 3 // 4 != h_cal:
        raise InputError(path, f"{where}.SensorWidth/SensorHeight", "a 4:3 or 16:9 colour calibration",
                         f"{w_cal} x {h_cal}", "the Azure Kinect SDK refuses other aspect ratios too")
    bw, bh = mode.calibration_image_binned_resolution
    ox, oy = mode.crop_offset
    # normalised -> pixels of the binned calibration image, minus the crop; then the SDK's "pixelized zero centred"
    # step: (0, 0) moves from the top-left pixel's corner to its centre (OpenCV's and gtforge's convention)
    try:
        return PinholeCamera(width_px=mode.output_image_resolution[0], height_px=mode.output_image_resolution[1],
                             fx_px=fx * bw, fy_px=fy * bh, cx_px=cx * bw - ox - 0.5, cy_px=cy * bh - oy - 0.5,
                             dist_coeffs=[k1, k2, p1, p2, k3, k4, k5, k6])
    except ValueError as exc:  # fx <= 0 etc.
        raise InputError(path, f"{where}.Intrinsics.ModelParameters", "positive fx, fy", f"{fx}, {fy}",
                         str(exc).splitlines()[0]) from None


def _kinect_T_cam_from_world(entry: dict, where: str, path: Path) -> np.ndarray:
    rt = _get(entry, "Rt", path, where)
    R = _numbers(_get(rt, "Rotation", path, f"{where}.Rt"), 9, path, f"{where}.Rt.Rotation").reshape(3, 3)  # row-major
    t_m = _numbers(_get(rt, "Translation", path, f"{where}.Rt"), 3, path, f"{where}.Rt.Translation")
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-5 or abs(np.linalg.det(R) - 1.0) > 1e-5:
        raise InputError(path, f"{where}.Rt.Rotation", "a rotation matrix (row-major 3x3, orthonormal, det +1)",
                         f"{R.ravel().round(6).tolist()}", "the calibration export is broken")
    return make_T(R, t_m * 1000.0)  # metres in the file -> mm


def read_kinect_calibration(path: str | Path, depth_mode: str | None, color_mode: str | None) -> KinectCalibration:
    """Azure Kinect ``calibration.json`` -> depth camera, colour camera and ``T_color_from_depth`` for one mode pair.

    Exactly the Azure Kinect SDK's arithmetic (src/transformation/mode_specific_calibration.c, in float64 where the
    SDK uses float32): pixel intrinsics from the normalised ones through the mode's binned resolution and crop, then
    -0.5 px (pixel corner -> pixel centre); distortion (k1..k6, p1, p2) as OpenCV's rational model; each camera's
    ``Rt`` is ``T_camera_from_world`` (the world is the depth camera, whose ``Rt`` is the identity), so
    ``T_color_from_depth = Rt_color @ inv(Rt_depth)`` (src/transformation/extrinsic_transformation.c), metres -> mm.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "an Azure Kinect calibration.json", "no such file", "check the path")
    try:
        data = json.loads(path.read_text(errors="replace"))
    except json.JSONDecodeError as exc:
        raise InputError(path, None, "valid JSON (Azure Kinect calibration.json)", *parse_error(exc, "JSON")) from None
    return kinect_calibration_from_dict(data, path, depth_mode, color_mode)


def kinect_calibration_from_dict(data: Any, path: str | Path, depth_mode: str | None,
                                 color_mode: str | None) -> KinectCalibration:
    path = Path(path)
    dmode = _mode(depth_mode, KINECT_DEPTH_MODES, "kinect_depth_mode", path)
    cmode = _mode(color_mode, KINECT_COLOR_MODES, "kinect_color_mode", path)
    info = _get(data, "CalibrationInformation", path, "")
    cameras = _get(info, "Cameras", path, "CalibrationInformation")
    if not isinstance(cameras, list):
        raise InputError(path, "CalibrationInformation.Cameras", "a list of cameras", type(cameras).__name__,
                         "is the calibration.json complete (as k4a_device_get_raw_calibration writes it)?")
    d_entry, d_where = _kinect_camera_entry(cameras, KINECT_DEPTH_LOCATION, path)
    c_entry, c_where = _kinect_camera_entry(cameras, KINECT_COLOR_LOCATION, path)
    depth = _kinect_mode_camera(d_entry, d_where, dmode, path, is_depth=True)
    color = _kinect_mode_camera(c_entry, c_where, cmode, path, is_depth=False)
    T_color_from_world = _kinect_T_cam_from_world(c_entry, c_where, path)
    T_depth_from_world = _kinect_T_cam_from_world(d_entry, d_where, path)
    T_color_from_depth = T_color_from_world @ invert_T(T_depth_from_world)

    def radius(entry, where):  # calibration.c, fill_in_camera_cal_data: <= 1e-4 means "not estimated" -> 1.7
        r = entry.get("MetricRadius", 0.0)
        return float(r) if isinstance(r, (int, float)) and r > 1e-4 else 1.7

    return KinectCalibration(depth, color, T_color_from_depth, radius(d_entry, d_where), radius(c_entry, c_where))


# ---- Mech-Eye API intrinsics YAML ----------------------------------------------------------------
def _finite(v: float, info) -> float:
    if not math.isfinite(v):
        raise ValueError(f"{info.field_name} must be finite")
    return v


class MechEyeCameraMatrix(GTModel):
    """``CameraMatrix``: fx, fy, cx, cy in pixels."""

    fx: float = Field(gt=0)
    fy: float = Field(gt=0)
    cx: float
    cy: float
    _fin = field_validator("fx", "fy", "cx", "cy")(_finite)


class MechEyeCameraDistortion(GTModel):
    """``CameraDistortion``: OpenCV's k1, k2, p1, p2, k3."""

    k1: float
    k2: float
    p1: float
    p2: float
    k3: float
    _fin = field_validator("k1", "k2", "p1", "p2", "k3")(_finite)


class MechEyeIntrinsics2DCamera(GTModel):
    """``Intrinsics2DCamera``: ``camera_matrix`` + ``camera_distortion``."""

    camera_matrix: MechEyeCameraMatrix
    camera_distortion: MechEyeCameraDistortion


class MechEyeTransformation(GTModel):
    """``Transformation``: ``rotation`` (3x3, rows) and ``translation`` (mm); p_texture = R @ p_depth + t."""

    rotation: list[list[float]]
    translation: list[float]

    @field_validator("rotation")
    @classmethod
    def _rot(cls, v):
        R = np.asarray(v, np.float64)
        if R.shape != (3, 3) or not np.isfinite(R).all():
            raise ValueError(f"shape {R.shape}, expected 3 rows of 3 finite numbers")
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-5 or abs(np.linalg.det(R) - 1.0) > 1e-5:
            raise ValueError("not a rotation matrix (orthonormal, det +1)")
        return R.tolist()

    @field_validator("translation")
    @classmethod
    def _t(cls, v):
        if len(v) != 3 or not all(math.isfinite(x) for x in v):
            raise ValueError(f"{len(v)} numbers, expected 3 finite numbers (x, y, z in mm)")
        return v

    @property
    def T_texture_from_depth(self) -> np.ndarray:
        return make_T(np.array(self.rotation), np.array(self.translation))


class MechEyeCameraIntrinsics(GTModel):
    """``CameraIntrinsics``: ``texture``, ``depth``, ``depth_to_texture``."""

    texture: MechEyeIntrinsics2DCamera
    depth: MechEyeIntrinsics2DCamera
    depth_to_texture: MechEyeTransformation  # identity where the texture camera is the depth camera


class MechEyeSize(GTModel):
    width: int = Field(gt=0)
    height: int = Field(gt=0)


class MechEyeCameraResolutions(GTModel):
    """``CameraResolutions``: ``texture`` and ``depth`` image sizes (px)."""

    texture: MechEyeSize
    depth: MechEyeSize


class MechEyeIntrinsicsFile(VersionedFile):
    """What the Mech-Eye API reports about a camera, as YAML (docs/cameras.md has an example).

    Field names are the Mech-Eye API's (Python ``mecheye.area_scan_3d_camera``; C++ ``mmind::eye`` uses camelCase:
    ``cameraMatrix``, ``cameraDistortion``, ``depthToTexture``): ``camera_intrinsics`` is what
    ``Camera.get_camera_intrinsics`` fills in, ``camera_resolutions`` what ``Camera.get_camera_resolutions`` does.
    """

    KIND: ClassVar[str] = "Mech-Eye API intrinsics file"

    camera_intrinsics: MechEyeCameraIntrinsics
    camera_resolutions: MechEyeCameraResolutions

    @staticmethod
    def _camera(c: MechEyeIntrinsics2DCamera, size: MechEyeSize) -> PinholeCamera:
        m, d = c.camera_matrix, c.camera_distortion
        return PinholeCamera(width_px=size.width, height_px=size.height, fx_px=m.fx, fy_px=m.fy, cx_px=m.cx,
                             cy_px=m.cy, dist_coeffs=[d.k1, d.k2, d.p1, d.p2, d.k3])

    def cameras(self) -> StructuredLightCameras:
        """Texture camera, depth camera and ``T_mech_from_depth``; one camera (depth None) when the API reports
        the same intrinsics for both and no transformation (models whose texture camera is the depth camera)."""
        ci, res = self.camera_intrinsics, self.camera_resolutions
        texture = self._camera(ci.texture, res.texture)
        depth = self._camera(ci.depth, res.depth)
        T_mech_from_depth = ci.depth_to_texture.T_texture_from_depth  # (mech: the texture camera)
        if depth == texture and np.array_equal(T_mech_from_depth, np.eye(4)):
            return StructuredLightCameras(texture, None, None)
        return StructuredLightCameras(texture, depth, T_mech_from_depth)


def read_mecheye_intrinsics(path: str | Path) -> StructuredLightCameras:
    return MechEyeIntrinsicsFile.read(path).cameras()


def is_mecheye_intrinsics(data: Any) -> bool:
    return isinstance(data, dict) and "camera_intrinsics" in data


# ---- the session's entry point -----------------------------------------------------------------
def load_structured_light_cameras(path: str | Path, *, depth_mode: str | None = None,
                                  color_mode: str | None = None) -> StructuredLightCameras:
    """The structured-light unit's cameras from one file, recognised by content:

    - Azure Kinect / Orbbec ``calibration.json`` (``CalibrationInformation``): colour = texture camera, depth camera,
      ``T_mech_from_depth = T_color_from_depth``; needs ``depth_mode`` and ``color_mode`` (:data:`KINECT_DEPTH_MODES`,
      :data:`KINECT_COLOR_MODES`);
    - Mech-Eye API intrinsics YAML (``camera_intrinsics`` + ``camera_resolutions``);
    - one camera as gtforge / ROS camera_info / OpenCV YAML (:func:`gtforge.io.cameras.load_camera`): depth None.
    """

    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "a camera file (gtforge/ROS/OpenCV YAML, Mech-Eye API YAML, Kinect JSON)",
                         "no such file", "check the path (session.yaml: mech_intrinsics)")
    text = path.read_text(errors="replace")
    data = None
    if text.lstrip().startswith("{"):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(path, None, "valid JSON", *parse_error(exc, "JSON")) from None
        if not is_kinect_calibration(data):
            keys = list(data)[:5] if isinstance(data, dict) else type(data).__name__
            raise InputError(path, None, "an Azure Kinect calibration.json (top-level 'CalibrationInformation')",
                             f"a JSON file with {keys}", "gtforge reads cameras as YAML or as the Kinect JSON")
    elif not text.lstrip().startswith("%YAML"):
        try:
            data = load_yaml(text)
        except yaml.YAMLError:
            data = None  # load_camera reports the parse error
    if is_kinect_calibration(data):
        k = kinect_calibration_from_dict(data, path, depth_mode, color_mode)
        return StructuredLightCameras(k.color, k.depth, k.T_color_from_depth)
    if depth_mode is not None or color_mode is not None:
        raise InputError(path, "kinect_depth_mode/kinect_color_mode", "an Azure Kinect calibration.json with them",
                         "a camera file that is not one", "remove the kinect_* fields from session.yaml, or point "
                         "mech_intrinsics at the Kinect's calibration.json")
    if is_mecheye_intrinsics(data):
        return MechEyeIntrinsicsFile.from_dict(data, path).cameras()
    return StructuredLightCameras(load_camera(path), None, None)
