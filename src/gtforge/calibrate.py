"""Stage 1: ``T_zed_from_mech`` from checkerboard captures.

Per pose: corners in the structured-light texture and the rectified ZED-left image (consistent
order from the pattern), PnP in each, ``T_zed_from_mech_i = T_zed_from_board_i @ inv(T_mech_from_board_i)``.
Fusion: rotation mean on SO(3) with median/MAD outlier rejection, then joint refinement of the
extrinsic and every board pose over all corner reprojections in both cameras
(``scipy.optimize.least_squares``, Huber loss), 1-sigma uncertainty from the Jacobian, and
leave-one-pose-out cross-validation. ``use_depth`` adds a 3D-to-2D solve through the depth camera's
own measurement of the board.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np

from gtforge.core.targets.board import BoardSpec, PoseObs, detect_corners, solve_pnp
from gtforge.core.targets.extrinsic import (
    board_corners_from_depth,
    jackknife_scale,
    joint_refine,
    measured_square_size_mm,
    rms_px,
    robust_initial_extrinsic,
    transfer_error,
)
from gtforge.core.camera import PinholeCamera, RectifiedStereo, Rig
from gtforge.core.targets.coverage import coverage_report
from gtforge.core.geometry import invert_T, perturb_left, pose_difference, transform_points
from gtforge.core.zed.rectification import RectificationMeter
from gtforge.core.targets.detection import PairSkipped, captures_detected_ahead, detect_target, match_target_views
from gtforge.core.targets.models import MIN_COMMON_CORNERS, check_board_model
from gtforge.errors import InputError
from gtforge.io.calibrated_session import calibration_output_path, session_board
from gtforge.io.captures import leave_out_hint, missing_capture_file, open_session
from gtforge.io.zed_rectification import rectified_by, self_rectify, settle_zed_conf_reading
from gtforge.records.calibration import (
    CalibrateParams,
    CalibrationFile,
    MethodResult,
    PoseResult,
)

# scipy is imported inside the functions that use it: importing it slows every process start

log = logging.getLogger("gtforge.calibrate")

LOO_WARN_PX = 0.3  # verdict WARN when the leave-one-pose-out transfer error exceeds this


# ---- PnP ------------------------------------------------------------------------------------


# ---- fusion ---------------------------------------------------------------------------------


# ---- depth-based corners ----------------------------------------------------------------------


# ---- main entry -------------------------------------------------------------------------------
def detect_pose(name: str, texture: np.ndarray, depth_mm: np.ndarray | None, zed_left: np.ndarray,
                mech: PinholeCamera, zed: RectifiedStereo, board: BoardSpec,
                blur_px: float) -> tuple[PoseObs | None, PoseResult]:
    if getattr(board, "kind", "checkerboard") != "checkerboard":
        return detect_pose_target(name, texture, depth_mm, zed_left, mech, zed, board, blur_px)
    dm = detect_corners(texture, board)
    dz = detect_corners(zed_left, board)
    if dm is None or dz is None:
        which = " and ".join(w for w, d in (("structured-light", dm), ("ZED", dz)) if d is None)
        log.warning("capture %s: board not found in the %s image; skipped", name, which)
        return None, PoseResult(capture=name, status="skipped", reason=f"board not found in the {which} image")
    X = board.corners_board()
    T_mech_from_board = solve_pnp(X, dm.corners_uv, mech)
    T_zed_from_board = solve_pnp(X, dz.corners_uv, zed.left)
    blurred = bool(dm.sharpness_px > blur_px or dz.sharpness_px > blur_px)  # NaN (unmeasurable) is not blurred
    if blurred:
        log.warning("capture %s: blurred board (edge width %.1f / %.1f px)", name, dm.sharpness_px, dz.sharpness_px)
    def finite_or_none(x: float) -> float | None:
        return x if np.isfinite(x) else None

    rep = PoseResult(capture=name, status="used", sharpness_mech_px=finite_or_none(dm.sharpness_px),
                     sharpness_zed_px=finite_or_none(dz.sharpness_px), blurred=blurred)
    return PoseObs(name, dm.corners_uv, dz.corners_uv, T_mech_from_board, T_zed_from_board, depth_mm, dm, dz), rep


def calibrate_observations(obs: list[PoseObs], reports: list[PoseResult], mech: PinholeCamera,
                           zed: RectifiedStereo, params: CalibrateParams,
                           progress: Callable[[str], None] | None = None, depth_cam: PinholeCamera | None = None,
                           T_mech_from_depth: np.ndarray | None = None, coverage: bool = False) -> CalibrationFile:
    """Fuse and refine the extrinsic from detected poses (``obs``); ``reports`` is updated in place.
    ``depth_cam``/``T_mech_from_depth``: the depth map's camera when it is not the texture camera. ``coverage``: also
    fill ``coverage`` (where the points fell, distances, tilts, what to capture next: gtforge.core.targets.coverage; a
    few tenths of a second)."""
    t0 = time.perf_counter()
    board = params.board.spec()
    if len(obs) < params.min_poses:
        raise InputError(None, "captures", f"at least {params.min_poses} poses where both cameras see the board",
                         f"{len(obs)} usable", "add board captures, or check the board size (--cols/--rows)")
    T_zed_from_mech_per_pose = [o.T_zed_from_board @ invert_T(o.T_mech_from_board) for o in obs]
    T_zed_from_mech_init, keep, rot_dev, tr_dev = robust_initial_extrinsic(T_zed_from_mech_per_pose, params)
    rep_by_name = {r.capture: r for r in reports}
    for o, k, rd, td in zip(obs, keep, rot_dev, tr_dev):
        r = rep_by_name[o.name]
        r.init_rot_dev_deg, r.init_trans_dev_mm = float(rd), float(td)
        if not k:
            r.status, r.reason = "outlier", f"per-pose extrinsic off by {rd:.2f} deg / {td:.1f} mm"
            log.warning("capture %s: rejected as an outlier (%s)", o.name, r.reason)
    used = [o for o, k in zip(obs, keep) if k]
    if len(used) < params.min_poses:
        raise InputError(None, "captures", f"at least {params.min_poses} consistent poses", f"{len(used)}",
                         "the per-pose estimates disagree; check the board size and the image pairing")
    # the depth camera's own view of each board: its square size, and the --use-depth solve
    corners_depth = {}
    for o in used:
        X = board_corners_from_depth(o, mech, board, depth_cam, T_mech_from_depth)
        if X is not None and np.all(np.isfinite(X)):
            corners_depth[o.name] = X
    square_measured = dev_pct = None
    if len(corners_depth) >= 2:
        ids_of = {o.name: o.ids for o in used}
        square_measured = float(np.median([measured_square_size_mm(X, board, ids_of[n])
                                           for n, X in corners_depth.items()]))
        dev_pct = (square_measured / board.square_size_mm - 1.0) * 100.0
        if params.square_check_pct and abs(dev_pct) > params.square_check_pct:
            ratio = square_measured / board.square_size_mm
            # a ratio of two length units (depth in m read as mm, or the reverse): the depth's unit, not the board
            unit = next((f for f in (1000.0, 0.001, 10.0, 0.1, 25.4, 1 / 25.4) if abs(ratio / f - 1.0) < 0.05), None)
            hint = (f"the depth reads {ratio:.4g}x the board: set the depth maps' unit (depth_unit / depth_scale_mm "
                    "in session.yaml, docs/capture-layout.md)" if unit is not None else
                    f"pass --square-mm {square_measured:.1f} if that is the board; if the board is right, the depth "
                    "is off (depth_unit / depth_scale_mm in session.yaml)")
            raise InputError(None, "--square-mm", f"the board's square size as the depth camera measures it "
                             f"(within {params.square_check_pct:g} %)",
                             f"{board.square_size_mm:g} mm declared, {square_measured:.2f} mm measured in the depth "
                             f"of {len(corners_depth)} poses ({dev_pct:+.1f} %)", hint)
    if progress:
        progress("joint refinement")
    ref = joint_refine(used, mech, zed.left, board, T_zed_from_mech_init, params.huber_px)
    allres = []
    region_res: dict[str, list[float]] = {}
    for i, o in enumerate(used):
        r = rep_by_name[o.name]
        r.rms_mech_px, r.rms_zed_px = rms_px(ref.res_mech[i]), rms_px(ref.res_zed[i])
        e = np.concatenate([np.linalg.norm(ref.res_mech[i], axis=1), np.linalg.norm(ref.res_zed[i], axis=1)])
        r.max_px = float(e.max())
        allres.append(e)
        # errors by ZED image region (3x3 grid)
        gx = np.clip((o.zed_uv[:, 0] / zed.left.width_px * 3).astype(int), 0, 2)
        gy = np.clip((o.zed_uv[:, 1] / zed.left.height_px * 3).astype(int), 0, 2)
        for k, en in enumerate(np.linalg.norm(ref.res_zed[i], axis=1)):
            region_res.setdefault(f"{['top', 'middle', 'bottom'][gy[k]]}-{['left', 'centre', 'right'][gx[k]]}",
                                  []).append(en)
    allres = np.concatenate(allres)
    cov = ref.cov_extrinsic
    loo_means, loo_maxs, loo_T = [], [], []
    if params.leave_one_out and len(used) > params.min_poses:
        for i, o in enumerate(used):
            if progress:
                progress(f"leave-one-out {i + 1}/{len(used)}")
            rest = [u for j, u in enumerate(used) if j != i]
            T_mech_from_board_rest = [t for j, t in enumerate(ref.T_mech_from_board) if j != i]
            ref_i = joint_refine(rest, mech, zed.left, board, ref.T_zed_from_mech, params.huber_px,
                                 T_mech_from_board_rest)
            e = transfer_error(o, ref_i.T_zed_from_mech, zed.left, board)
            r = rep_by_name[o.name]
            r.loo_transfer_mean_px, r.loo_transfer_max_px = float(e.mean()), float(e.max())
            loo_means.append(e.mean())
            loo_maxs.append(e.max())
            loo_T.append(ref_i.T_zed_from_mech)
    T_zed_from_mech = ref.T_zed_from_mech
    # The Jacobian covariance assumes independent corner errors; a detector's errors are not (perspective and
    # blur bias whole poses). The leave-one-pose-out solutions' jackknife spread sees that: where it is larger (the
    # RMS ratio over the six parameters), the covariance is scaled up by the ratio (never down).
    jack_scale = jackknife_scale(T_zed_from_mech, loo_T, ref.cov_extrinsic)
    cov = cov * (jack_scale or 1.0)
    methods = [MethodResult(method="reprojection", T_zed_from_mech=T_zed_from_mech.tolist(),
                            rms_zed_px=rms_px(np.concatenate([np.reshape(r, (-1, 2)) for r in ref.res_zed])))]
    method = "reprojection"
    verdict_reasons: list[str] = []
    fail = False
    if params.use_depth:
        T_zed_from_mech_depth, rms_d, cov_d = _depth_method(used, corners_depth, zed, T_zed_from_mech)
        if T_zed_from_mech_depth is not None:
            dr, dt = pose_difference(T_zed_from_mech, T_zed_from_mech_depth)
            methods.append(MethodResult(method="depth", T_zed_from_mech=T_zed_from_mech_depth.tolist(),
                                        rms_zed_px=rms_d, rot_diff_to_primary_deg=dr, trans_diff_to_primary_mm=dt))
            sr = float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))))
            st = float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0)))
            lim_deg, lim_mm = max(params.methods_agree_deg, 5 * sr), max(params.methods_agree_mm, 5 * st)
            if dr > lim_deg or dt > lim_mm:
                fail = True
                verdict_reasons.append(
                    f"--use-depth: the depth method differs from the reprojection method by {dr:.3f} deg / {dt:.2f} mm "
                    f"(allowed {lim_deg:.3f} deg / {lim_mm:.2f} mm): the depth's scale or bias, or the board size, "
                    "is off")
            T_zed_from_mech, method = T_zed_from_mech_depth, "depth"
            if cov_d is not None:
                cov = cov_d * (jack_scale or 1.0)  # the ZED corners' correlated errors affect both solves
        else:
            verdict_reasons.append("--use-depth: fewer than 2 poses with board depth; the reprojection method was used")
    sig_r = np.degrees(np.sqrt(np.clip(np.diag(cov)[:3], 0, None)))
    sig_t = np.sqrt(np.clip(np.diag(cov)[3:], 0, None))
    n_bad = sum(r.status != "used" for r in reports)
    if n_bad:
        verdict_reasons.append(f"{n_bad} capture(s) skipped or rejected as outliers (see poses)")
    if any(r.blurred for r in reports if r.status == "used"):
        verdict_reasons.append("some used poses are blurred")
    if len(used) < 6:
        verdict_reasons.append(f"only {len(used)} poses: 6 or more give a better-constrained extrinsic")
    if dev_pct is not None and params.square_warn_pct and abs(dev_pct) > params.square_warn_pct:
        verdict_reasons.append(f"the board's squares measure {square_measured:.2f} mm in the depth, {dev_pct:+.1f} % "
                               f"from the declared {board.square_size_mm:g} mm: a wrong --square-mm moves the "
                               "extrinsic far beyond its sigma; check the board's size (or the depth's scale)")
    loo_mean = float(np.mean(loo_means)) if loo_means else None
    if loo_mean is not None and loo_mean > LOO_WARN_PX:
        verdict_reasons.append(f"leave-one-out transfer {loo_mean:.3f} px > {LOO_WARN_PX} px")
    rig = Rig(zed=zed, mech=mech, T_zed_from_mech=T_zed_from_mech, depth_cam=depth_cam,
              T_mech_from_depth=None if T_mech_from_depth is None else np.asarray(T_mech_from_depth).tolist())
    result = CalibrationFile(
        rig=rig, board=params.board, method=method, captures_used=[o.name for o in used],
        rms_px=float(np.sqrt(np.mean(allres ** 2))), max_px=float(allres.max()),
        sigma_rot_xyz_deg=sig_r.tolist(), sigma_trans_xyz_mm=sig_t.tolist(),
        sigma_rot_deg=float(np.sqrt(np.sum(sig_r ** 2))), sigma_trans_mm=float(np.sqrt(np.sum(sig_t ** 2))),
        loo_transfer_mean_px=loo_mean,
        loo_transfer_max_px=float(np.max(loo_maxs)) if loo_maxs else None,
        poses=sorted(reports, key=lambda r: -(r.max_px or 0.0)),
        methods=methods, cov_extrinsic_rad_mm=cov.tolist() if np.all(np.isfinite(cov)) else None,
        cov_jackknife_scale=jack_scale,
        square_size_measured_mm=square_measured,
        verdict="FAIL" if fail else ("WARN" if verdict_reasons else "PASS"), verdict_reasons=verdict_reasons,
        residuals_by_region_px={k: float(np.sqrt(np.mean(np.square(v)))) for k, v in region_res.items()},
        time_s=time.perf_counter() - t0)
    if coverage:
        result.coverage = coverage_report(used=used, T_mech_from_board=ref.T_mech_from_board,
                                          T_zed_from_mech=ref.T_zed_from_mech, mech=mech, zed_cam=zed.left, board=board,
                                          cov=cov if np.all(np.isfinite(cov)) else None,
                                          rms_px=float(np.sqrt(np.mean(allres ** 2))), jack_scale=jack_scale)
    result._residuals = {o.name: dict(mech_uv=o.mech_uv, res_mech=ref.res_mech[i], zed_uv=o.zed_uv,
                                      res_zed=ref.res_zed[i])
                         for i, o in enumerate(used)}
    return result


def _depth_method(used: list[PoseObs], corners_depth: dict[str, np.ndarray], zed: RectifiedStereo,
                  T_zed_from_mech_init: np.ndarray) -> tuple[np.ndarray | None, float, np.ndarray | None]:
    """3D-2D solve: the depth camera's board corners (mech frame) against the ZED detections, all poses at once.
    Returns (T_zed_from_mech, RMS px, 6x6 covariance in the CalibrationFile parameterisation)."""
    from scipy.optimize import least_squares
    P3 = [corners_depth[o.name] for o in used if o.name in corners_depth]
    P2 = [o.zed_uv for o in used if o.name in corners_depth]
    if len(P3) < 2:
        log.warning("--use-depth: fewer than 2 poses with board depth; depth method skipped")
        return None, float("nan"), None
    P3, P2 = np.concatenate(P3), np.concatenate(P2)

    def residuals(x):
        return (zed.left.project(transform_points(perturb_left(T_zed_from_mech_init, x), P3)) - P2).ravel()

    sol = least_squares(residuals, np.zeros(6), method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    T_zed_from_mech = perturb_left(T_zed_from_mech_init, sol.x)
    res = sol.fun.reshape(-1, 2)
    # re-linearise at the solution so the covariance is in the parameterisation around the written T_zed_from_mech
    J = least_squares(lambda x: (zed.left.project(transform_points(perturb_left(T_zed_from_mech, x), P3)) - P2).ravel(),
                      np.zeros(6), max_nfev=1, method="lm").jac
    s2 = float(np.sum(res ** 2) / max(res.size - 6, 1))
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov = None
    return T_zed_from_mech, rms_px(res), cov


def calibrate(session_dir: str | Path, out_path: str | Path | None = None, params: CalibrateParams | None = None,
              captures: list[str] | None = None, exclude: list[str] | None = None,
              progress: Callable[[str], None] | None = None) -> CalibrationFile:
    """Calibrate from a capture session's ``board/`` captures; writes ``out_path`` (YAML) when given
    (an existing folder, or a path ending in ``/``, gets ``calibration.yaml`` inside it)."""

    params = params or CalibrateParams()
    session = open_session(session_dir)
    params = params.model_copy(update={"board": session_board(session, params.board,
                                                              "board" in params.model_fields_set)})
    check_board_model(params.board)
    board = params.board.spec()
    if out_path is not None:
        out_path = calibration_output_path(out_path, session=session)
    dirs = session.select("board", captures, exclude)

    # raw ZED images + SN.conf: the conf reading comes from the board images (re-opens the session with it)
    session, zed_conf = settle_zed_conf_reading(session, dirs, board, progress=progress)
    selfcal = None
    if params.self_rectify:
        # the captures with both images: the scenes' texture constrains the rows as well as the boards (at most
        # params.self_rectification.max_scenes of them, evenly spread)
        scene_root = session.root / session.config.scenes_dir
        scene_dirs = session.capture_dirs("scenes") if scene_root.is_dir() and any(scene_root.iterdir()) else []
        selfcal = self_rectify(session, dirs + scene_dirs, params.self_rectification, progress)
        if selfcal.correction is not None:
            session = open_session(session_dir, zed_conf_reading=zed_conf.reading if zed_conf else None,
                                   zed_right_correction=selfcal.correction)
    meter = RectificationMeter(board, session.zed.left, rectified_by(session), zed_right=session.zed.right)
    obs, reports = [], []

    # each capture's board detections found ahead on a thread: detect_pose and the meter get them remembered
    ahead = captures_detected_ahead(dirs, lambda d: session.load_capture(d, need_right=False), board,
                                    lambda cap: [(cap.mech_texture, session.mech), (cap.zed_left, session.zed.left),
                                                 (cap.zed_right, meter.cam_right)])
    for k, (d, cap, exc) in enumerate(ahead):
        if progress:
            progress(f"detect {d.name} ({k + 1}/{len(dirs)})")
        if exc is not None:  # a file missing: skipped, as a capture without the board; a file wrong: stop
            if not missing_capture_file(exc):
                raise leave_out_hint(exc, d.name) from None
            log.warning("capture %s skipped: %s (restore the file, or leave the capture out: --captures NAMES, or "
                        "for gtforge run its folder moved out of the session)",
                        d.name, exc)
            reports.append(PoseResult(capture=d.name, status="skipped", reason=f"file missing: {exc}"))
            continue
        o, rep = detect_pose(d.name, cap.mech_texture, cap.depth_mm, cap.zed_left, session.mech, session.zed,
                             board, params.blur_sharpness_px)
        reports.append(rep)
        if o is not None:
            obs.append(o)
            meter.add(d.name, cap.zed_right, left_detection=o.det_zed)
    result = calibrate_observations(obs, reports, session.mech, session.zed, params, progress, session.depth_cam,
                                    session.T_mech_from_depth, coverage=True)
    result.session_dir = str(Path(session_dir).resolve())
    result.zed_conf, result.rectification = zed_conf, meter.result()
    result.zed_self_rectification = selfcal
    stereo_warnings = ((zed_conf.warnings if zed_conf else [])
                       + (result.rectification.warnings if result.rectification else []))
    if selfcal is not None and selfcal.status == "not determined":
        stereo_warnings.append(selfcal.summary_line())
    if stereo_warnings:
        result.verdict_reasons = result.verdict_reasons + stereo_warnings
        result.verdict = "WARN" if result.verdict == "PASS" else result.verdict
    if out_path is not None:
        result.write(out_path)
    return result


def detect_pose_target(name: str, texture, depth_mm, zed_left, mech, zed, spec, blur_px: float,
                       min_common: int = MIN_COMMON_CORNERS):
    """``gtforge.calibrate.detect_pose`` for ChArUco and circle grids: points matched by id between the two
    cameras; a pose with fewer than ``min_common`` common points, or collinear ones, is skipped with the reason.
    Each camera's board pose (PnP) uses all its own points; the extrinsic only the common ones."""

    dm = detect_target(texture, spec, mech, where=f"{name}: structured-light image")
    dz = detect_target(zed_left, spec, zed.left, where=f"{name}: ZED-left image")
    if dm is None or dz is None:
        which = " and ".join(w for w, d in (("structured-light", dm), ("ZED", dz)) if d is None)
        log.warning("capture %s: board not found in the %s image; skipped", name, which)
        return None, PoseResult(capture=name, status="skipped", reason=f"board not found in the {which} image")
    counts = dict(n_points_mech=len(dm.ids), n_points_zed=len(dz.ids))
    pair = match_target_views(spec, dm, mech, dz, zed.left, ("structured-light", "ZED"), min_common)
    if isinstance(pair, PairSkipped):
        log.warning("capture %s: %s; skipped", name, pair.reason)
        if pair.n_common is not None:
            counts["n_points_common"] = pair.n_common
        return None, PoseResult(capture=name, status="skipped", reason=pair.reason, **counts)
    counts["n_points_common"] = len(pair.ids)
    dm, dz = pair.det_a, pair.det_b
    blurred = bool(dm.sharpness_px > blur_px or dz.sharpness_px > blur_px)
    if blurred:
        log.warning("capture %s: blurred board (edge width %.1f / %.1f px)", name, dm.sharpness_px, dz.sharpness_px)

    def fin(x: float) -> float | None:
        return float(x) if np.isfinite(x) else None

    rep = PoseResult(capture=name, status="used", sharpness_mech_px=fin(dm.sharpness_px),
                     sharpness_zed_px=fin(dz.sharpness_px), blurred=blurred, **counts)
    obs = PoseObs(name, pair.uv_a, pair.uv_b, pair.T_a_from_board, pair.T_b_from_board, depth_mm, dm, dz, ids=pair.ids)
    return obs, rep
