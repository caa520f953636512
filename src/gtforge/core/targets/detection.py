"""Finding ChArUco and circle-grid targets (``gtforge.core.targets.models``) in an image: markers and interpolated
corners refined to sub-pixel, circle centres with their perspective bias corrected, the pose from them, and one-line
reasons when a target is not found (a wrong dictionary, a board too small for its markers, a grid cut by the border).

Over 500 lines on purpose: both targets' detectors share the sub-pixel refinement, the layout checks and the
diagnosis of a target that is not found."""
from __future__ import annotations

import logging
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from gtforge.core.targets.board import Detection, detect_corners, remembered_detection, solve_pnp
from gtforge.core.geometry import transform_points
from gtforge.core.alignment.photometric import to_gray
from gtforge.core.targets.models import (
    ARUCO_DICTIONARIES,
    MIN_COMMON_CORNERS,
    CharucoSpec,
    CircleGridSpec,
    aruco_dictionary,
    collinear,
    neighbour_pairs,
)
from gtforge.errors import InputError
from gtforge.infra.digest import blake3_hex
from gtforge.infra.threads import ordered_map

log = logging.getLogger("gtforge.core.targets.models")


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
    det = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), cv2.aruco.DetectorParameters())
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
    return float(np.median([np.linalg.norm(np.diff(np.vstack([c.reshape(4, 2), c.reshape(4, 2)[:1]]), axis=0),
                                           axis=1).mean()
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
    dict_size = aruco_dictionary(spec.dictionary).bytesList.shape[0]
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
                         f"ids up to {ids.max()}",
                         f"saw ids up to {ids.max()}: a {fam}_{_dict_size_for(int(ids.max()))} "
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
    """cornerSubPix half-window from the local square size in pixels (as gtforge.core.targets.board: 0.3 of a square,
    2-15)."""
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



def _disk_window(g: np.ndarray, u0: float, v0: float, R: float):
    """The pixels of ``g`` within ``R`` of ``(u0, v0)``: ``(patch, xx, yy, inwin)`` over the bounding box cut to the
    image, ``inwin`` the disk's mask in it."""
    H, W = g.shape
    x0, x1 = int(max(0, np.floor(u0 - R))), int(min(W - 1, np.ceil(u0 + R)))
    y0, y1 = int(max(0, np.floor(v0 - R))), int(min(H - 1, np.ceil(v0 + R)))
    yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    return g[y0:y1 + 1, x0:x1 + 1], xx, yy, (xx - u0) ** 2 + (yy - v0) ** 2 <= R * R


def circle_radii_px(gray: np.ndarray, uv: np.ndarray, spacing_px: np.ndarray) -> np.ndarray:
    """Each circle's own radius (px) as the image shows it: the pixels darker than half way between the circle's
    darkest and the white around it, connected to its centre, inside half its spacing to its neighbours, taken as
    a disk's area (a symmetric blur moves the half-way contour little). NaN where that window shows no contrast.
    Needed where a circle is larger than the declared diameter: a marker dot twice the others' size (ROS-Industrial's
    modified circle grid), or a diameter declared too small."""
    g = gray.astype(np.float64)
    out = np.full(len(uv), np.nan)
    for k, ((u0, v0), s) in enumerate(zip(uv, spacing_px)):
        patch, xx, yy, inwin = _disk_window(g, u0, v0, max(3.0, 0.5 * s))
        x0, y0 = xx[0, 0], yy[0, 0]
        lo, hi = np.percentile(patch[inwin], 2), np.percentile(patch[inwin], 98)
        if hi - lo < 10:
            continue
        _, lab = cv2.connectedComponents(((patch < 0.5 * (lo + hi)) & inwin).astype(np.uint8), connectivity=8)
        c = lab[int(np.clip(round(v0) - y0, 0, lab.shape[0] - 1)), int(np.clip(round(u0) - x0, 0, lab.shape[1] - 1))]
        if c == 0:
            continue
        out[k] = np.sqrt((lab == c).sum() / np.pi)
    return out



def refine_circle_centres(gray: np.ndarray, uv: np.ndarray, radius_px: np.ndarray, iters: int = 3,
                          max_window_px: np.ndarray | None = None) -> np.ndarray:
    """Darkness-weighted centroids (the centroid of the dark disk's area, blur-invariant for a symmetric blur)
    in windows of 1.5 radii (at most ``max_window_px``: short of the neighbours), re-centred ``iters`` times; the
    weight is the darkness below the local white level, clipped at 0 and with the noise floor's 10 % removed so the
    white around the circle weighs nothing. The window must hold the whole disk and white around it: a window
    inside a larger dark disk has only noise and shading to weigh and walks off by pixels."""
    g = gray.astype(np.float64)
    out = uv.astype(np.float64).copy()
    for k in range(len(out)):
        R = max(3.0, 1.5 * radius_px[k])
        if max_window_px is not None:
            R = max(3.0, min(R, max_window_px[k]))
        for _ in range(iters):
            patch, xx, yy, inwin = _disk_window(g, *out[k], R)
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
    def circle_at(p):
        # as dark as the grid's circles, inside a ring that is white all round (the plate), not table or border
        c = sample(p)
        rg = sample((p[:, None, :] + ring[None]).reshape(-1, 2)).reshape(len(p), -1)
        return (c >= 0) & (c < dark + 0.3 * (white - dark)) & ((rg > mid).sum(1) >= len(t) - 1)

    # the homography of a flat grid misplaces the positions beyond it under lens distortion or a bent plate (a
    # wide-angle lens: by a radius, OpenCV's circles7.png), so each position is also tried at the darkest point
    # near it: in the image blurred by a radius (a disk's darkest point is then its centre), within 0.3 of the
    # position's distance to the grid (one spacing there; the grid's own circles are farther)
    gs = cv2.GaussianBlur(gray, (0, 0), max(1.0, r_px)).astype(np.float32)
    for side, xy in sides.items():
        p = cv2.perspectiveTransform(xy.reshape(-1, 1, 2), Hm).reshape(-1, 2)
        reach = 0.3 * np.linalg.norm(p[:, None] - uv[None], axis=2).min(1)
        n = max(1, int(np.ceil(reach.max() / max(1.0, r_px / 2))))
        o = np.mgrid[-n:n + 1, -n:n + 1].reshape(2, -1).T.astype(np.float64) / n
        o = o[np.hypot(o[:, 0], o[:, 1]) <= 1]
        near = (p[:, None, :] + o[None] * reach[:, None, None]).reshape(-1, 2).astype(np.float32)
        vals = cv2.remap(gs, near[:, 0].reshape(-1, 1), near[:, 1].reshape(-1, 1), cv2.INTER_LINEAR,
                         borderValue=-1).reshape(len(p), -1)
        darkest = near.reshape(len(p), -1, 2)[np.arange(len(p)), np.argmin(np.where(vals < 0, np.inf, vals), 1)]
        circles = circle_at(p) | circle_at(darkest.astype(np.float64))
        if circles.sum() >= max(2, len(p) // 2):
            return side
    return None



def grid_is_regular(uv: np.ndarray, spec: CircleGridSpec, max_ratio: float = 0.5) -> bool:
    """Whether ``findCirclesGrid``'s points form the declared grid in order: along every row and column (every
    other row for asymmetric grids, whose rows alternate) the second difference of consecutive centres stays below
    ``max_ratio`` of their spacing; an asymmetric grid's row between two others also lies half way between its
    neighbours in them (its stagger is to the declared side). Perspective and lens distortion keep these under
    0.16 in real photos (wide-angle lens, steep views); the grid finder's clustering mode can return points out of
    order and twice the same circle (ratios of several), and on an asymmetric grid with an even row count, rows
    paired the wrong way round (the stagger to the other side)."""
    P = uv.reshape(spec.rows, spec.cols, 2)
    worst = 0.0
    if spec.cols >= 3:
        sd = np.linalg.norm(P[:, :-2] - 2 * P[:, 1:-1] + P[:, 2:], axis=2)
        worst = max(worst, float((sd / np.maximum(np.linalg.norm(P[:, 2:] - P[:, :-2], axis=2) / 2, 1e-9)).max()))
    st = 2 if spec.asymmetric else 1
    if spec.rows >= 2 * st + 1:
        sd = np.linalg.norm(P[:-2 * st] - 2 * P[st:-st] + P[2 * st:], axis=2)
        worst = max(worst, float((sd / np.maximum(np.linalg.norm(P[2 * st:] - P[:-2 * st], axis=2) / 2, 1e-9)).max()))
    if spec.asymmetric and spec.rows >= 3 and spec.cols >= 2:
        # circle (i+1, j) at ((2j + (i+1)%2) s, (i+1) s) is the midpoint of (i, j) and (i+2, j+1) for even i, of
        # (i, j) and (i+2, j-1) for odd i
        for i in range(spec.rows - 2):
            if i % 2 == 0:
                a, m, b = P[i, :-1], P[i + 1, :-1], P[i + 2, 1:]
            else:
                a, m, b = P[i, 1:], P[i + 1, 1:], P[i + 2, :-1]
            off = np.linalg.norm(m - (a + b) / 2, axis=1) / np.maximum(np.linalg.norm(b - a, axis=1) / 2, 1e-9)
            worst = max(worst, float(off.max()))
    return worst < max_ratio



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
                if ok and not grid_is_regular(c.reshape(-1, 2).astype(np.float64), spec):
                    log.debug("%s: findCirclesGrid's points are not a regular grid in order; trying on", where)
                    ok = False
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
    spacing_px = sp / np.maximum(cnt, 1)
    # each circle's size as the image shows it (a larger marker dot, a diameter declared wrong), the declared one
    # where it cannot be measured
    own = circle_radii_px(gray, uv, spacing_px)
    r_px = np.where(np.isfinite(own), own, spacing_px * (spec.diameter_mm / 2) / nn_mm)
    side = _grid_continues(gray, spec, uv, float(np.median(r_px)))
    if side is not None:
        raise InputError(where, "board.cols/rows", f"a {spec.cols}x{spec.rows} circle grid",
                         f"more circles beyond its {side} edge", "a larger grid: count the circles per row (--cols) "
                         "and the rows (--rows) on the plate")
    # windows from each circle's own size, kept short of its neighbours' edges
    uv = refine_circle_centres(gray, uv, r_px, max_window_px=spacing_px - float(np.median(r_px)))
    # findCirclesGrid can return a grid with a stray blob in it and the circles after it numbered wrongly (seen on the
    # generator's texture images at 0.3x); such a grid is not used: one homography of the declared layout must put
    # every centre within a quarter spacing (a wrong id is a spacing off; lens distortion is removed first)
    frac, _ = _layout_fits(spec.corners_board()[:, :2], _undistorted_px(uv, cam),
                           max(1.0, 0.25 * float(np.median(nn_px))))
    if frac < 1.0:
        log.info("%s: a circle grid off the declared layout (%d of %d centres) not used", where,
                 int(round((1 - frac) * spec.n_corners)), spec.n_corners)
        return None
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



def _camera_key(cam) -> str | None:
    """A camera's every number, for ``remembered_detection`` (circle centres are corrected with the camera)."""
    if cam is None:
        return None
    dump = getattr(cam, "model_dump_json", None)
    return dump() if dump is not None else blake3_hex(pickle.dumps(cam))


def detect_target(image: np.ndarray, spec, cam=None, where: str = "board") -> Detection | None:
    """Any target's points with ids (indices into ``spec.corners_board()``)."""

    if isinstance(spec, (CharucoSpec, CircleGridSpec)):  # remembered by the pixels, as detect_corners is
        find = detect_charuco if isinstance(spec, CharucoSpec) else detect_circles
        return remembered_detection(type(spec).__name__, image, (repr(spec), _camera_key(cam)),
                                    lambda: find(image, spec, cam, where))
    d = detect_corners(image, spec)
    if d is not None and d.ids is None:
        d.ids = np.arange(spec.n_corners)
    return d



def detect_ahead(spec, views) -> None:
    """Detect ``spec`` in every ``(image, camera)`` of ``views`` (an image may be None) into the remembered detections
    (``gtforge.core.targets.board.remembered_detection``), on a capture's thread (``gtforge.infra.threads``), for the
    stage's loop that then asks ``detect_target``/``detect_corners`` for them in order. An error is left for that
    loop to meet where it met it before (a detection that raises is not remembered, so it raises there again)."""
    for image, cam in views:
        if image is None:
            continue
        try:
            detect_target(image, spec, cam)
        except Exception:  # noqa: BLE001 (raised again, in order, by the stage's own call)
            pass


def captures_detected_ahead(dirs, load, spec, views) -> Iterator[tuple[Path, object, InputError | None]]:
    """``load(d)`` for every capture folder of ``dirs``, with ``spec`` detected in the ``(image, camera)`` pairs that
    ``views(capture)`` names (``detect_ahead``), on ``gtforge.infra.threads.ordered_map``'s threads, yielded in the
    folders' order as ``(d, capture, None)``, or ``(d, None, exc)`` where ``load`` raised an ``InputError``: the
    calibration stages' loops skip a missing file and stop on a wrong one, in order, as they read them one by one."""
    def one(d):
        try:
            cap = load(d)
        except InputError as exc:
            return None, exc
        detect_ahead(spec, views(cap))
        return cap, None

    for d, (cap, exc) in zip(dirs, ordered_map(one, dirs)):
        yield d, cap, exc


def pnp_bias_corrected(spec, det: Detection, cam, solve_pnp) -> tuple[np.ndarray, np.ndarray]:
    """PnP from a detection; for circles, the centroids are corrected for the perspective bias at the PnP pose and
    solved again (the bias changes by far less than itself between the two poses). Returns (T_cam_from_board, uv
    used)."""
    X = spec.corners_board()[det.ids]
    T_cam_from_board = solve_pnp(X, det.corners_uv, cam)
    uv = det.corners_uv
    if isinstance(spec, CircleGridSpec):
        for _ in range(2):
            uv = det.corners_uv - circle_centre_bias(spec, T_cam_from_board, cam)[det.ids]
            T_cam_from_board = solve_pnp(X, uv, cam)
    return T_cam_from_board, uv



def unmirror_symmetric_grid(spec: CircleGridSpec, det: Detection, cam, solve_pnp) -> Detection:
    """A symmetric grid's numbering may come back mirrored (rows counted from the other side): PnP then puts the
    board's z axis (into the board) towards the camera, a board seen from behind. Count the rows the other way."""
    X = spec.corners_board()
    T_cam_from_board = solve_pnp(X, det.corners_uv, cam)
    if T_cam_from_board[:3, 2] @ T_cam_from_board[:3, 3] >= 0:
        return det
    uv = det.corners_uv.reshape(spec.rows, spec.cols, 2)[::-1].reshape(-1, 2).copy()
    return Detection(uv, det.sharpness_px, det.method, det.pattern_contrast, det.ids)


@dataclass
class TargetPair:
    """One pose of a target seen by two cameras (``a``, ``b``), its points matched by id (``match_target_views``).

    ``det_a``/``det_b`` are the detections as numbered for the match (a symmetric grid: unmirrored, ``b``'s numbering
    turned to ``a``'s); ``uv_*_all`` all of a camera's points in its ``det_*.ids`` order and ``uv_a``/``uv_b`` the
    common ones (``ids``, sorted), circle centres corrected for the perspective bias at that camera's own PnP pose
    (``T_*_from_board``, solved on all of its points)."""

    ids: np.ndarray
    uv_a: np.ndarray
    uv_b: np.ndarray
    T_a_from_board: np.ndarray
    T_b_from_board: np.ndarray
    det_a: Detection
    det_b: Detection
    uv_a_all: np.ndarray
    uv_b_all: np.ndarray


@dataclass
class PairSkipped:
    """Why a pose's two views cannot be matched: ``reason`` (one line); ``n_common`` the ids both saw, when the
    two views passed their own checks."""

    reason: str
    n_common: int | None = None


def match_target_views(spec, det_a: Detection, cam_a, det_b: Detection, cam_b, names: tuple[str, str] = ("a", "b"),
                       min_common: int = MIN_COMMON_CORNERS) -> TargetPair | PairSkipped:
    """Match two cameras' detections of one pose by id (any target; a checkerboard's ids are all its corners).

    Each view needs ``min_common`` points not on one line (else its PnP is not unique), the two together as many
    common ones, not on one line either; otherwise the reason comes back (``names``: the cameras' names in it,
    e.g. "structured-light", "ZED"). Circle centres are corrected for the perspective bias at each camera's own PnP
    pose (``pnp_bias_corrected``). A symmetric circle grid is numbered alike in both: each view's mirrored numbering
    is undone (``unmirror_symmetric_grid``), then, as the two cameras look the same way (their relative rotation about
    the view axis is far below 90 degrees), ``b``'s numbering is reversed when the board's x axis points the other way
    in it than in ``a``. ``cam_a``/``cam_b`` must model the images the points were found in (lens included)."""

    X = spec.corners_board()
    det_a, det_b = (d if d.ids is not None else Detection(d.corners_uv, d.sharpness_px, d.method,
                                                          d.pattern_contrast, np.arange(len(d.corners_uv)))
                    for d in (det_a, det_b))
    for d, name in ((det_a, names[0]), (det_b, names[1])):
        if len(d.ids) < min_common:
            return PairSkipped(f"only {len(d.ids)} board points in the {name} image (need {min_common})")
        if collinear(X[d.ids]):
            return PairSkipped(f"the board points in the {name} image lie on one line")
    symmetric = isinstance(spec, CircleGridSpec) and not spec.asymmetric
    if symmetric:
        det_a = unmirror_symmetric_grid(spec, det_a, cam_a, solve_pnp)
        det_b = unmirror_symmetric_grid(spec, det_b, cam_b, solve_pnp)
    T_a_from_board, uv_a_all = pnp_bias_corrected(spec, det_a, cam_a, solve_pnp)
    T_b_from_board, uv_b_all = pnp_bias_corrected(spec, det_b, cam_b, solve_pnp)
    if symmetric and T_a_from_board[:3, 0] @ T_b_from_board[:3, 0] < 0:
        det_b = Detection(det_b.corners_uv[::-1].copy(), det_b.sharpness_px, det_b.method, det_b.pattern_contrast,
                          det_b.ids)
        T_b_from_board, uv_b_all = pnp_bias_corrected(spec, det_b, cam_b, solve_pnp)
    common, ia, ib = np.intersect1d(det_a.ids, det_b.ids, return_indices=True)
    if len(common) < min_common:
        return PairSkipped(f"only {len(common)} board points seen by both cameras (need {min_common})", len(common))
    if collinear(X[common]):
        return PairSkipped("the board points both cameras see lie on one line", len(common))
    return TargetPair(common, uv_a_all[ia], uv_b_all[ib], T_a_from_board, T_b_from_board, det_a, det_b, uv_a_all,
                      uv_b_all)


def matched_points(name: str, texture, zed_left, mech, zed_cam, spec,
                   min_common: int = MIN_COMMON_CORNERS) -> tuple[Detection, Detection, np.ndarray] | str:
    """For validate: the two cameras' points of one pose restricted to the ids both saw, as detections (ids sorted,
    circle centres corrected for the perspective bias, a symmetric grid numbered alike), plus the ids; or the
    reason the pose cannot be used (as calibrate's ``detect_pose_target`` gives it)."""
    dm = detect_target(texture, spec, mech, where=f"{name}: structured-light image")
    dz = detect_target(zed_left, spec, zed_cam, where=f"{name}: ZED-left image")
    if dm is None or dz is None:
        which = " and ".join(w for w, d in (("structured-light", dm), ("ZED", dz)) if d is None)
        return f"board not found in the {which} image"
    pair = match_target_views(spec, dm, mech, dz, zed_cam, ("structured-light", "ZED"), min_common)
    if isinstance(pair, PairSkipped):
        return pair.reason
    dm, dz = pair.det_a, pair.det_b
    return (Detection(pair.uv_a, dm.sharpness_px, dm.method, dm.pattern_contrast, pair.ids),
            Detection(pair.uv_b, dz.sharpness_px, dz.method, dz.pattern_contrast, pair.ids), pair.ids)
