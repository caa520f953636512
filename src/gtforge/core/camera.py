"""Camera and rig models (pydantic) with projection helpers.

Shapes: ``pts_cam`` ``(N, 3)`` mm in the camera frame; ``uv`` ``(N, 2)`` as ``(u, v)`` px with
pixel centres at integer coordinates (docs/conventions.md).
"""
from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import ClassVar

import numpy as np
from pydantic import ConfigDict, Field, field_validator, model_validator

from gtforge.core import lens
from gtforge.core.geometry import invert_T
from gtforge.core.schema import GTModel, Matrix4, VersionedFile, matrix4_array
from gtforge.errors import InputError
from gtforge.infra import disk_cache
from gtforge.infra.digest import blake3_hex

ZED_EYE_WIDTHS = {2208: "2K", 1920: "FHD", 1280: "HD", 672: "VGA"}


def _finite(v: float, name: str) -> float:
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite")
    return v


DIST_LENGTHS = (0, 4, 5, 8, 12, 14)
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")


class PinholeCamera(GTModel):
    """Pinhole camera with OpenCV lens distortion.

    ``dist_coeffs`` in OpenCV's order ``(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]])``:
    0, 4, 5, 8 (rational), 12 (thin prism) or 14 (tilted sensor) numbers (docs/conventions.md).
    Files written before the full lens models carry ``dist_k1_k2_p1_p2_k3``; it is read as ``dist_coeffs``.
    """

    width_px: int = Field(gt=0)
    height_px: int = Field(gt=0)
    fx_px: float = Field(gt=0)
    fy_px: float = Field(gt=0)
    cx_px: float
    cy_px: float
    dist_coeffs: list[float] = Field(default_factory=list)

    @model_validator(mode="before")
    @classmethod
    def _legacy_dist(cls, data):
        if isinstance(data, dict) and "dist_k1_k2_p1_p2_k3" in data:
            data = dict(data)
            legacy = data.pop("dist_k1_k2_p1_p2_k3")
            if "dist_coeffs" in data:
                raise ValueError("give dist_coeffs or the older dist_k1_k2_p1_p2_k3, not both")
            data["dist_coeffs"] = legacy
        return data

    @field_validator("fx_px", "fy_px", "cx_px", "cy_px")
    @classmethod
    def _fin(cls, v: float, info) -> float:
        return _finite(v, info.field_name)

    @field_validator("dist_coeffs")
    @classmethod
    def _dist(cls, v: list[float]) -> list[float]:
        if len(v) not in DIST_LENGTHS:
            raise ValueError(f"{len(v)} distortion coefficients; OpenCV models have "
                             f"{', '.join(map(str, DIST_LENGTHS))} "
                             "(k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tau_x tau_y]]]])")
        if not all(math.isfinite(x) for x in v):
            raise ValueError("distortion coefficients must be finite")
        return [float(x) for x in v]

    # ---- convenience -----------------------------------------------------------------------
    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx_px, 0, self.cx_px], [0, self.fy_px, self.cy_px], [0, 0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """The coefficients as OpenCV takes them (``cv2.projectPoints`` etc.); ``(0,)`` when undistorted."""
        return np.array(self.dist_coeffs, dtype=np.float64)

    @property
    def has_distortion(self) -> bool:
        return any(x != 0.0 for x in self.dist_coeffs)

    @property
    def size_wh(self) -> tuple[int, int]:
        return self.width_px, self.height_px

    @classmethod
    def from_K(cls, K: np.ndarray, width_px: int, height_px: int, dist=None) -> "PinholeCamera":
        K = np.asarray(K, float)
        return cls(width_px=int(width_px), height_px=int(height_px), fx_px=float(K[0, 0]), fy_px=float(K[1, 1]),
                   cx_px=float(K[0, 2]), cy_px=float(K[1, 2]),
                   dist_coeffs=[] if dist is None else [float(x) for x in np.ravel(dist)])

    def scaled(self, factor: float) -> "PinholeCamera":
        """The same lens at another resolution (pixel centres stay at integer coordinates)."""
        return self.model_copy(update=dict(
            width_px=int(round(self.width_px * factor)), height_px=int(round(self.height_px * factor)),
            fx_px=self.fx_px * factor, fy_px=self.fy_px * factor,
            cx_px=(self.cx_px + 0.5) * factor - 0.5, cy_px=(self.cy_px + 0.5) * factor - 0.5))

    # ---- projection ------------------------------------------------------------------------
    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply the lens model to normalised coordinates ``(N, 2)`` (``gtforge.core.lens.distort``)."""
        return lens.distort(xy, self.dist_coeffs)

    def project(self, pts_cam: np.ndarray) -> np.ndarray:
        """``(N, 3)`` points in this camera's frame -> ``(N, 2)`` pixels (distortion applied)."""
        pts = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
        xy = pts[:, :2] / pts[:, 2:3]
        if self.has_distortion:
            xy = self.distort_normalized(xy)
        return np.stack([self.fx_px * xy[:, 0] + self.cx_px, self.fy_px * xy[:, 1] + self.cy_px], axis=1)

    def undistort_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        """``(N, 2)`` pixels -> ``(N, 2)`` normalised ``(x, y)`` with ``z = 1`` (distortion removed;
        NaN where the lens model has no inverse, far outside its valid field)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        xy_d = np.stack([(uv[:, 0] - self.cx_px) / self.fx_px, (uv[:, 1] - self.cy_px) / self.fy_px], axis=1)
        return lens.undistort(xy_d, self.dist_coeffs) if self.has_distortion else xy_d

    def unproject(self, uv: np.ndarray, depth_mm: np.ndarray) -> np.ndarray:
        """``(N, 2)`` pixels and their z-depth (mm) -> ``(N, 3)`` points in the camera frame."""
        xy = self.undistort_to_normalized(uv)
        z = np.asarray(depth_mm, dtype=np.float64).reshape(-1)
        return np.stack([xy[:, 0] * z, xy[:, 1] * z, z], axis=1)

    def ray_grid(self) -> np.ndarray:
        """``(H, W, 2)`` float64 normalised coordinates of every pixel centre (cached, read-only)."""
        return _ray_grid_cached(self.model_dump_json())

    def ray_planes(self) -> np.ndarray:
        """The ray grid as two planes: ``(2, H, W)`` float64, C-contiguous (x, then y; cached, read-only). The
        depth reprojection's kernels read x and y each from its own plane."""
        return _ray_planes_cached(self.model_dump_json())

    def check_image_size(self, shape: tuple[int, ...], file=None, what: str = "image") -> None:
        h, w = shape[:2]
        if (w, h) != (self.width_px, self.height_px):
            raise InputError(file, "size", f"{self.width_px}x{self.height_px} px (from the intrinsics)",
                             f"{w}x{h} px",
                             f"is this {what} from the camera the intrinsics describe, or at another resolution?")


# a ray grid through a lens model at least this large is kept on disk between commands (``infra.disk_cache``): at
# 1920x1200 its undistortion costs 0.3-0.6 CPU s, which a rerun of build-dataset would otherwise pay before its first
# scene (benchmarks/RESULTS.md, "Round 5 (issue 39)"); reading it back costs about 0.03 s. Smaller grids are cheap.
RAY_GRID_DISK_CACHE_MIN_PX = 1_000_000


@functools.lru_cache(maxsize=1)
def _ray_grid_code_digest() -> str | None:
    """What a cached ray grid's values depend on beside the camera: the code that computes them (this module and
    ``lens``), numpy's and numba's versions and the CPU numba compiles for. None where the code's source cannot be
    read (no disk cache then)."""
    import llvmlite.binding
    import numba

    try:
        parts = [Path(__file__).read_bytes(), Path(lens.__file__).read_bytes()]
    except OSError:
        return None
    parts.append(f"{np.__version__} {numba.__version__} {llvmlite.binding.get_host_cpu_name()}".encode())
    return blake3_hex(b"\0".join(parts))


@functools.lru_cache(maxsize=8)
def _ray_planes_cached(cam_json: str) -> np.ndarray:
    cam = PinholeCamera.model_validate_json(cam_json)
    code = _ray_grid_code_digest() if cam.width_px * cam.height_px >= RAY_GRID_DISK_CACHE_MIN_PX else None
    on_disk = cam.has_distortion and code is not None
    shape = (2, cam.height_px, cam.width_px)
    if on_disk:
        # kept as planes, the form the reprojection reads: splitting an (H, W, 2) grid after reading it costs a
        # fork server more than reading it (benchmarks/RESULTS.md, "Round 8 (issue 39)")
        key = blake3_hex((cam_json + code).encode())[:32]
        planes = disk_cache.load_array("ray_grid", key)
        if planes is not None and planes.shape == shape and planes.dtype == np.float64:
            return planes
    # undistort_to_normalized of every pixel centre, without the (N, 2) pixel list: the distorted normalised
    # coordinates are separable in u and v
    xy = np.empty((cam.height_px, cam.width_px, 2))
    xy[..., 0] = ((np.arange(cam.width_px, dtype=np.float64) - cam.cx_px) / cam.fx_px)[None, :]
    xy[..., 1] = ((np.arange(cam.height_px, dtype=np.float64) - cam.cy_px) / cam.fy_px)[:, None]
    if cam.has_distortion:
        xy = lens.undistort(xy.reshape(-1, 2), cam.dist_coeffs).reshape(xy.shape)
    planes = np.ascontiguousarray(np.moveaxis(xy, -1, 0))
    if on_disk:
        disk_cache.store_array("ray_grid", key, planes)
    planes.setflags(write=False)
    return planes


@functools.lru_cache(maxsize=8)
def _ray_grid_cached(cam_json: str) -> np.ndarray:
    xy = np.stack(tuple(_ray_planes_cached(cam_json)), axis=-1)
    xy.setflags(write=False)
    return xy


class RectifiedStereo(GTModel):
    """A rectified stereo pair: left camera (no distortion), positive baseline, doffs = cx_right - cx_left."""

    left: PinholeCamera
    baseline_mm: float = Field(gt=0)
    doffs_px: float = 0.0

    @field_validator("left")
    @classmethod
    def _no_dist(cls, v: PinholeCamera) -> PinholeCamera:
        if v.has_distortion:
            raise ValueError("a rectified camera has no distortion")
        return v

    @field_validator("baseline_mm", "doffs_px")
    @classmethod
    def _fin(cls, v: float, info) -> float:
        return _finite(v, info.field_name)

    @property
    def f_px(self) -> float:
        return self.left.fx_px

    @property
    def right(self) -> PinholeCamera:
        return self.left.model_copy(update=dict(cx_px=self.left.cx_px + self.doffs_px))

    @property
    def T_zedr_from_zed(self) -> np.ndarray:
        T_zedr_from_zed = np.eye(4)
        T_zedr_from_zed[0, 3] = -self.baseline_mm
        return T_zedr_from_zed

    def depth_to_disparity(self, depth_mm: np.ndarray) -> np.ndarray:
        """z-depth (mm) -> disparity (px); NaN stays NaN."""
        with np.errstate(divide="ignore", invalid="ignore"):
            d = (self.f_px * self.baseline_mm) / np.asarray(depth_mm, np.float64) - self.doffs_px
        d = np.where(np.asarray(depth_mm) > 0, d, np.nan)
        return d.astype(np.float32)

    def disparity_to_depth(self, disp_px: np.ndarray) -> np.ndarray:
        """disparity (px) -> z-depth (mm); NaN or non-positive ``d + doffs`` is NaN (never huge)."""
        d = np.asarray(disp_px, np.float64) + self.doffs_px
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(d > 0, (self.f_px * self.baseline_mm) / d, np.nan)
        return z.astype(np.float32)


class ScaleCorrections(GTModel):
    """Corrections of the disparity-scale terms a vertical check cannot see (``gtforge.scale_calibration``; the
    baseline's correction is in ``Rig.zed.baseline_mm`` itself). The identity changes nothing.

    * ``depth_scale`` / ``depth_offset_mm``: the depth map reads ``depth_scale * z + depth_offset_mm`` for a true
      z-depth z (mm); every stage that reprojects the depth first undoes it, ``z = (depth - offset) / scale``.
    * ``zed_right_yaw_deg``: the right camera is turned by this about its y axis relative to the rectified right
      camera (``T_actual_from_rectified = R_y(yaw)``); the right image is corrected by the homography
      ``K_right R_y(yaw) K_right^-1`` (rectified pixel -> pixel of the image as captured) before it is written or
      compared: composed with the ZED self-rectification into the one resampling of the right image that opening the
      session makes (``CalibrationFile.open_session``, ``gtforge.core.zed.selfcal.corrected_right``)."""

    depth_scale: float = Field(1.0, gt=0)
    depth_offset_mm: float = 0.0
    zed_right_yaw_deg: float = 0.0

    @field_validator("depth_scale", "depth_offset_mm", "zed_right_yaw_deg")
    @classmethod
    def _fin(cls, v: float, info) -> float:
        return _finite(v, info.field_name)

    @property
    def changes_depth(self) -> bool:
        return self.depth_scale != 1.0 or self.depth_offset_mm != 0.0


class Rig(VersionedFile):
    """Rectified ZED pair + structured-light unit + ``T_zed_from_mech``.

    Frames (docs/conventions.md): ``mech`` is the structured-light unit's texture camera (the 2D image the
    board is found in); ``depth`` is the camera whose pixel grid the depth map is on. For Mech-Eye-style units
    with one camera they are the same (``depth_cam`` and ``T_mech_from_depth`` absent); for units with a
    separate depth camera (Mech-Eye API's texture/depth intrinsics, Azure Kinect, Orbbec) every stage that
    uses the depth composes ``T_zed_from_depth = T_zed_from_mech @ T_mech_from_depth``.
    """

    KIND: ClassVar[str] = "rig description (cameras + T_zed_from_mech)"

    model_config = ConfigDict(arbitrary_types_allowed=True)

    zed: RectifiedStereo
    mech: PinholeCamera
    T_zed_from_mech: Matrix4  # float64 (4, 4), read-only
    depth_cam: PinholeCamera | None = None
    T_mech_from_depth: Matrix4 | None = None
    # gtforge calibrate-scale: depth scale/offset and the right camera's yaw (None: none; docs/pipeline.md)
    scale_corrections: ScaleCorrections | None = None

    def __eq__(self, other) -> bool:  # the poses are arrays: compare what the file would hold
        return isinstance(other, Rig) and self.model_dump(mode="json") == other.model_dump(mode="json")

    __hash__ = None

    @property
    def T_mech_from_zed(self) -> np.ndarray:
        return invert_T(self.T_zed_from_mech)

    @property
    def depth_camera(self) -> PinholeCamera:
        """The camera of the depth map's pixel grid (the texture camera when there is one camera)."""
        return self.depth_cam if self.depth_cam is not None else self.mech

    @property
    def T_mech_from_depth_or_identity(self) -> np.ndarray:
        return np.eye(4) if self.T_mech_from_depth is None else np.array(self.T_mech_from_depth)

    @property
    def T_zed_from_depth(self) -> np.ndarray:
        return self.T_zed_from_mech @ self.T_mech_from_depth_or_identity

    @property
    def separate_depth_camera(self) -> bool:
        return self.depth_cam is not None or self.T_mech_from_depth is not None

    def corrected_depth_mm(self, depth_mm: np.ndarray) -> np.ndarray:
        """The depth map with ``scale_corrections``' depth scale and offset undone (the array itself when none)."""
        c = self.scale_corrections
        if c is None or not c.changes_depth:
            return depth_mm
        return ((np.asarray(depth_mm, np.float64) - c.depth_offset_mm) / c.depth_scale).astype(np.float32)

    @property
    def zed_right_yaw_deg(self) -> float:
        return 0.0 if self.scale_corrections is None else self.scale_corrections.zed_right_yaw_deg

    def with_extrinsic(self, T_zed_from_mech: np.ndarray) -> "Rig":
        return self.model_copy(update={"T_zed_from_mech": matrix4_array(T_zed_from_mech)})


class StereoCalibrationFile(VersionedFile):
    """gtforge's own YAML for a rectified ZED pair."""

    KIND: ClassVar[str] = "gtforge ZED calibration file"

    zed: RectifiedStereo


class CameraFile(VersionedFile):
    """gtforge's own YAML for a single camera."""

    KIND: ClassVar[str] = "gtforge camera file"

    camera: PinholeCamera
