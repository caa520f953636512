"""Calibration targets other than the full checkerboard: ChArUco (partial views) and circle grids.

One board definition, ``BoardModel`` (``kind`` + sizes + ArUco dictionary + legacy flag), is given on the
command line or in session.yaml, recorded in the calibration file and turned by ``BoardModel.spec()`` into the
geometry the stages and the generator use (``gtforge.synthetic.BoardSpec`` for the checkerboard, ``CharucoSpec``,
``CircleGridSpec`` here; all share ``corners_board()``, ``extent_mm()``, ``albedo()``). Every detection carries
``ids``: indices into ``corners_board()`` (board order), so a board cut by the image border still gives its
visible points, matched between cameras by id.

Point meanings (docs/targets.md): ChArUco corners are the chessboard's inner corners, OpenCV's ids
(``CharucoBoard.getChessboardCorners()``, origin moved to corner 0); circle-grid points are circle centres in
``cv2.findCirclesGrid``'s order.
"""
from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from typing import ClassVar, Literal

import cv2
import numpy as np
from pydantic import model_serializer

from gtforge.core.board import Detection
from gtforge.errors import InputError
from gtforge.io.formats import to_gray
from gtforge.core.schema import GTModel
from gtforge.synthetic import BoardSpec, GridCounts

log = logging.getLogger("gtforge.core.targets")

BoardKind = Literal["checkerboard", "charuco", "circles_symmetric", "circles_asymmetric"]
# dictionaries tried when the declared one finds no markers (the error then names what the board carries)
ARUCO_DICTIONARIES = ("DICT_4X4_1000", "DICT_5X5_1000", "DICT_6X6_1000", "DICT_7X7_1000", "DICT_ARUCO_ORIGINAL",
                      "DICT_APRILTAG_36h11", "DICT_APRILTAG_25h9", "DICT_APRILTAG_16h5")
MIN_COMMON_CORNERS = 6  # a pose needs this many points seen by both cameras (PnP on a plane needs 4; margin)


class BoardModel(GTModel):
    """The calibration target, as declared (CLI ``--board``/``--cols``/... or session.yaml ``board:``).

    ``cols`` x ``rows``: inner corners (checkerboard); **squares** (ChArUco, as OpenCV's ``CharucoBoard`` and board
    generators count them); circles per row x rows (circle grids, ``cv2.findCirclesGrid``'s pattern size).
    ``square_size_mm``: the square side, or the circle spacing (asymmetric grids: OpenCV's spacing, the centre
    of circle ``(row i, col j)`` at ``((2 j + i % 2) s, i s)``)."""

    kind: BoardKind = "checkerboard"
    cols: int = 12
    rows: int = 9
    square_size_mm: float = 20.0
    marker_size_mm: float | None = None  # ChArUco: the ArUco marker's side
    dictionary: str | None = None  # ChArUco: OpenCV's predefined dictionary name, e.g. DICT_5X5_100
    legacy_pattern: bool = False  # ChArUco boards made before OpenCV 4.6 with an even row count
    circle_diameter_mm: float | None = None  # circle grids (None: half the spacing)

    @model_serializer(mode="wrap")
    def _compact(self, handler):
        # a checkerboard record stays what it was before the other targets existed (older files, older readers)
        d = handler(self)
        if self.kind == "checkerboard":
            return {k: d[k] for k in ("cols", "rows", "square_size_mm")}
        return {k: v for k, v in d.items() if v is not None}

    def spec(self):
        if self.kind == "checkerboard":
            return BoardSpec(self.cols, self.rows, self.square_size_mm)
        if self.kind == "charuco":
            return CharucoSpec(self.cols, self.rows, self.square_size_mm,
                               self.marker_size_mm if self.marker_size_mm is not None else 0.75 * self.square_size_mm,
                               self.dictionary or "DICT_5X5_100", self.legacy_pattern)
        return CircleGridSpec(self.cols, self.rows, self.square_size_mm,
                              self.circle_diameter_mm or 0.5 * self.square_size_mm,
                              self.kind == "circles_asymmetric")

    def describe(self) -> str:
        if self.kind == "checkerboard":
            return f"checkerboard {self.cols} x {self.rows} inner corners, {self.square_size_mm:g} mm squares"
        if self.kind == "charuco":
            return (f"ChArUco {self.cols} x {self.rows} squares, {self.square_size_mm:g} mm squares, "
                    f"{self.marker_size_mm:g} mm markers, {self.dictionary}"
                    + (", legacy pattern" if self.legacy_pattern else ""))
        return (f"{'asymmetric' if self.kind == 'circles_asymmetric' else 'symmetric'} circle grid "
                f"{self.cols} x {self.rows}, spacing {self.square_size_mm:g} mm, "
                f"circles {self.circle_diameter_mm or 0.5 * self.square_size_mm:g} mm")


def board_model_of(spec) -> BoardModel:
    """The declaration that gives ``spec`` back (the generator writes it into session.yaml)."""
    if isinstance(spec, CharucoSpec):
        return BoardModel(kind="charuco", cols=spec.squares_x, rows=spec.squares_y, square_size_mm=spec.square_size_mm,
                          marker_size_mm=spec.marker_size_mm, dictionary=spec.dictionary,
                          legacy_pattern=spec.legacy_pattern)
    if isinstance(spec, CircleGridSpec):
        return BoardModel(kind="circles_asymmetric" if spec.asymmetric else "circles_symmetric", cols=spec.cols,
                          rows=spec.rows, square_size_mm=spec.square_size_mm, circle_diameter_mm=spec.diameter_mm)
    return BoardModel(cols=spec.cols, rows=spec.rows, square_size_mm=spec.square_size_mm)


def _dictionary(name: str):
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def check_board_model(board: BoardModel, where: str = "board") -> None:
    """Refuse a declaration no detector can honour (one line, naming the field)."""
    from gtforge.core.board import check_board_spec

    if board.kind == "checkerboard":
        check_board_spec(board.spec(), where)
        return
    if not board.square_size_mm > 0:
        raise InputError(None, f"{where}.square_size_mm", "a positive size (mm)", str(board.square_size_mm))
    if board.kind == "charuco":
        if board.cols < 3 or board.rows < 3:
            raise InputError(None, f"{where}.cols/rows", "at least 3x3 squares (ChArUco counts squares)",
                             f"{board.cols}x{board.rows}")
        if board.dictionary is None or not hasattr(cv2.aruco, board.dictionary) or not board.dictionary.startswith("DICT_"):
            raise InputError(None, f"{where}.dictionary", "an OpenCV ArUco dictionary name such as DICT_5X5_100",
                             repr(board.dictionary), "the board generator's settings name it (dictionary/--dictionary)")
        if board.marker_size_mm is None or not 0 < board.marker_size_mm < board.square_size_mm:
            raise InputError(None, f"{where}.marker_size_mm", f"a marker side between 0 and the square "
                             f"({board.square_size_mm:g} mm)", repr(board.marker_size_mm), "measure a marker's black "
                             "outline on the print (--marker-mm)")
        n_markers = (board.cols * board.rows) // 2
        size = _dictionary(board.dictionary).bytesList.shape[0]
        if n_markers > size:
            raise InputError(None, f"{where}.dictionary", f"a dictionary with at least {n_markers} markers for a "
                             f"{board.cols}x{board.rows} board", f"{board.dictionary} ({size} markers)")
        return
    if board.cols < 3 or board.rows < 3:
        raise InputError(None, f"{where}.cols/rows", "at least 3x3 circles", f"{board.cols}x{board.rows}")
    if board.kind == "circles_symmetric" and board.cols == board.rows:
        raise InputError(None, f"{where}.cols/rows", "a symmetric grid with different counts per row and column",
                         f"{board.cols}x{board.rows}", "a square grid looks the same turned by 90 degrees")
    d = board.circle_diameter_mm or 0.5 * board.square_size_mm
    nn = board.square_size_mm * (np.sqrt(2) if board.kind == "circles_asymmetric" else 1.0)
    if not 0 < d < nn:
        raise InputError(None, f"{where}.circle_diameter_mm", f"a diameter below the circles' spacing ({nn:.3g} mm)",
                         f"{d:g}")


# ---- ChArUco ---------------------------------------------------------------------------------
@functools.lru_cache(maxsize=16)
def _cv_charuco(sx: int, sy: int, s: float, m: float, dictionary: str, legacy: bool):
    b = cv2.aruco.CharucoBoard((sx, sy), s, m, _dictionary(dictionary))
    b.setLegacyPattern(legacy)
    return b


@functools.lru_cache(maxsize=8)
def _charuco_texture(sx: int, sy: int, s: float, m: float, dictionary: str, legacy: bool, px_per_square: int):
    """OpenCV's own drawing of the board, ``px_per_square`` pixels per square, no margin: square edges fall on pixel
    edges, so sampling it by ``floor`` gives the exact chessboard edges (the corners' ground truth)."""
    return _cv_charuco(sx, sy, s, m, dictionary, legacy).generateImage((sx * px_per_square, sy * px_per_square),
                                                                        marginSize=0, borderBits=1)


@dataclass(frozen=True)
class CharucoSpec(GridCounts):
    """ChArUco board: ``squares_x`` x ``squares_y`` squares. Board frame as the checkerboard's: origin at inner
    corner 0 (OpenCV's ChArUco corner id 0), x along the id order, z into the board."""

    squares_x: int
    squares_y: int
    square_size_mm: float
    marker_size_mm: float
    dictionary: str
    legacy_pattern: bool = False
    margin_mm: float = 15.0
    kind: ClassVar[str] = "charuco"
    px_per_square: ClassVar[int] = 120

    @property
    def cols(self) -> int:
        return self.squares_x - 1

    @property
    def rows(self) -> int:
        return self.squares_y - 1

    @property
    def n_markers(self) -> int:
        return (self.squares_x * self.squares_y) // 2

    def cv_board(self):
        return _cv_charuco(self.squares_x, self.squares_y, self.square_size_mm, self.marker_size_mm, self.dictionary,
                           self.legacy_pattern)

    def corners_board(self) -> np.ndarray:
        c = np.asarray(self.cv_board().getChessboardCorners(), np.float64).reshape(-1, 3)
        return c - np.array([self.square_size_mm, self.square_size_mm, 0.0])

    def extent_mm(self) -> tuple[float, float, float, float]:
        s, m = self.square_size_mm, self.margin_mm
        return (-s - m, (self.squares_x - 1) * s + m, -s - m, (self.squares_y - 1) * s + m)

    def albedo(self, xy: np.ndarray) -> np.ndarray:
        tex = _charuco_texture(self.squares_x, self.squares_y, self.square_size_mm, self.marker_size_mm,
                               self.dictionary, self.legacy_pattern, self.px_per_square)
        s = self.square_size_mm
        p = (xy + s) / s * self.px_per_square  # texture pixels, continuous (pixel k covers [k, k+1))
        iu, iv = np.floor(p[:, 0]).astype(np.int64), np.floor(p[:, 1]).astype(np.int64)
        inside = (iu >= 0) & (iu < tex.shape[1]) & (iv >= 0) & (iv < tex.shape[0])
        val = np.full(len(xy), 255, np.uint8)
        val[inside] = tex[iv[inside], iu[inside]]
        return np.where(val > 127, 0.88, 0.08)

    @property
    def diagonal_mm(self) -> float:
        s = self.square_size_mm
        return float(np.hypot((self.cols - 1) * s, (self.rows - 1) * s))


# ---- circle grids ----------------------------------------------------------------------------
@dataclass(frozen=True)
class CircleGridSpec(GridCounts):
    """Dark circles on a white plate, OpenCV's layout and order (``cv2.findCirclesGrid``): ``cols`` circles per
    row, ``rows`` rows; symmetric: centre ``(j s, i s)``; asymmetric: ``((2 j + i % 2) s, i s)``."""

    cols: int
    rows: int
    square_size_mm: float  # the spacing
    diameter_mm: float
    asymmetric: bool = False
    margin_mm: float = 15.0

    @property
    def kind(self) -> str:
        return "circles_asymmetric" if self.asymmetric else "circles_symmetric"

    def corners_board(self) -> np.ndarray:
        i, j = np.mgrid[0:self.rows, 0:self.cols]
        s = self.square_size_mm
        x = (2 * j + (i % 2)) * s if self.asymmetric else j * s
        return np.stack([x.ravel(), (i * s).ravel(), np.zeros(i.size)], axis=1).astype(np.float64)

    def extent_mm(self) -> tuple[float, float, float, float]:
        c = self.corners_board()
        m = self.margin_mm + self.diameter_mm / 2
        return (c[:, 0].min() - m, c[:, 0].max() + m, c[:, 1].min() - m, c[:, 1].max() + m)

    def albedo(self, xy: np.ndarray) -> np.ndarray:
        s = self.square_size_mm
        # nearest centre by rounding to the lattice (asymmetric: the nearer of the two row candidates)
        r = (self.diameter_mm / 2) ** 2
        dark = np.zeros(len(xy), bool)
        iy = np.round(xy[:, 1] / s).astype(np.int64)
        for di in (-1, 0, 1):
            i = iy + di
            ok_i = (i >= 0) & (i < self.rows)
            off = np.where(i % 2 == 1, s, 0.0) if self.asymmetric else 0.0
            step = 2 * s if self.asymmetric else s
            j = np.round((xy[:, 0] - off) / step).astype(np.int64)
            ok = ok_i & (j >= 0) & (j < self.cols)
            cx, cy = j * step + off, i * s
            dark |= ok & ((xy[:, 0] - cx) ** 2 + (xy[:, 1] - cy) ** 2 <= r)
        return np.where(dark, 0.08, 0.88)

    @property
    def diagonal_mm(self) -> float:
        c = self.corners_board()
        return float(np.hypot(np.ptp(c[:, 0]), np.ptp(c[:, 1])))


def neighbour_pairs(spec, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (into ``ids``) of nearest neighbours on the board (square or circle spacing apart)."""
    X = spec.corners_board()[ids, :2]
    d = np.linalg.norm(X[:, None] - X[None], axis=2)
    nn = spec.square_size_mm * (np.sqrt(2) if getattr(spec, "asymmetric", False) else 1.0)
    a, b = np.nonzero(np.triu(np.abs(d - nn) < 1e-6 * nn))
    return a, b


def collinear(X: np.ndarray, min_ratio: float = 0.05) -> bool:
    """Whether board points ``(N, 3)`` lie (nearly) on one line: their second principal extent is below
    ``min_ratio`` of the first (PnP then has no unique solution)."""
    if len(X) < 3:
        return True
    sv = np.linalg.svd(X[:, :2] - X[:, :2].mean(0), compute_uv=False)
    return bool(sv[1] < min_ratio * sv[0])


# ---- blur (edge width) for every target -------------------------------------------------------
def edge_width_px(gray: np.ndarray, pts_uv: np.ndarray, radius_px: float) -> float:
    """Median 10-90 % edge width (px) in patches around ``pts_uv``: contrast over the steepest gradient.
    For a step blurred by a Gaussian of sigma, contrast / max gradient = sigma * sqrt(2 pi) and the 10-90 % width
    is 2.56 sigma, so width = 1.02 * contrast / max gradient (OpenCV's chessboard sharpness measures the same width,
    which only full checkerboards can use)."""
    g = gray.astype(np.float32)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8, cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8
    mag = np.hypot(gx, gy)
    H, W = g.shape
    r = int(max(3, round(radius_px)))
    widths = []
    for u, v in np.round(pts_uv).astype(int):
        if u - r < 0 or v - r < 0 or u + r >= W or v + r >= H:
            continue
        patch, mp = g[v - r:v + r + 1, u - r:u + r + 1], mag[v - r:v + r + 1, u - r:u + r + 1]
        c = np.percentile(patch, 95) - np.percentile(patch, 5)
        gm = np.percentile(mp, 99)
        if gm > 0 and c > 10:
            widths.append(1.02 * c / gm)
    return float(np.median(widths)) if widths else float("nan")


# ---- detection -------------------------------------------------------------------------------
def _undistorted_px(uv: np.ndarray, cam) -> np.ndarray:
    """Pixels with the lens distortion removed (an ideal pinhole with the same K); as given without a camera."""
    if cam is None or not np.any(cam.dist_coeffs):
        return np.asarray(uv, np.float64).reshape(-1, 2)
    xy = cam.undistort_to_normalized(uv)
    return np.stack([xy[:, 0] * cam.fx_px + cam.cx_px, xy[:, 1] * cam.fy_px + cam.cy_px], axis=1)


def _layout_fits(obj_xy: np.ndarray, img_uv: np.ndarray, tol_px: float) -> tuple[float, np.ndarray]:
    """Fraction of points a single homography maps within ``tol_px`` (a planar board: 1.0 when the declared layout
    is right), and the inlier mask."""
    if len(obj_xy) < 8:
        return 1.0, np.ones(len(obj_xy), bool)
    Hm, _ = cv2.findHomography(obj_xy.astype(np.float64), img_uv.astype(np.float64), cv2.RANSAC, tol_px)
    if Hm is None:
        return 0.0, np.zeros(len(obj_xy), bool)
    p = cv2.perspectiveTransform(obj_xy.reshape(-1, 1, 2).astype(np.float64), Hm).reshape(-1, 2)
    inl = np.linalg.norm(p - img_uv, axis=1) < tol_px
    return float(inl.mean()), inl


def _markers(gray: np.ndarray, dictionary: str):
    det = cv2.aruco.ArucoDetector(_dictionary(dictionary), cv2.aruco.DetectorParameters())
    corners, ids, _ = det.detectMarkers(gray)
    if ids is None:
        return [], np.zeros(0, int)
    return corners, ids.ravel().astype(int)


def _family_largest(dictionary: str) -> str:
    for fam in ("4X4", "5X5", "6X6", "7X7"):
        if f"_{fam}_" in dictionary:
            return f"DICT_{fam}_1000"
    return dictionary


def _marker_side_px(corners) -> float:
    return float(np.median([np.linalg.norm(np.diff(np.vstack([c.reshape(4, 2), c.reshape(4, 2)[:1]]), axis=0), axis=1).mean()
                            for c in corners]))


def _charuco_layout_fits(spec: CharucoSpec, corners, ids: np.ndarray, cam) -> float:
    """Fraction of the detected markers' corners where the declared board puts them (one homography)."""
    keep = [k for k, i in enumerate(ids) if i < spec.n_markers]
    if len(keep) < 3:
        return 1.0
    b = spec.cv_board()
    where_id = {int(i): k for k, i in enumerate(np.asarray(b.getIds()).ravel())}
    objp = b.getObjPoints()
    obj = np.concatenate([np.asarray(objp[where_id[int(ids[k])]]).reshape(4, 3) for k in keep])
    img = np.concatenate([np.asarray(corners[k]).reshape(4, 2) for k in keep])
    tol = max(1.0, 0.15 * _marker_side_px([corners[k] for k in keep]))
    frac, _ = _layout_fits(obj[:, :2], _undistorted_px(img, cam), tol)
    return frac


def diagnose_charuco(gray: np.ndarray, spec: CharucoSpec, cam=None, where: str = "board") -> None:
    """Raise ``InputError`` naming what the image shows when it is not the declared ChArUco board: markers of
    another dictionary, ids beyond the board's, a layout that only the other legacy flag or another size fits.
    Returns when the image shows no markers at all (no board) or agrees with the declaration."""
    decl = (f"{spec.squares_x}x{spec.squares_y} {spec.dictionary}"
            + (" legacy" if spec.legacy_pattern else ""))
    corners, ids = _markers(gray, _family_largest(spec.dictionary))
    dict_size = _dictionary(spec.dictionary).bytesList.shape[0]
    if len(ids) < 4:
        best = None
        for name in ARUCO_DICTIONARIES:
            if name == _family_largest(spec.dictionary):
                continue
            c2, i2 = _markers(gray, name)
            if len(i2) >= 4 and (best is None or len(i2) > len(best[1])):
                best = (name, i2)
        if best is not None:
            name, i2 = best
            raise InputError(where, "board.dictionary", f"ChArUco markers of {spec.dictionary}",
                             f"{len(i2)} markers of the {name.removesuffix('_1000').replace('DICT_', '')} family "
                             f"(ids up to {i2.max()}) and {len(ids)} of {spec.dictionary}'s",
                             f"a {name.removesuffix('_1000')}_{_dict_size_for(int(i2.max()))} dictionary? "
                             "(--dictionary / session.yaml board.dictionary)")
        return
    def beyond(limit: int) -> bool:
        # one misread marker (a larger dictionary has more codes to misread into) is no evidence; several are
        n = int((ids >= limit).sum())
        return n >= 2 and n >= 0.1 * len(ids)

    if not beyond(spec.n_markers):
        ids_ok = ids < spec.n_markers
        corners, ids = [c for c, k in zip(corners, ids_ok) if k], ids[ids_ok]
    if len(ids) and beyond(dict_size):
        fam = spec.dictionary.rsplit("_", 1)[0]
        raise InputError(where, "board.dictionary", f"marker ids below {dict_size} ({spec.dictionary})",
                         f"ids up to {ids.max()}", f"saw ids up to {ids.max()}: a {fam}_{_dict_size_for(int(ids.max()))} "
                         "dictionary, or a larger board?")
    if len(ids) and beyond(spec.n_markers):
        sx, sy = spec.squares_x + 1, spec.squares_y + 1
        counted_corners = ((sx * sy) // 2 > ids.max())  # the usual slip: inner corners declared, not squares
        raise InputError(where, "board.cols/rows", f"marker ids 0-{spec.n_markers - 1} (a {decl} board has "
                         f"{spec.n_markers} markers)", f"ids up to {ids.max()}",
                         f"saw ids up to {ids.max()}: " + (
                             f"ChArUco counts squares; {spec.squares_x}x{spec.squares_y} inner corners is --cols {sx} "
                             f"--rows {sy}?" if counted_corners else
                             f"a larger board (at least {ids.max() + 1} markers, e.g. "
                             f"{_size_for(int(ids.max()) + 1)} squares)?"))
    # a few misread markers (small or blurred ones) are normal and dropped later, corner by corner; a layout
    # mismatch leaves most markers unexplained
    if len(ids) < 6 or _charuco_layout_fits(spec, corners, ids, cam) >= 0.6:
        return
    # the ids belong to the board but sit elsewhere: the legacy flag, or another size with as many markers
    alt = CharucoSpec(spec.squares_x, spec.squares_y, spec.square_size_mm, spec.marker_size_mm, spec.dictionary,
                      not spec.legacy_pattern)
    if _charuco_layout_fits(alt, corners, ids, cam) >= 0.9:
        raise InputError(where, "board.legacy_pattern", f"the marker layout of a {decl} board",
                         f"the layout of the {'non-legacy' if spec.legacy_pattern else 'legacy'} pattern "
                         f"(legacy_pattern: {str(not spec.legacy_pattern).lower()})",
                         "boards made before OpenCV 4.6 with an even row count use the legacy pattern "
                         f"({'--no-legacy-pattern' if spec.legacy_pattern else '--legacy-pattern'})")
    for sx in range(3, 21):
        for sy in range(3, 21):
            if (sx, sy) == (spec.squares_x, spec.squares_y) or (sx * sy) // 2 <= ids.max():
                continue
            for legacy in (False, True):
                cand = CharucoSpec(sx, sy, spec.square_size_mm, spec.marker_size_mm, spec.dictionary, legacy)
                if _charuco_layout_fits(cand, corners, ids, cam) >= 0.95:
                    raise InputError(where, "board.cols/rows", f"the marker layout of a {decl} board",
                                     f"the layout of a {sx}x{sy}{' legacy' if legacy else ''} board",
                                     f"declare --cols {sx} --rows {sy} (ChArUco counts squares)")
    raise InputError(where, "board", f"the marker layout of a {decl} board", "markers that no single plane "
                     "of that layout explains", "check the board's size (ChArUco counts squares) and legacy flag")


def _dict_size_for(max_id: int) -> int:
    return next(n for n in (50, 100, 250, 1000) if n > max_id)


def _size_for(n_markers: int) -> str:
    """The smallest near-square board (squares, 3 <= rows <= cols <= 2 rows) with at least ``n_markers`` markers."""
    best = min(((sx * sy, sx - sy, sx, sy) for sy in range(3, 60) for sx in range(sy, 2 * sy + 1)
                if (sx * sy) // 2 >= n_markers))
    return f"{best[2]}x{best[3]}"


def _subpix_window(corners_uv: np.ndarray, ids: np.ndarray, spec) -> int:
    """cornerSubPix half-window from the local square size in pixels (as gtforge.core.board: 0.3 of a square, 2-15)."""
    a, b = neighbour_pairs(spec, ids)
    if len(a) == 0:
        return 5
    sq_px = float(np.median(np.linalg.norm(corners_uv[a] - corners_uv[b], axis=1)))
    return int(max(2, min(15, round(sq_px * 0.3))))


def refine_charuco_corners(gray: np.ndarray, uv: np.ndarray, ids: np.ndarray, spec: CharucoSpec, iters: int = 6,
                           blur_margin_px: float = 2.0, min_square_px: float = 16.0,
                           max_move_px: float = 0.5) -> np.ndarray:
    """Sub-pixel ChArUco corners: the cornerSubPix equations (every window pixel's gradient is orthogonal to the
    pixel's offset from the corner, Foerstner) over a window of 0.45 squares with the markers masked out. A plain
    ``cornerSubPix`` window either stays inside the white gap between corner and markers (a few pixels: noisy) or
    takes in marker edges, whose gradients pull the corner (measured on the generator: 0.09-0.14 px mean error,
    against 0.03-0.07 px for the checkerboard). The mask comes from each corner's local square axes (its
    neighbours by id): window pixels whose board position falls inside a marker square's inner part (the marker,
    grown by ``blur_margin_px``) are left out; the edges along the square sides stay."""
    g = gray.astype(np.float32)
    gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3) / 8
    H, W = g.shape
    s = spec.square_size_mm
    gap = 0.5 * (s - spec.marker_size_mm)
    pos = {int(i): k for k, i in enumerate(ids)}
    cols = spec.cols
    out = uv.astype(np.float64).copy()
    for k, cid in enumerate(ids):
        r, c = divmod(int(cid), cols)
        axes = []
        for dr, dc in ((0, 1), (1, 0)):
            fwd, bwd = pos.get((r + dr) * cols + c + dc) if c + dc < cols and r + dr < spec.rows else None, \
                pos.get((r - dr) * cols + c - dc) if c - dc >= 0 and r - dr >= 0 else None
            if fwd is not None and bwd is not None:
                axes.append((uv[fwd] - uv[bwd]) / 2)
            elif fwd is not None:
                axes.append(uv[fwd] - uv[k])
            elif bwd is not None:
                axes.append(uv[k] - uv[bwd])
            else:
                axes.append(None)
        if axes[0] is None or axes[1] is None:
            continue  # no local axes: keep OpenCV's corner
        A = np.column_stack(axes)  # px per square along board x, y
        try:
            Ainv = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            continue
        sq_px = float(np.sqrt(abs(np.linalg.det(A))))
        if min(np.linalg.norm(A[:, 0]), np.linalg.norm(A[:, 1])) < min_square_px:
            continue  # too few pixels between corner and markers for the masked window: keep OpenCV's corner
        R = 0.45 * sq_px
        mg = blur_margin_px / min(np.linalg.norm(A[:, 0]), np.linalg.norm(A[:, 1])) * s  # mm, the shorter axis
        p = out[k].copy()
        for _ in range(iters):
            u0, v0 = int(round(p[0])), int(round(p[1]))
            ri = int(np.ceil(R))
            if u0 - ri < 1 or v0 - ri < 1 or u0 + ri >= W - 1 or v0 + ri >= H - 1:
                break
            yy, xx = np.mgrid[v0 - ri:v0 + ri + 1, u0 - ri:u0 + ri + 1]
            d = np.stack([xx - p[0], yy - p[1]], axis=-1).reshape(-1, 2)
            b = (d @ Ainv.T) * s  # board mm offsets from the corner
            lx, ly = np.mod(b[:, 0], s), np.mod(b[:, 1], s)
            in_marker = (lx > gap - mg) & (lx < s - gap + mg) & (ly > gap - mg) & (ly < s - gap + mg)
            r2 = (d ** 2).sum(1)
            w = np.exp(-r2 / (2 * (0.5 * R) ** 2)) * (r2 <= R * R) * ~in_marker
            ggx = gx[v0 - ri:v0 + ri + 1, u0 - ri:u0 + ri + 1].ravel()
            ggy = gy[v0 - ri:v0 + ri + 1, u0 - ri:u0 + ri + 1].ravel()
            q = np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float64)
            a11, a12, a22 = (w * ggx * ggx).sum(), (w * ggx * ggy).sum(), (w * ggy * ggy).sum()
            M = np.array([[a11, a12], [a12, a22]])
            bb = np.array([(w * (ggx * ggx * q[:, 0] + ggx * ggy * q[:, 1])).sum(),
                           (w * (ggx * ggy * q[:, 0] + ggy * ggy * q[:, 1])).sum()])
            if np.linalg.cond(M) > 1e6:
                break
            p_new = np.linalg.solve(M, bb)
            if np.linalg.norm(p_new - uv[k]) > max_move_px:
                p = uv[k]
                break  # ran off (weak edges): OpenCV's corner is within a few tenths of a pixel, keep it
            done = np.linalg.norm(p_new - p) < 1e-3
            p = p_new
            if done:
                break
        out[k] = p
    return out


def detect_charuco(image: np.ndarray, spec: CharucoSpec, cam=None, where: str = "board",
                   min_corners: int = 4) -> Detection | None:
    """ChArUco corners ``(N, 2)`` with their ids (sorted), or None. OpenCV's ``CharucoDetector`` (markers, then
    corners interpolated from them), then ``cornerSubPix`` with the checkerboard's window rule; corners whose
    window would leave the image are dropped (the window is needed whole); corners a homography of the declared
    layout does not explain are dropped (never a wrong id). A declaration the image contradicts raises
    ``InputError`` (``diagnose_charuco``)."""
    gray = to_gray(image)
    diagnose_charuco(gray, spec, cam, where)
    det = cv2.aruco.CharucoDetector(spec.cv_board())
    ch_corners, ch_ids, m_corners, m_ids = det.detectBoard(gray)
    if ch_ids is None or len(ch_ids) < min_corners:
        return None
    ids = ch_ids.ravel().astype(int)
    uv = ch_corners.reshape(-1, 2).astype(np.float32)
    win = _subpix_window(uv, ids, spec)
    # the markers come within (square - marker) / 2 of every corner: a window reaching their edges would pull the
    # corner towards them, so the window stays inside that gap
    gap_px = 0.5 * (spec.square_size_mm - spec.marker_size_mm) / spec.square_size_mm * (2 * win / 0.6)
    sq_win = win
    win = int(max(2, min(win, np.floor(0.9 * gap_px))))
    H, W = gray.shape
    inside = (uv[:, 0] >= win + 1) & (uv[:, 1] >= win + 1) & (uv[:, 0] <= W - win - 2) & (uv[:, 1] <= H - win - 2)
    uv, ids = uv[inside], ids[inside]
    if len(ids) < min_corners:
        return None
    uv = refine_charuco_corners(gray, uv.astype(np.float64), ids, spec)
    X = spec.corners_board()
    sq_px = 2 * sq_win / 0.6
    _, inl = _layout_fits(X[ids, :2], _undistorted_px(uv, cam), max(1.0, 0.1 * sq_px))
    if (~inl).any():
        log.info("%s: %d ChArUco corner(s) off the declared layout dropped", where, int((~inl).sum()))
    uv, ids = uv[inl], ids[inl]
    order = np.argsort(ids)
    uv, ids = uv[order], ids[order]
    if len(ids) < min_corners:
        return None
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
    mask = np.zeros(gray.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(hull).astype(np.int32)], 1)
    vals = gray[mask > 0]
    contrast = float(np.percentile(vals, 90) - np.percentile(vals, 10)) if vals.size else 0.0
    sharp = edge_width_px(gray, uv, 0.35 * sq_px)
    return Detection(uv, sharp, "charuco", contrast, ids)


def _blob_detectors(gray: np.ndarray, spec: CircleGridSpec):
    """OpenCV's blob detector as findCirclesGrid uses it by default (large circles allowed), then a lenient one for
    small circles (more clutter passes: tried second)."""
    p = cv2.SimpleBlobDetector_Params()
    p.maxArea = max(p.maxArea, float(gray.size) / max(spec.n_corners, 1))
    yield cv2.SimpleBlobDetector_create(p)
    p.minArea = 8  # small circles (distant board, small images)
    p.minThreshold, p.thresholdStep = 30, 5
    yield cv2.SimpleBlobDetector_create(p)
    # circles seen up to ~70 degrees off-axis stay convex ellipses with an axis ratio above 0.3; wood grain and
    # other clutter blobs mostly do not
    p.minArea = 8
    p.filterByCircularity = True
    p.minCircularity = 0.5
    p.minConvexity = 0.85
    p.minInertiaRatio = 0.3
    yield cv2.SimpleBlobDetector_create(p)


def refine_circle_centres(gray: np.ndarray, uv: np.ndarray, radius_px: np.ndarray, iters: int = 3) -> np.ndarray:
    """Darkness-weighted centroids (the centroid of the dark disk's area, blur-invariant for a symmetric blur)
    in windows of 1.5 radii, re-centred ``iters`` times; the weight is the darkness below the local white level,
    clipped at 0 and with the noise floor's 10 % removed so the white around the circle weighs nothing."""
    g = gray.astype(np.float64)
    H, W = g.shape
    out = uv.astype(np.float64).copy()
    for k in range(len(out)):
        R = max(3.0, 1.5 * radius_px[k])
        for _ in range(iters):
            u0, v0 = out[k]
            x0, x1 = int(max(0, np.floor(u0 - R))), int(min(W - 1, np.ceil(u0 + R)))
            y0, y1 = int(max(0, np.floor(v0 - R))), int(min(H - 1, np.ceil(v0 + R)))
            patch = g[y0:y1 + 1, x0:x1 + 1]
            yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
            inwin = (xx - u0) ** 2 + (yy - v0) ** 2 <= R * R
            white, black = np.percentile(patch[inwin], 95), np.percentile(patch[inwin], 2)
            if white - black < 10:
                break
            w = np.clip((white - patch) / (white - black) - 0.1, 0, None) * inwin
            s = w.sum()
            if s <= 0:
                break
            out[k] = [(w * xx).sum() / s, (w * yy).sum() / s]
    return out


def _plate_only(gray: np.ndarray) -> np.ndarray:
    """The image with everything outside the largest bright region (the plate, circles included) set to white:
    dark clutter around the plate (table grain, cables) then makes no blobs for the grid finder."""
    _, bw = cv2.threshold(gray, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(bw)
    if n < 2:
        return gray
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    cnts, _ = cv2.findContours((lab == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    mask = np.zeros(gray.shape, np.uint8)
    cv2.drawContours(mask, cnts, -1, 1, thickness=-1)
    out = gray.copy()
    out[mask == 0] = 255
    return out


def _grid_continues(gray: np.ndarray, spec: CircleGridSpec, uv: np.ndarray, r_px: float) -> str | None:
    """The side ("left", "right", "top", "bottom" in grid terms) beyond which the image shows more circles of the
    grid, or None. ``findCirclesGrid`` happily returns a smaller grid inside a larger one (a 6x5 in a 7x5), which
    would number the circles differently in the two cameras: the positions one spacing beyond each edge (a homography
    of the declared layout) are checked for a dark disk inside a white ring, as the grid's own circles look."""
    X = spec.corners_board()[:, :2]
    Hm, _ = cv2.findHomography(X, uv, 0)
    if Hm is None:
        return None
    g = cv2.GaussianBlur(gray, (0, 0), max(0.5, r_px / 4)).astype(np.float32)

    def sample(p):
        return cv2.remap(g, p[:, 0].astype(np.float32).reshape(-1, 1), p[:, 1].astype(np.float32).reshape(-1, 1),
                         cv2.INTER_LINEAR, borderValue=-1).ravel()

    dark = float(np.median(sample(uv)))
    t = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ring = np.stack([np.cos(t), np.sin(t)], 1) * 1.6 * r_px
    white = float(np.median(sample((uv[:, None, :] + ring[None]).reshape(-1, 2))))
    if white - dark < 30:
        return None
    mid = 0.5 * (white + dark)
    s = spec.square_size_mm
    i_all, j_all = np.mgrid[0:spec.rows, 0:spec.cols]

    def pos(i, j):
        x = (2 * j + (i % 2)) * s if spec.asymmetric else j * s
        return np.stack([x, i * s], 1).astype(np.float64)

    sides = {"left": pos(np.arange(spec.rows), np.full(spec.rows, -1)),
             "right": pos(np.arange(spec.rows), np.full(spec.rows, spec.cols)),
             "top": pos(np.full(spec.cols, -2 if spec.asymmetric else -1), np.arange(spec.cols)),
             "bottom": pos(np.full(spec.cols, spec.rows + (1 if spec.asymmetric else 0)), np.arange(spec.cols))}
    for side, xy in sides.items():
        p = cv2.perspectiveTransform(xy.reshape(-1, 1, 2), Hm).reshape(-1, 2)
        c = sample(p)
        rg = sample((p[:, None, :] + ring[None]).reshape(-1, 2)).reshape(len(p), -1)
        # as dark as the grid's circles, inside a ring that is white all round (the plate), not table or border
        circles = (c >= 0) & (c < dark + 0.3 * (white - dark)) & ((rg > mid).sum(1) >= len(t) - 1)
        if circles.sum() >= max(2, len(p) // 2):
            return side
    return None


def detect_circles(image: np.ndarray, spec: CircleGridSpec, cam=None, where: str = "board") -> Detection | None:
    """Circle centres in ``cv2.findCirclesGrid``'s order (ids 0..N-1; the whole grid is needed), refined by
    ``refine_circle_centres``. The perspective bias of a circle's centre is removed later, once the pose is known
    (``circle_centre_bias``)."""
    gray = to_gray(image)
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if spec.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    ok = False
    for img in (gray, _plate_only(gray)):
        for blob in _blob_detectors(img, spec):
            for fl in (flags, flags | cv2.CALIB_CB_CLUSTERING):
                ok, c = cv2.findCirclesGrid(img, spec.pattern_size, flags=fl, blobDetector=blob)
                if ok:
                    break
            if ok:
                break
        if ok:
            break
    if not ok:
        return None
    uv = c.reshape(-1, 2).astype(np.float64)
    ids = np.arange(spec.n_corners)
    a, b = neighbour_pairs(spec, ids)
    nn_px = np.linalg.norm(uv[a] - uv[b], axis=1)
    # per-circle radius from its own neighbour spacing (perspective changes it across the board)
    sp = np.zeros(len(uv))
    cnt = np.zeros(len(uv))
    np.add.at(sp, a, nn_px)
    np.add.at(sp, b, nn_px)
    np.add.at(cnt, a, 1)
    np.add.at(cnt, b, 1)
    nn_mm = spec.square_size_mm * (np.sqrt(2) if spec.asymmetric else 1.0)
    r_px = sp / np.maximum(cnt, 1) * (spec.diameter_mm / 2) / nn_mm
    side = _grid_continues(gray, spec, uv, float(np.median(r_px)))
    if side is not None:
        raise InputError(where, "board.cols/rows", f"a {spec.cols}x{spec.rows} circle grid",
                         f"more circles beyond its {side} edge", "a larger grid: count the circles per row (--cols) "
                         "and the rows (--rows) on the plate")
    uv = refine_circle_centres(gray, uv, r_px)
    H, W = gray.shape
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
    mask = np.zeros(gray.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(hull).astype(np.int32)], 1)
    vals = gray[mask > 0]
    contrast = float(np.percentile(vals, 95) - np.percentile(vals, 5)) if vals.size else 0.0
    sharp = edge_width_px(gray, uv, 1.3 * float(np.median(r_px)))
    return Detection(uv, sharp, "circles", contrast, ids)


def circle_centre_bias(spec: CircleGridSpec, T_cam_from_board: np.ndarray, cam, n: int = 72) -> np.ndarray:
    """``(N, 2)`` px: where each circle's image centroid (what the detector measures) lies minus where its centre
    projects. A circle seen obliquely projects to an ellipse whose centre is not the centre's image (it is pushed
    away from the vanishing line; up to tenths of a pixel for large circles at 30-45 degrees). Computed from the
    projected outline (lens distortion included): the area centroid of the projected polygon."""
    from gtforge.core.geometry import transform_points

    X = spec.corners_board()
    r = spec.diameter_mm / 2
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([r * np.cos(t), r * np.sin(t), np.zeros(n)], axis=1)
    pts = (X[:, None, :] + ring[None]).reshape(-1, 3)
    uv = cam.project(transform_points(T_cam_from_board, pts)).reshape(len(X), n, 2)
    x, y = uv[..., 0], uv[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cr = x * y1 - x1 * y
    A = cr.sum(1) / 2
    cx = ((x + x1) * cr).sum(1) / (6 * A)
    cy = ((y + y1) * cr).sum(1) / (6 * A)
    centre = cam.project(transform_points(T_cam_from_board, X))
    return np.stack([cx, cy], axis=1) - centre


def detect_target(image: np.ndarray, spec, cam=None, where: str = "board") -> Detection | None:
    """Any target's points with ids (indices into ``spec.corners_board()``)."""
    from gtforge.core.board import detect_corners

    if isinstance(spec, CharucoSpec):
        return detect_charuco(image, spec, cam, where)
    if isinstance(spec, CircleGridSpec):
        return detect_circles(image, spec, cam, where)
    d = detect_corners(image, spec)
    if d is not None and d.ids is None:
        d.ids = np.arange(spec.n_corners)
    return d


def _pnp_bias_corrected(spec, det: Detection, cam, solve_pnp) -> tuple[np.ndarray, np.ndarray]:
    """PnP from a detection; for circles, the centroids are corrected for the perspective bias at the PnP pose and
    solved again (the bias changes by far less than itself between the two poses). Returns (T, uv used)."""
    X = spec.corners_board()[det.ids]
    T = solve_pnp(X, det.corners_uv, cam)
    uv = det.corners_uv
    if isinstance(spec, CircleGridSpec):
        for _ in range(2):
            uv = det.corners_uv - circle_centre_bias(spec, T, cam)[det.ids]
            T = solve_pnp(X, uv, cam)
    return T, uv


def _unmirror(spec: CircleGridSpec, det: Detection, cam, solve_pnp) -> Detection:
    """A symmetric grid's numbering may come back mirrored (rows counted from the other side): PnP then puts the
    board's z axis (into the board) towards the camera, a board seen from behind. Count the rows the other way."""
    X = spec.corners_board()
    T = solve_pnp(X, det.corners_uv, cam)
    if T[:3, 2] @ T[:3, 3] >= 0:
        return det
    uv = det.corners_uv.reshape(spec.rows, spec.cols, 2)[::-1].reshape(-1, 2).copy()
    return Detection(uv, det.sharpness_px, det.method, det.pattern_contrast, det.ids)


def detect_pose_target(name: str, texture, depth_mm, zed_left, mech, zed, spec, blur_px: float,
                       min_common: int = MIN_COMMON_CORNERS):
    """``gtforge.calibrate.detect_pose`` for ChArUco and circle grids: points matched by id between the two
    cameras; a pose with fewer than ``min_common`` common points, or collinear ones, is skipped with the reason.
    Each camera's board pose (PnP) uses all its own points; the extrinsic only the common ones."""
    from gtforge.calibrate import PoseObs, PoseReport, solve_pnp

    dm = detect_target(texture, spec, mech, where=f"{name}: structured-light image")
    dz = detect_target(zed_left, spec, zed.left, where=f"{name}: ZED-left image")
    if dm is None or dz is None:
        which = " and ".join(w for w, d in (("structured-light", dm), ("ZED", dz)) if d is None)
        log.warning("capture %s: board not found in the %s image; skipped", name, which)
        return None, PoseReport(capture=name, status="skipped", reason=f"board not found in the {which} image")
    X = spec.corners_board()
    counts = dict(n_points_mech=len(dm.ids), n_points_zed=len(dz.ids))
    for d, cam, cname in ((dm, mech, "structured-light"), (dz, zed.left, "ZED")):
        if len(d.ids) < min_common or collinear(X[d.ids]):
            why = (f"only {len(d.ids)} board points in the {cname} image (need {min_common})" if len(d.ids) < min_common
                   else f"the board points in the {cname} image lie on one line")
            log.warning("capture %s: %s; skipped", name, why)
            return None, PoseReport(capture=name, status="skipped", reason=why, **counts)
    if isinstance(spec, CircleGridSpec) and not spec.asymmetric:
        dm, dz = _unmirror(spec, dm, mech, solve_pnp), _unmirror(spec, dz, zed.left, solve_pnp)
    T_mb, uv_m_all = _pnp_bias_corrected(spec, dm, mech, solve_pnp)
    T_zb, uv_z_all = _pnp_bias_corrected(spec, dz, zed.left, solve_pnp)
    if isinstance(spec, CircleGridSpec) and not spec.asymmetric:
        # a symmetric grid has a 180-degree ambiguity: each camera may have numbered it from the other end. The
        # cameras look the same way (their relative rotation about the view axis is far below 90 degrees), so the
        # board's x axis points the same way in both; flip the ZED's numbering when it does not
        if T_mb[:3, 0] @ T_zb[:3, 0] < 0:
            dz = Detection(dz.corners_uv[::-1].copy(), dz.sharpness_px, dz.method, dz.pattern_contrast, dz.ids)
            T_zb, uv_z_all = _pnp_bias_corrected(spec, dz, zed.left, solve_pnp)
    common, im, iz = np.intersect1d(dm.ids, dz.ids, return_indices=True)
    counts["n_points_common"] = len(common)
    if len(common) < min_common:
        why = f"only {len(common)} board points seen by both cameras (need {min_common})"
        log.warning("capture %s: %s; skipped", name, why)
        return None, PoseReport(capture=name, status="skipped", reason=why, **counts)
    if collinear(X[common]):
        why = "the board points both cameras see lie on one line"
        log.warning("capture %s: %s; skipped", name, why)
        return None, PoseReport(capture=name, status="skipped", reason=why, **counts)
    blurred = bool(dm.sharpness_px > blur_px or dz.sharpness_px > blur_px)
    if blurred:
        log.warning("capture %s: blurred board (edge width %.1f / %.1f px)", name, dm.sharpness_px, dz.sharpness_px)

    def fin(x: float) -> float | None:
        return float(x) if np.isfinite(x) else None

    rep = PoseReport(capture=name, status="used", sharpness_mech_px=fin(dm.sharpness_px),
                     sharpness_zed_px=fin(dz.sharpness_px), blurred=blurred, **counts)
    obs = PoseObs(name, uv_m_all[im], uv_z_all[iz], T_mb, T_zb, depth_mm, dm, dz, ids=common)
    return obs, rep


def matched_points(name: str, texture, zed_left, mech, zed_cam, spec,
                   min_common: int = MIN_COMMON_CORNERS) -> tuple[Detection, Detection, np.ndarray] | str:
    """For validate: the two cameras' points of one pose restricted to the ids both saw, as detections (ids sorted,
    circle centres corrected for the perspective bias, a symmetric grid numbered alike), plus the ids; or the
    reason the pose cannot be used."""
    from gtforge.core.camera import RectifiedStereo

    zed = RectifiedStereo(left=zed_cam, baseline_mm=1.0)
    o, rep = detect_pose_target(name, texture, None, zed_left, mech, zed, spec, float("inf"), min_common)
    if o is None:
        return rep.reason
    dm = Detection(o.mech_uv, o.det_mech.sharpness_px, o.det_mech.method, o.det_mech.pattern_contrast, o.ids)
    dz = Detection(o.zed_uv, o.det_zed.sharpness_px, o.det_zed.method, o.det_zed.pattern_contrast, o.ids)
    return dm, dz, o.ids


# ---- generator: boards cut by the image border; light renders for tests ---------------------------
def random_partial_board_pose(rng: np.random.Generator, rig, board, corner: int, camera: str = "mech",
                              min_common: int = 12, tries: int = 3000) -> np.ndarray:
    """``T_world_from_board`` with the board cut by ``camera``'s image border ("mech" or "zed") near image corner
    ``corner`` (0 top-left, 1 top-right, 2 bottom-right, 3 bottom-left): some of its points outside that image, at
    least ``min_common`` inside both the texture and the ZED-left image (3 px from the border), the board above the
    table and seen at most 60 degrees off-axis. These are the poses a full-board rule loses."""
    from gtforge.core.geometry import invert_T, make_T, transform_points

    cam, T_cam_from_world = (rig.mech, rig.T_mech_from_world) if camera == "mech" else (rig.zed.left, rig.T_zed_from_world)
    X = board.corners_board()
    ex = board.extent_mm()
    outline = np.array([[ex[0], ex[2], 0], [ex[1], ex[2], 0], [ex[0], ex[3], 0], [ex[1], ex[3], 0]])
    centre_b = np.array([(ex[0] + ex[1]) / 2, (ex[2] + ex[3]) / 2, 0])
    fu, fv = [(0, 0), (1, 0), (1, 1), (0, 1)][corner]
    z_table = float(T_cam_from_world[2, 3])  # about the camera's distance to the table
    views = [(rig.mech, rig.T_mech_from_world), (rig.zed.left, rig.T_zed_from_world)]
    for _ in range(tries):
        a, b = rng.uniform(0.02, 0.2, size=2)
        u = (1 - a if fu else a) * cam.width_px
        v = (1 - b if fv else b) * cam.height_px
        xy = cam.undistort_to_normalized(np.array([[u, v]]))[0]
        if not np.all(np.isfinite(xy)):
            continue
        p_cam = np.array([xy[0], xy[1], 1.0]) * rng.uniform(0.55, 0.85) * z_table
        tilt = rng.uniform(-35, 35, size=2)
        R = cv2.Rodrigues(np.radians([tilt[0], tilt[1], 0.0]))[0] @ cv2.Rodrigues(np.radians([0, 0, rng.uniform(-30, 30)]))[0]
        T_cam_from_board = make_T(R, np.zeros(3))
        T_cam_from_board[:3, 3] = p_cam - R @ centre_b
        T = invert_T(T_cam_from_world) @ T_cam_from_board
        if (transform_points(T, outline)[:, 2] < 5).any():
            continue  # under the table
        inside_all, ok = [], True
        for c, Tcw in views:
            pc = transform_points(Tcw @ T, X)
            n_cam = (Tcw @ T)[:3, 2]
            m = pc.mean(0)
            if np.any(pc[:, 2] <= 0) or n_cam @ (m / np.linalg.norm(m)) < np.cos(np.radians(60)):
                ok = False
                break
            uv = c.project(pc)
            inside_all.append((uv[:, 0] >= 3) & (uv[:, 1] >= 3) & (uv[:, 0] <= c.width_px - 4) & (uv[:, 1] <= c.height_px - 4))
        if not ok:
            continue
        own = inside_all[0] if camera == "mech" else inside_all[1]
        both = inside_all[0] & inside_all[1]
        if own.all() or both.sum() < min_common or collinear(X[both]):
            continue
        return T
    raise RuntimeError(f"could not place a board cut by the {camera} image's corner {corner}")


@dataclass
class BoardViews:
    """What calibrate needs from one board capture (no right image), with the exact truth."""

    name: str
    mech_texture: np.ndarray
    mech_depth_mm: np.ndarray
    zed_left: np.ndarray
    T_mech_from_board: np.ndarray
    corners_mech_uv: np.ndarray
    corners_zed_uv: np.ndarray


def _render_cropped(scene, cam, T_cam_from_world: np.ndarray, T_world_from_board: np.ndarray, board,
                    supersample: int, background: float = 0.3) -> np.ndarray:
    """Linear RGB of ``scene`` rendered only inside the board's bounding box (a camera with the same lens and a
    shifted principal point sees exactly the same rays there); elsewhere a flat ``background``."""
    from gtforge.core.geometry import transform_points
    from gtforge.synthetic import render_image

    ex = board.extent_mm()
    t = np.linspace(0, 1, 24)
    edge = np.concatenate([np.stack([ex[0] + t * (ex[1] - ex[0]), np.full_like(t, y)], 1) for y in ex[2:]]
                          + [np.stack([np.full_like(t, x), ex[2] + t * (ex[3] - ex[2])], 1) for x in ex[:2]])
    pc = transform_points(T_cam_from_world @ T_world_from_board, np.column_stack([edge, np.zeros(len(edge))]))
    out = np.full((cam.height_px, cam.width_px, 3), background)
    pc = pc[pc[:, 2] > 0]
    if len(pc) == 0:
        return out
    uv = cam.project(pc)
    u0, v0 = (np.floor(uv.min(0)) - 6).astype(int)
    u1, v1 = (np.ceil(uv.max(0)) + 6).astype(int)
    u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, cam.width_px - 1), min(v1, cam.height_px - 1)
    if u1 <= u0 or v1 <= v0:
        return out
    crop = cam.model_copy(update=dict(width_px=int(u1 - u0 + 1), height_px=int(v1 - v0 + 1),
                                      cx_px=cam.cx_px - u0, cy_px=cam.cy_px - v0))
    out[v0:v1 + 1, u0:u1 + 1] = render_image(scene, crop, T_cam_from_world, supersample)
    return out


def render_board_views(name: str, rig, board, T_world_from_board: np.ndarray, rng: np.random.Generator, seed: int,
                       supersample: int = 2, image_noise: float = 1.0, blur_sigma_px: float = 0.6) -> BoardViews:
    """The texture, the depth (exact, projector shadows ignored: a flat board casts none on itself) and the
    rectified ZED-left image of one board pose, rendered inside the board's bounding box only (the table around it
    is flat grey): ``gtforge.synthetic.board_capture`` without the right image and the stereo truth, several
    times faster, for tests that only calibrate."""
    from gtforge.core.geometry import transform_points
    from gtforge.synthetic import OBJ_BOARD, PlaneObject, Scene, _table, finish_image, raycast_depth

    scene = Scene([_table(seed), PlaneObject(OBJ_BOARD, T_world_from_board, board.albedo, board.extent_mm())])
    tex = finish_image(_render_cropped(scene, rig.mech, rig.T_mech_from_world, T_world_from_board, board, supersample),
                       rng, blur_sigma_px, image_noise, gray=True)
    left = finish_image(_render_cropped(scene, rig.zed.left, rig.T_zed_from_world, T_world_from_board, board,
                                        supersample), rng, blur_sigma_px, image_noise)
    z, _, _ = raycast_depth(scene, rig.depth_camera, rig.T_depth_from_world)
    depth = np.where(np.isfinite(z), z, np.nan).astype(np.float32)
    T_mb = rig.T_mech_from_world @ T_world_from_board
    X = board.corners_board()
    return BoardViews(name, tex, depth, left, T_mb, rig.mech.project(transform_points(T_mb, X)),
                      rig.zed.left.project(transform_points(rig.T_zed_from_world @ T_world_from_board, X)))
