"""Checkerboard detection with an orientation fixed by the board pattern itself.

The board convention is in ``gtforge.core.targets.board.BoardSpec``: the square diagonally inside corner 0
(board x, y in [0, s]) is black. With ``cols + rows`` odd (12x9 is), a 180-degree turn makes it
white, so the corner order is the same in every camera whatever the viewpoint.
"""
from __future__ import annotations

import copy
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from gtforge.core.camera import PinholeCamera
from gtforge.core.geometry import make_T
from gtforge.core.alignment.photometric import to_gray
from gtforge.errors import InputError
from gtforge.infra.digest import blake3_hex


@dataclass
class Detection:
    corners_uv: np.ndarray  # (N, 2) float64, board order
    sharpness_px: float  # mean edge width (OpenCV estimateChessboardSharpness); larger = blurrier
    method: str  # "sb" or "classic"
    pattern_contrast: float  # mean |intensity difference| between dark and white squares
    # indices into the board's corners_board() (gtforge.core.targets.models); None: all, in order
    ids: np.ndarray | None = None


def check_board_spec(board: BoardSpec, where: str = "board") -> None:
    if board.cols < 3 or board.rows < 3:
        raise InputError(None, where, "at least 3x3 inner corners", f"{board.cols}x{board.rows}",
                         "count the inner corners (where 4 squares meet), not the squares: session.yaml's "
                         "board or --cols/--rows (docs/capture-layout.md 'Declaring the board')")
    if (board.cols + board.rows) % 2 == 0:
        raise InputError(None, where, "inner-corner counts with an odd sum (e.g. 12x9)",
                         f"{board.cols}x{board.rows}",
                         "a board with an even sum looks the same turned by 180 degrees, so corner order "
                         "cannot be made consistent between cameras")
    if not board.square_size_mm > 0:
        raise InputError(None, "square_size_mm", "a positive square size (mm)", str(board.square_size_mm),
                         "measure a square's side on the print and set square_size_mm (--square-mm)")


def _square_centres(c: np.ndarray, board: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    g = c.reshape(board.rows, board.cols, 2)
    centres = 0.25 * (g[:-1, :-1] + g[:-1, 1:] + g[1:, :-1] + g[1:, 1:])
    j, i = np.mgrid[0:board.rows - 1, 0:board.cols - 1]
    dark = ((i + j) % 2) == 0
    return centres.reshape(-1, 2), dark.ravel()


def orient_corners(gray: np.ndarray, corners_uv: np.ndarray, board: BoardSpec) -> tuple[np.ndarray, float]:
    """Return the corners in board order (reversed if the board was seen turned by 180 degrees)."""
    blur = cv2.blur(gray.astype(np.float32), (3, 3))
    centres, dark = _square_centres(corners_uv, board)
    vals = cv2.remap(blur, centres[:, 0].astype(np.float32).reshape(-1, 1),
                     centres[:, 1].astype(np.float32).reshape(-1, 1), cv2.INTER_LINEAR).ravel()
    contrast = float(vals[~dark].mean() - vals[dark].mean())
    if contrast < 0:
        return corners_uv[::-1].copy(), -contrast
    return corners_uv, contrast


def _find(gray: np.ndarray, ps: tuple[int, int], max_side_px: int) -> tuple[np.ndarray | None, str]:
    """Coarse corners: SB on a copy scaled to ``max_side_px`` (fast), then SB exhaustive at full size,
    then classic detection. Sub-pixel accuracy comes from the full-resolution refinement after this."""
    scale = min(1.0, max_side_px / max(gray.shape))
    if scale < 1.0:
        small = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        ok, c = cv2.findChessboardCornersSB(small, ps, flags=cv2.CALIB_CB_NORMALIZE_IMAGE)
        if ok:
            return (c.reshape(-1, 2) + 0.5) / scale - 0.5, "sb-coarse"  # pixel centres at integers
    ok, c = cv2.findChessboardCornersSB(gray, ps, flags=cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE
                                        | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if ok:
        return c.reshape(-1, 2), "sb"
    ok, c = cv2.findChessboardCorners(gray, ps, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    return (c.reshape(-1, 2), "classic") if ok else (None, "")


# ---- detections remembered by image content -------------------------------------------------------------------------
# The calibration stages detect the board in the same images again: validate in the ZED-left image twice (its pose
# and its rectification check), and `gtforge run` (one process) calibrate, validate and calibrate-scale in the same
# texture and ZED-left images. A detection is a pure function of the image's pixels and the settings, so it is
# remembered by the BLAKE3 of the pixels (about 2 ms for a 2K image, against 0.1-0.5 s for a detection) and handed
# out as a copy: the same result as detecting again. The stages also fill it ahead, a capture per thread
# (gtforge.infra.threads), and read it in order.
DETECTION_CACHE_SIZE = 512  # detections kept (a few kB each), the least recently used dropped first
_detections: OrderedDict[tuple, Detection | None] = OrderedDict()
_detections_lock = threading.Lock()


def remembered_detection(kind: str, image: np.ndarray, settings: tuple,
                         detect: Callable[[], Detection | None]) -> Detection | None:
    """``detect()``, or a copy of what it returned for the same ``kind``, pixels and ``settings`` before. A detection
    that raises is not remembered."""
    a = np.ascontiguousarray(image)
    key = (kind, blake3_hex(a.data.cast("B")), a.shape, a.dtype.str, settings)
    with _detections_lock:
        if key in _detections:
            _detections.move_to_end(key)
            return copy.deepcopy(_detections[key])
    det = detect()
    with _detections_lock:
        _detections[key] = copy.deepcopy(det)
        while len(_detections) > DETECTION_CACHE_SIZE:
            _detections.popitem(last=False)
    return det


def forget_detections() -> None:
    """Empty the remembered detections (tests and benchmarks time detection itself)."""
    with _detections_lock:
        _detections.clear()


def detect_corners(image: np.ndarray, board: BoardSpec, min_contrast: float = 20.0,
                   max_side_px: int = 1100) -> Detection | None:
    """Find the board's inner corners (``(N, 2)`` ``(u, v)``, board order) or ``None``.

    ``findChessboardCornersSB`` (on a reduced copy first for speed; then with the accuracy and exhaustive
    flags at full size), falling back to classic detection; always refined at full resolution by
    ``cornerSubPix`` with a window scaled to the square size (measured: mean error 0.03-0.07 px on the
    synthetic generator versus 0.06-0.1 px for SB's accuracy mode alone). Remembered by the image's pixels
    (``remembered_detection``).
    """
    return remembered_detection("checkerboard", image, (repr(board), float(min_contrast), int(max_side_px)),
                                lambda: _detect_corners(image, board, min_contrast, max_side_px))


def _detect_corners(image: np.ndarray, board: BoardSpec, min_contrast: float, max_side_px: int) -> Detection | None:
    gray = to_gray(image)
    ps = board.pattern_size
    c, method = _find(gray, ps, max_side_px)
    if c is None:
        return None
    c = c.reshape(-1, 2).astype(np.float32)
    sq_px = float(np.median(np.linalg.norm(np.diff(c.reshape(board.rows, board.cols, 2), axis=1), axis=2)))
    win = int(max(2, min(15, round(sq_px * 0.3))))
    c = cv2.cornerSubPix(gray, c.reshape(-1, 1, 2).copy(), (win, win), (-1, -1),
                         (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 200, 1e-5)).reshape(-1, 2)
    corners, contrast = orient_corners(gray, c.astype(np.float64), board)
    if contrast < min_contrast:
        return None
    try:
        sharp = cv2.estimateChessboardSharpness(gray, ps, corners.reshape(-1, 1, 2).astype(np.float32))
        sharpness = float(sharp[0][0])
        if sharpness >= 9999.0:  # OpenCV's "could not measure" value
            sharpness = float("nan")
    except cv2.error:
        sharpness = float("nan")
    return Detection(corners, sharpness, method, contrast)


class GridCounts:
    """``pattern_size`` and ``n_corners`` of a target whose points form ``cols`` x ``rows`` (every target kind)."""

    cols: int
    rows: int

    @property
    def pattern_size(self) -> tuple[int, int]:
        return (self.cols, self.rows)

    @property
    def n_corners(self) -> int:
        return self.cols * self.rows



@dataclass(frozen=True)
class BoardSpec(GridCounts):
    """Checkerboard: ``cols`` x ``rows`` inner corners, ``square_size_mm``.

    Board frame: origin at inner corner 0, x along a corner row, y down the columns, z into the board.
    The square diagonally outside corner 0 (board x, y in [-s, 0]) is **black**; with an odd
    ``cols + rows`` the opposite outer square is white, which fixes the 180-degree ambiguity.
    """

    cols: int = 12
    rows: int = 9
    square_size_mm: float = 20.0
    margin_mm: float = 15.0

    def corners_board(self) -> np.ndarray:
        """``(N, 3)`` inner corners in the board frame, OpenCV order (x fastest)."""
        j, i = np.mgrid[0:self.rows, 0:self.cols]
        s = self.square_size_mm
        return np.stack([i.ravel() * s, j.ravel() * s, np.zeros(i.size)], axis=1).astype(np.float64)

    def extent_mm(self) -> tuple[float, float, float, float]:
        s, m = self.square_size_mm, self.margin_mm
        return (-s - m, self.cols * s + m, -s - m, self.rows * s + m)

    def albedo(self, xy: np.ndarray) -> np.ndarray:
        s = self.square_size_mm
        ix = np.floor(xy[:, 0] / s)
        iy = np.floor(xy[:, 1] / s)
        inside = (ix >= -1) & (ix <= self.cols - 1) & (iy >= -1) & (iy <= self.rows - 1)
        dark = inside & (((ix + iy) % 2) == 0)
        return np.where(dark, 0.08, 0.88)

    @property
    def diagonal_mm(self) -> float:
        s = self.square_size_mm
        return float(np.hypot((self.cols - 1) * s, (self.rows - 1) * s))


@dataclass
class PoseObs:
    name: str
    mech_uv: np.ndarray  # (N, 2) detected in the structured-light texture (distorted pixels)
    zed_uv: np.ndarray  # (N, 2) detected in the rectified ZED left image
    T_mech_from_board: np.ndarray
    T_zed_from_board: np.ndarray
    depth_mm: np.ndarray | None = None
    det_mech: Detection | None = None
    det_zed: Detection | None = None
    ids: np.ndarray | None = None  # board-point ids of mech_uv/zed_uv rows (ChArUco, circles); None: all, in order

    def board_points(self, board) -> np.ndarray:
        """``(N, 3)`` board-frame points of this pose's ``mech_uv``/``zed_uv`` rows."""
        X = board.corners_board()
        return X if self.ids is None else X[self.ids]



def solve_pnp(obj_pts: np.ndarray, uv: np.ndarray, cam: PinholeCamera) -> np.ndarray:
    """``T_cam_from_obj`` from 3D-2D correspondences (IPPE for planar sets, then LM refinement)."""
    obj = np.ascontiguousarray(obj_pts, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(uv, np.float64).reshape(-1, 1, 2)
    planar = np.ptp(obj[:, 0, 2]) < 1e-9
    flag = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_EPNP
    ok, rvec, tvec = cv2.solvePnP(obj, img, cam.K, cam.dist, flags=flag)
    if not ok:
        raise RuntimeError("solvePnP failed")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, cam.K, cam.dist, rvec, tvec,
                                      (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-12))
    return make_T(cv2.Rodrigues(rvec)[0], tvec.ravel())
