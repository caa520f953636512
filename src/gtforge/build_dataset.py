"""Stage 2: disparity ground truth aligned with the rectified ZED left image, written in formats
stereo training code reads without glue (docs/dataset-format.md). Parallel, resumable, atomic."""
from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar, Literal

import cv2
import numba
import numpy as np
from pydantic import Field

try:
    import fcntl  # scene writer locks (POSIX); without it stale folders are removed unconditionally
except ImportError:  # pragma: no cover
    fcntl = None

import gtforge
from gtforge.calibrate import CalibrationFile, check_rig_matches_session
from gtforge.core.camera import RectifiedStereo, Rig
from gtforge.errors import InputError, Interrupted
from gtforge.core.geometry import finite_box, fit_plane_robust, mask_bounding_box
from gtforge.infra.atomic import atomic_copy_file, atomic_write_text, private_folder
from gtforge.infra.digest import blake3_file, sha256_file
from gtforge.io.outputs import require_output_folder
from gtforge.io.formats import (
    write_image,
    write_kitti_disparity_pair,
    write_label_png,
    write_pfm,
    write_ply,
    write_tiff_float,
)
from gtforge.infra.unbuffered import background_writes
from gtforge.core.reproject import ReprojectParams, reproject_to_zed, right_view_disparity
from gtforge.infra.scheduling import prestart_pool, release_written_pages, run_tasks
from gtforge.core.schema import GTModel, VersionedFile
from gtforge.core.uncertainty import SigmaStats, UncertaintyParams, disparity_sigma, sigma_stats_by_label
from gtforge.verify import SceneVerification, VerifyParams, verify_scene, zed_rows_used

if TYPE_CHECKING:
    from gtforge.io.captures import ReadRecord

log = logging.getLogger("gtforge.build_dataset")

REGION_NONE, REGION_BG, REGION_CENTRE, REGION_EDGE = 0, 1, 2, 3
# the KITTI view's disparity folders (its image_2/image_3 are links to the scene's im0/im1)
KITTI_DISPARITY_DIRS = ("disp_occ_0", "disp_noc_0", "disp_occ_1", "disp_noc_1")


class BuildParams(GTModel):
    mode: Literal["mesh", "splat"] = "mesh"
    max_slant_deg: float = Field(85.0, gt=0, lt=90)
    abs_tol_mm: float = Field(0.5, ge=0)
    occlusion_rel_tol: float = 0.01
    fruit_height_mm: float = Field(10.0, gt=0)  # points this far above the table plane are foreground
    plane_threshold_mm: float = Field(3.0, gt=0)
    min_component_frac: float = 0.2  # keep foreground components at least this share of the largest
    erosion_px: int = Field(15, ge=1)  # fruit centre = fruit eroded by this; edge = the rest
    lambda_edge: float = 1.4
    lambda_center: float = 1.0
    lambda_bg: float = 0.8
    split_train: float = 0.8
    split_val: float = 0.1
    split_seed: int = 0
    kitti: bool = True
    eth3d: bool = True
    crop_wh: tuple[int, int] | None = None
    ply: bool = False
    max_disp_px: float = 192.0  # statistics: share of pixels above this (many training repos drop them)
    verification: bool = True  # per-scene checks of the GT against its own images (gtforge.verify)
    sigma: bool = True  # disp0GT_sigma.pfm: per-pixel 1-sigma GT uncertainty (gtforge.core.uncertainty)
    right_gt: bool = True  # disp1GT.pfm + mask1nocc.png (+ KITTI disp_occ_1/disp_noc_1): the right view's GT
    uncertainty: UncertaintyParams = Field(default_factory=UncertaintyParams)
    verify: VerifyParams = Field(default_factory=VerifyParams)
    quarantine: bool = False  # leave flagged scenes out of the split lists (they stay in scenes/)

    def reproject_params(self) -> ReprojectParams:
        return ReprojectParams(self.mode, self.max_slant_deg, self.abs_tol_mm)

    def output_hash(self) -> str:
        """Hash of the parameters that change a scene's files (not the split lists)."""
        d = self.model_dump(exclude={"split_train", "split_val", "split_seed", "quarantine"})
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


class SceneStats(GTModel):
    valid_pct: float
    nonoccluded_pct: float
    fruit_pct: float
    disp_min_px: float | None
    disp_max_px: float | None
    over_max_disp_pct: float


class InputStamp(GTModel):
    """An input file's size and modification time when its BLAKE3 was taken (meta.json)."""

    size_bytes: int
    mtime_ns: int
    hashed_at_ns: int


class SceneMeta(VersionedFile):

    SCHEMA_VERSION: ClassVar[int] = 2  # 2: the inputs' BLAKE3 (input_blake3) instead of their SHA-256
    KIND: ClassVar[str] = "scene meta.json (from gtforge build-dataset)"
    schema_version: int = 2
    scene: str
    fruit_id: str | None = None
    gtforge_version: str
    calibration_sha256: str
    params_hash: str
    input_blake3: dict[str, str]  # the input files' BLAKE3 (io.digest), by name
    input_stamps: dict[str, InputStamp] = Field(default_factory=dict)  # resume fast path (inputs_unchanged)
    stats: SceneStats
    crop_xywh: list[int] | None = None
    fruit_mask_source: Literal["geometry", "user"] = "geometry"
    time_s: float = 0.0
    time_read_s: float = 0.0
    time_compute_s: float = 0.0
    time_write_s: float = 0.0
    verification: SceneVerification | None = None
    sigma: dict[str, SigmaStats] | None = None  # GT uncertainty per region: all, fruit, fruit_centre, ...
    sigma_extrinsic_included: bool = False  # False: the calibration file had no covariance (older gtforge)


class Manifest(VersionedFile):

    SCHEMA_VERSION: ClassVar[int] = 2  # 2: scene metas of schema 2
    KIND: ClassVar[str] = "dataset manifest.json (from gtforge build-dataset)"
    schema_version: int = 2
    gtforge_version: str
    calibration_path: str
    calibration_sha256: str
    session_dir: str
    params: BuildParams
    scenes: dict[str, SceneMeta]
    failures: dict[str, str] = Field(default_factory=dict)
    splits: dict[str, list[str]] = Field(default_factory=dict)
    flagged: dict[str, list[str]] = Field(default_factory=dict)  # scene -> why verification flagged it
    quarantined: list[str] = Field(default_factory=list)  # flagged scenes left out of the split lists


@dataclass
class BuildSummary:
    built: list[str]
    skipped_unchanged: list[str]
    failures: dict[str, str]
    out_dir: Path
    time_s: float
    splits: dict[str, list[str]] = field(default_factory=dict)
    flagged: dict[str, list[str]] = field(default_factory=dict)
    quarantined: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failures


# A recorded size + mtime is trusted only when the file was last modified this long before it was hashed:
# a file rewritten within the filesystem's timestamp granularity of the hash could keep both (as git's
# "racily clean" entries).
STAMP_MARGIN_NS = 2_000_000_000


def hash_inputs(paths: list[Path], read: dict[str, "ReadRecord"] | None = None
                ) -> tuple[dict[str, str], dict[str, "InputStamp"]]:
    """BLAKE3 of each input (``io.digest``), and its size + mtime taken just before hashing (for
    ``inputs_unchanged``).
    ``read``: files the capture reader already hashed as it read them (``Capture.read_records``), by name."""
    hashes, stamps = {}, {}
    for p in paths:
        r = (read or {}).get(p.name)
        if r is not None:
            hashes[p.name] = r.blake3
            stamps[p.name] = InputStamp(size_bytes=r.size_bytes, mtime_ns=r.mtime_ns, hashed_at_ns=r.read_at_ns)
            continue
        st = p.stat()
        now_ns = time.time_ns()
        hashes[p.name] = blake3_file(p)
        stamps[p.name] = InputStamp(size_bytes=st.st_size, mtime_ns=st.st_mtime_ns, hashed_at_ns=now_ns)
    return hashes, stamps


def inputs_unchanged(meta: "SceneMeta", paths: list[Path]) -> bool:
    """Resume check: the same input files with the same contents as when ``meta``'s scene was built.
    A file whose size and mtime equal the recorded ones (and was not modified within ``STAMP_MARGIN_NS``
    of being hashed) counts as unchanged without reading it; any other file is hashed and compared."""
    if {p.name for p in paths} != set(meta.input_blake3):
        return False
    for p in paths:
        st = p.stat()
        s = meta.input_stamps.get(p.name)
        if s is not None and s.size_bytes == st.st_size and s.mtime_ns == st.st_mtime_ns \
                and s.mtime_ns < s.hashed_at_ns - STAMP_MARGIN_NS:
            continue
        if blake3_file(p) != meta.input_blake3[p.name]:
            return False
    return True


def scene_files(params: BuildParams) -> list[str]:
    """The files build_one_scene writes into a scene folder with these parameters."""
    return (["im0.png", "im1.png", "disp0GT.pfm", "mask0nocc.png", "region.png", "weight.tiff", "depth0.tiff",
             "calib.txt", "meta.json"] + (["disp1GT.pfm", "mask1nocc.png"] if params.right_gt else [])
            + (["disp0GT_sigma.pfm"] if params.sigma else []) + (["cloud.ply"] if params.ply else []))


# ---- regions --------------------------------------------------------------------------------
def fruit_regions(depth_mm: np.ndarray, zed: RectifiedStereo, params: BuildParams,
                  user_mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(region labels uint8, fruit mask bool). Fruit from geometry: RANSAC plane of the table in the GT
    point cloud, points more than ``fruit_height_mm`` above it, the largest components."""
    valid = np.isfinite(depth_mm)
    if user_mask is not None:
        fruit = user_mask & valid
    else:
        fruit = np.zeros(valid.shape, bool)
        box = mask_bounding_box(valid)  # the GT's bounding box: the work below is done on it
        flat = np.flatnonzero(valid[box[0]:box[1], box[2]:box[3]]) if box else ()  # GT pixels, raster order
        if len(flat) >= 100:
            y0, y1, x0, x1 = box
            # the plane from 20000 random GT pixels: only their 3-D points are built
            rng = np.random.default_rng(0)
            v, u = np.divmod(flat[rng.choice(len(flat), min(len(flat), 20000), replace=False)], x1 - x0)
            v, u = v + y0, u + x0
            cam = zed.left  # rectified: no distortion, the ray of pixel (u, v) is ((u - cx) / fx, (v - cy) / fy, 1)
            z = depth_mm[v, u].astype(np.float64)
            sub = np.stack([(u - cam.cx_px) / cam.fx_px * z, (v - cam.cy_px) / cam.fy_px * z, z], axis=1)
            n, c, _ = fit_plane_robust(sub, params.plane_threshold_mm, iterations=300, rng=rng)
            if c > 0:  # orient the normal towards the camera (origin): height = n.p - c > 0 in front
                n, c = -n, -c
            # height n.p - c with p = z * ray, the ray linear in u and v: one broadcast (float64), no point cloud
            ray_x = (np.arange(x0, x1) - cam.cx_px) / cam.fx_px
            ray_y = (np.arange(y0, y1) - cam.cy_px) / cam.fy_px
            n_p = (n[0] * ray_x)[None, :] + (n[1] * ray_y + n[2])[:, None]  # n . ray
            n_p *= depth_mm[y0:y1, x0:x1]  # n . p (NaN where no GT)
            fg = (n_p > c + params.fruit_height_mm) & valid[y0:y1, x0:x1]
            fg_box = mask_bounding_box(fg)  # connected components on the foreground's bounding box: the same ones
            if fg_box:
                fy0, fy1, fx0, fx1 = fg_box
                n_cc, labels, stats, _ = cv2.connectedComponentsWithStats(
                    fg[fy0:fy1, fx0:fx1].view(np.uint8), connectivity=8)
                areas = stats[1:, cv2.CC_STAT_AREA]
                keep = np.zeros(n_cc, bool)
                keep[1:] = (areas >= params.min_component_frac * areas.max()) & (areas >= 50)
                fruit[y0 + fy0:y0 + fy1, x0 + fx0:x0 + fx1] = keep[labels]
    region = valid.astype(np.uint8) * np.uint8(REGION_BG)  # REGION_NONE (0) where no GT
    box = mask_bounding_box(fruit)
    if box:  # erode and label the fruit's bounding box plus the element's radius only: the same result
        k = 2 * params.erosion_px + 1
        r = k // 2
        y0, y1 = max(box[0] - r, 0), min(box[1] + r, fruit.shape[0])
        x0, x1 = max(box[2] - r, 0), min(box[3] + r, fruit.shape[1])
        f = fruit[y0:y1, x0:x1]  # within the GT
        centre = cv2.erode(f.view(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).view(bool)
        region[y0:y1, x0:x1][f] = REGION_EDGE
        region[y0:y1, x0:x1][centre] = REGION_CENTRE  # the erosion keeps fruit pixels only
    return region, fruit


def sgra_weights(region: np.ndarray, params: BuildParams) -> np.ndarray:
    """``weight.tiff``: the SGRA loss weight of each pixel's region (0 where no GT), float32."""
    lut = np.zeros(256, np.float32)  # by region label: one table look-up (0.3 ms) instead of three masked writes (2 ms)
    lut[[REGION_BG, REGION_CENTRE, REGION_EDGE]] = params.lambda_bg, params.lambda_center, params.lambda_edge
    return cv2.LUT(np.ascontiguousarray(region, np.uint8), lut)


def middlebury_calib_text(zed: RectifiedStereo, width: int, height: int, disp_range_px: tuple[float, float] | None,
                          cx_shift: float = 0.0, cy_shift: float = 0.0) -> str:
    """Middlebury's ``calib.txt``; ``disp_range_px``: the GT disparity's (min, max), None without GT."""
    f, cx, cy = zed.left.fx_px, zed.left.cx_px - cx_shift, zed.left.cy_px - cy_shift
    vmin = int(np.floor(disp_range_px[0])) if disp_range_px else 0
    vmax = int(np.ceil(disp_range_px[1])) if disp_range_px else 0
    ndisp = int(max(32, 16 * np.ceil((vmax + 1) / 16)))
    return (f"cam0=[{f:.6f} 0 {cx:.6f}; 0 {zed.left.fy_px:.6f} {cy:.6f}; 0 0 1]\n"
            f"cam1=[{f:.6f} 0 {cx + zed.doffs_px:.6f}; 0 {zed.left.fy_px:.6f} {cy:.6f}; 0 0 1]\n"
            f"doffs={zed.doffs_px:.6f}\nbaseline={zed.baseline_mm:.6f}\nwidth={width}\nheight={height}\n"
            f"ndisp={ndisp}\nisint=0\nvmin={vmin}\nvmax={vmax}\ndyavg=0\ndymax=0\n")


@numba.njit(cache=True)
def _disparity_summary(disp, over_px):
    """(number of finite values, their min, their max, how many exceed ``over_px``) in one pass (numpy's boolean
    selection and three reductions took 4-5 ms of a 2208x1242 map)."""
    n, n_over = 0, 0
    lo, hi = np.inf, -np.inf
    y0, y1, x0, x1 = finite_box(disp)  # none outside it
    for v in range(y0, y1):
        row = disp[v, x0:x1]
        for u in range(x1 - x0):
            d = row[u]
            if abs(d) < np.inf:  # finite (NaN compares false)
                n += 1
                lo = min(lo, d)
                hi = max(hi, d)
                if d > over_px:
                    n_over += 1
    return n, lo, hi, n_over


# ---- one scene ------------------------------------------------------------------------------
def build_scene_arrays(depth_mech_mm: np.ndarray, rig: Rig, params: BuildParams, user_mask: np.ndarray | None = None):
    """Ground-truth depth/disparity/occlusion in the ZED-left image, region labels and the fruit mask."""
    depth_mech_mm = rig.corrected_depth_mm(depth_mech_mm)  # (itself without calibrate-scale's depth correction)
    sd = reproject_to_zed(depth_mech_mm, rig.depth_camera, rig.T_zed_from_depth, rig.zed, params.reproject_params(),
                          params.occlusion_rel_tol, left_span=params.sigma and params.mode == "mesh")
    region, fruit = fruit_regions(sd.depth_mm, rig.zed, params, user_mask)
    return sd, region, fruit


def _crop_window(fruit: np.ndarray, crop_wh: tuple[int, int]) -> tuple[int, int, int, int]:
    H, W = fruit.shape
    cw, ch = min(crop_wh[0], W), min(crop_wh[1], H)
    box = mask_bounding_box(fruit)
    if box:
        uc, vc = (box[2] + box[3] - 1) / 2, (box[0] + box[1] - 1) / 2
    else:
        uc, vc = W / 2, H / 2
    x0 = int(np.clip(round(uc - cw / 2), 0, W - cw))
    y0 = int(np.clip(round(vc - ch / 2), 0, H - ch))
    return x0, y0, cw, ch


def build_one_scene(session_dir: str, capture_dir: str, sid: str, calib_path: str, calib_sha: str, out_dir: str,
                    params_json: str) -> tuple[str, str | None, dict | None]:
    """Worker: build capture ``capture_dir`` into ``scenes/<sid>/`` atomically.
    Returns (sid, error or None, meta dict)."""
    t0 = time.perf_counter()
    params = BuildParams.model_validate_json(params_json)
    cap_dir = Path(capture_dir)
    try:
        calib = _cached_calibration(calib_path, calib_sha)
        session = _cached_session(session_dir, calib)
        rig = calib.rig  # checked against the session by build_dataset before any worker starts
        # calibrate-scale's right-camera yaw: im1 is the right image re-rectified (decoded whole, written re-encoded)
        yawed = rig.zed_right_yaw_deg != 0.0
        # image content is needed by verification, a crop (re-encoded im0/im1) and the PLY's colours only; for
        # verification alone the images are decoded once the ground truth says how many ZED rows the checks read
        cap = session.load_capture(cap_dir, decode_images=bool(params.crop_wh) or params.ply or yawed)
        t_read = time.perf_counter()
        sd, region, fruit = build_scene_arrays(cap.mech_depth_mm, rig, params, cap.fruit_mask)
        decode_s = 0.0
        if yawed:
            from gtforge.scale_calibration import corrected_right_image

            cap.zed_right = corrected_right_image(cap.zed_right, rig)
        if params.verification:
            t = time.perf_counter()
            texture, zed_left, zed_right = session.decoded_images(cap, zed_rows_used(sd.depth_mm, params.verify))
            decode_s = time.perf_counter() - t
    except InputError as exc:
        return sid, str(exc), None
    disp, depth, noc, region_uncropped = sd.disparity_px, sd.depth_mm, sd.nonoccluded, region
    left, right = cap.zed_left, cap.zed_right
    disp1 = noc1 = None
    if params.right_gt:
        disp1, noc1 = right_view_disparity(sd.depth_mm, sd.depth_right_mm, rig.zed, params.occlusion_rel_tol)
    crop, sl = None, (slice(None), slice(None))
    cx_shift = cy_shift = 0.0
    if params.crop_wh:
        x0, y0, cw, ch = _crop_window(fruit, params.crop_wh)
        sl = (slice(y0, y0 + ch), slice(x0, x0 + cw))
        left, right, depth, disp, region, fruit, noc = (left[sl], right[sl], depth[sl], disp[sl], region[sl], fruit[sl],
                                                        noc[sl])
        if disp1 is not None:
            disp1, noc1 = disp1[sl], noc1[sl]
        crop, cx_shift, cy_shift = [x0, y0, cw, ch], float(x0), float(y0)
    n_valid, lo, hi, n_over = _disparity_summary(disp, params.max_disp_px)
    stats = SceneStats(valid_pct=100.0 * (n_valid / disp.size),
                       nonoccluded_pct=100.0 * (np.count_nonzero(noc) / noc.size),
                       fruit_pct=100.0 * (np.count_nonzero(fruit) / fruit.size),
                       disp_min_px=float(lo) if n_valid else None, disp_max_px=float(hi) if n_valid else None,
                       over_max_disp_pct=100.0 * (n_over / n_valid) if n_valid else 0.0)
    scenes = Path(out_dir) / "scenes"
    token = uuid.uuid4().hex[:12]  # unique across processes and machines (Dask workers share the folder)
    tmp = scenes / f".tmp-{sid}-{token}"
    lock = _lock_writer(scenes, sid, token)  # held until the scene is in place (see _remove_stale)
    write_s = 0.0
    try:
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        # renamed into place whole below: no temporary file per file. The files that do not depend on the
        # verification are written first: the large ones go from this process's writer thread while the verification
        # runs; all of them are complete when the inner context exits
        with private_folder(tmp), background_writes():
            t = time.perf_counter()
            for name, img, src in (("im0.png", left, cap.zed_left_file),
                                   ("im1.png", right, None if yawed else cap.zed_right_file)):
                if src is not None and crop is None:
                    atomic_copy_file(src, tmp / name)  # the input is already this RGB PNG: no re-encode
                else:
                    write_image(tmp / name, img)
            write_tiff_float(tmp / "depth0.tiff", depth)
            write_pfm(tmp / "disp0GT.pfm", disp)
            if disp1 is not None:
                write_pfm(tmp / "disp1GT.pfm", disp1)
                write_label_png(tmp / "mask1nocc.png", occlusion_mask(disp1, noc1))
            write_label_png(tmp / "mask0nocc.png", occlusion_mask(disp, noc))
            write_label_png(tmp / "region.png", region)
            write_tiff_float(tmp / "weight.tiff", sgra_weights(region, params), compression="zlib")  # 4 values: tiny
            disp_range = (stats.disp_min_px, stats.disp_max_px) if n_valid else None
            atomic_write_text(tmp / "calib.txt", middlebury_calib_text(rig.zed, disp.shape[1], disp.shape[0], disp_range,
                                                                      cx_shift, cy_shift))
            if params.ply:
                v, u = np.nonzero(np.isfinite(disp))
                K = rig.zed.left
                z = depth[v, u].astype(np.float64)
                pts = np.stack([(u + cx_shift - K.cx_px) / K.fx_px * z, (v + cy_shift - K.cy_px) / K.fy_px * z, z], axis=1)
                write_ply(tmp / "cloud.ply", pts, left[v, u] / 255.0)
            write_s += time.perf_counter() - t
            verification = None
            if params.verification:  # on the whole (uncropped) images
                verification, rendered = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region_uncropped,
                                                      zed_left, zed_right, texture, rig, params.verify)
                if verification.status == "flagged" and rendered is not None:
                    if zed_left.shape[0] < sd.depth_mm.shape[0]:  # the overlay shows the whole image
                        zed_left = session.decoded_images(cap)[1]
                    write_verification_overlay(Path(out_dir) / "verification" / f"{sid}_overlay.jpg", zed_left,
                                               rendered)
            sigma = None
            if params.sigma:
                shift = verification.texture_all.magnitude_px if verification is not None else None
                sigma = disparity_sigma(sd.disparity_px, sd.depth_mm, rig, calib.cov_extrinsic_rad_mm,
                                        params.uncertainty, sd.span_mm, shift)
                if calib.scale_calibration is not None:  # the scale terms' uncertainty (calibrate-scale)
                    from gtforge.scale_calibration import add_scale_sigma

                    sigma = add_scale_sigma(sigma, sd.depth_mm, rig, calib.scale_calibration)
                sigma = sigma[sl]
                t = time.perf_counter()
                write_pfm(tmp / "disp0GT_sigma.pfm", sigma)
                write_sigma_thumbnail(Path(out_dir) / "report" / f"{sid}_sigma.jpg", sigma)
                write_s += time.perf_counter() - t
            inputs, stamps = hash_inputs([p for p in cap.input_files if p.exists()], cap.read_records)
            meta = SceneMeta(scene=sid, fruit_id=cap.fruit_id, gtforge_version=gtforge.__version__,
                             calibration_sha256=calib_sha, params_hash=params.output_hash(), input_blake3=inputs,
                             input_stamps=stamps, stats=stats, crop_xywh=crop,
                             fruit_mask_source="user" if cap.fruit_mask is not None else "geometry",
                             verification=verification,
                             sigma=None if sigma is None else region_sigma_stats(sigma, region),
                             sigma_extrinsic_included=sigma is not None and calib.cov_extrinsic_rad_mm is not None)
            t_end = time.perf_counter()
            meta.time_s, meta.time_read_s = t_end - t0, t_read - t0 + decode_s  # (the images decoded for verification)
            meta.time_compute_s, meta.time_write_s = t_end - t_read - decode_s - write_s, write_s
            meta.write(tmp / "meta.json")
        final = scenes / sid
        old = scenes / f".old-{sid}-{token}"
        if final.exists():
            os.replace(final, old)
        os.replace(tmp, final)
        if old.exists():
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # (its writes have ended: background_writes waited for them)
        raise
    finally:
        _unlock_writer(scenes, sid, token, lock)
    with background_writes():
        write_scene_views(Path(out_dir), sid, params, disp, noc, disp1, noc1)
    kitti = Path(out_dir) / "kitti" / "training"
    release_written_pages([*(scenes / sid).iterdir(), *(kitti / d / f"{sid}_10.png" for d in KITTI_DISPARITY_DIRS)])
    return sid, None, meta.model_dump(mode="json")


def region_sigma_stats(sigma: np.ndarray, region: np.ndarray) -> dict[str, SigmaStats]:
    """Sigma statistics for all GT pixels, the fruit, its centre and edge, and the background (one pass)."""
    return sigma_stats_by_label(sigma, region, {
        "all": (REGION_BG, REGION_CENTRE, REGION_EDGE), "fruit": (REGION_CENTRE, REGION_EDGE),
        "fruit_centre": (REGION_CENTRE,), "fruit_edge": (REGION_EDGE,), "background": (REGION_BG,)})


def write_sigma_thumbnail(path: Path, sigma: np.ndarray, vmax_px: float = 0.1) -> None:
    """A small heat map of a scene's GT sigma for build_report.html (turbo, 0 to ``vmax_px``; black: no GT)."""
    s = np.asarray(sigma, np.float32)
    scale = min(1.0, 640 / s.shape[1])
    if scale < 1.0:  # nearest neighbour: the thumbnail's pixels are values of the map (inf stays inf)
        s = cv2.resize(s, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    grey = np.round(np.clip(np.nan_to_num(s, nan=0.0, posinf=0.0, neginf=0.0) / vmax_px, 0, 1) * 255).astype(np.uint8)
    bgr = cv2.applyColorMap(grey, cv2.COLORMAP_TURBO)
    bgr *= np.isfinite(s)[..., None]  # black where no GT (a boolean-mask assignment took 1.8 ms here)
    write_image(path, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))


def verify_one_scene(session_dir: str, dataset_dir: str, sid: str, calib_path: str,
                     params_json: str) -> tuple[str, dict]:
    """Worker for ``gtforge verify``: re-check a built scene against its captures. Returns (sid, SceneVerification)."""
    from gtforge.io.formats import read_image, read_pfm
    from gtforge.verify import SceneVerification, VerifyParams

    params = VerifyParams.model_validate_json(params_json)
    s = Path(dataset_dir) / "scenes" / sid
    try:
        calib = CalibrationFile.read(calib_path)
        session = _cached_session(session_dir, calib)
        rig = calib.rig
        meta = SceneMeta.read(s / "meta.json")
        folder = session.root / session.config.scenes_dir / sid
        if not folder.is_dir():
            raise InputError(folder, None, "the capture this scene was built from", "no such folder",
                             "verification needs the session's captures (pass --session if they moved)")
        cap = session.load_capture(folder)
        if rig.zed_right_yaw_deg != 0.0:  # calibrate-scale's yaw: the right image as the dataset's im1 has it
            from gtforge.scale_calibration import corrected_right_image

            cap.zed_right = corrected_right_image(cap.zed_right, rig)
        disp = read_pfm(s / "disp0GT.pfm")
        mask = read_image(s / "mask0nocc.png")
        region = read_image(s / "region.png")
    except InputError as exc:
        return sid, SceneVerification(status="not verifiable", reasons=[str(exc)]).model_dump(mode="json")
    H, W = cap.zed_left.shape[:2]
    if meta.crop_xywh:  # a cropped dataset: put the crop back where it was cut from
        x0, y0, cw, ch = meta.crop_xywh

        def uncrop(a, fill):
            full = np.full((H, W), fill, a.dtype)
            full[y0:y0 + ch, x0:x0 + cw] = a
            return full

        disp, mask, region = uncrop(disp, np.nan), uncrop(mask, 0), uncrop(region, 0)
    depth = rig.zed.disparity_to_depth(disp)
    ver, rendered = verify_scene(depth, disp, mask == 255, region, cap.zed_left, cap.zed_right, cap.mech_texture, rig,
                                 params)
    if ver.status == "flagged" and rendered is not None:
        write_verification_overlay(Path(dataset_dir) / "verification" / f"{sid}_overlay.jpg", cap.zed_left, rendered)
    return sid, ver.model_dump(mode="json")


def write_verification_overlay(path: Path, zed_left: np.ndarray, rendered_norm: np.ndarray) -> None:
    """A flagged scene's overlay for verification.html: ZED-left grey in green, the texture rendered through the
    ground truth in magenta (both locally normalised); aligned structures look grey, a shift shows as colour fringes."""
    from gtforge.io.formats import to_gray
    from gtforge.verify import local_normalize

    gray = to_gray(zed_left)
    if gray.shape != rendered_norm.shape:  # verify_scene renders at its work resolution (a factor smaller)
        gray = cv2.resize(gray, rendered_norm.shape[::-1], interpolation=cv2.INTER_AREA)
    g = local_normalize(gray.astype(np.float32), None, 3.0)

    def to8(a):
        return np.clip(128 + 50 * a, 0, 255).astype(np.uint8)

    rgb = np.stack([to8(rendered_norm), to8(g), to8(rendered_norm)], axis=2)
    rgb[rendered_norm == 0] = np.stack([to8(g)] * 3, axis=2)[rendered_norm == 0] // 2
    scale = min(1.0, 1280 / rgb.shape[1])
    if scale < 1.0:
        rgb = cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    write_image(path, rgb)


# Per worker process. A Dask worker (or this process with workers=1) lives across builds: an entry is
# reloaded when its files changed (session: their size and mtime; calibration: its sha256).
_SESSION_CACHE: dict = {}


def _cached_session(session_dir: str, calib: CalibrationFile):
    """The session as ``calib`` sees it (``CalibrationFile.open_session``: the SN.conf reading and the ZED
    self-rectification it recorded)."""
    corr = calib.zed_right_correction
    key = (session_dir, calib.zed_conf_reading, corr.model_dump_json() if corr is not None else None)
    hit = _SESSION_CACHE.get(key)
    if hit is None or hit[1] != _session_stamp(hit[0]):
        session = calib.open_session(session_dir)
        hit = _SESSION_CACHE[key] = (session, _session_stamp(session))
    return hit[0]


def _session_stamp(session) -> tuple:
    c = session.config
    stamp = []
    for name in ("session.yaml", c.mech_intrinsics, c.depth_intrinsics, c.zed_calibration, c.zed_right_info):
        if name:
            try:
                st = (session.root / name).stat()
                stamp.append((name, st.st_size, st.st_mtime_ns))
            except OSError:
                stamp.append((name, None, None))
    return tuple(stamp)


def _cached_calibration(path: str, sha256: str) -> CalibrationFile:
    key = ("calib", path)
    hit = _SESSION_CACHE.get(key)
    if hit is None or hit[1] != sha256:
        hit = _SESSION_CACHE[key] = (CalibrationFile.read(path), sha256)
    return hit[0]


# ---- splits and views -------------------------------------------------------------------------
def make_splits(scene_ids: list[str], fruit_ids: dict[str, str | None], params: BuildParams) -> dict[str, list[str]]:
    """Split by fruit: all scenes of one fruit land in the same split. Deterministic by ``split_seed``."""
    groups: dict[str, list[str]] = {}
    for s in sorted(scene_ids):
        groups.setdefault(fruit_ids.get(s) or f"scene:{s}", []).append(s)
    keys = sorted(groups)
    rng = np.random.default_rng(params.split_seed)
    rng.shuffle(keys)
    n = len(scene_ids)
    targets = {"train": params.split_train * n, "val": params.split_val * n}
    out = {"train": [], "val": [], "test": []}
    for k in keys:
        for split in ("train", "val", "test"):
            if split == "test" or len(out[split]) + len(groups[k]) / 2 <= targets[split]:
                out[split] += groups[k]
                break
    return {k: sorted(v) for k, v in out.items()}


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.tmp")
    if tmp.exists():
        tmp.unlink()
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copy2(src, tmp)
    os.replace(tmp, dst)


def occlusion_mask(disp: np.ndarray, nonoccluded: np.ndarray) -> np.ndarray:
    """``mask?nocc.png`` values: 255 non-occluded, 128 occluded in the other view, 0 no ground truth."""
    return _occlusion_mask(disp, nonoccluded)


@numba.njit(cache=True)
def _occlusion_mask(disp, nonoccluded):
    H, W = disp.shape
    mask = np.empty((H, W), np.uint8)
    for v in range(H):
        for u in range(W):
            mask[v, u] = 255 if nonoccluded[v, u] else (128 if abs(disp[v, u]) < np.inf else 0)
    return mask


def write_scene_views(out: Path, sid: str, params: BuildParams, disp: np.ndarray | None = None,
                      noc: np.ndarray | None = None, disp1: np.ndarray | None = None,
                      noc1: np.ndarray | None = None) -> None:
    """KITTI and ETH3D views of one built scene (links where possible). The arrays save re-reading."""
    from gtforge.io.formats import read_image, read_pfm

    s = out / "scenes" / sid
    if params.kitti:
        k = out / "kitti" / "training"
        _link(s / "im0.png", k / "image_2" / f"{sid}_10.png")
        _link(s / "im1.png", k / "image_3" / f"{sid}_10.png")
        if disp is None:
            disp = read_pfm(s / "disp0GT.pfm")
            noc = read_image(s / "mask0nocc.png") == 255
        write_kitti_disparity_pair(k / "disp_occ_0" / f"{sid}_10.png", k / "disp_noc_0" / f"{sid}_10.png", disp, noc)
        if disp1 is None and (s / "disp1GT.pfm").exists():
            disp1 = read_pfm(s / "disp1GT.pfm")
            noc1 = read_image(s / "mask1nocc.png") == 255
        if disp1 is not None:  # KITTI's right-view GT, as OpenStereo's RETURN_RIGHT_DISP reads it
            write_kitti_disparity_pair(k / "disp_occ_1" / f"{sid}_10.png", k / "disp_noc_1" / f"{sid}_10.png", disp1,
                                       noc1)
        else:  # built without the right view's GT (--no-right-gt): none from an earlier build stays in the view
            for d in ("disp_occ_1", "disp_noc_1"):
                (k / d / f"{sid}_10.png").unlink(missing_ok=True)
    if params.eth3d:
        e = out / "eth3d"
        for f in ("im0.png", "im1.png", "calib.txt"):
            _link(s / f, e / "two_view_training" / sid / f)
        for f in ("disp0GT.pfm", "mask0nocc.png"):
            _link(s / f, e / "two_view_training_gt" / sid / f)


def write_split_views(out: Path, splits: dict[str, list[str]], params: BuildParams) -> Path:
    """``OUT/views/<split>/``: each split in the folder layouts training repositories read from a fixed root, as
    relative symlinks into ``scenes/``, ``kitti/`` and ``eth3d/`` (nothing copied; the dataset stays relocatable):

    * ``Middlebury/MiddEval3/official_train.txt`` + ``training{F,H,Q}/<id>`` (RAFT-Stereo ``middlebury_F/H/Q``; IGEV-Stereo
      reads ``trainingH`` for the names; gtforge has one resolution, so F, H and Q are the same scenes);
    * ``Middlebury/2014/<id>/{im0,im1,im1E,im1L}.png, disp0.pfm, calib.txt`` (RAFT-Stereo ``middlebury_2014``; im1E and
      im1L, the 2014 dataset's other exposure and lighting, are im1);
    * ``ETH3D/two_view_training{,_gt}/<id>`` and ``KITTI/training/<kind>/<id>_10.png`` (RAFT-Stereo, IGEV-Stereo).

    A split with no scene gets no folder. The tree is built beside ``views/`` (same depth, so the relative links are the
    same) and swapped in by rename."""
    views = out / "views"
    tmp = out / f".views-{uuid.uuid4().hex[:12]}"
    tmp.mkdir()
    links: list[tuple[str, str]] = []  # (target, link), as absolute paths; made at the end, relative

    def link(target: Path, at: Path) -> None:
        links.append((os.fspath(target), os.fspath(at)))

    for split, ids in splits.items():
        if not ids:
            continue
        root = tmp / split
        midd = root / "Middlebury" / "MiddEval3"
        midd.mkdir(parents=True)
        atomic_write_text(midd / "official_train.txt", "\n".join(ids) + "\n")
        for sid in ids:
            scene = out / "scenes" / sid
            for res in "FHQ":
                link(scene, midd / f"training{res}" / sid)
            for name, src in (("im0.png", "im0.png"), ("im1.png", "im1.png"), ("im1E.png", "im1.png"),
                              ("im1L.png", "im1.png"), ("disp0.pfm", "disp0GT.pfm"), ("calib.txt", "calib.txt")):
                link(scene / src, root / "Middlebury" / "2014" / sid / name)
            if params.eth3d:
                for kind in ("two_view_training", "two_view_training_gt"):
                    link(out / "eth3d" / kind / sid, root / "ETH3D" / kind / sid)
            if params.kitti:
                for kind in ("image_2", "image_3", *KITTI_DISPARITY_DIRS):
                    f = out / "kitti" / "training" / kind / f"{sid}_10.png"
                    if f.exists():
                        link(f, root / "KITTI" / "training" / kind / f"{sid}_10.png")
    _make_symlinks(links)
    old = out / f".views-old-{uuid.uuid4().hex[:12]}"
    if views.exists():
        os.replace(views, old)
    os.replace(tmp, views)
    shutil.rmtree(old, ignore_errors=True)
    return views


def _make_symlinks(links: list[tuple[str, str]]) -> None:
    """Relative symlinks ``link -> target`` (absolute paths given), made folder by folder, each folder made once.
    In that order 4,080 links (240 scenes' split views) took 0.17 s on the project VM; made scene by scene, each link
    in another folder than the one before, they took 0.7-1.0 s of kernel time, while every other core was idle."""
    links = sorted(links, key=lambda ta: ta[1])
    made = set()
    for target, at in links:
        folder = os.path.dirname(at)
        if folder not in made:
            os.makedirs(folder, exist_ok=True)
            made.add(folder)
        os.symlink(os.path.relpath(target, folder), at)


def write_lists(out: Path, splits: dict[str, list[str]]) -> None:
    for split, ids in splits.items():
        lines = [f"scenes/{s}/im0.png scenes/{s}/im1.png scenes/{s}/disp0GT.pfm" for s in ids]
        atomic_write_text(out / "filenames" / f"{split}.txt", "\n".join(lines) + ("\n" if lines else ""))
        klines = [f"training/image_2/{s}_10.png training/image_3/{s}_10.png training/disp_occ_0/{s}_10.png" for s in ids]
        atomic_write_text(out / "filenames" / f"kitti_{split}.txt", "\n".join(klines) + ("\n" if klines else ""))


# ---- the stage --------------------------------------------------------------------------------
def build_dataset(session_dir: str | Path, calibration: str | Path, out_dir: str | Path,
                  params: BuildParams | None = None, workers: int | None = None, overwrite: bool = False,
                  strict: bool = False, scenes: list[str] | None = None, progress: bool = False,
                  scheduler: str | None = None) -> BuildSummary:
    """Build every scene of ``session_dir/scenes`` into ``out_dir``; see docs/dataset-format.md.
    ``scheduler``: a Dask scheduler address; its workers build the scenes (docs/cluster.md)."""

    t0 = time.perf_counter()
    prestart_pool(build_one_scene.__module__, workers, scheduler)  # (already started by the CLI)
    params = params or BuildParams()
    if not 0 <= params.split_train + params.split_val <= 1:
        raise InputError(None, "split", "train + val ratios <= 1", f"{params.split_train} + {params.split_val}")
    calib_path = Path(calibration)
    calib = CalibrationFile.read(calib_path)
    session = calib.open_session(session_dir)
    check_rig_matches_session(calib.rig, session, calib_path)
    calib_sha = sha256_file(calib_path)
    out = require_output_folder(out_dir, "--output")
    session.refuse_output_inside_captures(out)
    if params.crop_wh and (params.crop_wh[0] > session.zed.left.width_px
                           or params.crop_wh[1] > session.zed.left.height_px):
        raise InputError(None, "--crop", f"at most the ZED image size, {session.zed.left.width_px}x"
                         f"{session.zed.left.height_px} px", f"{params.crop_wh[0]}x{params.crop_wh[1]} px")
    dirs = session.select("scenes", scenes)
    if scheduler:
        from gtforge.infra.scheduling import check_scheduler_address

        check_scheduler_address(scheduler)  # before anything is written
    (out / "scenes").mkdir(parents=True, exist_ok=True)
    _remove_stale(out)
    phash = params.output_hash()
    todo, unchanged = [], []
    expected = scene_files(params)
    metas: dict[str, SceneMeta] = {}
    for d in dirs:
        meta_path = out / "scenes" / d.name / "meta.json"
        if not overwrite and meta_path.exists():
            try:
                m = SceneMeta.read(meta_path)
                files = [p for p in session.capture_files(d) if p.exists()]
                if _built_as_asked(m, meta_path.parent, phash, calib_sha, expected) and inputs_unchanged(m, files):
                    unchanged.append(d.name)
                    metas[d.name] = m
                    continue
            except InputError:
                pass
        todo.append(d)
    before = {d.name: _file_stamp(out / "scenes" / d.name / "meta.json") for d in todo}
    failures: dict[str, str] = {}
    built: list[str] = []
    recovered: list[str] = []  # landed by a worker that died before it reported them
    args = [(str(Path(session_dir).resolve()), str(d.absolute()), d.name, str(calib_path.resolve()), calib_sha,
             str(out.resolve()), params.model_dump_json()) for d in todo]
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    with Progress(TextColumn("build-dataset"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  disable=not (progress and args)) as bar:
        task = bar.add_task("scenes", total=len(args))

        def handle(result):
            sid, err, meta = result
            bar.advance(task)
            if err:
                failures[sid] = err
                log.error("scene %s failed: %s", sid, err)
                if strict:
                    raise InputError(None, f"scene {sid}", "a valid capture (--strict)", "an error", err)
            else:
                built.append(sid)
                metas[sid] = SceneMeta.model_validate(meta)

        def lost(a, reason):
            meta = _landed_meta(out, a[2], before[a[2]], phash, calib_sha, expected)
            if meta is None:
                return a[2], reason, None
            recovered.append(a[2])
            return a[2], None, meta.model_dump(mode="json")

        try:
            run_tasks(build_one_scene, args, handle, workers=workers, scheduler=scheduler, lost_result=lost)
        except (KeyboardInterrupt, Interrupted):
            _remove_stale(out)
            _write_manifest(out, session_dir, calib_path, calib_sha, params, metas, failures)
            raise Interrupted(f"interrupted: {len(built)} scene(s) built in this run and complete, "
                              f"{len(args) - len(built) - len(failures)} not built; rerun the same command to "
                              f"resume") from None
    # left by a worker process that died mid-scene (its scene was run again elsewhere); the locks after the views
    _remove_stale(out, locks=False)
    ok_ids = sorted(metas)
    fruit_ids = {s: metas[s].fruit_id for s in ok_ids}
    flagged = {s: metas[s].verification.reasons for s in ok_ids
               if metas[s].verification is not None and metas[s].verification.status == "flagged"}
    quarantined = sorted(flagged) if params.quarantine else []
    splits = final_splits(ok_ids, fruit_ids, params, quarantined)
    if params.verification:
        _write_verification(out, params, metas)
    for sid in unchanged:  # views of scenes built by an earlier run with other view options
        if (params.kitti and not (out / "kitti" / "training" / "disp_noc_0" / f"{sid}_10.png").exists()) or \
                (params.eth3d and not (out / "eth3d" / "two_view_training_gt" / sid / "mask0nocc.png").exists()):
            write_scene_views(out, sid, params)
    for sid in recovered:  # its worker died while writing them, or before: any of them may be missing
        write_scene_views(out, sid, params)
    write_lists(out, splits)
    write_split_views(out, splits, params)
    _write_manifest(out, session_dir, calib_path, calib_sha, params, metas, failures, splits, flagged, quarantined)
    from gtforge.reports.build import write_build_report

    write_build_report(Manifest.read(out / "manifest.json"), out)
    _remove_stale(out)  # the scenes' released locks (_unlock_writer)
    if flagged:
        log.warning("verification flagged %d scene(s)%s: %s (see %s)", len(flagged),
                    ", left out of the split lists (--quarantine)" if quarantined else "",
                    "; ".join(f"{k}: {v[0]}" + (f" (+{len(v) - 1} more)" if len(v) > 1 else "")
                              for k, v in list(flagged.items())[:5]) + (" ..." if len(flagged) > 5 else ""),
                    out / "verification.html")
    empty = [k for k, v in splits.items() if not v]
    if empty and ok_ids:
        log.warning("split(s) %s came out empty (%d scene(s), %d fruit): the list file(s) are empty; add scenes, "
                    "set fruit_ids in session.yaml, or change --split", ", ".join(empty), len(ok_ids),
                    len({fruit_ids[s] or s for s in ok_ids}))
    return BuildSummary(sorted(built), sorted(unchanged), failures, out, time.perf_counter() - t0, splits, flagged,
                        quarantined)


def final_splits(ok_ids: list[str], fruit_ids: dict[str, str | None], params: BuildParams,
                 quarantined: list[str]) -> dict[str, list[str]]:
    """The split lists: every built scene split by fruit, then quarantined scenes taken out (so a scene's split never
    depends on which other scenes were flagged)."""
    q = set(quarantined)
    return {k: [s for s in v if s not in q] for k, v in make_splits(ok_ids, fruit_ids, params).items()}


def _write_verification(out: Path, params: BuildParams, metas: dict[str, "SceneMeta"]) -> None:
    from gtforge.verify import VerificationReport, write_verification_report

    scenes = {s: m.verification for s, m in sorted(metas.items()) if m.verification is not None}
    for s, v in scenes.items():  # overlays of scenes no longer flagged
        if v.status != "flagged":
            (out / "verification" / f"{s}_overlay.jpg").unlink(missing_ok=True)
    write_verification_report(VerificationReport(dataset_dir=str(out.resolve()), params=params.verify, scenes=scenes),
                              out)


def _file_stamp(path: Path) -> tuple[int, int] | None:
    """``path``'s (inode, mtime in ns), None if it does not exist: tells a file written since from the one seen."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mtime_ns


def _landed_meta(out: Path, sid: str, stamp_before: tuple[int, int] | None, phash: str, calib_sha: str,
                 expected: list[str]) -> "SceneMeta | None":
    """The meta of scene ``sid`` if a worker of this run landed it whole (a new meta.json, for these parameters and
    this calibration, with every scene file) and then died before it reported it; else None."""
    meta_path = out / "scenes" / sid / "meta.json"
    if _file_stamp(meta_path) in (None, stamp_before):
        return None
    try:
        m = SceneMeta.read(meta_path)
    except InputError:
        return None
    return m if _built_as_asked(m, meta_path.parent, phash, calib_sha, expected) else None


def _built_as_asked(m: SceneMeta, scene_dir: Path, phash: str, calib_sha: str, expected: list[str]) -> bool:
    """Whether the scene in ``scene_dir`` (its meta ``m``) was built with these parameters and this calibration and
    still has every scene file (none deleted since)."""
    return m.params_hash == phash and m.calibration_sha256 == calib_sha and \
        all((scene_dir / name).is_file() for name in expected)


def _remove_stale(out: Path, locks: bool = True) -> None:
    """Temporary scene folders of a run that was killed or interrupted: never scenes, always removed.
    A replaced scene (``.old-<id>-<token>``) whose replacement never landed is put back. Folders whose writer
    still runs (its ``.lock-<id>-<token>`` is held: a Dask task cancelled by Ctrl-C, which runs to its end) are
    left alone: removing files under a live writer could let it rename a partial folder into place. ``locks``: also
    delete the lock files no writer holds (a finished scene's, ``_unlock_writer``)."""
    scenes = out / "scenes"
    for stale in scenes.glob(".tmp-*"):
        if not _writer_alive(scenes, stale.name):
            shutil.rmtree(stale, ignore_errors=True)
    for old in scenes.glob(".old-*"):
        if _writer_alive(scenes, old.name):
            continue
        sid = old.name[len(".old-"):].rsplit("-", 1)[0]
        if not (scenes / sid).exists():
            os.replace(old, scenes / sid)
        else:
            shutil.rmtree(old, ignore_errors=True)
    for lock in scenes.glob(".lock-*") if locks else ():
        if not _writer_alive(scenes, lock.name):
            lock.unlink(missing_ok=True)
    for stale in out.glob(".views-*"):  # a views/ tree being built or swapped when the run stopped
        shutil.rmtree(stale, ignore_errors=True)


def _lock_writer(scenes: Path, sid: str, token: str) -> int | None:
    """Take ``scenes/.lock-<sid>-<token>`` (flock; released by the kernel if this process dies)."""
    if fcntl is None:
        return None
    scenes.mkdir(parents=True, exist_ok=True)
    path = scenes / f".lock-{sid}-{token}"
    fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
    except OSError:  # a filesystem without locks: write unlocked, as without fcntl
        os.close(fd)
        path.unlink(missing_ok=True)
        return None
    return fd


def _unlock_writer(scenes: Path, sid: str, token: str, fd: int | None) -> None:
    """Release the lock. Its file stays until the run's end (``_remove_stale`` removes unheld locks): a file deleted
    per scene would make ext4 without a journal skip it, for a minute, each time it allocates an inode in that folder
    (``recently_deleted``): 1-2 % of a build's CPU, and up to 3 s while the split views' 4,080 links are made."""
    if fd is not None:
        os.close(fd)


def _writer_alive(scenes: Path, name: str) -> bool:
    """Whether the process writing hidden entry ``name`` (``.tmp-``/``.old-``/``.lock-<sid>-<token>``) holds its lock."""
    if fcntl is None:
        return False
    try:
        fd = os.open(scenes / (".lock-" + name.split("-", 1)[1]), os.O_RDWR)
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:  # a filesystem without locks: cannot tell, treat as stale (as without fcntl)
        return False
    finally:
        os.close(fd)
    return False


def _write_manifest(out: Path, session_dir, calib_path: Path, calib_sha: str, params: BuildParams,
                    metas: dict[str, SceneMeta], failures: dict[str, str], splits: dict | None = None,
                    flagged: dict | None = None, quarantined: list | None = None) -> None:
    Manifest(gtforge_version=gtforge.__version__, calibration_path=str(calib_path.resolve()), calibration_sha256=calib_sha,
             session_dir=str(Path(session_dir).resolve()), params=params, scenes={s: metas[s] for s in sorted(metas)},
             failures=failures, splits=splits or {}, flagged=flagged or {},
             quarantined=quarantined or []).write(out / "manifest.json")
