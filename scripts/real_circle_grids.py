"""gtforge's circle-grid detector on real photos: points found, per-pose PnP residuals with and without the
perspective-bias correction, and what failed (docs/targets.md, "Real circle-grid photos").

    PYTHONPATH=src python scripts/real_circle_grids.py FOLDER --board 'GLOB:COLSxROWS[a]' [--board ...]

FOLDER holds the photos of one camera; each ``--board`` names the images of one grid (a glob inside FOLDER) and
its circle counts as ``cv2.findCirclesGrid`` counts them (circles per row x rows; ``a``: asymmetric), e.g.
``'grid_*.png:4x11a'``. The photos come without intrinsics, so the camera is calibrated from them
(``cv2.calibrateCamera`` on gtforge's centres: fx = fy, principal point, k1, k2; from a single image focal length
and k1 only). Residuals are scale-free, so the spacing is nominal (20 mm); the circles' diameter relative to their
nearest-neighbour spacing matters for the bias correction and is measured from the photos (each circle's dark area
mapped to the board by the grid's homography) unless ``--diameter-ratio`` gives it.

Per image: gtforge's points (``detect_circles``: OpenCV's grid finder, then darkness-weighted centroids); the RMS
of the PnP residual without the bias correction (camera calibrated on the measured centres) and with it
(``pnp_bias_corrected``; camera calibrated again on the centres minus their bias at the first poses), its max, the
largest bias and how far correcting it turns the pose; OpenCV's own
centres (plain ``findCirclesGrid``) with the first camera, for comparison; and whether a grid declared one column
or one row short is refused, for symmetric grids (``findCirclesGrid`` finds a smaller symmetric grid inside a larger
one, which gtforge must refuse; its asymmetric finder returned none in these photos).
"""
from __future__ import annotations

import argparse
import fnmatch
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from gtforge.core.targets.board import Detection, solve_pnp
from gtforge.core.camera import PinholeCamera
from gtforge.core.geometry import pose_difference, transform_points
from gtforge.core.targets.detection import circle_centre_bias, detect_circles, pnp_bias_corrected
from gtforge.core.targets.models import CircleGridSpec
from gtforge.errors import InputError

SPACING_MM = 20.0  # nominal nearest-neighbour spacing: residuals do not depend on the board's scale
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


@dataclass
class Result:
    image: str
    grid: str
    expected: int
    found: int = 0
    failure: str = ""
    rms_raw: float = float("nan")  # PnP residual RMS (px) of the measured centres, first camera
    max_raw: float = float("nan")
    rms_corr: float = float("nan")  # of the bias-corrected centres, second camera
    max_corr: float = float("nan")
    bias_max: float = float("nan")  # largest perspective-bias shift of a circle (px)
    moved_deg: float = float("nan")  # how far the correction turns the board pose (second camera)
    moved_pct: float = float("nan")  # and moves it, % of the board's distance
    rms_opencv: float = float("nan")  # OpenCV's findCirclesGrid centres, first camera
    smaller_refused: str = ""  # one column short / one row short: "refused", "not found" or "ACCEPTED"
    uv: np.ndarray | None = field(default=None, repr=False)
    ids: np.ndarray | None = field(default=None, repr=False)
    opencv_uv: np.ndarray | None = field(default=None, repr=False)


def parse_board(text: str) -> tuple[str, int, int, bool]:
    m = re.fullmatch(r"(.+):(\d+)x(\d+)(a?)", text)
    if not m:
        raise SystemExit(f"--board {text!r}: expected GLOB:COLSxROWS or GLOB:COLSxROWSa (asymmetric)")
    return m[1], int(m[2]), int(m[3]), m[4] == "a"


def grid_spec(cols: int, rows: int, asymmetric: bool, diameter_ratio: float) -> CircleGridSpec:
    s = SPACING_MM / np.sqrt(2) if asymmetric else SPACING_MM  # spec.square_size_mm: nearest neighbours s*sqrt(2) apart
    return CircleGridSpec(cols=cols, rows=rows, square_size_mm=float(s), diameter_mm=diameter_ratio * SPACING_MM,
                          asymmetric=asymmetric)


def read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SystemExit(f"{path}: not an image OpenCV can read")
    if img.dtype != np.uint8:
        img = cv2.convertScaleAbs(img, alpha=255.0 / max(1, int(img.max())))
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB)
    return img


def gray_of(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img


def diameter_ratio_of(gray: np.ndarray, uv: np.ndarray, spec: CircleGridSpec) -> np.ndarray:
    """Per circle: its diameter over the nearest-neighbour spacing, on the board. The dark area (below half way
    between the circle's darkest and the white around it) around each centre, divided by the grid homography's
    local area scale there, is the circle's area on the board (for any view, up to the homography's variation
    across one circle)."""
    X = spec.corners_board()[:, :2]
    H, _ = cv2.findHomography(X, uv, 0)
    nn = SPACING_MM
    g = gray.astype(np.float64)
    out = []
    for (u, v), (x, y) in zip(uv, X):
        # local area scale: the Jacobian of the homography at the circle's centre
        d = 1e-3
        p = cv2.perspectiveTransform(np.array([[[x, y]], [[x + d, y]], [[x, y + d]]], np.float64), H).reshape(3, 2)
        a, b = p[1] - p[0], p[2] - p[0]
        jac = abs(a[0] * b[1] - a[1] * b[0]) / (d * d)
        rad = 0.5 * nn * np.sqrt(jac)  # half a spacing, in pixels
        x0, x1 = int(max(0, u - rad)), int(min(g.shape[1] - 1, u + rad))
        y0, y1 = int(max(0, v - rad)), int(min(g.shape[0] - 1, v + rad))
        patch = g[y0:y1 + 1, x0:x1 + 1]
        yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
        inside = (xx - u) ** 2 + (yy - v) ** 2 <= rad * rad
        if inside.sum() < 20:
            continue
        vals = patch[inside]
        mid = 0.5 * (np.percentile(vals, 2) + np.percentile(vals, 98))
        area_board = float(((patch < mid) & inside).sum()) / jac
        out.append(np.sqrt(4 * area_board / np.pi) / nn)
    return np.array(out)


def opencv_centres(gray: np.ndarray, spec: CircleGridSpec) -> np.ndarray | None:
    flags = cv2.CALIB_CB_ASYMMETRIC_GRID if spec.asymmetric else cv2.CALIB_CB_SYMMETRIC_GRID
    ok, c = cv2.findCirclesGrid(gray, spec.pattern_size, flags=flags)
    return c.reshape(-1, 2).astype(np.float64) if ok else None


def smaller_grid_refused(img: np.ndarray, spec: CircleGridSpec) -> str:
    """Declared one column, then one row, short: "refused" (gtforge's "more circles beyond" error), "not found"
    (no grid), or "ACCEPTED" (a grid inside the plate's, numbered unlike the whole one), one word per try."""
    out = []
    for cols, rows in ((spec.cols - 1, spec.rows), (spec.cols, spec.rows - 1)):
        small = CircleGridSpec(cols=cols, rows=rows, square_size_mm=spec.square_size_mm,
                               diameter_mm=spec.diameter_mm, asymmetric=spec.asymmetric)
        try:
            det = detect_circles(img, small)
        except InputError:
            out.append("refused")
            continue
        out.append("not found" if det is None else "ACCEPTED")
    return " / ".join(out)


def calibrate(views: list[tuple[np.ndarray, np.ndarray]], size: tuple[int, int]) -> tuple[PinholeCamera, float]:
    """fx = fy, principal point, k1, k2; no tangential terms, no k3 (more terms lower no set's RMS here). One view:
    focal length and k1 only, the principal point at the image centre."""
    W, H = size
    K0 = np.array([[W, 0, (W - 1) / 2], [0, W, (H - 1) / 2], [0, 0, 1.0]])
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_ASPECT_RATIO | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    if len(views) == 1:
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_K2
    rms, K, dist, _, _ = cv2.calibrateCamera([X.astype(np.float32) for X, _ in views],
                                             [uv.astype(np.float32).reshape(-1, 1, 2) for _, uv in views],
                                             (W, H), K0, np.zeros(5), flags=flags)
    return PinholeCamera.from_K(K, W, H, dist.ravel()), float(rms)


def residual(cam: PinholeCamera, T_cam_from_board: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    return np.linalg.norm(cam.project(transform_points(T_cam_from_board, X)) - uv, axis=1)


def measure(folder: Path, boards: list[tuple[str, int, int, bool]], diameter_ratio: float | None = None,
            check_smaller: bool = True) -> dict:
    """Detect, calibrate, and measure every image of ``folder`` that a board's glob names."""
    names = sorted(p.name for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    jobs = []
    for pattern, cols, rows, asym in boards:
        for n in names:
            if fnmatch.fnmatch(n, pattern):
                jobs.append((n, cols, rows, asym))
    if not jobs:
        raise SystemExit(f"{folder}: no image matches {[b[0] for b in boards]}")
    ratio0 = diameter_ratio if diameter_ratio is not None else 0.5
    results: list[Result] = []
    specs, size = {}, None
    ratios: dict[tuple, list] = {}  # per grid: diameter / spacing of every circle found
    for n, cols, rows, asym in jobs:
        img = read_rgb(Path(folder) / n)
        H, W = img.shape[:2]
        if size is None:
            size = (W, H)
        elif size != (W, H):
            raise SystemExit(f"{n}: {W}x{H}, the other images {size[0]}x{size[1]}: one camera per folder")
        spec = grid_spec(cols, rows, asym, ratio0)
        r = Result(n, f"{cols}x{rows}{' asym.' if asym else ''}", spec.n_corners)
        try:
            det = detect_circles(img, spec, where=n)
        except InputError as e:
            det, r.failure = None, f"refused: {e}"
        if det is None:
            r.failure = r.failure or "grid not found (findCirclesGrid, every blob detector and the plate-only image)"
        else:
            r.found, r.uv, r.ids = len(det.ids), det.corners_uv, det.ids
            ratios.setdefault((cols, rows, asym), []).append(diameter_ratio_of(gray_of(img), det.corners_uv, spec))
        r.opencv_uv = opencv_centres(gray_of(img), spec)
        if check_smaller and not asym:  # OpenCV's asymmetric finder returns no grid inside a larger one
            r.smaller_refused = smaller_grid_refused(img, spec)
        results.append(r)
        specs[n] = (cols, rows, asym)
    ratio = {g: diameter_ratio if diameter_ratio is not None else
             (float(np.median(np.concatenate(ratios[g]))) if g in ratios else ratio0) for g in set(specs.values())}
    spec_of = {n: grid_spec(*specs[n], ratio[specs[n]]) for n in specs}
    ok = [r for r in results if r.uv is not None]
    if not ok:
        return dict(results=results, camera=None, camera_corr=None, diameter_ratio=ratio, calib_rms=float("nan"),
                    calib_rms_corr=float("nan"), size=size)
    # first camera: on the measured centres
    cam, calib_rms = calibrate([(spec_of[r.image].corners_board()[r.ids], r.uv) for r in ok], size)
    corrected = {}
    for r in ok:
        spec = spec_of[r.image]
        X = spec.corners_board()[r.ids]
        T_cam_from_board = solve_pnp(X, r.uv, cam)
        e = residual(cam, T_cam_from_board, X, r.uv)
        r.rms_raw, r.max_raw = float(np.sqrt(np.mean(e ** 2))), float(e.max())
        bias = circle_centre_bias(spec, T_cam_from_board, cam)[r.ids]
        corrected[r.image] = r.uv - bias
        if r.opencv_uv is not None:
            T_cam_from_board_opencv = solve_pnp(X, r.opencv_uv, cam)
            r.rms_opencv = float(np.sqrt(np.mean(residual(cam, T_cam_from_board_opencv, X, r.opencv_uv) ** 2)))
    # second camera: on the centres less their perspective bias, then gtforge's bias-corrected PnP with it
    cam2, calib_rms2 = calibrate([(spec_of[r.image].corners_board()[r.ids], corrected[r.image]) for r in ok], size)
    for r in ok:
        spec = spec_of[r.image]
        X = spec.corners_board()[r.ids]
        det = Detection(r.uv, 0.0, "circles", 0.0, r.ids)
        T_cam_from_board, uv = pnp_bias_corrected(spec, det, cam2, solve_pnp)
        e = residual(cam2, T_cam_from_board, X, uv)
        r.rms_corr, r.max_corr = float(np.sqrt(np.mean(e ** 2))), float(e.max())
        r.bias_max = float(np.linalg.norm(r.uv - uv, axis=1).max())
        T_cam_from_board_raw = solve_pnp(X, r.uv, cam2)
        r.moved_deg, dt = pose_difference(T_cam_from_board_raw, T_cam_from_board)
        r.moved_pct = 100 * dt / float(np.linalg.norm(T_cam_from_board[:3, 3]))
    return dict(results=results, camera=cam, camera_corr=cam2, diameter_ratio=ratio, calib_rms=calib_rms,
                calib_rms_corr=calib_rms2, size=size)


def _f(x: float, nd: int = 3) -> str:
    return "-" if not np.isfinite(x) else f"{x:.{nd}f}"


def table(out: dict) -> str:
    lines = ["| image | grid | points found | PnP RMS (px), no bias correction | PnP RMS (px), bias-corrected "
             "| max (px) | largest bias (px) | pose turned by the correction (deg) | OpenCV's centres: PnP RMS (px) "
             "| declared one column / one row short |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in out["results"]:
        found = f"{r.found} / {r.expected}" if not r.failure else f"0 / {r.expected}: {r.failure}"
        lines.append(f"| {r.image} | {r.grid} | {found} | {_f(r.rms_raw)} | {_f(r.rms_corr)} | {_f(r.max_corr)} | "
                     f"{_f(r.bias_max)} | {_f(r.moved_deg, 4)} | {_f(r.rms_opencv)} | {r.smaller_refused or '-'} |")
    return "\n".join(lines)


def camera_line(out: dict) -> str:
    cam = out["camera"]
    if cam is None:
        return "camera: not calibrated (the grid was found in no image)"
    c2 = out["camera_corr"]
    d = ", ".join(f"{x:.4f}" for x in cam.dist_coeffs[:2])
    return (f"camera {out['size'][0]}x{out['size'][1]}: f {cam.fx_px:.1f} px, centre ({cam.cx_px:.1f}, "
            f"{cam.cy_px:.1f}), k1 k2 {d}; calibrateCamera RMS {out['calib_rms']:.3f} px "
            f"({out['calib_rms_corr']:.3f} px on the bias-corrected centres, f {c2.fx_px:.1f}); circle diameter / "
            "spacing " + ", ".join(f"{g[0]}x{g[1]}{'a' if g[2] else ''} {v:.3f}"
                                   for g, v in out["diameter_ratio"].items()))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--board", action="append", required=True, help="GLOB:COLSxROWS, 'a' appended for asymmetric")
    ap.add_argument("--diameter-ratio", type=float, help="circle diameter / nearest-neighbour spacing (default: "
                    "measured from the photos)")
    ap.add_argument("--no-smaller-check", action="store_true",
                    help="skip declaring the grid one column / one row short")
    a = ap.parse_args(argv)
    out = measure(a.folder, [parse_board(b) for b in a.board], a.diameter_ratio, not a.no_smaller_check)
    print(camera_line(out))
    print(table(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
