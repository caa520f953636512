"""How well the ZED pair is rectified, and which SN.conf reading the images support.

**Vertical disparity** is ``v_left - v_right`` (px) of one scene point in the two rectified images; a
perfectly rectified pair has 0 everywhere. On board captures the points are the board's points (checkerboard
or ChArUco corners, circle centres: any target of ``gtforge.core.targets.models``), detected in both images and matched
by id (a ChArUco board cut by the border gives the corners both images show). Circle centres are corrected for
their perspective bias in each image at that image's own PnP pose first (``matched_board_points``). Two figures
per set of points:

* from the detected corners as they are (``mean_abs_px``, ``max_abs_px``...): includes corner-detector
  noise (a few hundredths of a pixel per image);
* from a homography fitted per pose to each image's corners (``fit_*``): a rectified camera sees the
  planar board through an exact homography, so the fit averages the detector noise out and leaves the
  rectification's own error. Decisions (the SN.conf reading, the warning threshold) use this one.

**SN.conf reading** (``gtforge.io.cameras.ZED_CONF_READINGS``, docs/conventions.md): with raw images and
an SN.conf, the board points are detected once per raw image (and matched by id; circle centres corrected at
each raw image's PnP pose, lens included); each candidate reading is evaluated by mapping those raw points
through its rectification (lens model inverted, ``R1``/``R2`` applied, projected with ``P1``/``P2``: the
same mapping ``cv2.undistortPoints(R=, P=)`` performs, with the inverse solved to 1e-9 px by
``gtforge.core.lens``) and the reading with the smallest vertical disparity is kept. A reading whose rectified
right camera sits at ``-x`` contradicts the images (their disparities are positive) and is not eligible.

Scenes have no board: ``scene_vertical_disparity`` measures the same quantity on SIFT matches refined by
pyramidal Lucas-Kanade tracking (forward-backward checked).
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import cv2
import numpy as np
from pydantic import Field, PrivateAttr

from gtforge.core.targets.board import BoardSpec, Detection
from gtforge.core.camera import PinholeCamera
from gtforge.core.alignment.photometric import to_gray
from gtforge.core.schema import GTModel
from gtforge.core.targets.detection import PairSkipped, TargetPair, detect_target, match_target_views
from gtforge.core.targets.models import MIN_COMMON_CORNERS

if TYPE_CHECKING:
    pass

log = logging.getLogger("gtforge.core.zed.rectification")

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


def board_pose_vertical_disparity(capture: str, left_uv: np.ndarray, right_uv: np.ndarray, board: BoardSpec,
                                  ids: np.ndarray | None = None) -> tuple[PoseVerticalDisparity, np.ndarray]:
    """One pose: the board's points ``(N, 2)`` in the rectified left and right images, ``ids`` (indices into
    ``board.corners_board()``; ``None``: every point, in board order) the same for both.

    Returns the figures and the ``(N, 3)`` points ``(u_left, v_left, v_left - v_right)``."""
    left_uv = np.asarray(left_uv, np.float64).reshape(-1, 2)
    right_uv = np.asarray(right_uv, np.float64).reshape(-1, 2)
    n = board.n_corners if ids is None else len(ids)
    if left_uv.shape != right_uv.shape or len(left_uv) != n or n < 4:
        raise ValueError(f"{left_uv.shape=} and {right_uv.shape=} but expected ({n}, 2) each, at least 4 points")
    X = board.corners_board() if ids is None else board.corners_board()[ids]
    Xb = X[:, :2].reshape(-1, 1, 2)
    fitted = []
    for uv in (left_uv, right_uv):
        H, _ = cv2.findHomography(Xb, uv.reshape(-1, 1, 2), 0)
        fitted.append(cv2.perspectiveTransform(Xb, H).reshape(-1, 2))
    dv = left_uv[:, 1] - right_uv[:, 1]
    dv_fit = fitted[0][:, 1] - fitted[1][:, 1]
    pv = PoseVerticalDisparity(capture=capture, disparity_median_px=float(np.median(left_uv[:, 0] - right_uv[:, 0])),
                               **_stats(dv, dv_fit))
    return pv, np.column_stack([left_uv, dv])


def matched_board_points(spec, left: Detection, left_cam: PinholeCamera, right: Detection, right_cam: PinholeCamera,
                         min_common: int = MIN_COMMON_CORNERS) -> TargetPair | PairSkipped:
    """A pose's left and right detections (any target) matched by id for the vertical disparity.

    Circle centres: the centroid of a circle's image is not the image of its centre (``circle_centre_bias``). The two
    cameras see each circle from 63 mm apart, so the bias is mostly, not wholly, common to both (measured on the
    generator at 0.3x: biases up to 0.11 px per image differ between left and right by up to 0.0002 px vertically and
    0.011 px horizontally). Each image's centroids are corrected at that image's own PnP pose (its camera:
    ``left_cam``/``right_cam``, lens included for raw images) before left and right are compared. A symmetric circle
    grid's right numbering is turned to the left one's (``gtforge.core.targets.detection.match_target_views``)."""
    return match_target_views(spec, left, left_cam, right, right_cam, ("left", "right"), min_common)


class RectificationMeter:
    """Collects the board points of both rectified images pose by pose; ``result()`` summarises.

    Any target (``gtforge.core.targets.models``): the left and right points are matched by id; a pose with fewer than 6
    common points (``MIN_COMMON_CORNERS``) or collinear ones is skipped with the reason; circle centres are
    corrected for their perspective bias in each image (``matched_board_points``). ``add`` detects the board in the
    right image (and in the left one unless its detection or points are given). ``zed_right``: the rectified right
    camera (``RectifiedStereo.right``), for the right image's PnP (circle-centre bias, a symmetric grid's numbering);
    default ``zed_left``, which differs only by ``doffs_px``."""

    def __init__(self, board: BoardSpec, zed_left: PinholeCamera, rectified_by: str,
                 threshold_px: float = VERTICAL_WARN_PX, zed_right: PinholeCamera | None = None):
        self.board, self.cam, self.rectified_by, self.threshold_px = board, zed_left, rectified_by, threshold_px
        self.cam_right = zed_right if zed_right is not None else zed_left
        self.poses: list[PoseVerticalDisparity] = []
        self.points: list[np.ndarray] = []
        self.skipped: dict[str, str] = {}

    def add(self, capture: str, right_image: np.ndarray | None, left_uv: np.ndarray | None = None,
            left_image: np.ndarray | None = None,
            left_detection: Detection | None = None) -> PoseVerticalDisparity | None:
        """``left_detection``: the left image's detection (with ids; calibrate's); ``left_uv``: every board point in
        board order (a whole board); else ``left_image`` is searched."""
        if right_image is None:
            self.skipped[capture] = "no right image"
            return None
        if left_detection is None and left_uv is not None:
            left_uv = np.asarray(left_uv, np.float64).reshape(-1, 2)
            if len(left_uv) != self.board.n_corners:
                raise ValueError(f"{left_uv.shape=} but expected ({self.board.n_corners}, 2): give left_detection "
                                 "for a partial view")
            left_detection = Detection(left_uv, float("nan"), "given", 0.0, np.arange(len(left_uv)))
        if left_detection is None:
            if left_image is None:
                raise ValueError("give left_detection, left_uv or left_image")
            left_detection = detect_target(left_image, self.board, self.cam, where=f"{capture}: ZED-left image")
            if left_detection is None:
                self.skipped[capture] = "board not found in the left image"
                return None
        det_r = detect_target(right_image, self.board, self.cam_right, where=f"{capture}: ZED-right image")
        if det_r is None:
            self.skipped[capture] = "board not found in the right image"
            log.warning("capture %s: board not found in the rectified right image; its vertical disparity is "
                        "not measured", capture)
            return None
        pair = matched_board_points(self.board, left_detection, self.cam, det_r, self.cam_right)
        if isinstance(pair, PairSkipped):
            self.skipped[capture] = pair.reason
            log.warning("capture %s: %s; its vertical disparity is not measured", capture, pair.reason)
            return None
        pv, pts = board_pose_vertical_disparity(capture, pair.uv_a, pair.uv_b, self.board, pair.ids)
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
                            f"the board corners (threshold {self.threshold_px} px): stereo matching and the "
                            f"ground truth "
                            f"suffer; check the ZED calibration (the images were rectified {self.rectified_by})")
            log.warning(warnings[-1])
        q = RectificationQuality(rectified_by=self.rectified_by, overall=overall,
                                 poses=sorted(self.poses, key=lambda p: -(p.fit_mean_abs_px or 0.0)),
                                 by_region_left=_by_region(pts, self.cam.width_px, self.cam.height_px),
                                 skipped=dict(self.skipped), threshold_px=self.threshold_px, warnings=warnings)
        q._points = pts
        return q


# ---- SN.conf readings -----------------------------------------------------------------------
def rectify_points(cam: PinholeCamera, uv_raw: np.ndarray, R_rect_from_raw: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Raw (distorted) pixels ``(N, 2)`` -> rectified pixels ``(N, 2)`` (``cv2.undistortPoints(R=, P=)``)."""
    xy = cam.undistort_to_normalized(uv_raw)
    rays = np.column_stack([xy, np.ones(len(xy))]) @ np.asarray(R_rect_from_raw).T
    p = rays @ np.asarray(P)[:, :3].T
    return p[:, :2] / p[:, 2:3]


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


def scene_vertical_disparity(left: np.ndarray, right: np.ndarray,
                             min_points: int = 30) -> SceneVerticalDisparity | None:
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
