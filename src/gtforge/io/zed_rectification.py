"""How a session's ZED images are rectified, decided from the captures themselves: which reading of a factory
``SN<serial>.conf`` (``gtforge.io.cameras.ZED_CONF_READINGS``) the board corners or feature matches support, and the
right camera's self-rectification (``gtforge.core.zed.selfcal`` fits it; this module collects the matches over a
session's captures). calibrate runs both and stores the result; every later stage reads the captures with it."""
from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from gtforge.core.targets.board import BoardSpec
from gtforge.core.zed.rectification import (
    TIE_PX,
    VERTICAL_WARN_PX,
    VerticalDisparity,
    _stats,
    board_pose_vertical_disparity,
    match_points,
    matched_board_points,
    rectify_points,
)
from gtforge.core.schema import GTModel
from gtforge.core.zed.selfcal import Matches, SelfRectifyParams, ZedSelfRectification, fit_self_rectification
from gtforge.core.targets.detection import PairSkipped, detect_target
from gtforge.errors import InputError
from gtforge.infra.threads import ordered_map
from gtforge.io.cameras import (
    DEFAULT_ZED_CONF_READING,
    ZED_CONF_READINGS,
    ZedFactoryCalibration,
    check_zed_conf_reading,
    describe_zed_conf_reading,
)
from gtforge.io.captures import Session, evenly_spread, leave_out_hint, missing_capture_file, open_session

log = logging.getLogger("gtforge.io.zed_rectification")


def rectified_by(session: Session) -> str:
    """Who rectified the ZED images a session's captures load as, worded to follow "rectified" / "rectified:"
    ("before gtforge, e.g. by the ZED SDK" or "by gtforge, from SN123.conf read as ...")."""
    rect = getattr(session, "rectification", None)
    corrected = "" if getattr(rect, "correction", None) is None else \
        ", the right camera corrected by gtforge's self-rectification"
    if getattr(rect, "right_yaw_deg", 0.0):
        corrected += f", the right camera's yaw ({rect.right_yaw_deg:+.4f} deg, calibrate-scale) undone"
    if rect is not None and getattr(rect, "factory", None) is not None:
        return (f"by gtforge, from {rect.factory.path.name} read as '{rect.reading}': "
                f"{describe_zed_conf_reading(rect.reading)}{corrected}")
    return "before gtforge, e.g. by the ZED SDK" + corrected



@dataclass
class RawBoardPair:
    """The board's points detected in one raw (unrectified) left/right pair, matched by id (circle centres
    corrected for their perspective bias in each raw image); also carries raw feature matches (``ids`` None)."""

    capture: str
    left_uv: np.ndarray  # (N, 2) raw left pixels
    right_uv: np.ndarray  # (N, 2) raw right pixels
    ids: np.ndarray | None = None  # indices into the board's corners_board(); None: every point, board order



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
    """Every reading's vertical disparity on the raw board points (best eligible first), and each reading's
    ``(N,)`` per-point ``v_left - v_right`` (for comparing two readings' rectifications)."""
    if not pairs:
        raise ValueError("no raw board pairs to score the readings on")
    scores, per_corner = [], {}
    for reading in readings:
        sr = factory.stereo_rectify(reading)
        dvs, fits, disp = [], [], []
        for p in pairs:
            ul = rectify_points(factory.left, p.left_uv, sr.R_rect_from_raw_left, sr.P_left)
            ur = rectify_points(factory.right, p.right_uv, sr.R_rect_from_raw_right, sr.P_right)
            pv, _ = board_pose_vertical_disparity(p.capture, ul, ur, board, p.ids)
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
        warn = ("no board capture shows the board in both raw ZED images: the SN.conf reading could not be "
                f"checked; '{reading}' is used" + ("" if override else " (the default)"))
        log.warning(warn)
        return ZedConfChoice(conf_file=conf, resolution=factory.resolution, reading=reading,
                             formula=describe_zed_conf_reading(reading),
                             chosen_by="session.yaml" if override else "default", threshold_px=threshold_px,
                             captures=[], candidates=[], warnings=[warn])
    scores, per_corner = score_readings(factory, pairs, board)
    eligible = [s for s in scores if s.eligible]
    disp = np.median([board_pose_vertical_disparity(p.capture, p.left_uv, p.right_uv, board, p.ids)[0]
                      .disparity_median_px for p in pairs])
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
    """Without a board seen in both raw images: every reading scored on feature matches between the raw left
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

    def one(d: Path) -> RawBoardPair | None:
        cap = raw.load_capture(d, need_right=True)
        if cap.zed_right is None:
            return None
        pl, pr = match_points(cap.zed_left, cap.zed_right, rectified=False)
        return RawBoardPair(d.name, pl, pr)

    out = []
    for k, (d, pair) in enumerate(zip(dirs, ordered_map(one, dirs))):  # the captures on threads, in order
        if progress:
            progress(f"raw ZED matches {d.name} ({k + 1}/{len(dirs)})")
        if pair is not None:
            out.append(pair)
    return out



def _default_reading() -> str:
    return DEFAULT_ZED_CONF_READING



def detect_raw_pairs(session: Session, dirs: list[Path], board: BoardSpec,
                     progress: Callable[[str], None] | None = None) -> tuple[list[RawBoardPair], dict[str, str]]:
    """The board's points in the raw left and right images of each capture in ``dirs`` (detected once), matched by
    id: any target of ``gtforge.core.targets.models`` (``gtforge.core.zed.rectification.matched_board_points``: circle
    centres corrected at each raw image's PnP pose with the conf's lens models, which no reading changes; a symmetric
    grid numbered alike). A capture whose board is not found, or that gives fewer than 6 common points or collinear
    ones, is left out with the reason."""
    factory = getattr(getattr(session, "rectification", None), "factory", None)
    if factory is None:
        raise ValueError("detect_raw_pairs needs a session with raw ZED images and an SN.conf")
    raw = dataclasses.replace(session, rectification=None)

    def detect(d: Path):
        cap = raw.load_capture(d, need_right=True)
        dl = detect_target(cap.zed_left, board, factory.left, where=f"{d.name}: raw ZED-left image")
        dr = detect_target(cap.zed_right, board, factory.right, where=f"{d.name}: raw ZED-right image") \
            if dl is not None and cap.zed_right is not None else None
        return dl, dr

    pairs, skipped = [], {}
    for k, (d, (dl, dr)) in enumerate(zip(dirs, ordered_map(detect, dirs))):  # the captures on threads, in order
        if progress:
            progress(f"raw ZED corners {d.name} ({k + 1}/{len(dirs)})")
        if dl is None or dr is None:
            skipped[d.name] = f"board not found in the raw {'left' if dl is None else 'right'} ZED image"
            continue
        pair = matched_board_points(board, dl, factory.left, dr, factory.right)
        if isinstance(pair, PairSkipped):
            skipped[d.name] = f"raw ZED images: {pair.reason}"
            continue
        pairs.append(RawBoardPair(d.name, pair.uv_a, pair.uv_b, pair.ids))
    return pairs, skipped



def settle_zed_conf_reading(session: Session, dirs: list[Path], board: BoardSpec,
                            threshold_px: float = VERTICAL_WARN_PX,
                            progress: Callable[[str], None] | None = None) -> tuple[Session, ZedConfChoice | None]:
    """For raw ZED images + SN.conf: choose the reading from the board captures in ``dirs`` (any target; or take
    session.yaml's ``zed_conf_reading``, still scored) and return the session re-opened with it.
    Other sessions come back unchanged, with ``None``."""

    rect = getattr(session, "rectification", None)
    if rect is None or getattr(rect, "factory", None) is None:
        return session, None
    pairs, _ = detect_raw_pairs(session, dirs, board, progress)
    override = getattr(session.config, "zed_conf_reading", None)
    choice = None
    if not pairs and override is None:
        # no board usable in both raw images: the readings are decided on feature matches, scenes included
        scene_root = session.root / session.config.scenes_dir
        scenes = session.capture_dirs("scenes") if scene_root.is_dir() and any(scene_root.iterdir()) else []
        choice = choose_reading_by_matches(rect.factory, raw_matches(session, list(dirs) + scenes, progress),
                                           threshold_px)
    if choice is None:
        choice = choose_reading(rect.factory, pairs, board, override, threshold_px)
    if choice.reading != rect.reading:
        session = open_session(session.root, zed_conf_reading=choice.reading)
    return session, choice


def collect_matches(session: Session, dirs: Sequence[Path], max_features: int = 8000,
                    progress: Callable[[str], None] | None = None) -> tuple[list[Matches], dict[str, str]]:
    """Feature matches between the left and right images of each capture, as the session rectifies them (the captures
    on ``gtforge.infra.threads.ordered_map``'s threads: the same matches as one after the other)."""

    def one(d: Path) -> tuple[Matches | None, str | None]:
        try:
            cap = session.load_capture(d, need_right=True)
        except InputError as exc:  # a capture's file missing: no matches from it (calibrate skips it); wrong: stop
            if missing_capture_file(exc):
                return None, f"file missing: {exc}"
            if d.parent.name == session.config.board_dir:  # (calibrate --captures leaves a board capture out)
                raise leave_out_hint(exc, d.name) from None
            raise
        if cap.zed_right is None:
            return None, "no right image"
        pl, pr = match_points(cap.zed_left, cap.zed_right, max_features=max_features)
        if not len(pl):
            return None, "no left-right match (too little texture?)"
        # named with its folder: boards and scenes are matched together and both number from 000
        return Matches(f"{d.parent.name}/{d.name}", pl, pr), None

    out, skipped = [], {}
    for k, (d, (m, why)) in enumerate(zip(dirs, ordered_map(one, dirs))):
        if progress:
            progress(f"left-right matches {d.parent.name}/{d.name} ({k + 1}/{len(dirs)})")
        if m is None:
            skipped[f"{d.parent.name}/{d.name}"] = why
        else:
            out.append(m)
    return out, skipped


def self_rectify(session: Session, dirs: Sequence[Path], params: SelfRectifyParams | None = None,
                 progress: Callable[[str], None] | None = None) -> ZedSelfRectification:
    """Match left and right in the captures of ``dirs`` (boards and scenes alike) as ``session`` rectifies them, fit
    the right camera's correction and decide whether it is applied (module docstring). Every board capture is
    matched, and at most ``params.max_scenes`` scene captures (``evenly_spread`` over their order in ``dirs``)."""

    params = params or SelfRectifyParams()
    scene_root = (session.root / session.config.scenes_dir).resolve()
    in_scenes = [Path(d).parent.resolve() == scene_root for d in dirs]
    scenes = evenly_spread([d for d, s in zip(dirs, in_scenes) if s], params.max_scenes)
    chosen = set(scenes)
    matched = [d for d, s in zip(dirs, in_scenes) if not s or d in chosen]
    matches, skipped = collect_matches(session, matched, params.max_features, progress)
    res = fit_self_rectification(matches, session.zed, params, rectified_by(session), skipped)
    res.scenes_not_matched = sum(in_scenes) - len(scenes)
    (log.info if res.status == "applied" else log.warning if res.status == "not determined" else log.info)(
        res.summary_line())
    return res
