"""Calibration targets other than the full checkerboard: ChArUco (partial views) and circle grids.

One board definition, ``BoardModel`` (``kind`` + sizes + ArUco dictionary + legacy flag), is given on the
command line or in session.yaml, recorded in the calibration file and turned by ``BoardModel.spec()`` into the
geometry the stages and the generator use (``gtforge.core.targets.board.BoardSpec`` for the checkerboard,
``CharucoSpec``, ``CircleGridSpec`` here; all share ``corners_board()``, ``extent_mm()``, ``albedo()``). Every detection
carries ``ids``: indices into ``corners_board()`` (board order), so a board cut by the image border still gives its
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
from pydantic import Field, model_serializer

from gtforge.core.targets.board import BoardSpec, GridCounts, check_board_spec
from gtforge.core.schema import GTModel
from gtforge.errors import InputError

log = logging.getLogger("gtforge.core.targets.models")

BoardKind = Literal["checkerboard", "charuco", "circles_symmetric", "circles_asymmetric"]
# dictionaries tried when the declared one finds no markers (the error then names what the board carries)
ARUCO_DICTIONARIES = ("DICT_4X4_1000", "DICT_5X5_1000", "DICT_6X6_1000", "DICT_7X7_1000", "DICT_ARUCO_ORIGINAL",
                      "DICT_APRILTAG_36h11", "DICT_APRILTAG_25h9", "DICT_APRILTAG_16h5")
MAX_SQUARE_MM = 1000.0  # the largest square side (circle spacing) a board may declare
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
    # finite (an infinite size reached calibrate's solver, a traceback; import wrote it into session.yaml as null),
    # and under a metre: 1e300 mm overflowed the same solver
    square_size_mm: float = Field(20.0, gt=0, le=MAX_SQUARE_MM, allow_inf_nan=False)
    marker_size_mm: float | None = Field(None, gt=0, allow_inf_nan=False)  # ChArUco: the ArUco marker's side
    dictionary: str | None = None  # ChArUco: OpenCV's predefined dictionary name, e.g. DICT_5X5_100
    legacy_pattern: bool = False  # ChArUco boards made before OpenCV 4.6 with an even row count
    circle_diameter_mm: float | None = Field(None, gt=0, allow_inf_nan=False)  # circle grids (None: half the spacing)

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


def aruco_dictionary(name: str):
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


def check_board_model(board: BoardModel, where: str = "board") -> None:
    """Refuse a declaration no detector can honour (one line, naming the field)."""

    if board.kind == "checkerboard":
        check_board_spec(board.spec(), where)
        return
    if not board.square_size_mm > 0:
        raise InputError(None, f"{where}.square_size_mm", "a positive size (mm)", str(board.square_size_mm),
                         "measure the square side (circle grids: the spacing) on the print (--square-mm)")
    if board.kind == "charuco":
        if board.cols < 3 or board.rows < 3:
            raise InputError(None, f"{where}.cols/rows", "at least 3x3 squares (ChArUco counts squares)",
                             f"{board.cols}x{board.rows}", "count the board's squares, as the generator's settings "
                             "give them (--cols/--rows; docs/capture-layout.md 'Declaring the board')")
        if (board.dictionary is None or not hasattr(cv2.aruco, board.dictionary)
                or not board.dictionary.startswith("DICT_")):
            raise InputError(None, f"{where}.dictionary", "an OpenCV ArUco dictionary name such as DICT_5X5_100",
                             repr(board.dictionary), "the board generator's settings name it (dictionary/--dictionary)")
        if board.marker_size_mm is None or not 0 < board.marker_size_mm < board.square_size_mm:
            raise InputError(None, f"{where}.marker_size_mm", f"a marker side between 0 and the square "
                             f"({board.square_size_mm:g} mm)", repr(board.marker_size_mm), "measure a marker's black "
                             "outline on the print (--marker-mm)")
        n_markers = (board.cols * board.rows) // 2
        size = aruco_dictionary(board.dictionary).bytesList.shape[0]
        if n_markers > size:
            raise InputError(None, f"{where}.dictionary", f"a dictionary with at least {n_markers} markers for a "
                             f"{board.cols}x{board.rows} board", f"{board.dictionary} ({size} markers)",
                             "check cols/rows (ChArUco counts squares) and the dictionary the generator's settings "
                             "name (--dictionary)")
        return
    if board.cols < 3 or board.rows < 3:
        raise InputError(None, f"{where}.cols/rows", "at least 3x3 circles", f"{board.cols}x{board.rows}",
                         "count the circles per row and the rows (--cols/--rows; docs/capture-layout.md "
                         "'Declaring the board')")
    if board.kind == "circles_symmetric" and board.cols == board.rows:
        raise InputError(None, f"{where}.cols/rows", "a symmetric grid with different counts per row and column",
                         f"{board.cols}x{board.rows}", "a square grid looks the same turned by 90 degrees")
    if board.kind == "circles_asymmetric" and board.rows % 2 == 0:
        raise InputError(None, f"{where}.cols/rows", "an asymmetric grid with an odd row count (OpenCV's pattern "
                         "is 4x11)", f"{board.cols}x{board.rows}", "with an even row count it looks the same turned "
                         "by 180 degrees; OpenCV's grid finder then numbers it from either end, or out of order")
    d = board.circle_diameter_mm or 0.5 * board.square_size_mm
    nn = board.square_size_mm * (np.sqrt(2) if board.kind == "circles_asymmetric" else 1.0)
    if not 0 < d < nn:
        raise InputError(None, f"{where}.circle_diameter_mm", f"a diameter below the circles' spacing ({nn:.3g} mm)",
                         f"{d:g}", "measure a circle's diameter on the print (--circle-mm); square_size_mm is the "
                         "spacing of the centres")


# ---- ChArUco ---------------------------------------------------------------------------------
@functools.lru_cache(maxsize=16)
def _cv_charuco(sx: int, sy: int, s: float, m: float, dictionary: str, legacy: bool):
    b = cv2.aruco.CharucoBoard((sx, sy), s, m, aruco_dictionary(dictionary))
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


# ---- detection -------------------------------------------------------------------------------


# ---- generator: boards cut by the image border; light renders for tests ---------------------------


