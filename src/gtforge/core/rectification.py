"""How well the ZED pair is rectified, and which SN.conf reading the images support.

**Vertical disparity** is ``v_left - v_right`` (px) of one scene point in the two rectified images; a
perfectly rectified pair has 0 everywhere. On board captures the points are the board's inner corners,
detected in both images. Two figures per set of corners:

* from the detected corners as they are (``mean_abs_px``, ``max_abs_px``...): includes corner-detector
  noise (a few hundredths of a pixel per image);
* from a homography fitted per pose to each image's corners (``fit_*``): a rectified camera sees the
  planar board through an exact homography, so the fit averages the detector noise out and leaves the
  rectification's own error. Decisions (the SN.conf reading, the warning threshold) use this one.

**SN.conf reading** (``gtforge.io.cameras.ZED_CONF_READINGS``, docs/conventions.md): with raw images and
an SN.conf, the board corners are detected once per raw image; each candidate reading is evaluated by
mapping those raw corners through its rectification (lens model inverted, ``R1``/``R2`` applied,
projected with ``P1``/``P2``: the same mapping ``cv2.undistortPoints(R=, P=)`` performs, with the
inverse solved to 1e-9 px by ``gtforge.core.lens``) and the reading with the smallest vertical disparity is
kept. A reading whose rectified right camera sits at ``-x`` contradicts the images (their disparities
are positive) and is not eligible.

Scenes have no board: ``scene_vertical_disparity`` measures the same quantity on SIFT matches refined by
pyramidal Lucas-Kanade tracking (forward-backward checked).
"""
from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np
from pydantic import Field, PrivateAttr

from gtforge.core.board import detect_corners
from gtforge.core.camera import PinholeCamera
from gtforge.errors import InputError
from gtforge.io.cameras import (
    ZED_CONF_READINGS,
    ZedFactoryCalibration,
    check_zed_conf_reading,
    describe_zed_conf_reading,
)
from gtforge.io.formats import to_gray
from gtforge.core.schema import GTModel
from gtforge.synthetic import BoardSpec

if TYPE_CHECKING:
    from gtforge.io.captures import Session

log = logging.getLogger("gtforge.core.rectification")

VERTICAL_WARN_PX = 0.15  # mean |vertical disparity| (homography-fitted) above this: the rectification is suspect
TIE_PX = 0.02  # two readings whose rectified corners differ by less than this are the same rectification
ROWS, COLS = ("top", "middle", "bottom"), ("left", "centre", "right")


# ---- figures --------------------------------------------------------------------------------
class VerticalDisparity(GTModel):
    """``v_left - v_right`` (px) over a set of corresponding points in the two rectified images."""

    n_points: int
    mean_px: float  # signed
    mean_abs_px: float
    rms_px: float
    max_abs_px: float
    fit_mean_abs_px: float | None = None  # per-pose homography fits (board corners only)
    fit_max_abs_px: float | None = None


class PoseVerticalDisparity(VerticalDisparity):
    capture: str
    disparity_median_px: float  # u_left - u_right: positive when the right camera is at +x


class RegionVerticalDisparity(GTModel):
    n_points: int
    mean_px: float
    mean_abs_px: float


class RectificationQuality(GTModel):
    """Vertical disparity of the board corners in the rectified ZED images (calibrate, validate)."""

    rectified_by: str  # who rectified the images gtforge measured: reads after "rectified" ("before gtforge, ...")
    overall: VerticalDisparity
    poses: list[PoseVerticalDisparity]  # worst first
    by_region_left: dict[str, RegionVerticalDisparity]  # 3x3 grid of the rectified left image
    skipped: dict[str, str] = Field(default_factory=dict)  # capture -> why it was not measured
    threshold_px: float = VERTICAL_WARN_PX
    warnings: list[str] = Field(default_factory=list)
    # (N, 3): u_left, v_left, v_left - v_right of every corner, for the reports (not written to files)
    _points: np.ndarray = PrivateAttr(default_factory=lambda: np.zeros((0, 3)))


def _stats(dv: np.ndarray, dv_fit: np.ndarray | None = None) -> dict:
    dv = np.asarray(dv, np.float64)
    out = {"n_points": int(dv.size), "mean_px": float(dv.mean()), "mean_abs_px": float(np.abs(dv).mean()),
           "rms_px": float(np.sqrt(np.mean(dv ** 2))), "max_abs_px": float(np.abs(dv).max())}
    if dv_fit is not None:
        out.update(fit_mean_abs_px=float(np.abs(dv_fit).mean()), fit_max_abs_px=float(np.abs(dv_fit).max()))
    return out


def region_name(uv: np.ndarray, width_px: int, height_px: int) -> list[str]:
    """3x3 grid cell of each ``(u, v)``: ``top-left`` ... ``bottom-right`` (as calibrate's residual table)."""
    gx = np.clip((np.asarray(uv)[:, 0] / width_px * 3).astype(int), 0, 2)
    gy = np.clip((np.asarray(uv)[:, 1] / height_px * 3).astype(int), 0, 2)
    return [f"{ROWS[j]}-{COLS[i]}" for i, j in zip(gx, gy)]


def _by_region(points: np.ndarray, width_px: int, height_px: int) -> dict[str, RegionVerticalDisparity]:
    names = np.array(region_name(points[:, :2], width_px, height_px))
    out = {}
    for r in ROWS:
        for c in COLS:
            k = f"{r}-{c}"
            dv = points[names == k, 2]
            if dv.size:
                out[k] = RegionVerticalDisparity(n_points=int(dv.size), mean_px=float(dv.mean()),
                                                 mean_abs_px=float(np.abs(dv).mean()))
    return out


def board_pose_vertical_disparity(capture: str, left_uv: np.ndarray, right_uv: np.ndarray,
                                  board: BoardSpec) -> tuple[PoseVerticalDisparity, np.ndarray]:
    """One pose: the board's corners ``(N, 2)`` in the rectified left and right images (board order).

    Returns the figures and the ``(N, 3)`` points ``(u_left, v_left, v_left - v_right)``."""
    left_uv = np.asarray(left_uv, np.float64).reshape(-1, 2)
    right_uv = np.asarray(right_uv, np.float64).reshape(-1, 2)
    if left_uv.shape != right_uv.shape or len(left_uv) != board.n_corners:
        raise ValueError(f"{left_uv.shape=} and {right_uv.shape=} but expected ({board.n_corners}, 2) each")
    Xb = board.corners_board()[:, :2].reshape(-1, 1, 2)
    fitted = []
    for uv in (left_uv, right_uv):
        H, _ = cv2.findHomography(Xb, uv.reshape(-1, 1, 2), 0)
        fitted.append(cv2.perspectiveTransform(Xb, H).reshape(-1, 2))
    dv = left_uv[:, 1] - right_uv[:, 1]
    dv_fit = fitted[0][:, 1] - fitted[1][:, 1]
    pv = PoseVerticalDisparity(capture=capture, disparity_median_px=float(np.median(left_uv[:, 0] - right_uv[:, 0])),
                               **_stats(dv, dv_fit))
    return pv, np.column_stack([left_uv, dv])


class RectificationMeter:
    """Collects the board corners of both rectified images pose by pose; ``result()`` summarises.

    ``add`` detects the board in the right image (and in the left one unless its corners are given)."""

    def __init__(self, board: BoardSpec, zed_left: PinholeCamera, rectified_by: str,
                 threshold_px: float = VERTICAL_WARN_PX):
        self.board, self.cam, self.rectified_by, self.threshold_px = board, zed_left, rectified_by, threshold_px
        self.poses: list[PoseVerticalDisparity] = []
        self.points: list[np.ndarray] = []
        self.skipped: dict[str, str] = {}

    def add(self, capture: str, right_image: np.ndarray | None, left_uv: np.ndarray | None = None,
            left_image: np.ndarray | None = None) -> PoseVerticalDisparity | None:
        if right_image is None:
            self.skipped[capture] = "no right image"
            return None
        if left_uv is None:
            if left_image is None:
                raise ValueError("give left_uv or left_image")
            det = detect_corners(left_image, self.board)
            if det is None:
                self.skipped[capture] = "board not found in the left image"
                return None
            left_uv = det.corners_uv
        det_r = detect_corners(right_image, self.board)
        if det_r is None:
            self.skipped[capture] = "board not found in the right image"
            log.warning("capture %s: board not found in the rectified right image; its vertical disparity is not measured",
                        capture)
            return None
        pv, pts = board_pose_vertical_disparity(capture, left_uv, det_r.corners_uv, self.board)
        self.poses.append(pv)
        self.points.append(pts)
        return pv

    def result(self) -> RectificationQuality | None:
        if not self.poses:
            return None
        pts = np.concatenate(self.points)
        fit = np.concatenate([[p.fit_mean_abs_px] * p.n_points for p in self.poses])
        fit_max = max(p.fit_max_abs_px for p in self.poses)
        overall = VerticalDisparity(**_stats(pts[:, 2]))
        overall.fit_mean_abs_px, overall.fit_max_abs_px = float(fit.mean()), float(fit_max)
        warnings = []
        if overall.fit_mean_abs_px > self.threshold_px:
            warnings.append(f"the rectified ZED pair keeps {overall.fit_mean_abs_px:.3f} px mean vertical disparity on "
                            f"the board corners (threshold {self.threshold_px} px): stereo matching and the ground truth "
                            f"suffer; check the ZED calibration (the images were rectified {self.rectified_by})")
            log.warning(warnings[-1])
        q = RectificationQuality(rectified_by=self.rectified_by, overall=overall,
                                 poses=sorted(self.poses, key=lambda p: -(p.fit_mean_abs_px or 0.0)),
                                 by_region_left=_by_region(pts, self.cam.width_px, self.cam.height_px),
                                 skipped=dict(self.skipped), threshold_px=self.threshold_px, warnings=warnings)
        q._points = pts
        return q


def rectified_by(session: Session) -> str:
    """Who rectified the ZED images a session's captures load as, worded to follow "rectified" / "rectified:"
    ("before gtforge, e.g. by the ZED SDK" or "by gtforge, from SN123.conf read as ...")."""
    rect = getattr(session, "rectification", None)
    corrected = "" if getattr(rect, "correction", None) is None else \
        ", the right camera corrected by gtforge's self-rectification"
    if rect is not None and getattr(rect, "factory", None) is not None:
        return (f"by gtforge, from {rect.factory.path.name} read as '{rect.reading}': "
                f"{describe_zed_conf_reading(rect.reading)}{corrected}")
    return "before gtforge, e.g. by the ZED SDK" + corrected


# ---- SN.conf readings -----------------------------------------------------------------------
def rectify_points(cam: PinholeCamera, uv_raw: np.ndarray, R_rect_from_raw: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Raw (distorted) pixels ``(N, 2)`` -> rectified pixels ``(N, 2)`` (``cv2.undistortPoints(R=, P=)``)."""
    xy = cam.undistort_to_normalized(uv_raw)
    rays = np.column_stack([xy, np.ones(len(xy))]) @ np.asarray(R_rect_from_raw).T
    p = rays @ np.asarray(P)[:, :3].T
    return p[:, :2] / p[:, 2:3]


@dataclass
class RawBoardPair:
    """The board's corners detected in one raw (unrectified) left/right pair, board order."""

    capture: str
    left_uv: np.ndarray  # (N, 2) raw left pixels
    right_uv: np.ndarray  # (N, 2) raw right pixels


class ReadingScore(GTModel):
    reading: str
    formula: str
    R_rotvec_rad: list[float]  # what this reading passes to cv2.stereoRectify: X_right = R @ X_left + T
    T_mm: list[float]
    baseline_mm: float  # of the rectified pair it gives; negative: right camera at -x (ineligible)
    eligible: bool
    vertical: VerticalDisparity


class ZedConfChoice(GTModel):
    """Which SN.conf reading gtforge rectifies the raw ZED images with, and why (calibration file)."""

    conf_file: str
    resolution: str
    reading: str
    formula: str
    chosen_by: Literal["board images", "scene matches", "session.yaml", "default"]
    threshold_px: float
    captures: list[str]  # the raw board pairs every candidate was scored on
    candidates: list[ReadingScore]  # best first
    warnings: list[str] = Field(default_factory=list)

    def score(self, reading: str) -> ReadingScore | None:
        return next((c for c in self.candidates if c.reading == reading), None)


def score_readings(factory: ZedFactoryCalibration, pairs: list[RawBoardPair], board: BoardSpec,
                   readings: tuple[str, ...] = ZED_CONF_READINGS) -> tuple[list[ReadingScore], dict[str, np.ndarray]]:
    """Every reading's vertical disparity on the raw board corners (best eligible first), and each reading's
    ``(N,)`` per-corner ``v_left - v_right`` (for comparing two readings' rectifications)."""
    if not pairs:
        raise ValueError("no raw board pairs to score the readings on")
    scores, per_corner = [], {}
    for reading in readings:
        sr = factory.stereo_rectify(reading)
        dvs, fits, disp = [], [], []
        for p in pairs:
            ul = rectify_points(factory.left, p.left_uv, sr.R_rect_from_raw_left, sr.P_left)
            ur = rectify_points(factory.right, p.right_uv, sr.R_rect_from_raw_right, sr.P_right)
            pv, _ = board_pose_vertical_disparity(p.capture, ul, ur, board)
            dvs.append(ul[:, 1] - ur[:, 1])
            fits.append(np.full(len(ul), pv.fit_mean_abs_px))
            disp.append(pv.disparity_median_px)
        dv = np.concatenate(dvs)
        per_corner[reading] = dv
        vert = VerticalDisparity(**_stats(dv))
        vert.fit_mean_abs_px = float(np.concatenate(fits).mean())
        baseline = sr.baseline_signed_mm
        scores.append(ReadingScore(reading=reading, formula=describe_zed_conf_reading(reading),
                                   R_rotvec_rad=cv2.Rodrigues(sr.R)[0].ravel().tolist(), T_mm=sr.T_mm.tolist(),
                                   baseline_mm=baseline, eligible=bool(baseline > 0), vertical=vert))
    scores.sort(key=lambda s: (not s.eligible, s.vertical.fit_mean_abs_px))
    return scores, per_corner


def choose_reading(factory: ZedFactoryCalibration, pairs: list[RawBoardPair], board: BoardSpec,
                   override: str | None = None, threshold_px: float = VERTICAL_WARN_PX) -> ZedConfChoice:
    """Score every reading on ``pairs`` and keep the best eligible one (or ``override``, still scored)."""
    conf = str(factory.path)
    if override is not None:
        check_zed_conf_reading(override)
    if not pairs:
        reading = override or _default_reading()
        warn = ("no board capture shows the whole board in both raw ZED images: the SN.conf reading could not be "
                f"checked; '{reading}' is used" + ("" if override else " (the default)"))
        log.warning(warn)
        return ZedConfChoice(conf_file=conf, resolution=factory.resolution, reading=reading,
                             formula=describe_zed_conf_reading(reading),
                             chosen_by="session.yaml" if override else "default", threshold_px=threshold_px,
                             captures=[], candidates=[], warnings=[warn])
    scores, per_corner = score_readings(factory, pairs, board)
    eligible = [s for s in scores if s.eligible]
    disp = np.median([board_pose_vertical_disparity(p.capture, p.left_uv, p.right_uv, board)[0].disparity_median_px
                      for p in pairs])
    if not eligible or disp <= 0:
        raise InputError(factory.path, "board captures", "the board further right in the left raw image than in the "
                         "right one (positive disparity)", f"median raw disparity {disp:.1f} px",
                         "are the left and right images swapped (files, or halves of the side-by-side image)?")
    best = eligible[0]
    warnings = []
    if override is not None:
        reading, chosen_by = override, "session.yaml"
        mine = next(s for s in scores if s.reading == override)
        if not mine.eligible:
            raise InputError(None, "zed_conf_reading", "a reading that puts the right camera at +x",
                             f"'{override}' gives a baseline of {mine.baseline_mm:.2f} mm",
                             f"the board images favour '{best.reading}' (docs/conventions.md)")
        if mine.vertical.fit_mean_abs_px > best.vertical.fit_mean_abs_px + TIE_PX:
            warnings.append(f"session.yaml sets zed_conf_reading '{override}', which leaves "
                            f"{mine.vertical.fit_mean_abs_px:.3f} px mean vertical disparity on the board corners; "
                            f"'{best.reading}' would leave {best.vertical.fit_mean_abs_px:.3f} px")
    else:
        reading, chosen_by = best.reading, "board images"
        if len(eligible) > 1:
            second = eligible[1]
            same = np.max(np.abs(per_corner[best.reading] - per_corner[second.reading])) < TIE_PX
            if not same and second.vertical.fit_mean_abs_px - best.vertical.fit_mean_abs_px < TIE_PX:
                warnings.append(f"the SN.conf readings '{best.reading}' and '{second.reading}' fit the board captures "
                                f"equally well ({best.vertical.fit_mean_abs_px:.3f} / "
                                f"{second.vertical.fit_mean_abs_px:.3f} px); add board poses near the image edges and "
                                "at several distances, or set zed_conf_reading in session.yaml")
    chosen = next(s for s in scores if s.reading == reading)
    if chosen.vertical.fit_mean_abs_px > threshold_px:
        warnings.append(f"even the SN.conf reading '{reading}' leaves {chosen.vertical.fit_mean_abs_px:.3f} px mean "
                        f"vertical disparity on the raw board corners (threshold {threshold_px} px): the conf may "
                        f"belong to another camera or resolution ({factory.path.name}, {factory.resolution})")
    for w in warnings:
        log.warning(w)
    return ZedConfChoice(conf_file=conf, resolution=factory.resolution, reading=reading,
                         formula=describe_zed_conf_reading(reading), chosen_by=chosen_by, threshold_px=threshold_px,
                         captures=[p.capture for p in pairs], candidates=scores, warnings=warnings)


def choose_reading_by_matches(factory: ZedFactoryCalibration, matches: list[RawBoardPair],
                              threshold_px: float = VERTICAL_WARN_PX) -> ZedConfChoice | None:
    """Without a board seen whole in both raw images: every reading scored on feature matches between the raw left
    and right images (``match_points(rectified=False)``), the one with the smallest median |vertical disparity|
    kept. ``None`` where there are too few matches (fewer than 30) or no reading puts the right camera at +x."""
    pairs = [m for m in matches if len(m.left_uv)]
    if sum(len(m.left_uv) for m in pairs) < 30:
        return None
    scores = []
    for reading in ZED_CONF_READINGS:
        sr = factory.stereo_rectify(reading)
        dv = np.concatenate([rectify_points(factory.left, m.left_uv, sr.R_rect_from_raw_left, sr.P_left)[:, 1]
                             - rectify_points(factory.right, m.right_uv, sr.R_rect_from_raw_right, sr.P_right)[:, 1]
                             for m in pairs])
        # a match can slide along its epipolar line within RANSAC's 1 px: the scores leave out matches beyond 5 MAD
        med = float(np.median(dv))
        dv = dv[np.abs(dv - med) <= max(5.0 * 1.4826 * float(np.median(np.abs(dv - med))), 0.5)]
        vert = VerticalDisparity(**_stats(dv))
        baseline = sr.baseline_signed_mm
        scores.append((float(np.median(np.abs(dv))), ReadingScore(
            reading=reading, formula=describe_zed_conf_reading(reading),
            R_rotvec_rad=cv2.Rodrigues(sr.R)[0].ravel().tolist(), T_mm=sr.T_mm.tolist(), baseline_mm=baseline,
            eligible=bool(baseline > 0), vertical=vert)))
    scores.sort(key=lambda s: (not s[1].eligible, s[0]))
    if not scores[0][1].eligible:
        return None
    best_px, best = scores[0]
    warnings = [] if best_px <= threshold_px else [
        f"even the SN.conf reading '{best.reading}' leaves {best_px:.3f} px median vertical disparity on the raw "
        f"feature matches (threshold {threshold_px} px) before self-rectification"]
    return ZedConfChoice(conf_file=str(factory.path), resolution=factory.resolution, reading=best.reading,
                         formula=best.formula, chosen_by="scene matches", threshold_px=threshold_px,
                         captures=[m.capture for m in pairs], candidates=[s for _, s in scores], warnings=warnings)


def raw_matches(session: Session, dirs: list[Path], progress: Callable[[str], None] | None = None
                ) -> list[RawBoardPair]:
    """Feature matches between the raw left and right images of each capture in ``dirs``."""
    raw = dataclasses.replace(session, rectification=None)
    out = []
    for k, d in enumerate(dirs):
        if progress:
            progress(f"raw ZED matches {d.name} ({k + 1}/{len(dirs)})")
        cap = raw.load_capture(d, need_right=True)
        if cap.zed_right is not None:
            pl, pr = match_points(cap.zed_left, cap.zed_right, rectified=False)
            out.append(RawBoardPair(d.name, pl, pr))
    return out


def _default_reading() -> str:
    from gtforge.io.cameras import DEFAULT_ZED_CONF_READING

    return DEFAULT_ZED_CONF_READING


def detect_raw_pairs(session: Session, dirs: list[Path], board: BoardSpec,
                     progress: Callable[[str], None] | None = None) -> tuple[list[RawBoardPair], dict[str, str]]:
    """The board's corners in the raw left and right images of each capture in ``dirs`` (detected once)."""
    raw = dataclasses.replace(session, rectification=None)
    pairs, skipped = [], {}
    for k, d in enumerate(dirs):
        if progress:
            progress(f"raw ZED corners {d.name} ({k + 1}/{len(dirs)})")
        cap = raw.load_capture(d, need_right=True)
        dl = detect_corners(cap.zed_left, board)
        dr = detect_corners(cap.zed_right, board) if dl is not None and cap.zed_right is not None else None
        if dl is None or dr is None:
            skipped[d.name] = f"board not found in the raw {'left' if dl is None else 'right'} ZED image"
            continue
        pairs.append(RawBoardPair(d.name, dl.corners_uv, dr.corners_uv))
    return pairs, skipped


def settle_zed_conf_reading(session: Session, dirs: list[Path], board: BoardSpec,
                            threshold_px: float = VERTICAL_WARN_PX,
                            progress: Callable[[str], None] | None = None) -> tuple[Session, ZedConfChoice | None]:
    """For raw ZED images + SN.conf: choose the reading from the board captures in ``dirs`` (or take
    session.yaml's ``zed_conf_reading``, still scored) and return the session re-opened with it.
    Other sessions come back unchanged, with ``None``."""
    from gtforge.io.captures import open_session

    rect = getattr(session, "rectification", None)
    if rect is None or getattr(rect, "factory", None) is None:
        return session, None
    pairs, _ = detect_raw_pairs(session, dirs, board, progress)
    override = getattr(session.config, "zed_conf_reading", None)
    choice = None
    if not pairs and override is None:
        # no board seen whole in both raw images: the readings are decided on feature matches, scenes included
        scene_root = session.root / session.config.scenes_dir
        scenes = session.capture_dirs("scenes") if scene_root.is_dir() and any(scene_root.iterdir()) else []
        choice = choose_reading_by_matches(rect.factory, raw_matches(session, list(dirs) + scenes, progress),
                                           threshold_px)
    if choice is None:
        choice = choose_reading(rect.factory, pairs, board, override, threshold_px)
    if choice.reading != rect.reading:
        session = open_session(session.root, zed_conf_reading=choice.reading)
    return session, choice


# ---- scenes ---------------------------------------------------------------------------------
class SceneVerticalDisparity(VerticalDisparity):
    """Vertical disparity of matched scene points in one rectified pair (no board needed)."""

    median_px: float
    by_region_left: dict[str, RegionVerticalDisparity]


def match_points(left: np.ndarray, right: np.ndarray, max_features: int = 4000, ratio: float = 0.75,
                 fb_max_px: float = 0.05, win_px: int = 15, rectified: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Corresponding points ``(N, 2)`` left and right: SIFT matches (ratio test), refined by pyramidal
    Lucas-Kanade from the left point into the right image and kept when tracking back lands within
    ``fb_max_px`` of the start. ``rectified``: matches more than 8 px off the row are wrong; otherwise (raw images)
    matches that do not fit one epipolar geometry (RANSAC on the fundamental matrix, 1 px) are dropped."""
    gl, gr = to_gray(left), to_gray(right)
    sift = cv2.SIFT_create(nfeatures=max_features)
    kl, dl = sift.detectAndCompute(gl, None)
    kr, dr = sift.detectAndCompute(gr, None)
    if dl is None or dr is None or len(kl) < 2 or len(kr) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(dl, dr, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if not good:
        return np.zeros((0, 2)), np.zeros((0, 2))
    pl = np.float32([kl[m.queryIdx].pt for m in good])
    pr0 = np.float32([kr[m.trainIdx].pt for m in good])
    if rectified:
        keep = np.abs(pl[:, 1] - pr0[:, 1]) < 8.0  # rectified: matches far off the row are wrong
    elif len(pl) >= 8:
        _, inl = cv2.findFundamentalMat(pl, pr0, cv2.FM_RANSAC, 1.0, 0.999)
        keep = np.zeros(len(pl), bool) if inl is None else inl.ravel() == 1
    else:
        keep = np.zeros(len(pl), bool)
    pl, pr0 = np.round(pl[keep]).astype(np.float32), pr0[keep]
    if not len(pl):
        return np.zeros((0, 2)), np.zeros((0, 2))
    lk = {"winSize": (win_px, win_px), "maxLevel": 2,
          "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-4)}
    pr, st, _ = cv2.calcOpticalFlowPyrLK(gl, gr, pl.reshape(-1, 1, 2), pr0.reshape(-1, 1, 2).copy(),
                                         flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    pb, st_b, _ = cv2.calcOpticalFlowPyrLK(gr, gl, pr, pl.reshape(-1, 1, 2).copy(),
                                           flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
    pr, pb = pr.reshape(-1, 2), pb.reshape(-1, 2)
    ok = (st.ravel() == 1) & (st_b.ravel() == 1) & (np.linalg.norm(pb - pl, axis=1) < fb_max_px) & \
         (np.linalg.norm(pr - pr0, axis=1) < 2.0)
    return pl[ok].astype(np.float64), pr[ok].astype(np.float64)


def scene_vertical_disparity(left: np.ndarray, right: np.ndarray, min_points: int = 30) -> SceneVerticalDisparity | None:
    """The vertical disparity of a rectified scene pair from matched points (``None`` below ``min_points``);
    outliers beyond 5 x 1.4826 MAD (at least 0.5 px) from the median are dropped."""
    pl, pr = match_points(left, right)
    if len(pl) < min_points:
        return None
    dv = pl[:, 1] - pr[:, 1]
    med = float(np.median(dv))
    mad = 1.4826 * float(np.median(np.abs(dv - med)))
    ok = np.abs(dv - med) <= max(5 * mad, 0.5)
    if ok.sum() < min_points:
        return None
    pts = np.column_stack([pl[ok], dv[ok]])
    h, w = np.asarray(left).shape[:2]
    return SceneVerticalDisparity(median_px=float(np.median(dv[ok])), by_region_left=_by_region(pts, w, h),
                                  **_stats(dv[ok]))


# ---- console --------------------------------------------------------------------------------
def summary_lines(q: RectificationQuality | None, choice: ZedConfChoice | None = None) -> list[str]:
    """The lines ``gtforge calibrate`` / ``validate`` print about the rectification."""
    lines = []
    if choice is not None:
        line = f"SN.conf read as '{choice.reading}' ({choice.formula}), chosen by {choice.chosen_by}"
        others = [c for c in choice.candidates if c.eligible and c.reading != choice.reading]
        mine = choice.score(choice.reading)
        if mine is not None:
            line += f": {mine.vertical.fit_mean_abs_px:.3f} px on the raw board corners"
            if others:
                line += f" (next: '{others[0].reading}' {others[0].vertical.fit_mean_abs_px:.3f} px)"
        lines.append(line)
    if q is not None:
        o = q.overall
        lines.append(f"ZED vertical disparity on {len(q.poses)} poses: mean {o.fit_mean_abs_px:.3f} px (fitted corners), "
                     f"{o.mean_abs_px:.3f} px (detected; max {o.max_abs_px:.3f} px); threshold {q.threshold_px} px")
    else:
        lines.append("ZED vertical disparity: not measured (no right image with the whole board)")
    return lines
