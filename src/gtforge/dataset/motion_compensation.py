"""A scene whose fruit moved between the structured-light exposure and the ZED exposure: its ground truth rebuilt with
each fruit moved by its estimated rigid motion, or the reason why not (issue #37; docs/design/motion-compensation.md).

``verify_and_compensate`` is what build-dataset runs on each scene: verification (``verify_scene``, unchanged) and,
only when it flags the fruit (texture shift or stereo bias over the fruit) while the table agrees, per connected fruit
component the motion (``gtforge.core.alignment.fruit_motion``), the depth points of the moved fruit moved by it before
the z-buffered reprojection (``reproject_to_zed`` once for the table and once per moved fruit, the results merged by
their z-buffers: occlusions, regions, both views and masks come out of the existing code), and verification again.
The rebuilt ground truth replaces the first only when every moved fruit's motion converged and is within the limits
(``MotionParams``) and the rebuilt scene passes verification; the motion's covariance then goes into the fruit's
per-pixel sigma (``motion_sigma_px``). A moved fruit whose motion is too uncertain (``max_sigma_px``) does not keep the
scene flagged: its pixels lose their ground truth (holes) and the rest is rebuilt."""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from gtforge.core.alignment.fruit_motion import FruitMotionEstimate, MotionImages, estimate_fruit_motion
from gtforge.core.alignment.photometric import local_normalize, to_gray
from gtforge.core.camera import Rig
from gtforge.core.geometry import fit_plane_robust, mask_bounding_box, transform_points
from gtforge.core.ground_truth.regions import REGION_BG, REGION_CENTRE, REGION_EDGE, REGION_NONE, fruit_regions
from gtforge.core.ground_truth.render import render_texture
from gtforge.core.ground_truth.reproject import StereoDepth, disparity_and_nonoccluded, reproject_to_zed
from gtforge.dataset.scene_verification import verify_scene, write_verification_overlay
from gtforge.infra.atomic import atomic_write_text
from gtforge.records.dataset import BuildParams
from gtforge.records.verification import FruitMotion, MotionCompensation, SceneVerification, VerifyParams

SILHOUETTE_RING_PX = 1  # farther pixels this close to a moved fruit lose their ground truth (rebuild_with_motion)


@dataclass
class CheckedScene:
    """A scene's ground truth after verification (and compensation when it was needed): the arrays to write, the
    verification (its ``motion_compensation`` says what was done), verification's rendered texture (for the overlay),
    the motion's 1-sigma disparity (px, ZED-left, 0 where no fruit was moved; None: nothing moved) and, for a scene
    compensation was tried on, the rendered texture of the ground truth as first built (the "before" overlay)."""

    sd: StereoDepth
    region: np.ndarray
    fruit: np.ndarray
    verification: SceneVerification
    rendered: np.ndarray | None
    motion_sigma_px: np.ndarray | None = None
    rendered_before: np.ndarray | None = None


def fruit_motion_suspected(v: SceneVerification, params: VerifyParams) -> bool:
    """Did verification flag the fruit: its texture shift or its stereo disparity bias over the threshold?"""
    if v.status != "flagged":
        return False
    if any(r.startswith("texture shift over fruit ") for r in v.reasons):  # one fruit of several
        return True
    m = v.texture_fruit.magnitude_px
    s = v.stereo.get("fruit")
    return (m is not None and m > params.max_shift_px) or \
        (s is not None and s.disparity_bias_px is not None and abs(s.disparity_bias_px) > params.max_disparity_bias_px)


def verify_and_compensate(depth_mm: np.ndarray, rig: Rig, params: BuildParams, sd: StereoDepth, region: np.ndarray,
                          fruit: np.ndarray, zed_left: np.ndarray, zed_right: np.ndarray | None,
                          texture: np.ndarray | None, user_mask: np.ndarray | None = None,
                          whole_images: Callable[[], tuple] | None = None) -> CheckedScene:
    """Verify the scene; when verification flags fruit motion, try the compensation (module docstring).
    ``depth_mm``: the capture's depth map (the depth camera's grid); ``zed_left``/``zed_right`` may hold only their
    first rows (``zed_rows_used``); ``whole_images()`` returns ``(texture, left, right)`` whole, when a rebuilt ground
    truth needs more rows."""
    verification, rendered = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, zed_left, zed_right,
                                          texture, rig, params.verify)
    if not (params.motion.compensate and zed_right is not None and texture is not None
            and fruit_motion_suspected(verification, params.verify)):
        return CheckedScene(sd, region, fruit, verification, rendered)
    t0 = time.perf_counter()
    H = sd.depth_mm.shape[0]
    if zed_left.shape[0] < H and whole_images is not None:
        texture, zed_left, zed_right = whole_images()
    record, rebuilt = _compensate(depth_mm, rig, params, sd, region, fruit, zed_left, zed_right, texture, user_mask)
    before = verification
    if rebuilt is None and not record.reasons:
        record.reasons.append("too little of the table in the ground truth to tell the fruit's points from it")
    if rebuilt is not None:
        sd2, region2, fruit2, sigma2, moved = rebuilt
        ver2, rendered2 = verify_scene(sd2.depth_mm, sd2.disparity_px, sd2.nonoccluded, region2, zed_left, zed_right,
                                       texture, rig, params.verify, moved)
        if ver2.status == "ok":
            record = record.model_copy(update={"status": "compensated", "before": before,
                                               "time_s": time.perf_counter() - t0})
            return CheckedScene(sd2, region2, fruit2, ver2.model_copy(update={"motion_compensation": record}),
                                rendered2, sigma2, rendered)
        record.reasons.append("the rebuilt ground truth does not pass verification: " + "; ".join(ver2.reasons))
    record = record.model_copy(update={"status": "not compensated", "before": None,
                                       "time_s": time.perf_counter() - t0})
    verification = verification.model_copy(update={
        "reasons": verification.reasons + ["fruit motion not compensated: " + "; ".join(record.reasons)],
        "motion_compensation": record})
    return CheckedScene(sd, region, fruit, verification, rendered)


def _pad_rows(a: np.ndarray, H: int) -> np.ndarray:
    if a.shape[0] >= H:
        return a[:H]
    return np.concatenate([a, np.zeros((H - a.shape[0],) + a.shape[1:], a.dtype)])


def _compensate(depth_mm, rig: Rig, params: BuildParams, sd: StereoDepth, region, fruit, zed_left, zed_right, texture,
                user_mask) -> tuple[MotionCompensation, tuple | None]:
    """Estimate every fruit's motion; the rebuilt ``(sd, region, fruit, motion sigma)`` when it is to be tried."""
    mp, vp = params.motion, params.verify
    H, W = sd.depth_mm.shape
    sigma_n = vp.norm_sigma_px
    nl = local_normalize(to_gray(_pad_rows(zed_left, H)).astype(np.float32), None, sigma_n)
    nr = local_normalize(to_gray(_pad_rows(zed_right, H)).astype(np.float32), None, sigma_n)
    rend, ok = render_texture(sd.depth_mm, rig, texture, vp.texture_occlusion_tol_mm)
    n_rend = local_normalize(rend, ok, sigma_n)
    images = MotionImages(nl, nr, n_rend if mp.texture_term else None)
    reasons: list[str] = []
    # the table must agree: a shift of the table too is the calibration's, not the fruit's
    margin = int(np.ceil(2 * sigma_n)) + 2
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
    bg = cv2.erode((region == REGION_BG).view(np.uint8), kernel).view(bool) & ok
    vb, ub = np.nonzero(bg)
    if mp.texture_term and len(vb) >= vp.min_pixels:
        shift = images.initial_shift_px(vb, ub)
        if np.hypot(*shift) > vp.max_shift_px:
            reasons.append(f"the table's texture is shifted too ({shift[0]:+.2f}, {shift[1]:+.2f}) px: not a fruit "
                           "motion (the calibration?)")
            return MotionCompensation(status="not compensated", reasons=reasons), None
    n_cc, labels = cv2.connectedComponents(fruit.view(np.uint8), connectivity=8)
    fruits: list[FruitMotion] = []
    moved: dict[int, FruitMotionEstimate] = {}
    dropped: dict[int, FruitMotionEstimate] = {}
    cam = rig.zed.left
    for k in range(1, n_cc):
        comp = labels == k
        use = cv2.erode(comp.view(np.uint8), kernel).view(bool) & sd.nonoccluded & np.isfinite(sd.depth_mm)
        v, u = np.nonzero(use)
        X = cam.unproject(np.stack([u, v], axis=1), sd.depth_mm[v, u])
        est = estimate_fruit_motion(X, (v, u), images, rig.zed, use_texture=mp.texture_term) if len(v) >= 100 \
            else None
        if est is None:
            fruits.append(FruitMotion(component=k, n_pixels=int(len(v)), status="not estimated",
                                      reason="too few textured pixels, or the fit diverged"))
            continue
        fm = _fruit_record(k, est, sd, rig)
        angle_deg = float(np.degrees(np.linalg.norm(est.rotvec_rad)))
        dist_mm = float(np.linalg.norm(est.translation_mm))
        if not est.converged:
            fm.status, fm.reason = "undetermined", "the fit did not converge"
        elif dist_mm > mp.max_translation_mm or angle_deg > mp.max_rotation_deg:
            fm.status = "beyond limit"
            fm.reason = (f"moved {dist_mm:.1f} mm, turned {angle_deg:.1f} deg (limits {mp.max_translation_mm:g} mm, "
                         f"{mp.max_rotation_deg:g} deg): the ZED may see surface the depth camera never saw")
        elif fm.chi2_still < mp.min_chi2:
            fm.status, fm.reason = "still", f"no significant motion (chi2 {fm.chi2_still:.1f} < {mp.min_chi2:g})"
        elif fm.disparity_sigma_px > mp.max_sigma_px:
            # too uncertain for the ground truth's accuracy: rather than lose the scene, this fruit's pixels lose
            # their ground truth (it still occludes, where its estimate puts it) and the rest is rebuilt
            fm.status = "no ground truth"
            fm.reason = (f"the motion's disparity sigma {fm.disparity_sigma_px:.4f} px > {mp.max_sigma_px:g} px: "
                         "its pixels have no ground truth (holes)")
            dropped[k] = est
        else:
            fm.status = "moved"
            moved[k] = est
        fruits.append(fm)
    for fm in fruits:
        if fm.status in ("beyond limit", "undetermined"):
            reasons.append(f"fruit {fm.component}: {fm.status}: {fm.reason}")
    if not moved and not dropped and not reasons:
        reasons.append("no fruit moved significantly: the flag has another cause")
    record = MotionCompensation(status="not compensated", reasons=reasons, fruit=fruits)
    if reasons:
        return record, None
    return record, rebuild_with_motion(depth_mm, rig, params, sd, labels, moved, user_mask, dropped)


def _fruit_record(k: int, est: FruitMotionEstimate, sd: StereoDepth, rig: Rig) -> FruitMotion:
    C = est.cov_rad_mm
    sig = np.sqrt(np.clip(np.diag(C), 0, None))
    try:
        chi2_still = float(np.r_[est.rotvec_rad, est.translation_mm] @ np.linalg.solve(
            C, np.r_[est.rotvec_rad, est.translation_mm]))
    except np.linalg.LinAlgError:
        chi2_still = float("inf")
    return FruitMotion(component=k, n_pixels=est.n_points, centre_zed_mm=est.centre_mm.tolist(),
                       T_zed_moved_from_zed=est.T_zed_moved_from_zed.tolist(),
                       rotvec_deg=np.degrees(est.rotvec_rad).tolist(), translation_mm=est.translation_mm.tolist(),
                       sigma_rot_deg=np.degrees(sig[:3]).tolist(), sigma_translation_mm=sig[3:].tolist(),
                       cov_rad_mm=C.tolist(), disparity_sigma_px=_disparity_sigma_p95(est, rig),
                       chi2_still=chi2_still, residual_rms=est.residual_rms, status="moved")


def _motion_jacobian(P: np.ndarray, centre_moved: np.ndarray) -> np.ndarray:
    """d(point)/d(omega, t) (N, 3, 6) of points ``P`` of a fruit moved about ``centre_moved`` (left perturbation)."""
    q = P - centre_moved
    J = np.zeros((len(P), 3, 6))
    J[:, 0, 1], J[:, 0, 2] = q[:, 2], -q[:, 1]
    J[:, 1, 0], J[:, 1, 2] = -q[:, 2], q[:, 0]
    J[:, 2, 0], J[:, 2, 1] = q[:, 1], -q[:, 0]
    J[:, :, 3:] = np.eye(3)
    return J


def _disparity_sigma_p95(est: FruitMotionEstimate, rig: Rig) -> float:
    """The motion's 1-sigma disparity at the fruit's own points (their depth's change), 95th percentile, px."""
    return float(np.percentile(_point_disparity_sigma(est, rig), 95))


def _point_disparity_sigma(est: FruitMotionEstimate, rig: Rig) -> np.ndarray:
    P = est.moved_points_mm
    J = _motion_jacobian(P, est.centre_mm + est.translation_mm)[:, 2, :]  # each point's depth change
    var = np.einsum("ni,ij,nj->n", J, est.cov_rad_mm, J)
    fB = rig.zed.f_px * rig.zed.baseline_mm
    return fB / P[:, 2] ** 2 * np.sqrt(np.clip(var, 0, None))


def rebuild_with_motion(depth_mm: np.ndarray, rig: Rig, params: BuildParams, sd: StereoDepth, labels: np.ndarray,
                        moved: dict[int, FruitMotionEstimate], user_mask: np.ndarray | None = None,
                        dropped: dict[int, FruitMotionEstimate] | None = None):
    """The ground truth with each moved fruit's depth points moved: ``(StereoDepth, region, fruit, motion sigma,
    (owner, motions))``, ``owner`` which moved fruit each ZED-left pixel shows (0: none) and ``motions`` each one's
    ``T_zed_moved_from_zed`` (``verify_scene``'s ``moved``); None when the ground truth holds too little table.

    The depth camera's points above the table plane (fit to the ground truth's background) are grouped into connected
    components on the depth camera's grid; each takes the ZED-left fruit component (``labels``) most of its visible
    points fall on. The table and every fruit left where it was are reprojected as built; each moved fruit alone with
    ``T_zed_moved_from_zed @ T_zed_from_depth`` (a rigid motion of the points is a change of the extrinsic for them);
    the views are merged by their z-buffers. A surface the depth camera never saw (the table the fruit uncovered)
    stays without ground truth. Each fruit of ``dropped`` (its motion too uncertain) is moved likewise, so that it
    occludes where it went, and then its ZED-left pixels lose their ground truth (NaN, not non-occluded); the fruit
    mask still shows it, the regions (0: no ground truth) do not."""
    depth = np.asarray(rig.corrected_depth_mm(depth_mm), np.float32)
    Hd, Wd = depth.shape
    cam_d = rig.depth_camera
    vd, ud = np.nonzero(np.isfinite(depth))
    P = transform_points(rig.T_zed_from_depth, cam_d.unproject(np.stack([ud, vd], axis=1), depth[vd, ud]))
    # the table plane from the ground truth's background
    H, W = sd.depth_mm.shape
    zl = rig.zed.left
    vb, ub = np.nonzero(labels == 0)
    okb = np.isfinite(sd.depth_mm[vb, ub])
    vb, ub = vb[okb], ub[okb]
    if len(vb) < 100:  # no table to tell the fruit from
        return None
    rng = np.random.default_rng(0)
    pick = rng.choice(len(vb), min(len(vb), 20000), replace=False)
    Pb = zl.unproject(np.stack([ub[pick], vb[pick]], axis=1), sd.depth_mm[vb[pick], ub[pick]])
    n, c, _ = fit_plane_robust(Pb, params.plane_threshold_mm, iterations=300, rng=rng)
    if c > 0:
        n, c = -n, -c
    above = P @ n - c > params.plane_threshold_mm
    cand = np.zeros((Hd, Wd), np.uint8)
    cand[vd[above], ud[above]] = 1
    n_d, lab_d = cv2.connectedComponents(cand, connectivity=8)
    # each depth-grid component -> the ZED-left component its visible points fall on
    uv = zl.project(P)
    ui, vi = np.round(uv[:, 0]).astype(np.int64), np.round(uv[:, 1]).astype(np.int64)
    inside = above & (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
    zed_lab = np.zeros(len(P), np.int64)
    zi = np.where(inside, vi * W + ui, 0)
    gt_z = sd.depth_mm.reshape(-1)[zi]
    visible = inside & (np.abs(gt_z - P[:, 2]) < 2.0)
    zed_lab[visible] = labels.reshape(-1)[zi[visible]]
    dlab = lab_d[vd, ud]
    owner = np.zeros(n_d, np.int64)
    for j in range(1, n_d):
        counts = np.bincount(zed_lab[(dlab == j) & (zed_lab > 0)], minlength=labels.max() + 1)
        if counts.sum():
            owner[j] = int(np.argmax(counts))
    point_owner = owner[dlab]  # ZED-left component of every finite depth point (0: table / unassigned)
    part_of = np.zeros((Hd, Wd), np.int64)
    part_of[vd, ud] = point_owner
    rp = params.reproject_params()
    parts = []
    dropped = dropped or {}
    every = {**moved, **dropped}
    rest = np.where(np.isin(part_of, list(every)), np.nan, depth).astype(np.float32)
    parts.append((0, reproject_to_zed(rest, cam_d, rig.T_zed_from_depth, rig.zed, rp, params.occlusion_rel_tol,
                                      left_span=params.sigma and params.mode == "mesh")))
    for k, est in every.items():
        dk = np.where(part_of == k, depth, np.nan).astype(np.float32)
        parts.append((k, reproject_to_zed(dk, cam_d, est.T_zed_moved_from_zed @ rig.T_zed_from_depth, rig.zed, rp,
                                          params.occlusion_rel_tol, left_span=params.sigma and params.mode == "mesh")))
    left = parts[0][1].depth_mm.copy()
    right = parts[0][1].depth_right_mm.copy()
    span = None if parts[0][1].span_mm is None else parts[0][1].span_mm.copy()
    who = np.zeros((H, W), np.int64)
    who_right = np.zeros((H, W), np.int64)
    for k, p in parts[1:]:
        nearer = np.isfinite(p.depth_mm) & ~(left <= p.depth_mm)  # NaN in left: nearer
        left[nearer] = p.depth_mm[nearer]
        who[nearer] = k
        if span is not None:
            span[nearer] = p.span_mm[nearer]
        who_right[np.isfinite(p.depth_right_mm) & ~(right <= p.depth_right_mm)] = k
        right = np.fmin(right, p.depth_right_mm)
    disp, noc = disparity_and_nonoccluded(left, right, rig.zed, params.occlusion_rel_tol)
    region, fruit = fruit_regions(left, rig.zed, params, user_mask)
    # the ring of farther surface just outside a moved fruit: the depth grid's mesh stops up to a pixel short of the
    # fruit's limb, and a moved fruit's limb lies in front of table the depth camera measured (a fruit left still
    # mostly has its own shadow there: no ground truth), so these pixels showed the table where the ZED saw the fruit
    # (measured: benchmarks/RESULTS.md, "Motion-compensated ground truth")
    if SILHOUETTE_RING_PX > 0 and every:
        k = 2 * SILHOUETTE_RING_PX + 1
        ring = cv2.dilate((who > 0).view(np.uint8), np.ones((k, k), np.uint8)).view(bool) & (who == 0)
        left[ring], disp[ring], noc[ring] = np.nan, np.nan, False
        if span is not None:
            span[ring] = np.nan
        # the right view's (disp1GT) likewise
        ring_right = cv2.dilate((who_right > 0).view(np.uint8), np.ones((k, k), np.uint8)).view(bool) & (who_right == 0)
        right = np.where(ring_right, np.nan, right).astype(right.dtype)
    if dropped:
        hole = np.isin(who, list(dropped))
        left[hole], disp[hole], noc[hole] = np.nan, np.nan, False
        if span is not None:
            span[hole] = np.nan
        who[hole] = 0
        right = np.where(np.isin(who_right, list(dropped)), np.nan, right).astype(right.dtype)
    # region.png is 0 wherever disp0GT has no value, as in every other scene (docs/dataset-format.md): the regions were
    # found on the merged depth before the ring and the holes lost theirs, and weight.tiff follows the regions
    region[~np.isfinite(disp)] = REGION_NONE
    sd2 = StereoDepth(left, disp, right, noc, span)
    return sd2, region, fruit, motion_sigma_px(left, who, moved, rig), \
        (who, {k: e.T_zed_moved_from_zed for k, e in moved.items()})


def motion_sigma_px(depth_zed_mm: np.ndarray, who: np.ndarray, moved: dict[int, FruitMotionEstimate],
                    rig: Rig) -> np.ndarray:
    """The 1-sigma disparity (px) the motions' covariances give each ZED-left pixel of a moved fruit (``who``: which
    fruit each pixel shows, 0 none): the surface moved by ``dX`` changes the depth along a pixel's ray ``r = (x, y,
    1)`` by ``n.dX / n.r`` (``n`` the surface normal, from the depth map), and the disparity by ``f B / Z^2`` times
    that. Grazing rays (``|n.r| < 0.1 |r|``) take the bound at 0.1."""
    out = np.zeros(depth_zed_mm.shape, np.float32)
    box = mask_bounding_box(who > 0)
    if not box:
        return out
    # the moved fruit's bounding box + 1 px (the normals' differences) only
    H, W = depth_zed_mm.shape
    y0, y1, x0, x1 = max(box[0] - 1, 0), min(box[1] + 1, H), max(box[2] - 1, 0), min(box[3] + 1, W)
    zl = rig.zed.left
    vv, uu = np.mgrid[y0:y1, x0:x1]
    d = np.asarray(depth_zed_mm[y0:y1, x0:x1], np.float64)
    Pimg = np.stack([(uu - zl.cx_px) / zl.fx_px * d, (vv - zl.cy_px) / zl.fy_px * d, d], axis=2)
    nrm = np.cross(np.gradient(Pimg, axis=1), np.gradient(Pimg, axis=0))
    fB = rig.zed.f_px * rig.zed.baseline_mm
    for k, est in moved.items():
        v, u = np.nonzero((who[y0:y1, x0:x1] == k) & np.isfinite(d))
        if not len(v):
            continue
        P = Pimg[v, u]
        nk = nrm[v, u]
        v, u = v + y0, u + x0
        nk = nk / np.maximum(np.linalg.norm(nk, axis=1, keepdims=True), 1e-12)
        r = np.stack([(u - zl.cx_px) / zl.fx_px, (v - zl.cy_px) / zl.fy_px, np.ones(len(u))], axis=1)
        nr = np.einsum("ni,ni->n", nk, r)
        rn = np.linalg.norm(r, axis=1)
        nr = np.where(np.isfinite(nr), np.sign(nr) * np.maximum(np.abs(nr), 0.1 * rn), 0.1 * rn)
        J = _motion_jacobian(P, est.centre_mm + est.translation_mm)
        a = np.einsum("ni,nij->nj", np.nan_to_num(nk), J) / nr[:, None]
        var = np.einsum("ni,ij,nj->n", a, est.cov_rad_mm, a)
        out[v, u] = (fB / P[:, 2] ** 2 * np.sqrt(np.clip(var, 0, None))).astype(np.float32)
    return out


def add_motion_sigma(sigma_px: np.ndarray, motion_px: np.ndarray) -> np.ndarray:
    """``sigma_px`` with the motion's sigma added in quadrature (float32; NaN/inf stay)."""
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.asarray(sigma_px, np.float64) ** 2 + np.asarray(motion_px, np.float64) ** 2
                       ).astype(np.float32)


def write_motion_overlays(folder: Path, sid: str, zed_left: np.ndarray, checked: CheckedScene) -> None:
    """A compensated scene's overlays for verification.html: ``<sid>_motion_before.jpg`` (the ground truth as first
    built) and ``<sid>_motion_after.jpg`` (rebuilt with the fruit moved)."""
    if checked.rendered_before is None or checked.rendered is None:
        return
    write_verification_overlay(folder / f"{sid}_motion_before.jpg", zed_left, checked.rendered_before)
    write_verification_overlay(folder / f"{sid}_motion_after.jpg", zed_left, checked.rendered)


def write_compensated_list(out: Path, compensated: list[str]) -> None:
    """``filenames/compensated.txt``: the scenes whose ground truth was rebuilt with their fruit moved, one a line (no
    file when there is none)."""
    path = out / "filenames" / "compensated.txt"
    if compensated:
        atomic_write_text(path, "\n".join(compensated) + "\n")
    else:
        path.unlink(missing_ok=True)


def moved_fruit_of(region: np.ndarray, depth_zed_mm: np.ndarray, rig: Rig, record: MotionCompensation
                   ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """``verify_scene``'s ``moved`` for a compensated scene read back from its files (``gtforge verify``): each fruit
    component of ``region.png`` is the moved fruit whose moved centroid its points lie nearest (``record``)."""
    motions = {f.component: np.array(f.T_zed_moved_from_zed) for f in record.fruit
               if f.status == "moved" and f.T_zed_moved_from_zed is not None}
    owner = np.zeros(region.shape, np.int64)
    if not motions:
        return owner, motions
    centres = {k: transform_points(T_zed_moved_from_zed,
                                   np.array([next(f.centre_zed_mm for f in record.fruit if f.component == k)]))[0]
               for k, T_zed_moved_from_zed in motions.items()}
    fruit = (region == REGION_CENTRE) | (region == REGION_EDGE)
    n_cc, labels = cv2.connectedComponents(fruit.view(np.uint8), connectivity=8)
    for j in range(1, n_cc):
        v, u = np.nonzero((labels == j) & np.isfinite(depth_zed_mm))
        if not len(v):
            continue
        c = rig.zed.left.unproject(np.stack([u, v], axis=1), depth_zed_mm[v, u]).mean(axis=0)
        k = min(centres, key=lambda key: float(np.linalg.norm(centres[key] - c)))
        if np.linalg.norm(centres[k] - c) < 30.0:  # mm: the fruit's own points (a fruit left still is farther)
            owner[labels == j] = k
    return owner, motions
