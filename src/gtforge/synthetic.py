"""Truth-exact synthetic scenes for tests, the demo and the benchmarks.

Ray-casts analytic scenes (a table plane, a checkerboard at a known pose, a striped spheroid
"watermelon") into a structured-light camera (lens distortion, depth noise, a projector offset that
casts depth shadows) and a rectified ZED-like stereo pair (anti-aliased by supersampling, blurred,
noisy). Every truth is exact: the extrinsic, board poses, corner pixels in both cameras, z-depth and
disparity at ZED-left pixel centres, which ZED-left pixels the depth camera really saw, the fruit mask.

World frame: the table is ``z = 0``, ``z`` up. Deterministic by seed.

One module over 500 lines on purpose: the scenes, rigs, renderers and session writers share one scene model and
change together whenever a new effect is simulated; tests and benchmarks import them from one place.
"""
from __future__ import annotations

import os
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np

from gtforge.core.targets.board import BoardSpec
from gtforge.core.camera import CameraFile, PinholeCamera, RectifiedStereo, StereoCalibrationFile
from gtforge.core.measure.gauges import GaugesFile, GaugeSpec
from gtforge.core.geometry import (
    T_from_rotvec,
    invert_T,
    look_at_T_cam_from_world,
    make_T,
    perturb_left,
    transform_points,
)
from gtforge.core.schema import VersionedFile
from gtforge.core.targets.models import board_model_of, collinear
from gtforge.io.cameras import check_zed_conf_reading, write_zed_conf
from gtforge.io.captures import SessionFile
from gtforge.io.formats import write_image, write_png16, write_tiff_float

OBJ_NONE, OBJ_TABLE, OBJ_BOARD, OBJ_FRUIT = 0, 1, 2, 3
# threads rendering an image's row chunks (render_image)
RENDER_THREADS = min(4, os.cpu_count() or 1)


# ---- board -----------------------------------------------------------------------------------


# ---- procedural texture ----------------------------------------------------------------------
class ValueNoise:
    """Smooth deterministic 2-D noise (bilinear value noise, several octaves)."""

    def __init__(self, seed: int, cell_mm: float = 6.0, octaves: int = 3, size: int = 256):
        rng = np.random.default_rng(seed)
        self.grids = [rng.random((size, size)) for _ in range(octaves)]
        self.cell_mm = cell_mm
        self.size = size

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        out = np.zeros(len(xy))
        amp, total = 1.0, 0.0
        for k, g in enumerate(self.grids):
            p = xy / (self.cell_mm / 2 ** k)
            i0 = np.floor(p).astype(np.int64)
            f = p - i0
            f = f * f * (3 - 2 * f)
            x0, y0 = i0[:, 0] % self.size, i0[:, 1] % self.size
            x1, y1 = (x0 + 1) % self.size, (y0 + 1) % self.size
            a = g[y0, x0] * (1 - f[:, 0]) + g[y0, x1] * f[:, 0]
            b = g[y1, x0] * (1 - f[:, 0]) + g[y1, x1] * f[:, 0]
            out += amp * (a * (1 - f[:, 1]) + b * f[:, 1])
            total += amp
            amp *= 0.5
        return out / total


# ---- scene objects ---------------------------------------------------------------------------
class PlaneObject:
    def __init__(self, obj_id: int, T_world_from_local: np.ndarray, albedo, extent=None):
        self.obj_id = obj_id
        self.T_world_from_local = T_world_from_local
        self.T_local_from_world = invert_T(T_world_from_local)
        self.albedo_fn = albedo
        self.extent = extent

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ol = transform_points(self.T_local_from_world, o)
        dl = d @ self.T_local_from_world[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -ol[:, 2] / dl[:, 2]
        t = np.where(np.isfinite(t) & (t > 1e-9), t, np.inf)
        if self.extent is not None:
            p = ol + t[:, None] * dl
            x0, x1, y0, y1 = self.extent
            inside = (p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1)
            t = np.where(inside, t, np.inf)
        return t

    def shade(self, p_world: np.ndarray) -> np.ndarray:
        pl = transform_points(self.T_local_from_world, p_world)
        a = self.albedo_fn(pl[:, :2])
        return a[:, None] * np.ones(3) if a.ndim == 1 else a

    def normal(self, p_world: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.T_world_from_local[:3, 2], p_world.shape)


class SpheroidObject:
    """Axis-aligned ellipsoid resting on the table, watermelon-striped."""

    def __init__(self, obj_id: int, centre: np.ndarray, radii: np.ndarray, stripes: int, phase: float, seed: int):
        self.obj_id = obj_id
        self.c = np.asarray(centre, float)
        self.r = np.asarray(radii, float)
        self.stripes = stripes
        self.phase = phase
        self.noise = ValueNoise(seed + 1000, cell_mm=4.0)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        os_ = (o - self.c) / self.r
        ds = d / self.r
        a = np.einsum("ij,ij->i", ds, ds)
        b = 2 * np.einsum("ij,ij->i", os_, ds)
        c = np.einsum("ij,ij->i", os_, os_) - 1
        disc = b * b - 4 * a * c
        sq = np.sqrt(np.maximum(disc, 0))
        t0 = (-b - sq) / (2 * a)
        t1 = (-b + sq) / (2 * a)
        t = np.where(t0 > 1e-9, t0, np.where(t1 > 1e-9, t1, np.inf))
        return np.where(disc >= 0, t, np.inf)

    def shade(self, p_world: np.ndarray) -> np.ndarray:
        q = (p_world - self.c) / self.r
        phi = np.arctan2(q[:, 1], q[:, 0])
        lat = np.arcsin(np.clip(q[:, 2], -1, 1))
        n = self.noise(np.stack([phi * 100, lat * 100], axis=1))
        wobble = 0.35 * np.sin(3 * lat + self.phase)
        stripe = np.sin(self.stripes * phi + wobble + self.phase) > 0.25
        base = np.array([0.35, 0.62, 0.25])
        dark = np.array([0.08, 0.28, 0.10])
        col = np.where(stripe[:, None], dark, base)
        return col * (0.75 + 0.5 * n[:, None])

    def normal(self, p_world: np.ndarray) -> np.ndarray:
        n = (p_world - self.c) / self.r ** 2
        return n / np.linalg.norm(n, axis=1, keepdims=True)


class Scene:
    """Objects hit by rays. ``shade_by_object``: each pixel is shaded by the object it hit; False (the scenes made
    before several fruit: kept so that their images stay bit-identical) by the last object of the hit one's id."""

    def __init__(self, objects: list, shade_by_object: bool = False):
        self.objects = objects
        self.shade_by_object = shade_by_object

    def raycast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rays ``o + t d`` (``(N, 3)`` each, or ``o`` ``(3,)``) -> nearest ``t`` (inf: miss) and object id (with
        ``shade_by_object``: 1 + the object's index, which ``shade`` takes)."""
        o = np.broadcast_to(np.asarray(o, float), d.shape)
        t_best = np.full(len(d), np.inf)
        id_best = np.zeros(len(d), np.int8)
        for k, obj in enumerate(self.objects):
            t = obj.intersect(o, d)
            closer = t < t_best
            t_best[closer] = t[closer]
            id_best[closer] = k + 1 if self.shade_by_object else obj.obj_id
        return t_best, id_best

    def object_ids(self, hit: np.ndarray) -> np.ndarray:
        """``raycast``'s ids as object ids (``OBJ_*``)."""
        if not self.shade_by_object:
            return hit
        return np.array([0] + [o.obj_id for o in self.objects], np.int8)[hit]

    def shade(self, p: np.ndarray, ids: np.ndarray, light_dir: np.ndarray) -> np.ndarray:
        out = np.full((len(p), 3), 0.5)
        for k, obj in enumerate(self.objects):
            m = ids == (k + 1 if self.shade_by_object else obj.obj_id)
            if m.any():
                lam = np.abs(obj.normal(p[m]) @ light_dir)
                out[m] = obj.shade(p[m]) * (0.55 + 0.45 * lam)[:, None]
        return out


# ---- the rig ---------------------------------------------------------------------------------
@dataclass
class SyntheticRig:
    """``mech`` is the structured-light unit's texture camera; ``depth_cam`` (with ``T_mech_from_depth``) its depth
    camera when the two differ (None: one camera). The projector sits at ``p_projector_in_mech_mm`` in the depth
    camera's frame (the texture camera's when there is one camera)."""

    mech: PinholeCamera
    zed: RectifiedStereo
    T_zed_from_mech: np.ndarray
    p_projector_in_mech_mm: np.ndarray = field(default_factory=lambda: np.array([-70.0, 0.0, 0.0]))
    T_zed_from_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    depth_cam: PinholeCamera | None = None
    T_mech_from_depth: np.ndarray | None = None
    # the real right ZED camera turned about its own centre against the rectified model the files describe (a factory
    # rectification's residual, corrected by gtforge.core.zed.selfcal): rotation vector (rad) of the image-only error
    zed_right_rotation_error_rad: np.ndarray | None = None
    # errors in the files the pipeline trusts (issue #25, scale terms): ``zed`` is the true geometry the images are
    # rendered with, ``zed_file`` what zed_calibration.yaml says (None: the same); the right camera is turned by
    # ``right_yaw_rad`` about its y axis (T_actual_from_ideal = R_y(yaw)) and the depth map reads
    # ``depth_scale * z + depth_offset_mm`` for a true z
    zed_file: RectifiedStereo | None = None
    right_yaw_rad: float = 0.0
    depth_scale: float = 1.0
    depth_offset_mm: float = 0.0

    @property
    def T_zedr_actual_from_zedr(self) -> np.ndarray:
        """The right camera's true pose relative to the ideal rectified right camera (a yaw about its y axis)."""
        c, s = np.cos(self.right_yaw_rad), np.sin(self.right_yaw_rad)
        return make_T(np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]), np.zeros(3))

    @property
    def T_mech_from_world(self) -> np.ndarray:
        return invert_T(self.T_zed_from_mech) @ self.T_zed_from_world

    @property
    def depth_camera(self) -> PinholeCamera:
        return self.depth_cam if self.depth_cam is not None else self.mech

    @property
    def T_depth_from_world(self) -> np.ndarray:
        if self.T_mech_from_depth is None:
            return self.T_mech_from_world
        return invert_T(self.T_mech_from_depth) @ self.T_mech_from_world


def default_rig(scale: float = 1.0, distance_mm: float = 650.0) -> SyntheticRig:
    """A ZED Mini (2K: 2208x1242, 63 mm baseline) beside a Mech-Eye-like camera (1920x1200, distorted),
    both looking down at a table from about ``distance_mm``; ``scale`` shrinks both resolutions."""
    zed_left = PinholeCamera(width_px=2208, height_px=1242, fx_px=1066.0, fy_px=1066.0, cx_px=1112.3, cy_px=615.8)
    mech = PinholeCamera(width_px=1920, height_px=1200, fx_px=1745.0, fy_px=1748.5, cx_px=967.2, cy_px=588.9,
                         dist_coeffs=[-0.085, 0.11, 0.0006, -0.0004, -0.03])
    if scale != 1.0:
        zed_left, mech = zed_left.scaled(scale), mech.scaled(scale)
    zed = RectifiedStereo(left=zed_left, baseline_mm=63.0, doffs_px=0.0)
    # Mech-Eye 115 mm to the right of the ZED left camera, 18 mm lower, toed in by ~6 degrees.
    T_zed_from_mech = T_from_rotvec(np.radians([1.2, -6.0, 0.7]), [115.0, 18.0, 4.0])
    T_zed_from_world = look_at_T_cam_from_world([-40.0, -330.0, distance_mm], [-40.0, 0.0, 0.0], up_world=(0, 1, 0))
    return SyntheticRig(mech, zed, T_zed_from_mech, T_zed_from_world=T_zed_from_world)


def two_camera_rig(scale: float = 1.0, distance_mm: float = 650.0) -> SyntheticRig:
    """``default_rig`` whose structured-light unit has a separate depth camera (as the Mech-Eye API reports, or an
    Azure Kinect / Orbbec): 1280x1024, its own lens, 45 mm beside the texture camera and turned by about 1 degree."""
    rig = default_rig(scale, distance_mm)
    depth_cam = PinholeCamera(width_px=1280, height_px=1024, fx_px=1180.0, fy_px=1176.5, cx_px=645.3, cy_px=508.1,
                              dist_coeffs=[-0.061, 0.093, -0.0004, 0.0007, -0.021])
    if scale != 1.0:
        depth_cam = depth_cam.scaled(scale)
    rig.depth_cam = depth_cam
    rig.T_mech_from_depth = T_from_rotvec(np.radians([0.35, -0.9, 0.4]), [-45.0, 6.0, 2.5])
    return rig


# ---- rendering ---------------------------------------------------------------------------------
def _subsample_offsets(ss: int) -> np.ndarray:
    g = (np.arange(ss) + 0.5) / ss - 0.5
    du, dv = np.meshgrid(g, g)
    return np.stack([du.ravel(), dv.ravel()], axis=1)


def render_image(scene: Scene, cam: PinholeCamera, T_cam_from_world: np.ndarray, supersample: int = 3,
                 rows_per_chunk: int = 48, T_light_from_world: np.ndarray | None = None) -> np.ndarray:
    """Linear-intensity RGB float image ``(H, W, 3)`` in [0, 1], box-filtered over ``supersample**2`` rays.
    The light comes from the camera's direction, or from ``T_light_from_world``'s when given (a camera turned by a
    small error sees the scene under the same light)."""
    T_world_from_cam = invert_T(T_cam_from_world)
    centre = T_world_from_cam[:3, 3]
    R = T_world_from_cam[:3, :3]
    R_light = R if T_light_from_world is None else invert_T(T_light_from_world)[:3, :3]
    grid = cam.ray_grid()  # (H, W, 2) normalised coordinates of pixel centres
    # local Jacobian of the normalised coordinates w.r.t. pixel offsets (central differences)
    jac_u = np.gradient(grid, axis=1)
    jac_v = np.gradient(grid, axis=0)
    offs = _subsample_offsets(supersample)
    light = -R_light[:, 2] + np.array([0.3, -0.2, 0.0])
    light /= np.linalg.norm(light)
    H, W = cam.height_px, cam.width_px
    out = np.zeros((H, W, 3))

    def chunk(r0: int) -> None:
        r1 = min(H, r0 + rows_per_chunk)
        g = grid[r0:r1].reshape(-1, 2)
        ju, jv = jac_u[r0:r1].reshape(-1, 2), jac_v[r0:r1].reshape(-1, 2)
        acc = np.zeros((len(g), 3))
        for du, dv in offs:
            xy = g + du * ju + dv * jv
            d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
            d = d_cam @ R.T
            t, ids = scene.raycast(centre, d)
            p = centre + t[:, None] * d
            col = np.full((len(t), 3), 0.3)
            hit = np.isfinite(t)
            col[hit] = scene.shade(p[hit], ids[hit], light)
            acc += col
        out[r0:r1] = (acc / len(offs)).reshape(r1 - r0, W, 3)

    # row chunks are independent (each writes its own rows): threads render them side by side, numpy releasing the
    # GIL, with the same result as one after the other
    with ThreadPoolExecutor(RENDER_THREADS) as pool:
        list(pool.map(chunk, range(0, H, rows_per_chunk)))
    return out


GREY_WEIGHTS = np.array([0.299, 0.587, 0.114])  # RGB -> grey (ITU-R BT.601), the images' and the depth camera's


def finish_image(linear_rgb: np.ndarray, rng: np.random.Generator, blur_sigma_px: float = 0.6,
                 noise_sigma: float = 1.5, gray: bool = False) -> np.ndarray:
    img = linear_rgb * 255.0
    if blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma_px)
    if gray:
        img = img @ GREY_WEIGHTS
    img = img + rng.normal(0, noise_sigma, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def raycast_depth(scene: Scene, cam: PinholeCamera,
                  T_cam_from_world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact z-depth (mm, inf: miss), object ids and world points at every pixel centre."""
    T_world_from_cam = invert_T(T_cam_from_world)
    grid = cam.ray_grid().reshape(-1, 2)
    d = np.concatenate([grid, np.ones((len(grid), 1))], axis=1) @ T_world_from_cam[:3, :3].T
    t, ids = scene.raycast(T_world_from_cam[:3, 3], d)
    p = T_world_from_cam[:3, 3] + np.where(np.isfinite(t), t, 0)[:, None] * d
    shape = (cam.height_px, cam.width_px)
    return t.reshape(shape), scene.object_ids(ids).reshape(shape), p.reshape(shape + (3,))


def _visible_from(scene: Scene, origin: np.ndarray, p: np.ndarray, rel_tol: float = 1e-6) -> np.ndarray:
    """Whether each world point ``p`` is the first hit on the segment from ``origin``."""
    t, _ = scene.raycast(origin, p - origin)
    return t >= 1.0 - rel_tol - 1e-4 / np.maximum(np.linalg.norm(p - origin, axis=1), 1e-9)


def lit_mask(scene: Scene, rig: SyntheticRig, p_world: np.ndarray) -> np.ndarray:
    p_proj_world = transform_points(invert_T(rig.T_depth_from_world), rig.p_projector_in_mech_mm[None])[0]
    return _visible_from(scene, p_proj_world, p_world)


# ---- captures --------------------------------------------------------------------------------
@dataclass
class SyntheticCapture:
    name: str
    kind: str  # "board" or "scene"
    mech_texture: np.ndarray
    depth_mm: np.ndarray  # the depth camera's, float32, NaN invalid (shadows, misses)
    zed_left: np.ndarray
    zed_right: np.ndarray
    zed_depth_mm: np.ndarray  # exact z at ZED-left pixel centres, NaN where nothing is hit
    zed_disparity_px: np.ndarray  # exact f*B/Z - doffs, NaN where nothing is hit
    seen_by_mech: np.ndarray  # bool: ZED-left pixels whose surface point the depth camera measured
    fruit_mask: np.ndarray  # bool, ZED-left
    zed_right_disparity_px: np.ndarray | None = None  # exact disparity at ZED-right pixel centres (match: u + d)
    seen_by_mech_right: np.ndarray | None = None  # ZED-right pixels whose surface point the depth camera measured
    T_mech_from_board: np.ndarray | None = None
    corners_mech_uv: np.ndarray | None = None
    corners_zed_uv: np.ndarray | None = None
    fruit_id: str | None = None
    # the fruit ellipsoids in the ZED-left frame (fruit_ellipsoids_zed): centre_mm (K, 3), radii_mm (K, 3),
    # R_zed_from_fruit (K, 3, 3) (columns: the semi-axes' directions), and T_zed_from_world
    fruit_truth: dict | None = None
    # a separate depth camera's own image (its "infrared" image: uint16, pixel-aligned with depth_mm), written as IR.png
    depth_texture: np.ndarray | None = None


def fruit_ellipsoids_zed(scene: "Scene", T_zed_from_world: np.ndarray) -> dict:
    """Exact fruit shapes in the ZED-left frame: every ``SpheroidObject`` (world-axis-aligned ellipsoid, or one moved
    rigidly: ``RigidlyMoved``) as ``centre_mm`` (K, 3), ``radii_mm`` (K, 3), ``R_zed_from_fruit`` (K, 3, 3), plus
    ``T_zed_from_world``."""
    fr, T_world_from_still_per_fruit = [], []
    for o in scene.objects:
        if isinstance(o, RigidlyMoved) and isinstance(o.obj, SpheroidObject) and o.obj_id == OBJ_FRUIT:
            fr.append(o.obj)
            T_world_from_still_per_fruit.append(o.T_world_from_still)
        elif isinstance(o, SpheroidObject) and o.obj_id == OBJ_FRUIT:
            fr.append(o)
            T_world_from_still_per_fruit.append(None)  # (not moved)
    R = T_zed_from_world[:3, :3]
    moved = T_world_from_still_per_fruit
    return dict(fruit_centre_zed_mm=np.array([transform_points(T_zed_from_world if T_world_from_still is None
                                                               else T_zed_from_world @ T_world_from_still,
                                                               o.c[None])[0]
                                              for o, T_world_from_still in zip(fr, moved)]).reshape(-1, 3),
                fruit_radii_mm=np.array([o.r for o in fr]).reshape(-1, 3),
                fruit_R_zed_from_fruit=np.array([R if T_world_from_still is None
                                                 else R @ T_world_from_still[:3, :3]
                                                 for T_world_from_still in moved]).reshape(-1, 3, 3),
                T_zed_from_world=np.asarray(T_zed_from_world, float))


def _table(seed: int) -> PlaneObject:
    noise = ValueNoise(seed, cell_mm=5.0)

    def albedo(xy):
        n = noise(xy)
        grain = 0.5 + 0.5 * np.sin(xy[:, 0] * 0.05 + 4 * n)
        a = 0.35 + 0.35 * n + 0.12 * grain
        return np.stack([a * 1.0, a * 0.8, a * 0.6], axis=1)

    return PlaneObject(OBJ_TABLE, np.eye(4), albedo)


def render_capture(name: str, scene: Scene, rig: SyntheticRig, rng: np.random.Generator, *, kind: str,
                   supersample: int = 3, depth_noise_mm: float = 0.0, image_noise: float = 1.5,
                   blur_sigma_px: float = 0.6, zed_scene: Scene | None = None) -> SyntheticCapture:
    """Render one capture. ``zed_scene``: the scene as the ZED saw it when it differs from what the structured-light
    unit captured (an object that moved between the two captures); the ZED truth follows ``zed_scene``."""
    zed = rig.zed
    zed_scene = zed_scene or scene
    T_zedr_from_world = zed.T_zedr_from_zed @ rig.T_zed_from_world
    T_mech_from_world = rig.T_mech_from_world
    left = finish_image(render_image(zed_scene, zed.left, rig.T_zed_from_world, supersample), rng, blur_sigma_px,
                        image_noise)
    # the right image from the real right camera, turned against the rectified model the files describe (a yaw:
    # gtforge.scale_calibration; a residual rotation: gtforge.core.zed.selfcal); its truth below stays the ideal
    # rectified one
    T_zedr_image_from_world = rig.T_zedr_actual_from_zedr @ T_zedr_from_world
    if rig.zed_right_rotation_error_rad is not None:
        R_err = cv2.Rodrigues(np.asarray(rig.zed_right_rotation_error_rad, np.float64).reshape(3, 1))[0]
        T_zedr_image_from_world = make_T(R_err, np.zeros(3)) @ T_zedr_image_from_world
    right = finish_image(render_image(zed_scene, zed.right, T_zedr_image_from_world,
                                      supersample, T_light_from_world=T_zedr_from_world), rng, blur_sigma_px,
                         image_noise)
    tex = finish_image(render_image(scene, rig.mech, T_mech_from_world, supersample), rng, blur_sigma_px,
                       image_noise, gray=True)
    # structured-light depth at the depth camera's pixel centres, with projector shadows
    z_m, ids_m, p_m = raycast_depth(scene, rig.depth_camera, rig.T_depth_from_world)
    hit = np.isfinite(z_m)
    lit = np.zeros_like(hit)
    lit[hit] = lit_mask(scene, rig, p_m[hit])
    depth = np.where(hit & lit, z_m, np.nan)
    if rig.depth_scale != 1.0 or rig.depth_offset_mm != 0.0:  # a depth camera reading long / offset (issue #25)
        depth = rig.depth_scale * depth + rig.depth_offset_mm
    if depth_noise_mm > 0:
        depth = depth + rng.normal(0, depth_noise_mm, depth.shape)
    # ZED-left truth
    z_z, ids_z, p_z = raycast_depth(zed_scene, zed.left, rig.T_zed_from_world)
    hit_z = np.isfinite(z_z)
    zdepth = np.where(hit_z, z_z, np.nan).astype(np.float32)
    disp = zed.depth_to_disparity(np.where(hit_z, z_z, np.nan))
    seen = _seen_by_depth_camera(zed_scene, rig, p_z, hit_z)
    # ZED-right truth (Middlebury's disp1: the match of right pixel u is left pixel u + d)
    z_r, _, p_r = raycast_depth(zed_scene, zed.right, T_zedr_from_world)
    hit_r = np.isfinite(z_r)
    disp_r = zed.depth_to_disparity(np.where(hit_r, z_r, np.nan))
    seen_r = _seen_by_depth_camera(zed_scene, rig, p_r, hit_r)
    ir = None
    if rig.depth_cam is not None:  # a separate depth camera: its own image, as an Azure Kinect's infrared
        ir = depth_camera_image(scene, rig, f"{kind}/{name}", supersample, blur_sigma_px)
    return SyntheticCapture(name, kind, tex, depth.astype(np.float32), left, right, zdepth, disp, seen,
                            ids_z == OBJ_FRUIT, disp_r, seen_r,
                            fruit_truth=fruit_ellipsoids_zed(zed_scene, rig.T_zed_from_world), depth_texture=ir)


IR_COUNTS_PER_ALBEDO = 4000.0  # the depth camera's image: 16-bit counts for a white surface, as an infrared image's
IR_NOISE_COUNTS = 8.0


def depth_camera_image(scene: Scene, rig: SyntheticRig, key: str, supersample: int = 3,
                       blur_sigma_px: float = 0.6) -> np.ndarray:
    """A separate depth camera's own image of ``scene`` (uint16, pixel-aligned with its depth: an infrared image).
    Its noise is drawn from a generator of its own, seeded by ``key``, so a session's other images are the same with
    or without it."""
    rng = np.random.default_rng(zlib.crc32(key.encode()))
    grey = render_image(scene, rig.depth_camera, rig.T_depth_from_world, supersample) @ GREY_WEIGHTS
    if blur_sigma_px > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), blur_sigma_px)
    counts = grey * IR_COUNTS_PER_ALBEDO + rng.normal(0, IR_NOISE_COUNTS, grey.shape)
    return np.clip(np.round(counts), 0, 65535).astype(np.uint16)


def _seen_by_depth_camera(scene: Scene, rig: SyntheticRig, p_world: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Which of the (hit) image pixels' surface points the structured-light unit measured: inside the depth camera's
    image, visible from it and lit by the projector."""
    seen = np.zeros(hit.shape, bool)
    pts = p_world[hit]
    cam = rig.depth_camera
    p_cam = transform_points(rig.T_depth_from_world, pts)
    uv = cam.project(p_cam)
    inside = (p_cam[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= cam.width_px - 1) & \
             (uv[:, 1] >= 0) & (uv[:, 1] <= cam.height_px - 1)
    depth_centre = invert_T(rig.T_depth_from_world)[:3, 3]
    ok = inside.copy()
    ok[inside] = _visible_from(scene, depth_centre, pts[inside])
    ok[ok] = lit_mask(scene, rig, pts[ok])
    seen[hit] = ok
    return seen


def random_board_pose(rng: np.random.Generator, rig: SyntheticRig, board: BoardSpec, margin_px: float = 12.0,
                      tries: int = 500) -> np.ndarray:
    """``T_world_from_board`` with the whole board inside both cameras' images."""
    ex = board.extent_mm()
    outline = np.array([[ex[0], ex[2], 0], [ex[1], ex[2], 0], [ex[0], ex[3], 0], [ex[1], ex[3], 0]])
    centre_b = np.array([(ex[0] + ex[1]) / 2, (ex[2] + ex[3]) / 2, 0])
    for _ in range(tries):
        # board centre somewhere in the mech camera's view, 120-320 mm above the table
        T_world_from_mech = invert_T(rig.T_mech_from_world)
        u = rng.uniform(0.3, 0.7) * rig.mech.width_px
        v = rng.uniform(0.3, 0.7) * rig.mech.height_px
        xy = rig.mech.undistort_to_normalized(np.array([[u, v]]))[0]
        dist = rng.uniform(0.55, 0.85)
        p_mech = np.array([xy[0], xy[1], 1.0]) * dist * rig.T_mech_from_world[2, 3]
        c_world = transform_points(T_world_from_mech, p_mech[None])[0]
        # board faces the cameras (board z into the board = away from camera = world -z), tilted
        tilt = rng.uniform(-35, 35, size=2)
        yaw = rng.uniform(-180, 180)
        R = cv2.Rodrigues(np.radians([180.0 + tilt[0], tilt[1], 0.0]))[0] @ cv2.Rodrigues(np.radians([0, 0, yaw]))[0]
        T_world_from_board = make_T(R, np.zeros(3))
        T_world_from_board[:3, 3] = c_world - R @ centre_b
        ok = True
        views = [(rig.mech, rig.T_mech_from_world), (rig.zed.left, rig.T_zed_from_world),
                 (rig.zed.right, rig.zed.T_zedr_from_zed @ rig.T_zed_from_world)]
        if rig.depth_cam is not None:
            views.append((rig.depth_cam, rig.T_depth_from_world))
        for cam, T_cam_from_world in views:
            pc = transform_points(T_cam_from_world @ T_world_from_board, outline)
            if np.any(pc[:, 2] <= 0):
                ok = False
                break
            uv = cam.project(pc)
            if (uv.min(0) < margin_px).any() or uv[:, 0].max() > cam.width_px - margin_px or \
                    uv[:, 1].max() > cam.height_px - margin_px:
                ok = False
                break
            # obliquity: board normal vs viewing direction below 60 deg
            n_cam = (T_cam_from_world @ T_world_from_board)[:3, 2]
            view = pc.mean(0) / np.linalg.norm(pc.mean(0))
            if n_cam @ view < np.cos(np.radians(60)):
                ok = False
                break
        if ok and T_world_from_board[2, 3] > 60 and (T_world_from_board @ np.array([*centre_b, 1]))[2] > 100:
            return T_world_from_board
    raise RuntimeError("could not place the board inside both cameras; the rig geometry is off")


def board_capture(name: str, rig: SyntheticRig, board: BoardSpec, T_world_from_board: np.ndarray,
                  rng: np.random.Generator, seed: int, **kw) -> SyntheticCapture:
    scene = Scene([_table(seed), PlaneObject(OBJ_BOARD, T_world_from_board, board.albedo, board.extent_mm())])
    cap = render_capture(name, scene, rig, rng, kind="board", **kw)
    cap.T_mech_from_board = rig.T_mech_from_world @ T_world_from_board
    cb = board.corners_board()
    cap.corners_mech_uv = rig.mech.project(transform_points(cap.T_mech_from_board, cb))
    cap.corners_zed_uv = rig.zed.left.project(transform_points(rig.T_zed_from_world @ T_world_from_board, cb))
    return cap


def random_fruit_scene(rng: np.random.Generator, rig: SyntheticRig, seed: int) -> Scene:
    T_world_from_mech = invert_T(rig.T_mech_from_world)
    # fruit under the middle of the structured-light view
    p = T_world_from_mech[:3, 3]
    d = T_world_from_mech[:3, 2]
    t = -p[2] / d[2]
    c_table = p + t * d + np.array([rng.uniform(-60, 60), rng.uniform(-40, 40), 0.0])
    a = rng.uniform(85, 110)
    radii = np.array([a, a * rng.uniform(0.85, 1.0), rng.uniform(70, 90)])
    fruit = SpheroidObject(OBJ_FRUIT, c_table + [0, 0, radii[2]], radii, int(rng.integers(7, 11)),
                           float(rng.uniform(0, 6.28)), seed)
    return Scene([_table(seed), fruit])


def moved_fruit(scene: Scene, delta_mm) -> Scene:
    """The same scene with every fruit displaced by ``delta_mm`` (world frame, mm): a fruit that rolled between the
    structured-light capture and the ZED capture. Its texture moves with it."""
    objs = []
    for o in scene.objects:
        if isinstance(o, SpheroidObject):
            m = SpheroidObject.__new__(SpheroidObject)
            m.__dict__.update(o.__dict__)
            m.c = o.c + np.asarray(delta_mm, float)
            o = m
        objs.append(o)
    return Scene(objs)


class RigidlyMoved:
    """A scene object moved rigidly by ``T_world_from_still`` (its shape, texture and normals go with it): a
    fruit that rolled or turned between the structured-light exposure and the ZED exposure. ``still`` is the object's
    own frame as the structured-light exposure saw it (coordinates the world's at that exposure): a point ``p`` of it
    is at ``T_world_from_still @ p`` at the ZED's."""

    def __init__(self, obj, T_world_from_still: np.ndarray):
        self.obj = obj
        self.obj_id = obj.obj_id
        self.T_world_from_still = np.asarray(T_world_from_still, float)
        self.T_still_from_world = invert_T(self.T_world_from_still)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        # a rigid map keeps the ray's parameter t: the original object's hit along the ray taken back
        return self.obj.intersect(transform_points(self.T_still_from_world, np.broadcast_to(o, d.shape)),
                                  d @ self.T_still_from_world[:3, :3].T)

    def shade(self, p_world: np.ndarray) -> np.ndarray:
        return self.obj.shade(transform_points(self.T_still_from_world, p_world))

    def normal(self, p_world: np.ndarray) -> np.ndarray:
        return (self.obj.normal(transform_points(self.T_still_from_world, p_world))
                @ self.T_world_from_still[:3, :3].T)


def fruit_motion_T(centre_world_mm: np.ndarray, translation_mm, rotvec_deg) -> np.ndarray:
    """``T_world_from_still`` of a fruit turned by ``rotvec_deg`` (world axes, degrees) about its own centre
    ``centre_world_mm`` and then translated by ``translation_mm`` (world, mm)."""
    R = cv2.Rodrigues(np.radians(np.asarray(rotvec_deg, float)).reshape(3, 1))[0]
    c = np.asarray(centre_world_mm, float)
    return make_T(R, c + np.asarray(translation_mm, float) - R @ c)


def several_fruit_scene(rng: np.random.Generator, rig: SyntheticRig, seed: int, n_fruit: int,
                        partly_out: bool = True) -> Scene:
    """``n_fruit`` melon-sized spheroids (semi-axes 45-65 mm) side by side on the table under the structured-light
    view; with ``partly_out`` (and several fruit) the last one on its image's right border: partly out of the depth
    camera's view (the ZED, wider, sees all of it)."""
    T_world_from_mech = invert_T(rig.T_mech_from_world)
    p = T_world_from_mech[:3, 3]
    objs: list = [_table(seed)]
    for k in range(n_fruit):
        last = partly_out and k == n_fruit - 1 and n_fruit > 1
        n_in = n_fruit - 1 if partly_out else n_fruit  # fruit across the view's middle
        # the last one (partly_out) centred on the view's right border: half of it outside
        fu = 1.0 if last else (0.5 if n_in == 1 else 0.2 + 0.6 * k / (n_in - 1))
        fv = 0.5 + (0.0 if last else rng.uniform(-0.12, 0.12))
        xy = rig.mech.undistort_to_normalized(np.array([[fu * (rig.mech.width_px - 1), fv * (rig.mech.height_px - 1)]]))
        d = T_world_from_mech[:3, :3] @ np.array([xy[0, 0], xy[0, 1], 1.0])
        c_table = p + (-p[2] / d[2]) * d
        a = rng.uniform(55, 65)
        radii = np.array([a, a * rng.uniform(0.85, 1.0), rng.uniform(45, 55)])
        objs.append(SpheroidObject(OBJ_FRUIT, c_table + [0, 0, radii[2]], radii, int(rng.integers(7, 11)),
                                   float(rng.uniform(0, 6.28)), seed + 10 * k))
    return Scene(objs, shade_by_object=True)


def rigidly_moved_fruit(scene: Scene, motions) -> tuple[Scene, np.ndarray]:
    """The scene with its k-th fruit moved by ``motions[k] = (translation_mm, rotvec_deg)`` (world frame, about the
    fruit's own centre; ``fruit_motion_T``), and those ``T_world_from_still`` ``(K, 4, 4)``."""
    objs, T_world_from_still_per_fruit, k = [], [], 0
    for o in scene.objects:
        if isinstance(o, SpheroidObject) and o.obj_id == OBJ_FRUIT:
            t, r = motions[k] if k < len(motions) else ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            T_world_from_still = fruit_motion_T(o.c, t, r)
            T_world_from_still_per_fruit.append(T_world_from_still)
            k += 1
            if np.any(np.asarray(t, float)) or np.any(np.asarray(r, float)):
                o = RigidlyMoved(o, T_world_from_still)
        objs.append(o)
    if k != len(motions):
        raise ValueError(f"{len(motions)} fruit motions for a scene of {k} fruit")
    return Scene(objs, scene.shade_by_object), np.array(T_world_from_still_per_fruit).reshape(-1, 4, 4)


# ---- session writer --------------------------------------------------------------------------
class SyntheticTruth(VersionedFile):
    """``truth/rig_truth.yaml``: what the synthetic generator knows exactly."""

    KIND: ClassVar[str] = "synthetic truth file (truth/rig_truth.yaml)"

    T_zed_from_mech: list[list[float]]
    p_projector_in_mech_mm: list[float]
    board_cols: int
    board_rows: int
    square_size_mm: float
    seed: int
    depth_noise_mm: float
    T_mech_from_depth: list[list[float]] | None = None  # two-camera rigs only
    # errors in the files (issue #25): the ZED's true baseline (the file says zed_calibration.yaml's), the right
    # camera's yaw about its y axis, the depth map's scale and offset (depth = depth_scale * z + depth_offset_mm)
    zed_baseline_true_mm: float | None = None
    zed_right_yaw_deg: float = 0.0
    depth_scale: float = 1.0
    depth_offset_mm: float = 0.0


def write_capture(folder: Path, cap: SyntheticCapture, truth_dir: Path, fruit_motion_mm=(0.0, 0.0, 0.0),
                  motion_truth: dict | None = None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    write_image(folder / "2DImage.png", cap.mech_texture)
    write_tiff_float(folder / "DepthMap.tiff", cap.depth_mm)
    write_image(folder / "left.png", cap.zed_left)
    write_image(folder / "right.png", cap.zed_right)
    if cap.depth_texture is not None:
        write_png16(folder / "IR.png", cap.depth_texture)
    truth_dir.mkdir(parents=True, exist_ok=True)
    extra = {}
    if cap.T_mech_from_board is not None:
        extra = dict(T_mech_from_board=cap.T_mech_from_board, corners_mech_uv=cap.corners_mech_uv,
                     corners_zed_uv=cap.corners_zed_uv)
    if cap.zed_right_disparity_px is not None:
        extra.update(zed_right_disparity_px=cap.zed_right_disparity_px, seen_by_mech_right=cap.seen_by_mech_right)
    if cap.fruit_truth is not None:
        extra.update(cap.fruit_truth)
    if motion_truth:
        extra.update(motion_truth)
    np.savez_compressed(truth_dir / f"{cap.kind}_{cap.name}.npz", zed_depth_mm=cap.zed_depth_mm,
                        zed_disparity_px=cap.zed_disparity_px, seen_by_mech=cap.seen_by_mech,
                        fruit_mask=cap.fruit_mask, fruit_motion_mm=np.asarray(fruit_motion_mm, float), **extra)


def generate_session(out_dir: str | Path, *, n_board: int = 8, n_scenes: int = 3, scale: float = 0.5,
                     seed: int = 0, board: BoardSpec = BoardSpec(), depth_noise_mm: float = 0.03,
                     image_noise: float = 1.5, supersample: int = 3, two_camera: bool = False,
                     fruit_motion_mm: dict[int, tuple[float, float, float]] | None = None, progress=None,
                     partial_poses: int = 0, partial_camera: str = "mech",
                     zed_right_rotation_error_rad: tuple[float, float, float] | None = None,
                     zed_baseline_error_frac: float = 0.0, right_yaw_deg: float = 0.0,
                     depth_scale_error_frac: float = 0.0, depth_offset_mm: float = 0.0,
                     depth_pose_error_deg: tuple[float, float, float] | None = None,
                     fruit_rigid_motion: dict[int, list] | None = None, partly_out_of_view: bool = True) -> Path:
    """Write a capture session (docs/capture-layout.md) plus ``truth/``; returns ``out_dir``.

    ``zed_right_rotation_error_rad``: the right ZED image is rendered from a camera turned by this rotation vector
    against the rectified model in ``zed_calibration.yaml`` (a factory rectification's residual; the truth stays the
    model's).

    ``two_camera``: the structured-light unit has a separate depth camera (``two_camera_rig``); the session names it
    (``depth_intrinsics``, ``T_mech_from_depth``). ``fruit_motion_mm``: scene index -> the fruit's displacement
    (world mm) between the structured-light capture and the ZED capture (truth follows the ZED).
    ``fruit_rigid_motion``: scene index -> one ``(translation_mm, rotvec_deg)`` per fruit (world frame; the rotation
    about the fruit's own centre, ``fruit_motion_T``): that scene has that many fruit (``several_fruit_scene``, the
    last one partly out of the depth camera's view when there are several and ``partly_out_of_view``), each moved so
    between the two exposures
    (``((0, 0, 0), (0, 0, 0))``: a fruit that stayed still). Its truth (``truth/scene_<name>.npz``) is at the ZED's
    exposure, as for every scene, plus each fruit's exact motion in the ZED-left frame,
    ``fruit_T_zed_moved_from_zed`` (K, 4, 4) (where a point of the fruit was at the depth exposure -> where it is at
    the ZED's), ``fruit_motion_translation_mm`` / ``fruit_motion_rotvec_deg`` (K, 3: as given, world frame) and the
    truth had nothing moved, ``still_zed_disparity_px``.
    ``board``: any target of ``gtforge.core.targets.models`` (ChArUco, circle grids; session.yaml then declares it);
    ``partial_poses``: that many more board captures cut by ``partial_camera``'s image border, near its corners in
    turn (``gtforge.core.targets.models.random_partial_board_pose``).

    Errors in the files the pipeline trusts (issue #25; all 0: the files are exact): ``zed_baseline_error_frac`` the
    ZED's true baseline is ``(1 + it)`` times what zed_calibration.yaml says; ``right_yaw_deg`` the right camera is
    turned about its y axis (the right images are rendered so, the truth is the ideal rectified pair's);
    ``depth_scale_error_frac`` / ``depth_offset_mm`` the depth map reads ``(1 + k) z + offset``;
    ``depth_pose_error_deg`` (``two_camera`` only) session.yaml's ``T_mech_from_depth`` is the true one turned by this
    rotation vector (deg, the left perturbation of docs/conventions.md; truth/ keeps the true one). The truth
    (``zed_disparity_px``...) is what the images show with the true baseline, ``f * B_true / Z - doffs``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rig = two_camera_rig(scale) if two_camera else default_rig(scale)
    if zed_right_rotation_error_rad is not None:
        rig.zed_right_rotation_error_rad = np.asarray(zed_right_rotation_error_rad, np.float64)
    if zed_baseline_error_frac:
        rig.zed_file = rig.zed
        rig.zed = rig.zed.model_copy(update={"baseline_mm": rig.zed.baseline_mm * (1.0 + zed_baseline_error_frac)})
    rig.right_yaw_rad = float(np.radians(right_yaw_deg))
    rig.depth_scale, rig.depth_offset_mm = 1.0 + depth_scale_error_frac, float(depth_offset_mm)
    CameraFile(camera=rig.mech).write(out / "mech_intrinsics.yaml")
    StereoCalibrationFile(zed=rig.zed_file or rig.zed).write(out / "zed_calibration.yaml")
    T_mech_from_depth_rows = None if rig.T_mech_from_depth is None else rig.T_mech_from_depth.tolist()
    if two_camera:
        CameraFile(camera=rig.depth_cam).write(out / "depth_intrinsics.yaml")
    SyntheticTruth(T_zed_from_mech=rig.T_zed_from_mech.tolist(),
                   p_projector_in_mech_mm=rig.p_projector_in_mech_mm.tolist(),
                   board_cols=board.cols, board_rows=board.rows, square_size_mm=board.square_size_mm, seed=seed,
                   depth_noise_mm=depth_noise_mm, T_mech_from_depth=T_mech_from_depth_rows,
                   zed_baseline_true_mm=rig.zed.baseline_mm if rig.zed_file is not None else None,
                   zed_right_yaw_deg=float(right_yaw_deg), depth_scale=rig.depth_scale,
                   depth_offset_mm=rig.depth_offset_mm).write(out / "truth" / "rig_truth.yaml")
    kw = dict(supersample=supersample, depth_noise_mm=depth_noise_mm, image_noise=image_noise)
    fruit_ids = {}
    for i in range(n_board):
        T_world_from_board = random_board_pose(rng, rig, board)
        cap = board_capture(f"{i:03d}", rig, board, T_world_from_board, rng, seed + i, **kw)
        write_capture(out / "board" / cap.name, cap, out / "truth")
        if progress:
            progress(f"board {cap.name}")
    if partial_poses:
        for k in range(partial_poses):
            T_world_from_board = random_partial_board_pose(rng, rig, board, k % 4, partial_camera)
            cap = board_capture(f"{n_board + k:03d}", rig, board, T_world_from_board, rng, seed + n_board + k, **kw)
            write_capture(out / "board" / cap.name, cap, out / "truth")
    motions = fruit_motion_mm or {}
    rigid = fruit_rigid_motion or {}
    for i in range(n_scenes):
        motion_truth = None
        if i in rigid:  # several fruit, each with its own rigid motion (issue #37)
            scene = several_fruit_scene(rng, rig, seed + 100 + i, len(rigid[i]), partly_out_of_view)
            zed_scene, T_world_from_still_per_fruit = rigidly_moved_fruit(scene, rigid[i])
            motion = np.zeros(3)
            T_zed_from_world = rig.T_zed_from_world
            T_still_from_zed = invert_T(T_zed_from_world)
            z_still, _, _ = raycast_depth(scene, rig.zed.left, T_zed_from_world)
            motion_truth = dict(
                # (T_still_from_zed: the ZED frame's points in the still fruit's frame, the world's at the depth
                # exposure)
                fruit_T_zed_moved_from_zed=np.array([T_zed_from_world @ T_world_from_still @ T_still_from_zed
                                                     for T_world_from_still in T_world_from_still_per_fruit]
                                                    ).reshape(-1, 4, 4),
                fruit_motion_translation_mm=np.array([m[0] for m in rigid[i]], float).reshape(-1, 3),
                fruit_motion_rotvec_deg=np.array([m[1] for m in rigid[i]], float).reshape(-1, 3),
                still_zed_disparity_px=rig.zed.depth_to_disparity(np.where(np.isfinite(z_still), z_still, np.nan)))
        else:
            scene = random_fruit_scene(rng, rig, seed + 100 + i)
            motion = np.asarray(motions.get(i, (0.0, 0.0, 0.0)), float)
            zed_scene = moved_fruit(scene, motion) if np.any(motion) else None
        cap = render_capture(f"{i:03d}", scene, rig, rng, kind="scene", zed_scene=zed_scene, **kw)
        write_capture(out / "scenes" / cap.name, cap, out / "truth", motion, motion_truth)
        fruit_ids[cap.name] = f"fruit{i // 2:02d}"
        if progress:
            progress(f"scene {cap.name}")
    if depth_pose_error_deg is not None:
        if not two_camera:
            raise ValueError("depth_pose_error_deg needs two_camera=True (a separate depth camera)")
        T_mech_from_depth_rows = perturb_left(rig.T_mech_from_depth,
                                              np.r_[np.radians(depth_pose_error_deg), 0.0, 0.0, 0.0]).tolist()
    extra = (dict(depth_intrinsics="depth_intrinsics.yaml", T_mech_from_depth=T_mech_from_depth_rows) if two_camera
             else {})
    if board != BoardSpec():  # another target than the default: session.yaml declares it (targets.models)
        extra["board"] = board_model_of(board)
    SessionFile(fruit_ids=fruit_ids, **extra).write(out / "session.yaml")
    return out


# ---- raw (unrectified) ZED and its factory SN.conf -----------------------------------------------
# A distorted left/right pair with a known stereo extrinsic (R, T: X_right = R @ X_left + T, OpenCV's
# stereoRectify convention), written as SN<serial>.conf under any of the readings in
# gtforge.io.cameras.ZED_CONF_READINGS. The truth stays in the rectified frame OpenCV derives from the
# true (R, T): ``zed`` is that rectified left camera, so truth/ means the same as for a rectified session.
@dataclass
class RawZed:
    """Raw ZED cameras at one factory resolution plus the exact stereo extrinsic."""

    resolution: str  # "2K", "FHD", "HD" or "VGA" (the SN.conf section suffix)
    left: PinholeCamera  # distorted
    right: PinholeCamera  # distorted
    R: np.ndarray  # X_right = R @ X_left + T
    T_mm: np.ndarray

    def rectified(self) -> tuple[RectifiedStereo, np.ndarray, np.ndarray]:
        """OpenCV's rectification of the true extrinsic (zero disparity, alpha 0, as gtforge rectifies):
        ``(stereo, R_rect_from_raw_left, R_rect_from_raw_right)``."""
        size = self.left.size_wh
        R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(self.left.K, self.left.dist, self.right.K, self.right.dist, size,
                                                    self.R, self.T_mm.reshape(3, 1), flags=cv2.CALIB_ZERO_DISPARITY,
                                                    alpha=0, newImageSize=size)
        stereo = RectifiedStereo(left=PinholeCamera.from_K(P1[:, :3], *size), baseline_mm=float(-P2[0, 3] / P2[0, 0]),
                                 doffs_px=float(P2[0, 2] - P1[0, 2]))
        return stereo, R1, R2


def default_raw_zed() -> RawZed:
    """A ZED-Mini-like pair at VGA (672x376 per eye), barrel distortion, factory-typical misalignment:
    right camera 63 mm along +x, 0.21 mm down, 0.35 mm back; rotation of a few mrad."""
    left = PinholeCamera(width_px=672, height_px=376, fx_px=338.6, fy_px=337.9, cx_px=331.7, cy_px=192.4,
                         dist_coeffs=[-0.168, 0.0231, 0.00031, -0.00022, -0.0018])
    right = PinholeCamera(width_px=672, height_px=376, fx_px=337.8, fy_px=337.4, cx_px=339.2, cy_px=186.8,
                          dist_coeffs=[-0.171, 0.0247, -0.00014, 0.00029, -0.0012])
    R = cv2.Rodrigues(np.array([[0.0031], [-0.0042], [0.0011]]))[0]
    t_mm = np.array([-63.0, 0.21, -0.35])
    return RawZed("VGA", left, right, R, t_mm)


def zed_conf_values(raw: RawZed, reading: str) -> dict[str, float]:
    """The STEREO numbers (Baseline, TY, TZ, RX, CV, RZ) that ``reading`` decodes into ``raw``'s exact
    ``(R, T_mm)``: the inverse of ``gtforge.io.cameras.ZedFactoryCalibration.R_t_right_from_left``."""

    check_zed_conf_reading(reading)
    inv = reading.endswith("+inv-rot")
    R_conf = raw.R.T if inv else raw.R  # the reading applies Rodrigues(r)^T for "+inv-rot"
    r = cv2.Rodrigues(R_conf)[0].ravel()
    t_mm = raw.T_mm
    t = {"neg-x": np.array([-t_mm[0], t_mm[1], t_mm[2]]), "neg-all": -t_mm, "as-is": t_mm,
         "right-centre": -raw.R.T @ t_mm}[reading.removesuffix("+inv-rot")]
    return dict(Baseline=float(t[0]), TY=float(t[1]), TZ=float(t[2]), RX=float(r[0]), CV=float(r[1]), RZ=float(r[2]))


def write_raw_zed_conf(path: str | Path, raw: RawZed, reading: str) -> Path:
    """An SN<serial>.conf whose values encode ``raw`` exactly under ``reading``."""

    res = raw.resolution
    v = zed_conf_values(raw, reading)
    sections = {}
    for side, cam in (("LEFT", raw.left), ("RIGHT", raw.right)):
        d = list(cam.dist_coeffs) + [0.0] * (5 - len(cam.dist_coeffs))
        sections[f"{side}_CAM_{res}"] = dict(fx=cam.fx_px, fy=cam.fy_px, cx=cam.cx_px, cy=cam.cy_px,
                                             k1=d[0], k2=d[1], p1=d[2], p2=d[3], k3=d[4])
    # the vendor's layout: TY and TZ once for every resolution, the rotation per resolution
    sections["STEREO"] = {"Baseline": v["Baseline"], "TY": v["TY"], "TZ": v["TZ"],
                          f"CV_{res}": v["CV"], f"RX_{res}": v["RX"], f"RZ_{res}": v["RZ"]}
    return write_zed_conf(path, sections)


def raw_zed_rig(raw: RawZed, distance_mm: float = 650.0) -> SyntheticRig:
    """``default_rig`` at the raw cameras' resolution with ``zed`` replaced by the true rectified pair
    (``T_zed_from_world`` and ``T_zed_from_mech`` then refer to the rectified left camera)."""
    rig = default_rig(raw.left.width_px / 2208.0, distance_mm)
    stereo, _, _ = raw.rectified()
    rig.zed = stereo
    return rig


def render_raw_zed_images(scene: Scene, rig: SyntheticRig, raw: RawZed, rng: np.random.Generator,
                          supersample: int = 3, blur_sigma_px: float = 0.6,
                          image_noise: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """The raw (distorted, unrectified) left and right images of ``scene``."""
    _, R1, _ = raw.rectified()
    T_rawl_from_world = make_T(R1.T, np.zeros(3)) @ rig.T_zed_from_world
    T_rawr_from_world = make_T(raw.R, raw.T_mm) @ T_rawl_from_world
    left = finish_image(render_image(scene, raw.left, T_rawl_from_world, supersample), rng, blur_sigma_px, image_noise)
    right = finish_image(render_image(scene, raw.right, T_rawr_from_world, supersample), rng, blur_sigma_px,
                         image_noise)
    return left, right


class RawZedTruth(VersionedFile):
    """``truth/raw_zed_truth.yaml``: the exact stereo extrinsic of a raw ZED session and how its conf is written."""

    conf_file: str
    reading: str  # the reading under which the conf's numbers decode into R, T exactly
    R_rotvec_rad: list[float]  # X_right = R @ X_left + T
    T_mm: list[float]


def generate_raw_zed_session(out_dir: str | Path, *, reading: str = "neg-x", n_board: int = 4, n_scenes: int = 1,
                             seed: int = 0, board: BoardSpec = BoardSpec(), depth_noise_mm: float = 0.0,
                             image_noise: float = 1.0, supersample: int = 3, serial: int = 12345,
                             raw: RawZed | None = None,
                             conf_rotation_error_rad: tuple[float, float, float] | None = None,
                             progress=None) -> Path:
    """A capture session with raw ZED images (``left.png``/``right.png`` straight off the sensor) and
    ``SN<serial>.conf`` written under ``reading``; ``session.yaml`` says ``zed_rectified: false`` (and declares
    ``board`` when it is another target than the checkerboard: ChArUco, circle grids).
    ``truth/`` as in ``generate_session`` (in the true rectified frame) plus ``raw_zed_truth.yaml``."""

    raw = raw or default_raw_zed()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rig = raw_zed_rig(raw)
    conf = f"SN{serial}.conf"
    # conf_rotation_error_rad: the factory file describes a right camera turned by this much (about its own centre)
    # against the one that took the images
    conf_raw = raw
    if conf_rotation_error_rad is not None:  # X_right' = R_err @ X_right = R_err @ R @ X_left + R_err @ T
        R_err = cv2.Rodrigues(np.asarray(conf_rotation_error_rad, np.float64).reshape(3, 1))[0]
        conf_raw = RawZed(raw.resolution, raw.left, raw.right, R_err @ raw.R, R_err @ raw.T_mm)
    write_raw_zed_conf(out / conf, conf_raw, reading)
    CameraFile(camera=rig.mech).write(out / "mech_intrinsics.yaml")
    SyntheticTruth(T_zed_from_mech=rig.T_zed_from_mech.tolist(),
                   p_projector_in_mech_mm=rig.p_projector_in_mech_mm.tolist(),
                   board_cols=board.cols, board_rows=board.rows, square_size_mm=board.square_size_mm, seed=seed,
                   depth_noise_mm=depth_noise_mm).write(out / "truth" / "rig_truth.yaml")
    RawZedTruth(conf_file=conf, reading=reading, R_rotvec_rad=cv2.Rodrigues(raw.R)[0].ravel().tolist(),
                T_mm=raw.T_mm.tolist()).write(out / "truth" / "raw_zed_truth.yaml")
    kw = dict(supersample=supersample, depth_noise_mm=depth_noise_mm, image_noise=image_noise)
    fruit_ids = {}
    for i in range(n_board):
        T_world_from_board = random_board_pose(rng, rig, board)
        cap = board_capture(f"{i:03d}", rig, board, T_world_from_board, rng, seed + i, **kw)
        scene = Scene([_table(seed + i), PlaneObject(OBJ_BOARD, T_world_from_board, board.albedo, board.extent_mm())])
        cap.zed_left, cap.zed_right = render_raw_zed_images(scene, rig, raw, rng, supersample, image_noise=image_noise)
        write_capture(out / "board" / cap.name, cap, out / "truth")
        if progress:
            progress(f"board {cap.name}")
    for i in range(n_scenes):
        scene = random_fruit_scene(rng, rig, seed + 100 + i)
        cap = render_capture(f"{i:03d}", scene, rig, rng, kind="scene", **kw)
        cap.zed_left, cap.zed_right = render_raw_zed_images(scene, rig, raw, rng, supersample, image_noise=image_noise)
        write_capture(out / "scenes" / cap.name, cap, out / "truth")
        fruit_ids[cap.name] = f"fruit{i // 2:02d}"
        if progress:
            progress(f"scene {cap.name}")
    # another target than the default checkerboard: session.yaml declares it (as generate_session)
    extra = {} if board == BoardSpec() else {"board": board_model_of(board)}
    SessionFile(zed_calibration=conf, zed_rectified=False, fruit_ids=fruit_ids, **extra).write(out / "session.yaml")
    return out


# ---- gauge objects (VDI/VDE 2634-2: spheres, a sphere pair, a plane) ------------------------------
OBJ_GAUGE = 4


def _gauge_albedo(xy: np.ndarray) -> np.ndarray:
    """A matte grey with a fine speckle (texture for the ZED images; the structured-light depth ignores it)."""
    return 0.55 + 0.15 * np.sin(xy[:, 0] * 0.7) * np.sin(xy[:, 1] * 0.9)


class SphereGauge(SpheroidObject):
    """A calibrated sphere (matte, speckled)."""

    def __init__(self, centre: np.ndarray, diameter_mm: float, seed: int):
        super().__init__(OBJ_GAUGE, centre, np.full(3, diameter_mm / 2.0), 0, 0.0, seed)

    def shade(self, p_world: np.ndarray) -> np.ndarray:
        q = (p_world - self.c) / self.r
        n = self.noise(np.stack([np.arctan2(q[:, 1], q[:, 0]) * 60, np.arcsin(np.clip(q[:, 2], -1, 1)) * 60], axis=1))
        return (0.45 + 0.35 * n)[:, None] * np.ones(3)


class RodGauge:
    """A cylinder of ``diameter_mm`` from ``a`` to ``b`` (a ball bar's bar; open ends, inside the spheres)."""

    def __init__(self, a: np.ndarray, b: np.ndarray, diameter_mm: float):
        self.obj_id = OBJ_GAUGE
        self.a = np.asarray(a, float)
        self.length = float(np.linalg.norm(np.asarray(b, float) - self.a))
        self.ax = (np.asarray(b, float) - self.a) / self.length
        self.r = diameter_mm / 2

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        m = o - self.a
        dp = d - np.outer(d @ self.ax, self.ax)
        mp = m - np.outer(m @ self.ax, self.ax)
        A = np.einsum("ij,ij->i", dp, dp)
        B = 2 * np.einsum("ij,ij->i", mp, dp)
        C = np.einsum("ij,ij->i", mp, mp) - self.r ** 2
        disc = B * B - 4 * A * C
        sq = np.sqrt(np.maximum(disc, 0))
        t = np.full(len(d), np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            for tk in ((-B + sq) / (2 * A), (-B - sq) / (2 * A)):  # nearer last: it wins where both are valid
                s_ = np.einsum("ij,j->i", m + tk[:, None] * d, self.ax)
                ok = (disc >= 0) & (A > 1e-12) & (tk > 1e-9) & (s_ >= 0) & (s_ <= self.length)
                t = np.where(ok & (tk < t), tk, t)
        return t

    def shade(self, p_world: np.ndarray) -> np.ndarray:
        return np.full((len(p_world), 3), 0.6)

    def normal(self, p_world: np.ndarray) -> np.ndarray:
        m = p_world - self.a
        n = m - np.outer(m @ self.ax, self.ax)
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def gauge_scenes(rig: SyntheticRig, seed: int, sphere_diameter_mm: float = 100.0, pair_diameter_mm: float = 80.0,
                 pair_distance_mm: float = 240.0, plane_wh_mm: tuple[float, float] = (220.0, 150.0),
                 plane_tilt_deg: float = 20.0, pair_bar_mm: float = 0.0) -> dict[str, tuple[Scene, dict]]:
    """name -> (scene, truth in the world frame): a sphere resting on the table, two spheres at a known centre
    distance (``pair_bar_mm`` > 0: joined by a bar of that diameter, a ball bar), a tilted plate 60 mm above the
    table; all under the middle of the structured-light view."""
    T_world_from_mech = invert_T(rig.T_mech_from_world)
    p, d = T_world_from_mech[:3, 3], T_world_from_mech[:3, 2]
    c_table = p + (-p[2] / d[2]) * d
    out = {}
    r = sphere_diameter_mm / 2
    c = c_table + [0, 0, r]
    out["sphere"] = (Scene([_table(seed), SphereGauge(c, sphere_diameter_mm, seed)]),
                     dict(kind="sphere", centres_world_mm=np.array([c]), diameter_mm=sphere_diameter_mm))
    r = pair_diameter_mm / 2
    ang = np.radians(25.0)
    half = pair_distance_mm / 2 * np.array([np.cos(ang), np.sin(ang), 0.0])
    cs = np.array([c_table - half + [0, 0, r], c_table + half + [0, 0, r]])
    bar = [RodGauge(cs[0], cs[1], pair_bar_mm)] if pair_bar_mm > 0 else []
    out["sphere_pair"] = (Scene([_table(seed + 1)]
                                + [SphereGauge(x, pair_diameter_mm, seed + 2 + k) for k, x in enumerate(cs)]
                                + bar),
                          dict(kind="sphere_pair", centres_world_mm=cs, diameter_mm=pair_diameter_mm,
                               centre_distance_mm=pair_distance_mm))
    w, h = plane_wh_mm
    T_world_from_plate = make_T(cv2.Rodrigues(np.array([np.radians(plane_tilt_deg), 0.0, 0.0]))[0],
                                c_table + [0, 0, 60.0])
    out["plane"] = (Scene([_table(seed + 3),
                           PlaneObject(OBJ_GAUGE, T_world_from_plate, _gauge_albedo, (-w / 2, w / 2, -h / 2, h / 2))]),
                    dict(kind="plane", normal_world=T_world_from_plate[:3, 2],
                         point_world_mm=T_world_from_plate[:3, 3]))
    return out


def generate_gauges(session_dir: str | Path, *, scale: float = 0.5, seed: int = 0, depth_noise_mm: float = 0.0,
                    depth_scale: float = 1.0, image_noise: float = 1.5, supersample: int = 1, two_camera: bool = False,
                    names: tuple[str, ...] | None = None, **sizes) -> Path:
    """Add ``gauges/`` to a session written by ``generate_session`` (same ``scale``/``two_camera``): one capture per
    gauge object (``gauge_scenes``; ``sizes`` override its sizes) and ``gauges/gauges.yaml`` naming each object's
    calibrated size (docs/capture-layout.md). ``depth_scale``: the structured-light depth is multiplied by it (a
    depth scale error). ``names``: only these of ``sphere``, ``sphere_pair``, ``plane``. ``truth/gauge_<name>.npz``: the
    exact centres (ZED-left frame) or plane, and ZED-left truth. The rig is the session's as its
    ``truth/rig_truth.yaml`` records it: a separate depth camera and the errors put in the files (the ZED's true
    baseline, the right camera's yaw, the depth map's scale and offset) hold for the gauges as for the boards and
    scenes."""

    root = Path(session_dir)
    rig = _session_rig(root, scale, two_camera)
    rng = np.random.default_rng(seed + 7000)
    specs = []
    for name, (scene, truth) in gauge_scenes(rig, seed, **sizes).items():
        if names is not None and name not in names:
            continue
        cap = render_capture(name, scene, rig, rng, kind="gauge", supersample=supersample,
                             depth_noise_mm=depth_noise_mm, image_noise=image_noise)
        cap.depth_mm = (cap.depth_mm * np.float32(depth_scale)).astype(np.float32)
        cap.fruit_truth = None
        write_capture(root / "gauges" / name, cap, root / "truth")
        T_zed_from_world = rig.T_zed_from_world
        extra = {}
        if "centres_world_mm" in truth:
            extra["centres_zed_mm"] = transform_points(T_zed_from_world, truth["centres_world_mm"])
        if truth["kind"] == "plane":
            n = T_zed_from_world[:3, :3] @ truth["normal_world"]
            extra.update(plane_normal_zed=n, plane_offset_zed_mm=float(
                n @ transform_points(T_zed_from_world, truth["point_world_mm"][None])[0]))
        with np.load(root / "truth" / f"gauge_{name}.npz") as z:
            arrays = {k: z[k] for k in z.files}
        np.savez_compressed(root / "truth" / f"gauge_{name}.npz", **arrays, **extra)
        specs.append(GaugeSpec(capture=name, kind=truth["kind"], diameter_mm=truth.get("diameter_mm"),
                               centre_distance_mm=truth.get("centre_distance_mm")))
    GaugesFile(gauges=specs).write(root / "gauges" / "gauges.yaml")
    return root


def _session_rig(root: Path, scale: float, two_camera: bool) -> SyntheticRig:
    """The rig a session's captures were rendered with, from its ``truth/rig_truth.yaml`` where there is one (before,
    ``generate_gauges`` rendered with the plain one-camera rig whatever the session's: ``synth --gauges
    --separate-depth-camera`` wrote gauge depth maps of the texture camera's size, which validate refused, and
    ``--depth-scale-error-pct`` and the other file errors left the gauges exact)."""
    p = root / "truth" / "rig_truth.yaml"
    truth = SyntheticTruth.read(p) if p.is_file() else None
    two_camera = two_camera or (truth is not None and truth.T_mech_from_depth is not None)
    rig = two_camera_rig(scale) if two_camera else default_rig(scale)
    if truth is None:
        return rig
    if truth.zed_baseline_true_mm is not None:
        rig.zed_file = rig.zed
        rig.zed = rig.zed.model_copy(update={"baseline_mm": truth.zed_baseline_true_mm})
    rig.right_yaw_rad = float(np.radians(truth.zed_right_yaw_deg))
    rig.depth_scale, rig.depth_offset_mm = truth.depth_scale, truth.depth_offset_mm
    return rig


def random_partial_board_pose(rng: np.random.Generator, rig, board, corner: int, camera: str = "mech",
                              min_common: int = 12, tries: int = 3000) -> np.ndarray:
    """``T_world_from_board`` with the board cut by ``camera``'s image border ("mech" or "zed") near image corner
    ``corner`` (0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left): some of its points outside that image, at
    least ``min_common`` inside both the texture and the ZED-left image (3 px from the border), the board above the
    table and seen at most 60 degrees off-axis. These are the poses a full-board rule loses."""

    cam, T_cam_from_world = ((rig.mech, rig.T_mech_from_world) if camera == "mech"
                             else (rig.zed.left, rig.T_zed_from_world))
    X = board.corners_board()
    ex = board.extent_mm()
    outline = np.array([[ex[0], ex[2], 0], [ex[1], ex[2], 0], [ex[0], ex[3], 0], [ex[1], ex[3], 0]])
    centre_b = np.array([(ex[0] + ex[1]) / 2, (ex[2] + ex[3]) / 2, 0])
    fu, fv = [(0, 0), (1, 0), (1, 1), (0, 1)][corner]
    z_table = float(T_cam_from_world[2, 3])  # about the camera's distance to the table
    views = [(rig.mech, rig.T_mech_from_world), (rig.zed.left, rig.T_zed_from_world)]
    for _ in range(tries):
        a, b = rng.uniform(0.02, 0.2, size=2)
        u = (1 - a if fu else a) * cam.width_px
        v = (1 - b if fv else b) * cam.height_px
        xy = cam.undistort_to_normalized(np.array([[u, v]]))[0]
        if not np.all(np.isfinite(xy)):
            continue
        p_cam = np.array([xy[0], xy[1], 1.0]) * rng.uniform(0.55, 0.85) * z_table
        tilt = rng.uniform(-35, 35, size=2)
        R = (cv2.Rodrigues(np.radians([tilt[0], tilt[1], 0.0]))[0]
             @ cv2.Rodrigues(np.radians([0, 0, rng.uniform(-30, 30)]))[0])
        T_cam_from_board = make_T(R, np.zeros(3))
        T_cam_from_board[:3, 3] = p_cam - R @ centre_b
        T_world_from_board = invert_T(T_cam_from_world) @ T_cam_from_board
        if (transform_points(T_world_from_board, outline)[:, 2] < 5).any():
            continue  # under the table
        inside_all, ok = [], True
        for c, T_c_from_world in views:
            pc = transform_points(T_c_from_world @ T_world_from_board, X)
            n_cam = (T_c_from_world @ T_world_from_board)[:3, 2]
            m = pc.mean(0)
            if np.any(pc[:, 2] <= 0) or n_cam @ (m / np.linalg.norm(m)) < np.cos(np.radians(60)):
                ok = False
                break
            uv = c.project(pc)
            inside_all.append((uv[:, 0] >= 3) & (uv[:, 1] >= 3) & (uv[:, 0] <= c.width_px - 4)
                              & (uv[:, 1] <= c.height_px - 4))
        if not ok:
            continue
        own = inside_all[0] if camera == "mech" else inside_all[1]
        both = inside_all[0] & inside_all[1]
        if own.all() or both.sum() < min_common or collinear(X[both]):
            continue
        return T_world_from_board
    raise RuntimeError(f"could not place a board cut by the {camera} image's corner {corner}")



@dataclass
class BoardViews:
    """What calibrate needs from one board capture (no right image), with the exact truth."""

    name: str
    mech_texture: np.ndarray
    depth_mm: np.ndarray
    zed_left: np.ndarray
    T_mech_from_board: np.ndarray
    corners_mech_uv: np.ndarray
    corners_zed_uv: np.ndarray



def _render_cropped(scene, cam, T_cam_from_world: np.ndarray, T_world_from_board: np.ndarray, board,
                    supersample: int, background: float = 0.3) -> np.ndarray:
    """Linear RGB of ``scene`` rendered only inside the board's bounding box (a camera with the same lens and a
    shifted principal point sees exactly the same rays there); elsewhere a flat ``background``."""

    ex = board.extent_mm()
    t = np.linspace(0, 1, 24)
    edge = np.concatenate([np.stack([ex[0] + t * (ex[1] - ex[0]), np.full_like(t, y)], 1) for y in ex[2:]]
                          + [np.stack([np.full_like(t, x), ex[2] + t * (ex[3] - ex[2])], 1) for x in ex[:2]])
    pc = transform_points(T_cam_from_world @ T_world_from_board, np.column_stack([edge, np.zeros(len(edge))]))
    out = np.full((cam.height_px, cam.width_px, 3), background)
    pc = pc[pc[:, 2] > 0]
    if len(pc) == 0:
        return out
    uv = cam.project(pc)
    u0, v0 = (np.floor(uv.min(0)) - 6).astype(int)
    u1, v1 = (np.ceil(uv.max(0)) + 6).astype(int)
    u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, cam.width_px - 1), min(v1, cam.height_px - 1)
    if u1 <= u0 or v1 <= v0:
        return out
    crop = cam.model_copy(update=dict(width_px=int(u1 - u0 + 1), height_px=int(v1 - v0 + 1),
                                      cx_px=cam.cx_px - u0, cy_px=cam.cy_px - v0))
    out[v0:v1 + 1, u0:u1 + 1] = render_image(scene, crop, T_cam_from_world, supersample)
    return out



def render_board_views(name: str, rig, board, T_world_from_board: np.ndarray, rng: np.random.Generator, seed: int,
                       supersample: int = 2, image_noise: float = 1.0, blur_sigma_px: float = 0.6) -> BoardViews:
    """The texture, the depth (exact, projector shadows ignored: a flat board casts none on itself) and the
    rectified ZED-left image of one board pose, rendered inside the board's bounding box only (the table around it
    is flat grey): ``gtforge.synthetic.board_capture`` without the right image and the stereo truth, several
    times faster, for tests that only calibrate."""

    scene = Scene([_table(seed), PlaneObject(OBJ_BOARD, T_world_from_board, board.albedo, board.extent_mm())])
    tex = finish_image(_render_cropped(scene, rig.mech, rig.T_mech_from_world, T_world_from_board, board, supersample),
                       rng, blur_sigma_px, image_noise, gray=True)
    left = finish_image(_render_cropped(scene, rig.zed.left, rig.T_zed_from_world, T_world_from_board, board,
                                        supersample), rng, blur_sigma_px, image_noise)
    z, _, _ = raycast_depth(scene, rig.depth_camera, rig.T_depth_from_world)
    depth = np.where(np.isfinite(z), z, np.nan).astype(np.float32)
    T_mech_from_board = rig.T_mech_from_world @ T_world_from_board
    X = board.corners_board()
    return BoardViews(name, tex, depth, left, T_mech_from_board,
                      rig.mech.project(transform_points(T_mech_from_board, X)),
                      rig.zed.left.project(transform_points(rig.T_zed_from_world @ T_world_from_board, X)))
