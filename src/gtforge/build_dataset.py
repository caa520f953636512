"""Stage 2: disparity ground truth aligned with the rectified ZED left image, written in formats
stereo training code reads without glue (docs/dataset-format.md). Parallel, resumable, atomic."""
from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import dataclass, field
from collections.abc import Collection
from pathlib import Path
from typing import TYPE_CHECKING

import numba
import numpy as np

from gtforge.core.ground_truth.regions import occlusion_mask, region_sigma_stats, sgra_weights
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.dataset.motion_compensation import (
    add_motion_sigma,
    fruit_motion_suspected,
    verify_and_compensate,
    write_compensated_list,
    write_motion_overlays,
)
from gtforge.dataset.layout import (
    KITTI_DISPARITY_DIRS,
    file_stamp,
    hash_inputs,
    landed_meta,
    plan_scenes,
    require_dataset_folder,
    scene_files,
)
from gtforge.dataset.scene_folder import remove_stale_entries, scene_writer
from gtforge.dataset.scene_verification import write_verification_overlay
from gtforge.dataset.views import (
    final_splits,
    moved_between_splits,
    moved_splits_warning,
    scene_views_current,
    write_lists,
    write_scene_views,
    write_split_views,
)
from gtforge.dataset.worker_cache import cached_calibration, cached_session, scene_heap_bytes
from gtforge.io.middlebury import middlebury_calib_text
from gtforge.records.dataset import BuildParams, Manifest, SceneMeta, SceneStats
from gtforge.reports.build import write_sigma_thumbnail

try:
    import fcntl  # scene writer locks (POSIX); without it stale folders are removed unconditionally
except ImportError:  # pragma: no cover
    fcntl = None

import gtforge
from gtforge.core.geometry import finite_box, mask_bounding_box
from gtforge.core.ground_truth.reproject import prepare_rays, right_view_disparity
from gtforge.core.zed.scale_corrections import add_depth_pose_sigma, add_scale_sigma
from gtforge.core.ground_truth.uncertainty import disparity_sigma
from gtforge.dataset.scene_verification import verify_scene, zed_rows_used
from gtforge.errors import InputError, Interrupted, first_of
from gtforge.infra.atomic import atomic_copy_file, atomic_write_buffer, atomic_write_text, private_folder
from gtforge.infra.digest import sha256_file
from gtforge.infra.scheduling import (
    SchedulerLost,
    check_scheduler_address,
    prestart_pool,
    release_written_pages,
    run_tasks,
)
from gtforge.infra.unbuffered import background_writes
from gtforge.io.calibrated_session import check_rig_matches_session, open_with_calibration
from gtforge.io.formats import (
    KITTI_MAX_DISPARITY_PX,
    write_image,
    write_label_png,
    write_pfm,
    write_ply,
    write_tiff_float,
)
from gtforge.io.outputs import new_folders, remove_if_empty, require_output_folder
from gtforge.records.calibration import CalibrationFile
from gtforge.records.verification import SceneVerification, VerificationResult, VerifyParams
from gtforge.reports.build import write_build_report
from gtforge.reports.verification import write_verification_report

if TYPE_CHECKING:
    pass

log = logging.getLogger("gtforge.build_dataset")


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
    compensated: list[str] = field(default_factory=list)  # fruit motion compensated (issue 37)

    @property
    def ok(self) -> bool:
        return not self.failures


# ---- regions --------------------------------------------------------------------------------


@numba.njit(cache=True)
def _key_float(k):
    """The float32 whose bits ``b`` give the int32 ``k = b ^ ((b >> 31) & 0x7FFFFFFF)``, ordered as the floats are
    (-0.0 just below +0.0)."""
    return np.asarray(k ^ ((k >> np.int32(31)) & np.int32(0x7FFFFFFF)), np.int32).reshape(1).view(np.float32)[0]


@numba.njit(cache=True)
def _disparity_summary(disp, over_px):
    """(number of finite values, their min, their max, how many exceed ``over_px``) in one pass (numpy needs a
    boolean selection, which copies the values, and three reductions over the copy). ``disp``: float32. The min and max
    as integer reductions over the values' bits in float order (vectorised; a float min or max is a serial chain);
    where one of them is zero (-0.0 and +0.0 are equal floats but different keys) they are taken again as floats."""
    if disp.itemsize != 4:  # the bits are read as int32
        raise ValueError("_disparity_summary needs a float32 disparity map")
    n, n_over = 0, 0
    big, small = np.int32(2147483647), np.int32(-2147483648)
    kmin, kmax = big, small
    y0, y1, x0, x1 = finite_box(disp)  # none outside it
    for v in range(y0, y1):
        row = disp[v, x0:x1]
        bits = row.view(np.int32)
        c, c_over, rmin, rmax = 0, 0, big, small
        for u in range(x1 - x0):
            d = row[u]
            f = abs(d) < np.inf  # finite (NaN compares false)
            c += f
            c_over += f & (d > over_px)
            b = bits[u]
            key = b ^ ((b >> np.int32(31)) & np.int32(0x7FFFFFFF))  # (see _key_float)
            rmin = min(rmin, key if f else big)
            rmax = max(rmax, key if f else small)
        n += c
        n_over += c_over
        kmin, kmax = min(kmin, rmin), max(kmax, rmax)
    if n == 0:
        return n, np.inf, -np.inf, n_over
    lo, hi = np.float64(_key_float(kmin)), np.float64(_key_float(kmax))
    if lo == 0.0 or hi == 0.0:  # which zero: the first in raster order, as a float min or max gives
        lo, hi = np.inf, -np.inf
        for v in range(y0, y1):
            row = disp[v, x0:x1]
            for u in range(x1 - x0):
                d = row[u]
                if abs(d) < np.inf:
                    lo = min(lo, d)
                    hi = max(hi, d)
    return n, lo, hi, n_over


# ---- one scene ------------------------------------------------------------------------------


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


# What a scene's files are made with beyond its parameters: the ZED right image of a calibration that corrects the
# right camera is resampled once, by cubic B-spline at the exact positions (round 3; before, OpenCV's warp and a
# second resampling for the yaw). Such scenes are rebuilt on resume; the others' files are the same as before.
RIGHT_IMAGE_RESAMPLING = "one exact cubic B-spline resampling (round 3)"


def motion_matters(verification: SceneVerification | None, verify_params: VerifyParams) -> bool:
    """Whether a scene's files depend on the motion compensation's parameters: its verification suspected that its
    fruit moved (compensation was tried, or would be: ``fruit_motion_suspected``). Every other scene's files are the
    same with compensation on, off, or other limits, so changing those does not rebuild it."""
    return verification is not None and (verification.motion_compensation is not None
                                         or fruit_motion_suspected(verification, verify_params))


def scene_params_hash(params: BuildParams, calib, with_motion: bool = True) -> str:
    """The hash a scene's meta.json records and a resumed build compares (``BuildParams.output_hash``, with
    ``RIGHT_IMAGE_RESAMPLING`` where the calibration corrects the right camera); ``with_motion``: ``motion_matters``
    for the scene."""
    h = params.output_hash(with_motion)
    if calib.zed_right_correction is not None or calib.rig.zed_right_yaw_deg != 0.0:
        h = hashlib.sha256((h + RIGHT_IMAGE_RESAMPLING).encode()).hexdigest()[:16]
    return h


def build_one_scene(session_dir: str, capture_dir: str, sid: str, calib_path: str, calib_sha: str, out_dir: str,
                    params_json: str) -> tuple[str, str | None, dict | None]:
    """Worker: build capture ``capture_dir`` into ``scenes/<sid>/`` atomically.
    Returns (sid, error or None, meta dict)."""
    t0 = time.perf_counter()
    params = BuildParams.model_validate_json(params_json)
    cap_dir = Path(capture_dir)
    try:
        calib = cached_calibration(calib_path, calib_sha)
        session = cached_session(session_dir, calib)
        rig = calib.rig  # checked against the session by build_dataset before any worker starts
        # image content is needed by verification, a crop (re-encoded im0/im1) and the PLY's colours only; for
        # verification alone the images are decoded once the ground truth says how many ZED rows the checks read.
        # A right image the session corrects (self-rectification, calibrate-scale's yaw: one resampling, in the
        # session) is decoded whole and written re-encoded as im1
        cap = session.load_capture(cap_dir, decode_images=bool(params.crop_wh) or params.ply)
        t_read = time.perf_counter()
        sd, region, fruit = build_scene_arrays(cap.depth_mm, rig, params, cap.fruit_mask)
        decode_s = 0.0
        if params.verification:
            t = time.perf_counter()
            texture, zed_left, zed_right = session.decoded_images(cap, zed_rows_used(sd.depth_mm, params.verify))
            decode_s = time.perf_counter() - t
        checked = None
        if params.verification and params.motion.compensate:  # verified before the writes: a scene whose fruit moved
            # is rebuilt with the fruit moved when that passes verification (issue 37)
            checked = verify_and_compensate(cap.depth_mm, rig, params, sd, region, fruit, zed_left, zed_right, texture,
                                            cap.fruit_mask, lambda: session.decoded_images(cap))
            sd, region, fruit = checked.sd, checked.region, checked.fruit
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
    write_s = 0.0
    # the scene's folder lands whole when the block ends (no temporary file per file). The files that do not depend on
    # the verification are written first: the large ones go from this process's writer thread while the verification
    # runs; all of them are complete when the inner context exits
    with scene_writer(scenes, sid) as tmp:
        with private_folder(tmp), background_writes():
            t = time.perf_counter()
            for name, img, src in (("im0.png", left, cap.zed_left_file),
                                   ("im1.png", right, cap.zed_right_file)):
                if src is not None and crop is None:  # the input is already this RGB PNG: no re-encode
                    if src.name in cap.read_buffers:  # its bytes as decoded for verification: not read again
                        atomic_write_buffer(tmp / name, cap.read_buffers[src.name])
                    else:
                        atomic_copy_file(src, tmp / name)
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
            atomic_write_text(tmp / "calib.txt", middlebury_calib_text(rig.zed, disp.shape[1], disp.shape[0],
                                                                      disp_range, cx_shift, cy_shift))
            if params.ply:
                v, u = np.nonzero(np.isfinite(disp))
                K = rig.zed.left
                z = depth[v, u].astype(np.float64)
                pts = K.unproject(np.stack([u + cx_shift, v + cy_shift], axis=1), z)  # the uncropped image's pixels
                write_ply(tmp / "cloud.ply", pts, left[v, u] / 255.0)
            write_s += time.perf_counter() - t
            verification = None
            if params.verification:  # on the whole (uncropped) images
                verification, rendered = (checked.verification, checked.rendered) if checked is not None else \
                    verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region_uncropped, zed_left, zed_right,
                                 texture, rig, params.verify)
                if (verification.status == "flagged" or verification.compensated) and rendered is not None:
                    if zed_left.shape[0] < sd.depth_mm.shape[0]:  # the overlay shows the whole image
                        zed_left = session.decoded_images(cap)[1]
                    if verification.compensated:  # before/after
                        write_motion_overlays(Path(out_dir) / "verification", sid, zed_left, checked)
                    else:
                        write_verification_overlay(Path(out_dir) / "verification" / f"{sid}_overlay.jpg", zed_left,
                                                   rendered)
            sigma = None
            if params.sigma:
                shift = verification.texture_all.magnitude_px if verification is not None else None
                sigma = disparity_sigma(sd.disparity_px, sd.depth_mm, rig, calib.cov_extrinsic_rad_mm,
                                        params.uncertainty, sd.span_mm, shift)
                if calib.depth_alignment is not None:  # the depth camera's rotation's uncertainty (align-depth)
                    sigma = add_depth_pose_sigma(sigma, sd.depth_mm, rig,
                                                 calib.depth_alignment.result.covariance_rad_mm)
                if calib.scale_calibration is not None:  # the scale terms' uncertainty (calibrate-scale)

                    sigma = add_scale_sigma(sigma, sd.depth_mm, rig, calib.scale_calibration)
                if checked is not None and checked.motion_sigma_px is not None:  # the fruit's motion (issue 37)
                    sigma = add_motion_sigma(sigma, checked.motion_sigma_px)
                sigma = sigma[sl]
                t = time.perf_counter()
                write_pfm(tmp / "disp0GT_sigma.pfm", sigma)
                write_sigma_thumbnail(Path(out_dir) / "report" / f"{sid}_sigma.jpg", sigma)
                write_s += time.perf_counter() - t
            inputs, stamps = hash_inputs([p for p in cap.input_files if p.exists()], cap.read_records)
            meta = SceneMeta(scene=sid, fruit_id=cap.fruit_id, gtforge_version=gtforge.__version__,
                             calibration_sha256=calib_sha,
                             params_hash=scene_params_hash(params, calib, motion_matters(verification, params.verify)),
                             input_blake3=inputs, input_stamps=stamps, stats=stats, crop_xywh=crop,
                             fruit_mask_source="user" if cap.fruit_mask is not None else "geometry",
                             verification=verification,
                             sigma=None if sigma is None else region_sigma_stats(sigma, region),
                             sigma_extrinsic_included=sigma is not None and calib.cov_extrinsic_rad_mm is not None)
            t_end = time.perf_counter()
            meta.time_s, meta.time_read_s = t_end - t0, t_read - t0 + decode_s  # (the images decoded for verification)
            meta.time_compute_s, meta.time_write_s = t_end - t_read - decode_s - write_s, write_s
            meta.write(tmp / "meta.json")
    with background_writes():
        write_scene_views(Path(out_dir), sid, params, disp, noc, disp1, noc1)
    kitti = Path(out_dir) / "kitti" / "training"
    release_written_pages([*(scenes / sid).iterdir(), *(kitti / d / f"{sid}_10.png" for d in KITTI_DISPARITY_DIRS)])
    return sid, None, meta.model_dump(mode="json")


def warm_worker(session_dir: str, calib_path: str) -> None:
    """What every build worker computes for its first scene before the scene's own work, done once in the local pool's
    fork server (``prestart_pool(..., warm_up=...)``), whose workers inherit it: the calibration, the session opened
    with it and the depth camera's ray grid (about 0.7 CPU s a worker at full resolution, most of it the ray grid;
    benchmarks/RESULTS.md, "Round 4 (issue 39)"). ``session_dir``, ``calib_path``: resolved, as ``build_dataset``
    passes them to ``build_one_scene`` (the worker's cache is keyed by them, and by the calibration's hash)."""
    calib = cached_calibration(calib_path, sha256_file(calib_path))
    cached_session(session_dir, calib)
    prepare_rays(calib.rig.depth_camera)


def _warm_up_args(session_dir, calibration) -> tuple[str, tuple[str, str]]:
    """``prestart_pool``'s ``warm_up`` for a build of ``session_dir`` with ``calibration``."""
    return "warm_worker", (str(Path(session_dir).resolve()), str(Path(calibration).resolve()))


# ---- splits and views -------------------------------------------------------------------------


# ---- the stage --------------------------------------------------------------------------------
def build_dataset(session_dir: str | Path, calibration: str | Path, out_dir: str | Path,
                  params: BuildParams | None = None, *, workers: int | None = None, overwrite: bool = False,
                  strict: bool = False, scenes: list[str] | None = None, progress: bool = False,
                  scheduler: str | None = None, rebuild: Collection[str] = ()) -> BuildSummary:
    """Build every scene of ``session_dir/scenes`` into ``out_dir``; see docs/dataset-format.md.
    ``scheduler``: a Dask scheduler address; its workers build the scenes (docs/cluster.md). ``progress``: a bar on
    standard error while the scenes are built, where that is an interactive terminal. ``rebuild``: scene ids
    built again even where their folder looks up to date (``gtforge run``: files changed since it recorded them).

    The recipe: check the inputs; plan (``plan_scenes``: which scenes are up to date); build and land each of the
    others (``build_one_scene`` on the pool: compute, write into a temporary folder, rename it into place); finish
    (``finish_dataset``: verification report, views, splits, manifest, build report)."""

    t0 = time.perf_counter()
    prestart_pool(build_one_scene.__module__, workers, scheduler,  # (already started by the CLI)
                  warm_up=_warm_up_args(session_dir, calibration))
    params = params or BuildParams()
    if not (0 <= params.split_train <= 1 and 0 <= params.split_val <= 1
            and params.split_train + params.split_val <= 1):  # (NaN fails every comparison: refused too)
        raise InputError(None, "--split", "train and val ratios in [0, 1], train + val <= 1",
                         f"{params.split_train} + {params.split_val}",
                         "test gets the rest (1 - train - val): e.g. --split 0.8,0.1")
    calib_path = Path(calibration)
    calib = CalibrationFile.read(calib_path)
    session = open_with_calibration(session_dir, calib)
    check_rig_matches_session(calib.rig, session, calib_path)
    calib_sha = sha256_file(calib_path)
    out = require_output_folder(out_dir, "--output")
    session.refuse_output_over_inputs(out)
    require_dataset_folder(out, session, overwrite)
    if params.crop_wh and (params.crop_wh[0] > session.zed.left.width_px
                           or params.crop_wh[1] > session.zed.left.height_px):
        size = f"{session.zed.left.width_px}x{session.zed.left.height_px}"
        raise InputError(None, "--crop", f"at most the ZED image size, {size} px",
                         f"{params.crop_wh[0]}x{params.crop_wh[1]} px",
                         f"give --crop WxH within {size}, or build without --crop (--crop kitti is 1242x375)")
    most = min(session.zed.left.width_px, session.zed.left.height_px) // 2  # (more erodes every fruit away)
    if params.erosion_px > most:  # (--erosion-px 100000: a 40 GB kernel, OpenCV's out-of-memory traceback)
        raise InputError(None, "--erosion-px", f"at most half the ZED image's shorter side, {most} px",
                         f"{params.erosion_px} px", "leave --erosion-px out for its default (15 px at full size)")
    dirs = session.select("scenes", scenes)
    in_session = [d.name for d in session.capture_dirs("scenes")]  # (every scene, whatever --scenes chose)
    _warn_of_fruit_ids(session, in_session)
    if scheduler:
        check_scheduler_address(scheduler)  # before anything is written
    made = new_folders(out / "scenes", out)
    (out / "scenes").mkdir(parents=True, exist_ok=True)
    remove_stale_entries(out)
    expected = scene_files(params)

    def phash(m: SceneMeta) -> str:  # the hash a scene built as asked records (its own verification decides)
        return scene_params_hash(params, calib, motion_matters(m.verification, params.verify))

    todo, unchanged, metas = plan_scenes(session, dirs, out, phash, calib_sha, expected, overwrite,
                                         rebuild)
    for sid in unchanged:  # session.yaml's fruit_ids edited since: the splits follow them, not the scene's build
        fruit_id = session.config.fruit_ids.get(sid)
        if metas[sid].fruit_id != fruit_id:
            metas[sid] = metas[sid].model_copy(update={"fruit_id": fruit_id})
            metas[sid].write(out / "scenes" / sid / "meta.json")
    before = {d.name: file_stamp(out / "scenes" / d.name / "meta.json") for d in todo}
    failures: dict[str, str] = {}
    built: list[str] = []
    recovered: list[str] = []  # landed by a worker that died before it reported them
    args = [(str(Path(session_dir).resolve()), str(d.absolute()), d.name, str(calib_path.resolve()), calib_sha,
             str(out.resolve()), params.model_dump_json()) for d in todo]
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    # on stderr, as every stage's progress: standard output holds the results only (a pipe, a log)
    bar_console = Console(stderr=True)
    with Progress(TextColumn("build-dataset"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                  console=bar_console, disable=not (progress and args and bar_console.is_terminal)) as bar:
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
            meta = landed_meta(out, a[2], before[a[2]], phash, calib_sha, expected)
            if meta is None:
                return a[2], reason, None
            recovered.append(a[2])
            return a[2], None, meta.model_dump(mode="json")

        try:
            run_tasks(build_one_scene, args, handle, workers=workers, scheduler=scheduler, lost_result=lost,
                      heap_bytes=scene_heap_bytes(session.zed.left))
        except (SchedulerLost, KeyboardInterrupt, Interrupted) as exc:  # Ctrl-C, the scheduler gone: keep what is whole
            for a in args:  # scenes a worker finished whose result had not reached this process: complete all the same
                if a[2] not in metas and a[2] not in failures:
                    meta = landed_meta(out, a[2], before[a[2]], phash, calib_sha, expected)
                    if meta is not None:
                        built.append(a[2])
                        metas[a[2]] = meta
            remove_stale_entries(out)
            _write_manifest(out, session_dir, calib_path, calib_sha, params, metas, failures)
            detail = (f"{len(built)} scene(s) built in this run and complete, "
                      f"{len(args) - len(built) - len(failures)} not built")
            if isinstance(exc, SchedulerLost):
                raise SchedulerLost(exc.address, exc.cause, detail) from None
            raise Interrupted(f"interrupted: {detail}; rerun the same command to resume", detail) from None
        except InputError:  # the cluster could not be reached
            remove_if_empty(made)
            raise
    splits, flagged, quarantined = finish_dataset(out, session_dir, calib_path, calib_sha, params, metas, failures,
                                                  unchanged, recovered)
    ok_ids = sorted(metas)
    fruit_ids = {s: metas[s].fruit_id for s in ok_ids}
    _warn_of_kitti_range(metas, params)
    _warn_of_openstereo_right_paths(out, ok_ids, params)
    _warn_of_scenes_left_from_the_session(out, in_session)
    if flagged:
        log.warning("verification flagged %d scene(s)%s: %s (see %s)", len(flagged),
                    ", left out of the split lists (--quarantine)" if quarantined else "",
                    first_of((f"{k}: {v[0]}" + (f" (+{len(v) - 1} more)" if len(v) > 1 else "")
                              for k, v in flagged.items()), 5, "; "),
                    out / "verification.html")
    empty = [k for k, v in splits.items() if not v]
    if empty and ok_ids:
        n_fruit = len({fruit_ids[s] or s for s in ok_ids})
        log.warning("split(s) %s came out empty (%d scene(s), %d fruit): normal for a small session, the dataset is "
                    "complete; each fruit (all its scenes) lands in a split by a draw from its id, so the --split "
                    "shares hold over many fruit, not over %d; for a %s split capture more fruit (or set fruit_ids "
                    "in session.yaml, or change --split or --seed)%s", ", ".join(empty), len(ok_ids), n_fruit, n_fruit,
                    " and ".join(empty), "; --split 1,0 puts every scene in train" if "train" in empty else "")
    return BuildSummary(sorted(built), sorted(unchanged), failures, out, time.perf_counter() - t0, splits, flagged,
                        quarantined, [s for s in ok_ids if metas[s].verification is not None
                                      and metas[s].verification.compensated])


def _warn_of_fruit_ids(session, ids: list[str]) -> None:
    """``fruit_ids`` keys that name none of the session's scenes ``ids`` (a typo: ``'01'`` for ``'001'``) and, where it
    groups some scenes, the scenes it leaves out: each such scene is a fruit of its own in the splits, so a fruit can
    land in two."""
    fids = session.config.fruit_ids
    if not fids:
        return
    unknown = sorted(set(fids) - set(ids))
    left = [s for s in ids if s not in fids]
    where = session.root / "session.yaml"
    if unknown:
        log.warning("%s: fruit_ids names %s, which %s no scene (the scenes: %s): ignored; if it is a typo, its scene "
                    "is a fruit of its own and may land in another split than the rest of that fruit", where,
                    first_of(unknown), "is" if len(unknown) == 1 else "are", first_of(ids))
    if left:
        log.warning("%s: fruit_ids names no fruit for %d scene(s): %s: each is a fruit of its own in the splits", where,
                    len(left), first_of(left))


def _warn_of_kitti_range(metas: dict[str, SceneMeta], params: BuildParams) -> None:
    """Scenes whose ground truth reaches KITTI_MAX_DISPARITY_PX: the KITTI PNGs hold those pixels as invalid."""
    if not params.kitti:
        return
    over = {s: m.stats.disp_max_px for s, m in sorted(metas.items())
            if m.stats.disp_max_px is not None and m.stats.disp_max_px >= KITTI_MAX_DISPARITY_PX}
    if over:
        log.warning("%d scene(s) hold disparities beyond the %.3f px a KITTI 16-bit PNG can store (%s): kitti/ marks "
                    "those pixels invalid (0); the PFM ground truth (scenes/, eth3d/, views/) keeps them", len(over),
                    KITTI_MAX_DISPARITY_PX, first_of(f"{s} up to {d:.1f} px" for s, d in over.items()))


def _warn_of_openstereo_right_paths(out: Path, ids: list[str], params: BuildParams) -> None:
    """OpenStereo's KITTI reader (``RETURN_RIGHT_DISP``) finds a scene's right-view file by replacing every ``c_0`` in
    its left one's path with ``c_1`` (meant for ``disp_occ_0``): a scene id, or the dataset's path, that holds ``c_0``
    sends it to another scene's file (``sc_001`` -> ``sc_101``), or to none."""
    if not (params.kitti and params.right_gt):
        return
    hit = [s for s in ids if "c_0" in s]
    where = str(out.resolve())
    if hit or "c_0" in where:
        log.warning("OpenStereo's KITTI reader with RETURN_RIGHT_DISP replaces every 'c_0' in a path with 'c_1' to "
                    "find the right view's ground truth: %s 'c_0', so it would read another scene's file or none; %s "
                    "(the other readers are not affected)",
                    f"scene id(s) {first_of(hit)} hold" if hit else f"the dataset's path {where} holds",
                    "rename those capture folders in the session" if hit else "train from a path without 'c_0'")


def _warn_of_scenes_left_from_the_session(out: Path, in_session: list[str]) -> None:
    """Scene folders in ``out`` whose capture the session no longer holds (``in_session``: its scene ids; deleted or
    renamed since they were built): outside the manifest and the split lists, yet in scenes/, kitti/ and eth3d/, which
    some training code lists itself."""
    known = set(in_session)
    gone = sorted(d.name for d in (out / "scenes").iterdir()
                  if d.is_dir() and not d.name.startswith(".") and d.name not in known)
    if gone:
        log.warning("%d scene(s) in %s are no longer in the session (%s): left out of the manifest and the split "
                    "lists, but their files stay in scenes/, kitti/ and eth3d/, where training code that lists those "
                    "folders finds them; delete them there, or build into a new folder", len(gone), out / "scenes",
                    first_of(gone))


def finish_dataset(out: Path, session_dir, calib_path: Path, calib_sha: str, params: BuildParams,
                   metas: dict[str, SceneMeta], failures: dict[str, str], unchanged: list[str], recovered: list[str]
                   ) -> tuple[dict[str, list[str]], dict[str, list[str]], list[str]]:
    """After the scenes: verification.json/.html, the views a scene may lack, the split lists and views, the manifest
    and the build report; stale entries removed. Returns ``(splits, flagged, quarantined)``."""
    # left by a worker process that died mid-scene (its scene was run again elsewhere); the locks after the views
    remove_stale_entries(out, locks=False)
    ok_ids = sorted(metas)
    fruit_ids = {s: metas[s].fruit_id for s in ok_ids}
    flagged = {s: metas[s].verification.reasons for s in ok_ids
               if metas[s].verification is not None and metas[s].verification.status == "flagged"}
    quarantined = sorted(flagged) if params.quarantine else []
    compensated = [s for s in ok_ids if metas[s].verification is not None and metas[s].verification.compensated]
    splits = final_splits(ok_ids, fruit_ids, params, quarantined)
    try:
        before = Manifest.read(out / "manifest.json").splits if (out / "manifest.json").is_file() else {}
    except InputError:  # an older schema: nothing to compare with
        before = {}
    moved = moved_between_splits(before, splits)
    if moved:  # a model trained on the earlier train split has seen a scene now in val or test
        log.warning("%s", moved_splits_warning(moved))
    if params.verification:
        _write_verification(out, params, metas)
    for sid in unchanged:  # views of scenes built by an earlier run with other view options, deleted since, or of an
        # earlier build of the scene (a run stopped between a scene's landing and its views)
        if not scene_views_current(out, sid, params):
            write_scene_views(out, sid, params)
    for sid in recovered:  # its worker died while writing them, or before: any of them may be missing
        write_scene_views(out, sid, params)
    write_lists(out, splits)
    write_compensated_list(out, compensated)
    write_split_views(out, splits, params)
    _write_manifest(out, session_dir, calib_path, calib_sha, params, metas, failures, splits, flagged, quarantined,
                    compensated)
    write_build_report(Manifest.read(out / "manifest.json"), out)
    remove_stale_entries(out)  # the scenes' released locks (unlock_writer)
    return splits, flagged, quarantined


def _write_verification(out: Path, params: BuildParams, metas: dict[str, "SceneMeta"]) -> None:
    scenes = {s: m.verification for s, m in sorted(metas.items()) if m.verification is not None}
    write_verification_report(VerificationResult(dataset_dir=str(out.resolve()), params=params.verify, scenes=scenes),
                              out)


def _write_manifest(out: Path, session_dir, calib_path: Path, calib_sha: str, params: BuildParams,
                    metas: dict[str, SceneMeta], failures: dict[str, str], splits: dict | None = None,
                    flagged: dict | None = None, quarantined: list | None = None,
                    compensated: list | None = None) -> None:
    Manifest(gtforge_version=gtforge.__version__, calibration_path=str(calib_path.resolve()),
             calibration_sha256=calib_sha, session_dir=str(Path(session_dir).resolve()), params=params,
             scenes={s: metas[s] for s in sorted(metas)}, failures=failures, splits=splits or {}, flagged=flagged or {},
             quarantined=quarantined or [], compensated=compensated or []).write(out / "manifest.json")
