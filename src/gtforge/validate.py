"""Stage 3: prove the ground truth is aligned, on board captures.

XY: board corners detected in the structured-light texture, lifted to 3D with a local plane fit of
the depth around each corner, mapped with ``T_zed_from_mech`` into the ZED-left image and compared
with the corners detected there (px). Z: the board's ZED-left depth built exactly as build-dataset
does, read at the detected ZED corners, back-projected; corner-pair distances against the true
board geometry (%).
"""
from __future__ import annotations

import itertools
import logging
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from gtforge.core.targets.board import BoardSpec, check_board_spec, detect_corners, solve_pnp
from gtforge.core.camera import PinholeCamera, Rig
from gtforge.core.measure.gauges import (
    GAUGES_DIR,
    GAUGES_FILE,
    ORDER,
    GaugeLimits,
    GaugeParams,
    GaugeResult,
    GaugeSpec,
    GaugesResult,
    disparity_points,
    gauge_components,
    gauge_status,
    measure_raw_depth,
    measure_source,
    read_gauges_file,
)
from gtforge.core.geometry import fit_plane, fit_plane_robust, invert_T, transform_points
from gtforge.core.zed.rectification import RectificationMeter
from gtforge.core.ground_truth.reproject import ReprojectParams, project_depth_to_camera
from gtforge.core.targets.detection import captures_detected_ahead, matched_points
from gtforge.core.targets.models import check_board_model, neighbour_pairs
from gtforge.core.ground_truth.uncertainty import UncertaintyParams, disparity_sigma
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.errors import InputError
from gtforge.io.calibrated_session import check_rig_matches_session, open_with_calibration
from gtforge.io.captures import leave_out_hint, missing_capture_file, open_session
from gtforge.io.outputs import refuse_gtforge_folder, require_output_folder
from gtforge.io.zed_rectification import rectified_by
from gtforge.records.calibration import CalibrationFile
from gtforge.records.dataset import BuildParams
from gtforge.records.validation import PoseValidation, ValidateParams, ValidationResult
from gtforge.reports.gauges import write_gauges_html
from gtforge.reports.validation import write_validation_report

log = logging.getLogger("gtforge.validate")


def corners_3d_from_depth(corners_uv: np.ndarray, depth_mm: np.ndarray, cam: PinholeCamera,
                          radius_px: int = 8, depth_cam: PinholeCamera | None = None,
                          T_cam_from_depth: np.ndarray | None = None,
                          approx_cam: np.ndarray | None = None) -> np.ndarray:
    """Sub-pixel, NaN-tolerant 3-D corners measured by the depth camera: a plane through the depth patch around
    each corner, intersected with the corner's ray in ``cam``. ``(N, 3)`` mm in ``cam``'s frame (NaN where the patch
    is empty). With a separate depth camera (``depth_cam``, ``T_cam_from_depth``) the patch is found by mapping
    ``approx_cam`` (``(N, 3)`` approximate corners in ``cam``'s frame, e.g. from PnP) into the depth image."""
    depth_cam = depth_cam or cam
    same_camera = depth_cam is cam and T_cam_from_depth is None
    T_cam_from_depth = np.eye(4) if T_cam_from_depth is None else np.asarray(T_cam_from_depth, float)
    if same_camera:
        centres = np.asarray(corners_uv, float)
    else:
        centres = depth_cam.project(transform_points(invert_T(T_cam_from_depth), approx_cam))
    rays = depth_cam.ray_grid()
    H, W = depth_mm.shape
    xy = cam.undistort_to_normalized(corners_uv)
    out = np.full((len(corners_uv), 3), np.nan)
    for k, (u, v) in enumerate(centres):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        u0, u1 = max(int(round(u)) - radius_px, 0), min(int(round(u)) + radius_px + 1, W)
        v0, v1 = max(int(round(v)) - radius_px, 0), min(int(round(v)) + radius_px + 1, H)
        if u0 >= u1 or v0 >= v1:
            continue
        z = depth_mm[v0:v1, u0:u1].astype(np.float64)
        ok = np.isfinite(z)
        if ok.sum() < 6:
            continue
        r = rays[v0:v1, u0:u1][ok]
        pts = transform_points(T_cam_from_depth, np.stack([r[:, 0] * z[ok], r[:, 1] * z[ok], z[ok]], axis=1))
        n, c, _ = fit_plane_robust(pts, threshold_mm=1.0, iterations=30)
        d = np.array([xy[k, 0], xy[k, 1], 1.0])
        out[k] = d * (c / (d @ n))
    return out


def bilinear_valid(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear interpolation over the valid (finite) neighbours only; NaN where none is valid."""
    H, W = img.shape
    u, v = uv[:, 0], uv[:, 1]
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - u0, v - v0
    num = np.zeros(len(uv))
    den = np.zeros(len(uv))
    for du, dv, w in ((0, 0, (1 - fu) * (1 - fv)), (1, 0, fu * (1 - fv)), (0, 1, (1 - fu) * fv), (1, 1, fu * fv)):
        uu, vv = np.clip(u0 + du, 0, W - 1), np.clip(v0 + dv, 0, H - 1)
        val = img[vv, uu].astype(np.float64)
        ok = np.isfinite(val)
        num += np.where(ok, w * np.nan_to_num(val), 0)
        den += np.where(ok, w, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 1e-9, num / den, np.nan)


def _check_board(board_model) -> None:
    """The declaration's own checks: the checkerboard's as before, the other targets' (gtforge.core.targets.models)."""
    if board_model.kind == "checkerboard":
        check_board_spec(board_model.spec())
    else:
        check_board_model(board_model)


def validate_pose(name: str, texture, depth_mech_mm, zed_left, rig: Rig, board: BoardSpec, params: ValidateParams,
                  used_for_calibration: bool) -> tuple[PoseValidation | None, np.ndarray | None, str | None]:
    ids = None  # ChArUco / circle grids (gtforge.core.targets.models): the ids both cameras saw
    if getattr(board, "kind", "checkerboard") != "checkerboard":
        got = matched_points(name, texture, zed_left, rig.mech, rig.zed.left, board)
        if isinstance(got, str):
            return None, None, got
        dm, dz, ids = got
    else:
        dm = detect_corners(texture, board)
        dz = detect_corners(zed_left, board)
    if dm is None or dz is None:
        return None, None, "board not found in the " + ("structured-light" if dm is None else "ZED") + " image"
    X = board.corners_board() if ids is None else board.corners_board()[ids]
    # per-pose board models fitted to all detected corners: PnP (with the lens model) in the texture camera,
    # a homography in the rectified ZED (exact for a planar board); their residuals are the detectors' noise
    T_mech_from_board = solve_pnp(X, dm.corners_uv, rig.mech)
    uv_mech_fit = rig.mech.project(transform_points(T_mech_from_board, X))
    Hb, _ = cv2.findHomography(X[:, :2], dz.corners_uv, 0)
    uv_fit = cv2.perspectiveTransform(X[:, :2].reshape(-1, 1, 2), Hb).reshape(-1, 2)
    N = len(X)
    rms_m = float(np.sqrt(np.sum((dm.corners_uv - uv_mech_fit) ** 2) / max(2 * N - 6, 1)))  # per axis, dof-corrected
    rms_z = float(np.sqrt(np.sum((dz.corners_uv - uv_fit) ** 2) / max(2 * N - 8, 1)))
    approx = transform_points(T_mech_from_board, X)

    # XY: texture-camera corners lifted to 3-D by the depth camera, mapped into the ZED-left image
    def lift_mech(uv):
        return corners_3d_from_depth(uv, depth_mech_mm, rig.mech, params.corner_radius_px, rig.depth_cam,
                                     rig.T_mech_from_depth_or_identity if rig.separate_depth_camera else None, approx)

    P_mech = lift_mech(dm.corners_uv)
    ok = np.all(np.isfinite(P_mech), axis=1)
    if ok.sum() < 4:
        return None, None, "no depth around the board corners"
    p_proj = rig.zed.left.project(transform_points(rig.T_zed_from_mech, P_mech[ok]))
    diff = p_proj - dz.corners_uv[ok]
    e = np.linalg.norm(diff, axis=1)
    # the same with both detections replaced by their board models: what remains is ground-truth error
    P_model = lift_mech(uv_mech_fit)
    okm = np.all(np.isfinite(P_model), axis=1)
    e_model = np.linalg.norm(rig.zed.left.project(transform_points(rig.T_zed_from_mech, P_model[okm])) - uv_fit[okm],
                             axis=1)
    # noise floor: the mean XY error detector noise alone gives (2-D Gaussian: mean = sigma * sqrt(pi / 2)), the
    # texture camera's noise scaled into ZED pixels by the ratio of the board's corner spacings
    if ids is None:
        spacing_m = np.median(np.linalg.norm(np.diff(uv_mech_fit.reshape(board.rows, board.cols, 2), axis=1), axis=2))
        spacing_z = np.median(np.linalg.norm(np.diff(uv_fit.reshape(board.rows, board.cols, 2), axis=1), axis=2))
    else:
        a, b = neighbour_pairs(board, ids)
        spacing_m = np.median(np.linalg.norm(uv_mech_fit[a] - uv_mech_fit[b], axis=1))
        spacing_z = np.median(np.linalg.norm(uv_fit[a] - uv_fit[b], axis=1))
    floor = float(np.sqrt(np.pi / 2) * np.hypot(rms_m * spacing_z / spacing_m, rms_z))
    # Z: generated ZED-left depth at the detected ZED corners
    depth_zed = project_depth_to_camera(depth_mech_mm, rig.depth_camera, rig.T_zed_from_depth, rig.zed.left,
                                        ReprojectParams(params.mode, params.max_slant_deg))

    def lift(uv):
        z = bilinear_valid(depth_zed, uv)
        P = rig.zed.left.unproject(uv, np.nan_to_num(z, nan=1.0))
        P[~np.isfinite(z)] = np.nan
        return P

    P = lift(uv_fit)
    P_raw = lift(dz.corners_uv)
    first, last = 0, len(X) - 1
    D_true = float(np.linalg.norm(X[last] - X[first]))
    D_calc = float(np.linalg.norm(P[last] - P[first]))
    D_raw = float(np.linalg.norm(P_raw[last] - P_raw[first]))
    good = np.nonzero(np.all(np.isfinite(P), axis=1))[0]
    pairs = np.array(list(itertools.combinations(good, 2)))
    if len(pairs) == 0:
        return None, None, "no generated depth at the ZED corners"
    dc = np.linalg.norm(P[pairs[:, 0]] - P[pairs[:, 1]], axis=1)
    dg = np.linalg.norm(X[pairs[:, 0]] - X[pairs[:, 1]], axis=1)
    rel = (dc - dg) / dg * 100
    n, c = fit_plane(P[good])
    flat = float(np.sqrt(np.mean((P[good] @ n - c) ** 2)))
    scale = float(np.sum(dc * dg) / np.sum(dg * dg))
    pv = PoseValidation(capture=name, used_for_calibration=used_for_calibration, n_corners=int(ok.sum()),
                        xy_mean_px=float(e.mean()), xy_median_px=float(np.median(e)),
                        xy_rms_px=float(np.sqrt(np.mean(e ** 2))), xy_max_px=float(e.max()),
                        xy_noise_floor_px=floor,
                        xy_model_mean_px=float(e_model.mean()) if e_model.size else float("nan"),
                        detector_rms_mech_px=rms_m, detector_rms_zed_px=rms_z,
                        z_diagonal_calc_mm=D_calc, z_diagonal_true_mm=D_true,
                        z_error_pct=abs(D_calc - D_true) / D_true * 100 if np.isfinite(D_calc) else float("nan"),
                        z_error_raw_corners_pct=(abs(D_raw - D_true) / D_true * 100 if np.isfinite(D_raw)
                                                 else float("nan")),
                        z_pairs_mean_abs_pct=float(np.mean(np.abs(rel))),
                        z_pairs_max_abs_pct=float(np.max(np.abs(rel))),
                        flatness_rms_mm=flat, scale_error_pct=(scale - 1) * 100)
    vec = np.concatenate([dz.corners_uv[ok], diff], axis=1)
    return pv, vec, None


def validate(session_dir: str | Path, calibration: str | Path | None, out_dir: str | Path | None = None,
             params: ValidateParams | None = None, captures: list[str] | None = None,
             progress: Callable[[str], None] | None = None, gauges: bool = True) -> ValidationResult:
    """Validate a calibration on a session's board captures; writes ``validation.json``/``.html`` to ``out_dir``.

    (Calibrating on all board captures but the last K and validating on those K: ``gtforge.holdout``.) ``gauges``: also
    measure the gauge objects of ``gauges/gauges.yaml`` when the session has one (``gtforge.core.measure.gauges``;
    written to ``gauges.json``/``.html`` and ``validation.json``'s ``gauges``)."""

    params = params or ValidateParams()
    if params.board is not None:
        _check_board(params.board)
    session = open_session(session_dir)
    if out_dir is not None:
        check_report_folder(session, out_dir)
    dirs = session.select("board", captures)
    if calibration is None:
        raise InputError(None, "--calibration", "a calibration file (or --holdout K)", "none",
                         "pass -c with the file gtforge calibrate wrote, or --holdout K (calibrate without the last K "
                         "board captures and validate on them)")
    calib_path = Path(calibration)
    calib = CalibrationFile.read(calib_path)
    board_model = params.board or calib.board  # the calibration's board unless overridden
    board = board_model.spec()
    _check_board(board_model)
    # raw ZED images + SN.conf, a self-rectified ZED, calibrate-scale's yaw: the pair as every stage and the dataset
    # get it, so that the rectification measured below is the dataset's
    if calib.zed_conf is not None or calib.zed_right_correction is not None or calib.rig.zed_right_yaw_deg != 0.0:
        session = open_with_calibration(session_dir, calib)
    check_rig_matches_session(calib.rig, session, calib_path)  # as every other stage (a calibration of another rig)
    # the rectification on the board points (any target: matched by id, circle centres bias-corrected; docs/targets.md)
    meter = RectificationMeter(board, calib.rig.zed.left, rectified_by(session), zed_right=calib.rig.zed.right)
    warnings = []
    used = set(calib.captures_used)
    poses, vecs, skipped = [], [], {}

    # each capture's board detections found ahead on a thread: validate_pose and the meter get them remembered
    ahead = captures_detected_ahead(dirs, lambda d: session.load_capture(d, need_right=False), board,
                                    lambda cap: [(cap.mech_texture, calib.rig.mech), (cap.zed_left, calib.rig.zed.left),
                                                 (cap.zed_right, calib.rig.zed.right)])
    for k, (d, cap, exc) in enumerate(ahead):
        if progress:
            progress(f"validate {d.name} ({k + 1}/{len(dirs)})")
        if exc is not None:  # as calibrate: a file missing skips the capture; a file wrong stops
            if not missing_capture_file(exc):
                raise leave_out_hint(exc, d.name) from None
            skipped[d.name] = f"file missing: {exc}"
            log.warning("capture %s skipped: %s (restore the file, or leave the capture out: --captures NAMES, or "
                        "for gtforge run its folder moved out of the session)",
                        d.name, exc)
            continue
        pv, vec, err = validate_pose(d.name, cap.mech_texture, cap.depth_mm, cap.zed_left, calib.rig, board, params,
                                     d.name in used)
        meter.add(d.name, cap.zed_right, left_image=cap.zed_left)
        if err:
            skipped[d.name] = err
            log.warning("capture %s: %s; skipped", d.name, err)
            continue
        poses.append(pv)
        vecs.append(vec)
    if not poses:
        raise InputError(session_dir, "board captures", "at least one capture where both cameras see the board",
                         "none", "check the board size (--cols/--rows) and the capture folders")
    # counted among the captures validated (a capture skipped here, e.g. no board found, measures nothing)
    overlap = [p.capture for p in poses if p.capture in used]
    if overlap and Path(calib.session_dir or ".").resolve() == Path(session_dir).resolve():
        which = f"all {len(poses)}" if len(overlap) == len(poses) else f"{len(overlap)} of the {len(poses)}"
        warnings.append(f"{which} captures validated were also used for calibration "
                        f"({', '.join(overlap[:5])}{'...' if len(overlap) > 5 else ''}): the result is optimistic; "
                        "use --holdout K or separate captures")
        log.warning(warnings[-1])
    allv = np.concatenate(vecs)
    e = np.linalg.norm(allv[:, 2:], axis=1)
    zerr = np.array([p.z_error_pct for p in poses])
    xy_mean = float(e.mean())
    z_mean = float(np.nanmean(zerr))
    rect = meter.result()
    warnings += rect.warnings if rect is not None else []
    rep = ValidationResult(
        calibration_path=str(Path(calib_path).resolve()), session_dir=str(Path(session_dir).resolve()),
        thresholds={"xy_px": params.xy_threshold_px, "z_pct": params.z_threshold_pct},
        xy_mean_px=xy_mean, xy_median_px=float(np.median(e)), xy_rms_px=float(np.sqrt(np.mean(e ** 2))),
        xy_max_px=float(e.max()), z_error_mean_pct=z_mean, z_error_max_pct=float(np.nanmax(zerr)),
        flatness_rms_mm=float(np.mean([p.flatness_rms_mm for p in poses])),
        scale_error_pct=float(np.mean([p.scale_error_pct for p in poses])),
        pass_xy=xy_mean <= params.xy_threshold_px, pass_z=z_mean <= params.z_threshold_pct,
        passed=xy_mean <= params.xy_threshold_px and z_mean <= params.z_threshold_pct,
        xy_noise_floor_px=float(np.mean([p.xy_noise_floor_px for p in poses])),
        xy_model_mean_px=float(np.average([p.xy_model_mean_px for p in poses], weights=[p.n_corners for p in poses])),
        board=board_model, warnings=warnings, skipped=skipped, poses=poses, corner_errors=allv.tolist(),
        rectification=rect)

    if gauges and (session.root / GAUGES_DIR / GAUGES_FILE).is_file():
        rep.gauges = validate_gauges(session_dir, calib_path, out_dir, progress=progress, update_validation=False)
    if out_dir is not None:
        write_validation_report(rep, Path(out_dir), calib.rig.zed.left)
    return rep


def measure_gauge(spec: GaugeSpec, depth_mm: np.ndarray, rig, params: GaugeParams, limits: GaugeLimits
                  ) -> tuple[GaugeResult, dict]:
    """One gauge capture: its ground truth built as build-dataset builds a scene, fitted; the raw depth fitted too.
    Returns the result and the arrays the report draws (``residual_gt_mm``: (H, W) map on the ZED-left image)."""

    bp = BuildParams(fruit_height_mm=params.min_height_mm, min_component_frac=0.2)
    sd, _, fg = build_scene_arrays(depth_mm, rig, bp)
    P = disparity_points(sd.disparity_px, rig.zed)
    masks = gauge_components(fg, params.erosion_px)
    # stated per-pixel sigma of the GT disparity (no extrinsic term: it moves the object rigidly), as depth along z
    sig_d = disparity_sigma(sd.disparity_px, sd.depth_mm, rig, None,
                            UncertaintyParams(depth_noise=params.depth_noise), sd.span_mm)
    fb = rig.zed.left.fx_px * rig.zed.baseline_mm
    with np.errstate(invalid="ignore"):
        sig_z = np.where(np.isfinite(sig_d), P[..., 2] ** 2 / fb * sig_d, np.nan)
    gt, res_gt = measure_source(spec, P, masks, sig_z, np.zeros(3), np.array([0.0, 0.0, 1.0]), params, "gt")
    raw = None
    if gt.measurable:
        raw = measure_raw_depth(spec, gt, depth_mm, rig, P, fg, params)
    status, reasons = gauge_status(spec, gt, limits)
    return GaugeResult(capture=spec.capture, kind=spec.kind, spec=spec, gt=gt, raw=raw, status=status,
                       reasons=reasons), {"residual_gt_mm": res_gt}



def validate_gauges(session_dir: str | Path, calibration: str | Path, out_dir: str | Path | None = None,
                    params: GaugeParams | None = None, progress: Callable[[str], None] | None = None,
                    write_html: bool = True, update_validation: bool = True) -> GaugesResult:
    """Measure every gauge of ``session_dir/gauges/gauges.yaml``; ``gauges.json``/``gauges.html`` go to ``out_dir``.
    ``params``: None takes ``gauges.yaml``'s ``params`` (or the defaults). ``update_validation``: where ``out_dir``
    holds a whole validation of the same session and calibration (``validation.json``), its gauge section is replaced
    by these figures (its page too), so that the folder's two reports agree; one of another session or calibration
    is refused before anything is measured (the folder would hold both, disagreeing)."""
    import time

    t0 = time.perf_counter()
    calib = CalibrationFile.read(calibration)
    # (the gauges use the depth and the left image only)
    session = open_with_calibration(session_dir, calib, right_yaw=False)
    check_rig_matches_session(calib.rig, session, calibration)
    gfile = read_gauges_file(session.root)
    params = params if params is not None else (gfile.params or GaugeParams())
    if out_dir is not None:
        check_report_folder(session, out_dir)
        g = (session.root / GAUGES_DIR).resolve()
        o = Path(out_dir).resolve()
        if o == g or g in o.parents:
            raise InputError(out_dir, "--output", "a folder outside the session's captures", f"a path inside {g}",
                             "gtforge never writes into capture folders")
    whole = _whole_validation(out_dir, session_dir, calibration) if out_dir is not None and update_validation else None
    rig = calib.rig
    results, maps = [], {}
    for k, spec in enumerate(gfile.gauges):
        if progress:
            progress(f"gauge {spec.capture} ({k + 1}/{len(gfile.gauges)})")
        cap = session.load_capture(session.root / GAUGES_DIR / spec.capture, need_right=False, decode_images=False)
        res, arrays = measure_gauge(spec, cap.depth_mm, rig, params, gfile.limits)
        if res.status == "NOT MEASURABLE":
            log.warning("gauge %s: not measurable: %s", spec.capture, "; ".join(res.reasons))
        results.append(res)
        maps[spec.capture] = arrays
    worst = max((r.status for r in results), key=lambda s: ORDER[s])
    rep = GaugesResult(session_dir=str(Path(session_dir).resolve()), calibration_path=str(Path(calibration).resolve()),
                       limits=gfile.limits, params=params, gauges=results, status=worst,
                       time_s=time.perf_counter() - t0)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        rep.write(out / "gauges.json")
        if write_html:
            write_gauges_html(rep, maps, out / "gauges.html")
        if whole is not None:
            write_validation_report(whole.model_copy(update={"gauges": rep}), out, calib.rig.zed.left)
    return rep


REPORT_FILES = {"validation.json": ValidationResult, "gauges.json": GaugesResult}  # each with its .html page


def check_report_folder(session, out_dir: str | Path) -> None:
    """Every check of validate's ``--output`` before any work (validate, its gauges alone, its hold-out): outside the
    session's captures, a folder this user can write, no other gtforge stage's folder, and ``require_report_folder``."""
    session.refuse_output_over_inputs(out_dir)
    require_output_folder(out_dir, "--output")
    refuse_gtforge_folder(out_dir)
    require_report_folder(out_dir)


def require_report_folder(out_dir: str | Path) -> None:
    """``out_dir`` (``--output``) is new, or its ``validation.json``/``.html`` and ``gauges.json``/``.html``, those it
    has, are an earlier validation's: validate writes those four names, and a file of them that gtforge did not write
    (another tool's report, someone's notes) is refused, not overwritten."""
    p = Path(out_dir)
    if not p.is_dir():
        return
    hint = "give --output a folder of its own (validate writes validation.json/.html and gauges.json/.html there)"
    for name, model in REPORT_FILES.items():
        f, page = p / name, p / name.replace(".json", ".html")
        if f.exists() or f.is_symlink():
            try:
                model.read(f)
            except InputError:
                raise InputError(f, "--output", f"an earlier gtforge validation's {name} (validate writes over it)",
                                 "a file gtforge validate did not write", hint) from None
        elif page.exists() or page.is_symlink():
            raise InputError(page, "--output", f"{page.name} only beside the {name} gtforge validate wrote with it "
                             "(validate writes over both)", f"{page.name} without {name}", hint)


def _whole_validation(out_dir: str | Path, session_dir: str | Path, calibration: str | Path) -> ValidationResult | None:
    """``out_dir``'s earlier whole validation (``validation.json``) where there is one, of this session and
    calibration; one of another is refused: its board figures and these gauges' would sit side by side."""
    p = Path(out_dir) / "validation.json"
    if not p.is_file():
        return None
    whole = ValidationResult.read(p)
    here = (str(Path(session_dir).resolve()), str(Path(calibration).resolve()))
    if (whole.session_dir, whole.calibration_path) != here:
        theirs = whole.calibration_path if whole.calibration_path != here[1] else whole.session_dir
        raise InputError(out_dir, "--output", "a folder for these gauges' figures (new, or one validating this "
                         "session with this calibration)", f"the validation of {theirs} (validation.json)",
                         "give another folder, e.g. beside it")
    return whole
