"""Scene-based refinement of ``T_zed_from_mech``: align every scene's structured-light texture with its ZED-left image.

The board calibration fixes the extrinsic from a few dozen corners; a scene offers hundreds of thousands of textured
pixels. For each scene the ground truth is built once with the starting calibration; every usable ZED-left pixel
(textured, away from depth edges, seen by the texture camera) gives a 3-D point fixed in the structured-light frame,
``X_mech = T_mech_from_zed0 @ X_zed``, and the locally normalised texture value rendered there. A candidate extrinsic
``T_zed_from_mech`` moves those points to ``pi(T_zed_from_mech @ X_mech)`` in the ZED-left image; Gauss-Newton
(iteratively re-weighted with a Huber loss, a free gain and offset per scene) minimises the difference between the
normalised ZED-left image there and the texture values, over all scenes at once (direct photometric alignment, as ETH3D
aligned its images to its scans).

Robustness: after each solve every scene is verified with the new extrinsic (``gtforge.verify``); a scene that stays
flagged (a fruit that moved, a knocked rig) is left out and the rest solved again. Generalisation: each scene is also
held out in turn (leave-one-scene-out), refined without it, and its texture shift measured before and after.

Parameterisation (as ``gtforge.calibrate``): ``T_zed_from_mech = [exp(omega) R | t + delta_t]``, omega in rad, delta_t
in mm.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from pydantic import Field

from gtforge.core.targets.extrinsic import jackknife_scale
from gtforge.core.camera import Rig
from gtforge.core.geometry import perturb_left, pose_difference, rotvec_between, transform_points
from gtforge.core.alignment.photometric import (
    even_subset,
    huber_system,
    interior_mask,
    local_normalize,
    sample_spline,
    smooth_depth_mask,
    spline_prefilter,
    textured_mask,
    to_gray,
)
from gtforge.core.ground_truth.render import render_texture
from gtforge.core.schema import GTModel
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.dataset.scene_verification import verify_scene
from gtforge.errors import InputError
from gtforge.infra import defaults
from gtforge.io.calibrated_session import open_calibrated_session
from gtforge.records.calibration import CalibrationFile, RefinementInfo, SceneRefinement
from gtforge.records.dataset import BuildParams
from gtforge.records.verification import VerifyParams

log = logging.getLogger("gtforge.refine")


class RefineParams(GTModel):
    points_per_scene: int = Field(40000, ge=1000)  # usable pixels per scene, evenly subsampled
    huber: float = Field(0.5, gt=0)  # on normalised intensities (unit local standard deviation)
    iterations: int = Field(30, ge=1)  # Gauss-Newton steps per solve
    outer_iterations: int = Field(6, ge=1)  # solve, rebuild the scenes' GT with the result, solve again...
    # the scenes used when none are named: at most this many, evenly spread over the session (None: every scene); 48
    # full-resolution scenes take 90 s and 2.4 GB with the cross-validation, which grows as the square of their
    # number (benchmarks/RESULTS.md, round 22)
    max_scenes: int | None = Field(defaults.REFINE_MAX_SCENES, ge=1)
    converged_deg: float = 0.002  # ... until a pass moves the extrinsic by less than these (the passes jitter by
    # about 0.001 deg / 0.02 mm on the synthetic scenes at 0.4x: the noise floor of re-building the templates)
    converged_mm: float = 0.03
    min_scenes: int = Field(3, ge=1)
    # covariance: the scores (J^T w r) are summed over square tiles of the ZED-left image this size before their outer
    # products (a cluster-robust sandwich), so residuals correlated within a tile are not counted as independent
    cov_tile_px: int = Field(16, ge=1)
    leave_one_out: bool = True
    verify: VerifyParams = Field(default_factory=VerifyParams)


@dataclass
class ScenePoints:
    name: str
    X_mech: np.ndarray  # (N, 3) points in the mech frame
    value: np.ndarray  # (N,) normalised texture rendered at them
    grad: np.ndarray  # (N, 2) its gradient there (ZED px): the template's, as in the verification's estimator
    # cubic B-spline coefficients (float32) of the normalised ZED-left grey image: sampled at the projections by
    # ``sample_spline``, phase-unbiased like verify's texture check (Keys' cubic convolution was not: issue 41)
    zed_norm: np.ndarray




def scene_points(name: str, depth_zed_mm: np.ndarray, disparity_px: np.ndarray, texture: np.ndarray,
                 zed_left: np.ndarray, rig: Rig, params: RefineParams) -> ScenePoints | None:
    """The textured 3-D points of one scene from its ground truth built with ``rig`` (``depth_zed_mm``,
    ``disparity_px``), or None when too few."""
    vp = params.verify
    rend, ok = render_texture(depth_zed_mm, rig, texture, vp.texture_occlusion_tol_mm)
    n_rend = local_normalize(rend, ok, vp.norm_sigma_px)
    gray = to_gray(zed_left).astype(np.float32)
    n_zed = local_normalize(gray, None, vp.norm_sigma_px)
    use = (interior_mask(ok, int(np.ceil(2 * vp.norm_sigma_px))) & textured_mask(n_rend)
           & smooth_depth_mask(disparity_px))
    v, u = np.nonzero(use)
    if len(v) < vp.min_pixels:
        return None
    keep = even_subset(len(v), params.points_per_scene)
    v, u = v[keep], u[keep]
    cam = rig.zed.left
    z = depth_zed_mm[v, u].astype(np.float64)
    X_zed = cam.unproject(np.stack([u, v], axis=1), z)
    grad = np.stack([cv2.Sobel(n_rend, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)[v, u],
                     cv2.Sobel(n_rend, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)[v, u]], axis=1).astype(np.float64)
    return ScenePoints(name, transform_points(rig.T_mech_from_zed, X_zed), n_rend[v, u].astype(np.float64), grad,
                       spline_prefilter(n_zed).astype(np.float32))


def _scene_at(cap, rig: Rig, build: BuildParams, params: RefineParams):
    """One scene with the extrinsic of ``rig``: its ground truth built once, verified, and its points for the solve."""
    sd, region, _ = build_scene_arrays(cap.depth_mm, rig, build, cap.fruit_mask)
    # (the right image as build writes it: the session applied the calibration's corrections, calibrate-scale's yaw
    # included)
    ver, _ = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, cap.zed_left, cap.zed_right,
                          cap.mech_texture, rig, params.verify)
    return scene_points(cap.name, sd.depth_mm, sd.disparity_px, cap.mech_texture, cap.zed_left, rig, params), ver


def _scene_system(sp: ScenePoints, T_zed_from_mech: np.ndarray, rig: Rig, params: RefineParams,
                  tile_px: float | None = None):
    """One scene's Huber-IRLS normal equations at ``T_zed_from_mech`` over (omega, delta_t, gain, offset): ``(JTJ 8x8,
    JTr 8, weighted rss, count, S 8x8)``; ``S`` (only with ``tile_px``) sums the outer products of the score summed over
    ``tile_px``-square tiles of the ZED-left image (the cluster-robust "meat" of a sandwich covariance)."""
    cam = rig.zed.left
    X = transform_points(T_zed_from_mech, sp.X_mech)
    Z = X[:, 2]
    u = cam.fx_px * X[:, 0] / Z + cam.cx_px
    v = cam.fy_px * X[:, 1] / Z + cam.cy_px
    r = sample_spline(sp.zed_norm, u, v) - sp.value
    # the template's gradient (inverse-compositional style): the estimating equation is then the same as
    # the verification's, so a refined extrinsic verifies at zero shift (the ZED image's own gradient
    # converges elsewhere by ~0.02 px where the two images' blur differs)
    gx, gy = sp.grad[:, 0], sp.grad[:, 1]
    # d(u, v)/dX
    du = np.stack([cam.fx_px / Z, np.zeros_like(Z), -cam.fx_px * X[:, 0] / Z ** 2], axis=1)
    dv = np.stack([np.zeros_like(Z), cam.fy_px / Z, -cam.fy_px * X[:, 1] / Z ** 2], axis=1)
    dI_dX = gx[:, None] * du + gy[:, None] * dv  # (N, 3)
    RX = X - T_zed_from_mech[:3, 3]  # R @ X_mech
    # X = exp(w) R X_mech + t + dt: dX/dw = -[R X_mech]x, dX/ddt = I
    dI_dw = np.cross(RX, dI_dX)  # (a . (-[p]x w)) = (p x a) . w
    J = np.concatenate([dI_dw, dI_dX, -sp.value[:, None], -np.ones((len(r), 1))], axis=1)
    H, g, w, S = huber_system(J, r, params.huber, u, v, tile_px)
    return H, g, float(np.sum(w * r * r)), len(r), S


def _assemble(scenes: list[ScenePoints], T_zed_from_mech: np.ndarray, rig: Rig, params: RefineParams,
              tile_px: float | None = None):
    n = len(scenes)
    JTJ = np.zeros((6 + 2 * n, 6 + 2 * n))
    JTr = np.zeros(6 + 2 * n)
    S = np.zeros_like(JTJ) if tile_px is not None else None
    rss, cnt = 0.0, 0
    for k, sp in enumerate(scenes):
        A, b, rk, ck, Sk = _scene_system(sp, T_zed_from_mech, rig, params, tile_px)
        idx = np.r_[0:6, 6 + 2 * k, 7 + 2 * k]
        JTJ[np.ix_(idx, idx)] += A
        JTr[idx] += b
        if S is not None:
            S[np.ix_(idx, idx)] += Sk
        rss += rk
        cnt += ck
    return JTJ, JTr, rss, cnt, S


def sandwich_covariance(scenes: list[ScenePoints], T_zed_from_mech: np.ndarray, rig: Rig, params: RefineParams,
                        tile_px: float | None = None) -> np.ndarray:
    """The extrinsic's 6x6 covariance at the solution ``T_zed_from_mech``: ``H^-1 S H^-1`` over every parameter (the
    extrinsic and each scene's gain/offset), ``H = sum J^T w J`` and ``S = sum_tiles g g^T`` with ``g`` the score ``sum
    J^T w r`` of one ``tile_px`` tile of one scene (``params.cov_tile_px`` by default). It takes the residuals' size and
    their correlation within a tile from the data (a plain Gauss-Newton ``s^2 H^-1`` assumes independent pixels)."""
    H, _, _, _, S = _assemble(scenes, T_zed_from_mech, rig, params, float(tile_px or params.cov_tile_px))
    Hi = np.linalg.inv(H)
    C = (Hi @ S @ Hi)[:6, :6]
    return 0.5 * (C + C.T)


def covariance_estimates(scenes: list[ScenePoints], T_zed_from_mech: np.ndarray, rig: Rig, params: RefineParams,
                         tiles_px: tuple[float, ...] = (1, 4, 16, 64)) -> dict[str, np.ndarray]:
    """Diagnostics (benchmarks/bench_refine_uncertainty.py): the extrinsic's covariance at ``T_zed_from_mech`` by the
    sandwich with several tile sizes, the plain Gauss-Newton ``s^2 H^-1`` and that times the normalisation window's
    area (the estimator refine used first: one independent sample per window)."""
    out = {f"sandwich_{tp:g}px": sandwich_covariance(scenes, T_zed_from_mech, rig, params, tp) for tp in tiles_px}
    H, _, rss, cnt, _ = _assemble(scenes, T_zed_from_mech, rig, params)
    out["gn_iid"] = np.linalg.inv(H)[:6, :6] * rss / max(cnt - len(H), 1)
    out["gn_window"] = out["gn_iid"] * np.pi * (2 * params.verify.norm_sigma_px) ** 2
    return out


def solve_extrinsic(scenes: list[ScenePoints], T_zed_from_mech_init: np.ndarray, rig: Rig, params: RefineParams
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton (Huber IRLS) over the extrinsic and a gain/offset per scene. Returns (T_zed_from_mech, 6x6
    covariance: the tile sandwich of ``sandwich_covariance`` at T_zed_from_mech)."""
    T_zed_from_mech = T_zed_from_mech_init.copy()
    for _ in range(params.iterations):
        JTJ, JTr, rss, cnt, _ = _assemble(scenes, T_zed_from_mech, rig, params)
        try:
            step = -np.linalg.solve(JTJ, JTr)
        except np.linalg.LinAlgError:
            raise InputError(None, "scenes", "scenes whose texture constrains the extrinsic", "a singular system",
                             "add scenes with texture over the whole image") from None
        T_zed_from_mech = perturb_left(T_zed_from_mech, step[:6])
        if np.abs(step[:3]).max() < 1e-8 and np.abs(step[3:6]).max() < 1e-5:
            break
    # Not s^2 H^-1 times the normalisation window's area (pi (2 sigma)^2 = 113 px, "one independent sample per
    # window"): the sampled pixels' residuals are nearly independent, so that made the covariance ~100x too large
    # (NEES ~0.04 instead of 6 on synthetic truth; benchmarks/bench_refine_uncertainty.py). The sandwich measures the
    # correlation instead of assuming it.
    return T_zed_from_mech, sandwich_covariance(scenes, T_zed_from_mech, rig, params)


def refine(session_dir: str | Path, calibration: str | Path, out_path: str | Path | None = None,
           params: RefineParams | None = None, scenes: list[str] | None = None,
           progress: Callable[[str], None] | None = None) -> CalibrationFile:
    """Refine a calibration's extrinsic from a session's scene captures; writes ``out_path`` when given. The result is
    a normal calibration file whose ``refinement`` says where it came from."""

    t0 = time.perf_counter()
    params = params or RefineParams()
    calib_path = Path(calibration)
    calib = CalibrationFile.read(calib_path)
    session, out_path = open_calibrated_session(session_dir, calib, calib_path, out_path, "refined.yaml")
    rig0 = calib.rig
    build = BuildParams()
    dirs, not_selected = session.select_scenes(scenes, params.max_scenes)
    caps, pts, reports = {}, {}, {}
    flagged_before: set[str] = set()
    for k, d in enumerate(dirs):
        if progress:
            progress(f"scene {d.name} ({k + 1}/{len(dirs)}): ground truth with the starting calibration")
        cap = session.load_capture(d)
        sp, ver = _scene_at(cap, rig0, build, params)
        rep = SceneRefinement(scene=d.name, status="used", shift_before_px=ver.texture_all.magnitude_px)
        if sp is None:
            rep.status, rep.reason = "not usable", "too little textured ground truth"
        else:
            rep.n_points = len(sp.value)
            caps[d.name], pts[d.name] = cap, sp
            if ver.status == "flagged":
                flagged_before.add(d.name)
        reports[d.name] = rep
    if len(pts) < params.min_scenes:
        raise InputError(session.root / session.config.scenes_dir, None,
                         f"at least {params.min_scenes} scenes with textured ground truth", f"{len(pts)}",
                         "refinement needs several scenes; add scene captures")
    # the first solve over the scenes that verify with the starting calibration, where enough do: a few scenes off by
    # themselves (a depth bias, a fruit that moved) would otherwise pull the extrinsic towards them, and the good
    # scenes then verify as flagged too, so none could be left out. Where too few verify (the starting extrinsic
    # itself is off), every scene.
    used = [s for s in sorted(pts) if s not in flagged_before]
    if len(used) < params.min_scenes:
        used = sorted(pts)
    T_zed_from_mech = rig0.T_zed_from_mech
    cov = None
    flagged: dict[str, str] = {}
    # Solve; rebuild every scene's ground truth (and so its points and texture templates) with the result, verify
    # it, leave out the scenes still flagged; repeat until the extrinsic stops moving. The templates come from the GT,
    # so the solution is only self-consistent once they are built with the extrinsic being solved for.
    for outer in range(params.outer_iterations):
        if progress:
            progress(f"solving over {len(used)} scenes (pass {outer + 1})")
        T_zed_from_mech_new, cov = solve_extrinsic([pts[s] for s in used], T_zed_from_mech, rig0, params)
        rig = rig0.with_extrinsic(T_zed_from_mech_new)
        flagged = {}
        for s in sorted(pts):
            sp, ver = _scene_at(caps[s], rig, build, params)
            if sp is not None:
                pts[s] = sp
            reports[s].shift_after_px = ver.texture_all.magnitude_px
            reports[s].fruit_shift_after_px = ver.texture_fruit.magnitude_px
            if ver.status == "flagged":
                flagged[s] = "; ".join(ver.reasons)
        dr, dt = pose_difference(T_zed_from_mech, T_zed_from_mech_new)
        T_zed_from_mech = T_zed_from_mech_new
        if progress:
            progress(f"pass {outer + 1}: moved {dr:.5f} deg / {dt:.4f} mm; {len(flagged)} scene(s) flagged")
        new_used = [s for s in sorted(pts) if s not in flagged]
        if len(new_used) >= params.min_scenes and new_used != used:
            used = new_used
        elif dr < params.converged_deg and dt < params.converged_mm:
            break
    for s in sorted(pts):
        if s not in used:
            reports[s].status, reports[s].reason = "excluded", flagged.get(s, "flagged by verification")
    held_before, held_after, jack = [], [], []
    if params.leave_one_out and len(used) <= params.min_scenes:
        log.warning("leave-one-out skipped: %d scene(s) used, and a refinement without one of them needs %d; no "
                    "held-out figures (heldout_* null) and no jackknife on the covariance (capture more scenes)",
                    len(used), params.min_scenes)
    if params.leave_one_out and len(used) > params.min_scenes:
        for s in used:
            if progress:
                progress(f"leave-one-out: refine without {s}")
            T_zed_from_mech_without_s, _ = solve_extrinsic([pts[x] for x in used if x != s], T_zed_from_mech, rig0,
                                                           params)
            jack.append(T_zed_from_mech_without_s)
            _, ver = _scene_at(caps[s], rig0.with_extrinsic(T_zed_from_mech_without_s), build, params)
            reports[s].heldout_shift_px = ver.texture_all.magnitude_px
            held_before.append(reports[s].shift_before_px)
            held_after.append(ver.texture_all.magnitude_px)
    sig_jr = sig_jt = None
    jack_scale = None  # the refined file's own: not the board calibration's (leave-one-pose-out) factor
    if len(jack) >= 3:
        # jackknife spread of the leave-one-out solutions (captures scene-to-scene error the pixel model cannot)
        xs = np.array([np.concatenate([rotvec_between(T_zed_from_mech, T_zed_from_mech_k),
                                       T_zed_from_mech_k[:3, 3] - T_zed_from_mech[:3, 3]])
                       for T_zed_from_mech_k in jack])
        n = len(jack)
        cj = (n - 1) / n * (xs - xs.mean(0)).T @ (xs - xs.mean(0))
        sig_jr = float(np.degrees(np.sqrt(np.trace(cj[:3, :3]))))
        sig_jt = float(np.sqrt(np.trace(cj[3:, 3:])))
        # scaled up (never down) where the leave-one-scene-out spread is larger: the RMS ratio of the six variances,
        # as calibrate's leave-one-pose-out (the largest ratio of a few scenes' noisy spread over-inflated it)
        jack_scale = jackknife_scale(T_zed_from_mech, jack, cov)
        if jack_scale is not None:
            cov = cov * jack_scale
    dr, dt = pose_difference(rig0.T_zed_from_mech, T_zed_from_mech)
    info = RefinementInfo(refined_from=str(calib_path.resolve()), scenes_used=used,
                          scenes_excluded={s: r.reason for s, r in reports.items() if r.status != "used"},
                          scenes_not_selected=not_selected,
                          change_rot_deg=dr, change_trans_mm=dt,
                          heldout_shift_before_mean_px=float(np.mean(held_before)) if held_before else None,
                          heldout_shift_after_mean_px=float(np.mean(held_after)) if held_after else None,
                          sigma_jackknife_rot_deg=sig_jr, sigma_jackknife_trans_mm=sig_jt,
                          scenes=[reports[s] for s in sorted(reports)])
    sig_r = np.degrees(np.sqrt(np.clip(np.diag(cov)[:3], 0, None)))
    sig_t = np.sqrt(np.clip(np.diag(cov)[3:], 0, None))
    out = calib.model_copy(update=dict(
        rig=rig0.with_extrinsic(T_zed_from_mech), cov_extrinsic_rad_mm=cov.tolist(),
        cov_jackknife_scale=jack_scale, sigma_rot_xyz_deg=sig_r.tolist(),
        sigma_trans_xyz_mm=sig_t.tolist(), sigma_rot_deg=float(np.sqrt(np.sum(sig_r ** 2))),
        sigma_trans_mm=float(np.sqrt(np.sum(sig_t ** 2))), refinement=info,
        time_s=calib.time_s + time.perf_counter() - t0))
    out = CalibrationFile.model_validate(out.model_dump())  # re-validated: a normal calibration file
    if out_path is not None:
        out.write(out_path)
    return out


