"""Readers for camera intrinsics: ROS camera_info YAML, OpenCV FileStorage YAML, gtforge YAML,
and the ZED factory calibration ``SN<serial>.conf`` (with rectification, no ZED SDK needed).

ZED SN.conf (docs/conventions.md, "ZED SN.conf"): the published code reads the STEREO section in
incompatible ways; each reading is named in ``ZED_CONF_READINGS`` and ``ZedFactoryCalibration.extrinsics``
applies one. ``gtforge calibrate`` chooses it from the board images (``gtforge.core.zed.rectification``); the
rectified right camera always sits at ``+baseline_mm`` along the left camera's x axis.
"""
from __future__ import annotations

import configparser
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import cv2
import numpy as np
import yaml

from gtforge.core.camera import (
    DIST_LENGTHS,
    ZED_EYE_WIDTHS,
    CameraFile,
    PinholeCamera,
    RectifiedStereo,
    StereoCalibrationFile,
)
from gtforge.core.schema import load_yaml, parse_error
from gtforge.core.bspline import resample
from gtforge.errors import InputError
from gtforge.infra.atomic import atomic_write_text

log = logging.getLogger("gtforge.io.cameras")

ZED_RES_HEIGHTS = {"2K": 1242, "FHD": 1080, "HD": 720, "VGA": 376}


# ---- generic YAML intrinsics ------------------------------------------------------------------
def _load_yaml_any(path: Path) -> dict:
    if not path.is_file():
        raise InputError(path, None, "an intrinsics file", "no such file", "check the path")
    text = path.read_text(errors="replace")
    if text.lstrip().startswith("%YAML:1.0") or "!!opencv-matrix" in text:
        return {"__opencv__": True}
    try:
        data = load_yaml(text)
    except yaml.YAMLError as exc:
        got, hint = parse_error(exc, text=text)
        raise InputError(path, None, "valid YAML", got, f"{hint}; the formats read: docs/capture-layout.md") from None
    if not isinstance(data, dict):
        raise InputError(path, None, "a YAML mapping", type(data).__name__,
                         "write a ROS camera_info, OpenCV FileStorage or gtforge camera YAML (docs/capture-layout.md)")
    return data


def _matrix(data: dict, keys: tuple[str, ...], shape: tuple[int, int], path: Path, required=True):
    for k in keys:
        if k in data:
            v = data[k]
            if isinstance(v, dict):
                v = v.get("data")
            a = np.asarray(v, dtype=np.float64).reshape(-1) if v is not None else np.zeros(0)
            n = shape[0] * shape[1]
            if a.size < n:
                raise InputError(path, k, f"{n} numbers", f"{a.size}",
                                 f"write the whole {shape[0]}x{shape[1]} matrix, row by row; is the export truncated?")
            a = a[:n].reshape(shape)
            if not np.all(np.isfinite(a)):
                raise InputError(path, k, "finite numbers", "NaN/inf", "the calibration export is broken")
            return a
    if required:
        raise InputError(path, "/".join(keys), "this key", "missing", "is this a ROS camera_info or OpenCV YAML?")
    return None


def _distortion(data: dict, path: Path) -> np.ndarray:
    """Every OpenCV lens model: ROS plumb_bob (5) and rational_polynomial (8), OpenCV's 4/5/8/12/14 coefficients."""

    for k in ("distortion_coefficients", "D", "d"):
        if k in data:
            v = data[k]
            if isinstance(v, dict):
                v = v.get("data")
            a = np.zeros(0) if v is None else np.asarray(v, dtype=np.float64).reshape(-1)
            if a.size not in DIST_LENGTHS:
                raise InputError(path, k, f"{'/'.join(map(str, DIST_LENGTHS[1:]))} distortion coefficients "
                                 "(OpenCV order: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tau_x tau_y]]]])", f"{a.size}",
                                 "export the camera's OpenCV lens model (docs/cameras.md 'Lens models')")
            if not np.all(np.isfinite(a)):
                raise InputError(path, k, "finite numbers", "NaN/inf", "the calibration export is broken")
            return a
    return np.zeros(0)


def _size(data: dict, path: Path) -> tuple[int, int]:
    w = data.get("image_width", data.get("width"))
    h = data.get("image_height", data.get("height"))
    if w is None or h is None:
        raise InputError(path, "image_width/image_height", "the image size", "missing",
                         "add image_width and image_height: the size in px of the images this calibration is for")
    return int(w), int(h)


def _opencv_fs(path: Path) -> dict:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.isOpened():
        raise InputError(path, None, "an OpenCV FileStorage file", "unreadable",
                         "check that it opens with cv2.FileStorage, or export ROS camera_info or gtforge YAML "
                         "(docs/capture-layout.md)")
    out = {}
    for key in ("camera_matrix", "distortion_coefficients", "projection_matrix_right", "P2"):
        node = fs.getNode(key)
        if not node.empty():
            out[key] = node.mat()
    for key in ("image_width", "image_height", "baseline_mm", "doffs_px"):
        node = fs.getNode(key)
        if not node.empty():
            out[key] = node.real()
    fs.release()
    return out


def _camera_from_dict(data: dict, path: Path, rectified: bool) -> PinholeCamera:
    w, h = _size(data, path)
    if rectified and any(k in data for k in ("projection_matrix", "P", "p")):
        P = _matrix(data, ("projection_matrix", "P", "p"), (3, 4), path)
        K, dist = P[:, :3], np.zeros(5)
    else:
        K = _matrix(data, ("camera_matrix", "K", "k"), (3, 3), path)
        dist = _distortion(data, path)
        if rectified and np.any(dist != 0):
            raise InputError(path, "distortion_coefficients", "zeros for a rectified camera", str(dist.tolist()),
                             "pass the rectified (projection) matrix, or use SN.conf with raw images")
    try:
        return PinholeCamera.from_K(K, w, h, dist)
    except Exception as exc:  # pydantic error on fx <= 0 etc.
        raise InputError(path, "camera_matrix", "positive finite fx, fy", f"{K.ravel().tolist()}",
                         str(exc).splitlines()[0]) from None


def load_camera(path: str | Path) -> PinholeCamera:
    """Structured-light (or any) camera intrinsics from ROS / OpenCV / gtforge YAML."""
    path = Path(path)
    data = _load_yaml_any(path)
    if data.get("__opencv__"):
        data = _opencv_fs(path)
    elif "schema_version" in data:
        return CameraFile.from_dict(data, path).camera
    return _camera_from_dict(data, path, rectified=False)


def load_zed_rectified(path: str | Path, right_path: str | Path | None = None) -> RectifiedStereo:
    """Rectified ZED calibration: gtforge YAML, ROS camera_info left (+ right), or OpenCV YAML with
    ``camera_matrix`` and ``baseline_mm`` (or a right projection matrix ``P2``)."""
    path = Path(path)
    data = _load_yaml_any(path)
    if data.get("__opencv__"):
        data = _opencv_fs(path)
    elif "schema_version" in data:
        return StereoCalibrationFile.from_dict(data, path).zed
    left = _camera_from_dict(data, path, rectified=True)
    if right_path is not None:
        rp = Path(right_path)
        rdata = _load_yaml_any(rp)
        P = _matrix(rdata, ("projection_matrix", "P", "p"), (3, 4), rp)
        baseline_mm = -P[0, 3] / P[0, 0]
        doffs = P[0, 2] - left.cx_px
        src = rp
    elif "baseline_mm" in data:
        baseline_mm, doffs, src = (float(np.ravel(data["baseline_mm"])[0]),
                                   float(np.ravel(data.get("doffs_px", 0.0))[0]), path)
    elif any(k in data for k in ("projection_matrix_right", "P2")):
        P = _matrix(data, ("projection_matrix_right", "P2"), (3, 4), path)
        baseline_mm, doffs, src = -P[0, 3] / P[0, 0], P[0, 2] - left.cx_px, path
    else:
        raise InputError(path, "baseline_mm", "a baseline (baseline_mm, P2, or a right camera_info file)",
                         "missing", "pass --zed-right-info with the right camera's camera_info YAML")
    if not math.isfinite(baseline_mm) or baseline_mm <= 0:
        raise InputError(src, "baseline", "a positive baseline (right camera at +x, P[0,3] = -fx*B)",
                         f"{baseline_mm:.4g} mm", "were left and right swapped?")
    # ROS camera_info is written in metres by most drivers (P[0,3] = -fx*B[m]); gtforge works in mm.
    if baseline_mm < 1.0:
        baseline_mm *= 1000.0
    return RectifiedStereo(left=left, baseline_mm=float(baseline_mm), doffs_px=float(doffs))


# ---- ZED SN.conf ----------------------------------------------------------------------------
# How the STEREO numbers of SN<serial>.conf become OpenCV's (R, T) with X_right = R @ X_left + T
# (cv2.stereoRectify). The published code disagrees (docs/conventions.md, "ZED SN.conf"), so every
# reading is named here; gtforge calibrate keeps the one whose rectified board corners line up best.
# B = Baseline (sign as written), TY, TZ = TY_<res>, TZ_<res> (mm), r = (RX, CV, RZ)_<res> (rad).
ZedConfReading = Literal["neg-x", "neg-all", "as-is", "right-centre",
                         "neg-x+inv-rot", "neg-all+inv-rot", "as-is+inv-rot", "right-centre+inv-rot"]
ZED_CONF_READINGS: tuple[str, ...] = get_args(ZedConfReading)
ZED_CONF_TRANSLATIONS = {
    "neg-x": "T = (-B, TY, TZ)",
    "neg-all": "T = -(B, TY, TZ)",
    "as-is": "T = (B, TY, TZ)",
    "right-centre": "T = -R @ (B, TY, TZ)  ((B, TY, TZ) = right camera centre in the left frame)",
}
# Used where no image can decide (SDK-rectified images, a session opened before calibrate chose):
# Stereolabs' Python sample and Stereolabs' own SN.conf writer (zed-opencv-calibration) both use it.
DEFAULT_ZED_CONF_READING: str = "neg-x"


def describe_zed_conf_reading(reading: str) -> str:
    """One line: the formula of ``reading`` (e.g. ``R = Rodrigues(r)^T, T = -(B, TY, TZ)``)."""
    base, inv = reading.removesuffix("+inv-rot"), reading.endswith("+inv-rot")
    return f"R = Rodrigues(RX, CV, RZ){'^T' if inv else ''}, {ZED_CONF_TRANSLATIONS[base]}"


def check_zed_conf_reading(reading: str, file=None, field: str = "zed_conf_reading") -> str:
    if reading not in ZED_CONF_READINGS:
        raise InputError(file, field, f"one of {', '.join(ZED_CONF_READINGS)}", repr(reading),
                         "see docs/conventions.md, 'ZED SN.conf'")
    return reading


@dataclass
class StereoRectifyResult:
    """``cv2.stereoRectify`` (zero disparity, alpha 0) for one reading: rotations raw -> rectified,
    projection matrices, and the signed baseline ``-P2[0, 3] / P2[0, 0]`` (negative: right camera at -x)."""

    R: np.ndarray
    T_mm: np.ndarray
    R_rect_from_raw_left: np.ndarray
    R_rect_from_raw_right: np.ndarray
    P_left: np.ndarray
    P_right: np.ndarray

    @property
    def baseline_signed_mm(self) -> float:
        return float(-self.P_right[0, 3] / self.P_right[0, 0])


@dataclass
class ZedFactoryCalibration:
    """Raw (unrectified) ZED calibration for one resolution, as written in SN<serial>.conf.

    The STEREO values are kept as written (``baseline_conf_mm`` keeps its sign); ``R_t_right_from_left(reading)``
    turns them into OpenCV's ``(R, t_mm)`` (``cv2.stereoRectify``'s ``R, T``)."""

    resolution: str
    left: PinholeCamera
    right: PinholeCamera
    baseline_conf_mm: float  # STEREO Baseline, sign as written
    ty_mm: float  # TY_<res>
    tz_mm: float  # TZ_<res>
    rotvec_conf_rad: np.ndarray  # (RX, CV, RZ)_<res>
    path: Path
    notes: tuple[str, ...] = ()  # how the file was read where it left something out (a missing k3 read as 0)

    @property
    def size_wh(self) -> tuple[int, int]:
        return self.left.width_px, self.left.height_px

    def R_t_right_from_left(self, reading: str = DEFAULT_ZED_CONF_READING) -> tuple[np.ndarray, np.ndarray]:
        """``(R, t_mm)`` of ``X_right = R @ X_left + t_mm`` under ``reading`` (``ZED_CONF_READINGS``): the pair
        ``cv2.stereoRectify`` takes (its ``R, T``)."""
        check_zed_conf_reading(reading)
        R = cv2.Rodrigues(np.asarray(self.rotvec_conf_rad, np.float64).reshape(3, 1))[0]
        if reading.endswith("+inv-rot"):
            R = R.T
        t_conf_mm = np.array([self.baseline_conf_mm, self.ty_mm, self.tz_mm])
        base = reading.removesuffix("+inv-rot")
        t_mm = {"neg-x": np.array([-t_conf_mm[0], t_conf_mm[1], t_conf_mm[2]]), "neg-all": -t_conf_mm,
                "as-is": t_conf_mm, "right-centre": -R @ t_conf_mm}[base]
        return R, t_mm

    def stereo_rectify(self, reading: str = DEFAULT_ZED_CONF_READING) -> StereoRectifyResult:
        R, t_mm = self.R_t_right_from_left(reading)
        size = self.size_wh
        R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(self.left.K, self.left.dist, self.right.K, self.right.dist,
                                                    size, R, t_mm.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY,
                                                    alpha=0, newImageSize=size)
        return StereoRectifyResult(R, t_mm, R1, R2, P1, P2)

    # the default reading's extrinsics, by the names used before readings were explicit
    @property
    def R_right_from_left(self) -> np.ndarray:
        return self.R_t_right_from_left()[0]

    @property
    def t_right_in_left_mm(self) -> np.ndarray:
        """The right camera's centre in the left camera frame (mm) under the default reading."""
        R, t_mm = self.R_t_right_from_left()
        return -R.T @ t_mm

    def rectification(self, reading: str = DEFAULT_ZED_CONF_READING) -> ZedRectification:
        """Rectification maps and the rectified model under ``reading``; refuses a reading that puts the
        right camera on the left (the rectified pair would have negative disparities)."""
        sr = self.stereo_rectify(reading)
        size = self.size_wh
        baseline_mm = sr.baseline_signed_mm
        if baseline_mm <= 0:
            raise InputError(self.path, "STEREO.Baseline", "a right camera at +x after rectification",
                             f"baseline {baseline_mm:.3f} mm under the reading '{reading}' "
                             f"({describe_zed_conf_reading(reading)})",
                             "choose another zed_conf_reading in session.yaml, or let gtforge calibrate choose it "
                             "from the board captures (docs/conventions.md)")
        rect = RectifiedStereo(left=PinholeCamera.from_K(sr.P_left[:, :3], *size), baseline_mm=float(baseline_mm),
                               doffs_px=float(sr.P_right[0, 2] - sr.P_left[0, 2]))
        maps_l = cv2.initUndistortRectifyMap(self.left.K, self.left.dist, sr.R_rect_from_raw_left, sr.P_left[:, :3],
                                             size, cv2.CV_32FC1)
        maps_r = cv2.initUndistortRectifyMap(self.right.K, self.right.dist, sr.R_rect_from_raw_right,
                                             sr.P_right[:, :3], size, cv2.CV_32FC1)
        return ZedRectification(stereo=rect, maps_left=maps_l, maps_right=maps_r,
                                R_rect_from_raw_left=sr.R_rect_from_raw_left,
                                R_rect_from_raw_right=sr.R_rect_from_raw_right, P_left=sr.P_left,
                                P_right=sr.P_right, reading=reading, factory=self)


@dataclass
class ZedRectification:
    stereo: RectifiedStereo
    maps_left: tuple[np.ndarray, np.ndarray]
    maps_right: tuple[np.ndarray, np.ndarray]
    R_rect_from_raw_left: np.ndarray
    R_rect_from_raw_right: np.ndarray
    P_left: np.ndarray
    P_right: np.ndarray
    reading: str = DEFAULT_ZED_CONF_READING
    factory: ZedFactoryCalibration | None = None
    correction: object | None = None  # gtforge.core.zed.selfcal.ZedRightCorrection folded into the right maps
    # calibrate-scale's yaw of the right camera folded into the right maps too
    # (gtforge.core.zed.selfcal.corrected_right)
    right_yaw_deg: float = 0.0
    # how both images are sampled at their maps: bilinear (cv2.remap, which rounds positions to 1/32 px), or cubic
    # B-spline at the exact positions (gtforge.core.bspline.resample) once gtforge corrects the
    # right camera (gtforge.core.zed.selfcal.corrected_rectification): the same kernel for both eyes, or feature matches
    # (and a network) see two blurs (the real ZED Mini view: 0.123 px of rows with both bilinear, 0.137 with the right
    # image alone by spline, 0.111 with both)
    interpolation: Literal["linear", "cubic-bspline"] = "linear"

    def rectify(self, left_raw: np.ndarray, right_raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.interpolation == "cubic-bspline":
            return tuple(resample(img, mx.ravel().astype(np.float64), my.ravel().astype(np.float64), mx.shape)
                         for img, (mx, my) in ((left_raw, self.maps_left), (right_raw, self.maps_right)))
        left = cv2.remap(left_raw, *self.maps_left, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return left, cv2.remap(right_raw, *self.maps_right, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def resolution_from_eye_width(width_px: int, path=None) -> str:
    if width_px not in ZED_EYE_WIDTHS:
        raise InputError(path, "image width", f"a ZED eye width {sorted(ZED_EYE_WIDTHS)} px",
                         f"{width_px} px", "side-by-side images are 2x the eye width; pass the eye width")
    return ZED_EYE_WIDTHS[width_px]


def read_zed_conf(path: str | Path, eye_width_px: int) -> ZedFactoryCalibration:
    """Parse ``SN<serial>.conf`` (INI, case-insensitive keys) for the resolution of ``eye_width_px``."""
    path = Path(path)
    res = resolution_from_eye_width(eye_width_px, path)
    if not path.is_file():
        raise InputError(path, None, "a ZED SN<serial>.conf file", "no such file",
                         "download it from the ZED calibration server or copy it from /usr/local/zed/settings")
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    try:
        cp.read_string(path.read_text(errors="replace"))
    except configparser.Error as exc:
        raise InputError(path, None, "an INI file", f"a parse error ({str(exc).splitlines()[0]})",
                         "the conf file is damaged: download it again from the ZED calibration server") from None
    sections = {s.upper(): s for s in cp.sections()}

    def get(section: str, key: str) -> float:
        if section not in sections:
            have = ", ".join(sorted(sections)) or "none"
            raise InputError(path, f"[{section}]", "this section", f"missing (sections: {have})",
                             f"is this conf for the resolution {res} ({eye_width_px} px per eye)?")
        sec = cp[sections[section]]
        if key.lower() not in sec:
            raise InputError(path, f"[{section}] {key}", "this key", "missing", "the conf file is incomplete")
        raw = sec[key.lower()]
        try:
            val = float(raw)
        except ValueError:
            raise InputError(path, f"[{section}] {key}", "a number", repr(raw),
                             "the conf file is corrupt: download it again from the ZED calibration server") from None
        if not math.isfinite(val):
            raise InputError(path, f"[{section}] {key}", "a finite number", repr(raw), "the conf file is corrupt")
        return val

    def has(section: str, key: str) -> bool:
        return section in sections and key.lower() in cp[sections[section]]

    cams, notes = [], []
    for side in ("LEFT", "RIGHT"):
        sec = f"{side}_CAM_{res}"
        vals = {k: get(sec, k) for k in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")}
        # some factory files carry no k3 (the published numbers of many units stop at p2): 0 is OpenCV's default
        vals["k3"] = get(sec, "k3") if has(sec, "k3") else 0.0
        if not has(sec, "k3"):
            notes.append(f"[{sec}] has no k3: read as 0")
        h = ZED_RES_HEIGHTS[res]
        K = np.array([[vals["fx"], 0, vals["cx"]], [0, vals["fy"], vals["cy"]], [0, 0, 1]])
        cams.append(PinholeCamera.from_K(K, eye_width_px, h, [vals[k] for k in ("k1", "k2", "p1", "p2", "k3")]))
    baseline = get("STEREO", "Baseline")
    if abs(baseline) < 1.0:
        raise InputError(path, "[STEREO] Baseline", "the baseline in mm (e.g. 63 for a ZED Mini)", repr(baseline),
                         "SN.conf stores millimetres")
    # real factory files hold TY and TZ once for every resolution; older tools wrote TY_<res>, TZ_<res> (kept where
    # a file has them)
    ty, tz = (get("STEREO", f"{k}_{res}") if has("STEREO", f"{k}_{res}") else get("STEREO", k) for k in ("TY", "TZ"))
    rvec = np.array([get("STEREO", f"RX_{res}"), get("STEREO", f"CV_{res}"), get("STEREO", f"RZ_{res}")])
    for n in notes:
        log.info("%s: %s", path.name, n)
    return ZedFactoryCalibration(res, cams[0], cams[1], float(baseline), float(ty), float(tz), rvec, path, tuple(notes))


def write_zed_conf(path: str | Path, calib: dict[str, dict[str, float]]) -> Path:
    """Write an SN.conf-style INI (used by the synthetic generator and tests)."""

    lines = []
    for sec, kv in calib.items():
        lines.append(f"[{sec}]")
        lines += [f"{k}={v!r}" if isinstance(v, float) else f"{k}={v}" for k, v in kv.items()]  # the vendor's k=v
        lines.append("")
    return atomic_write_text(path, "\n".join(lines))
