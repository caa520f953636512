"""Where the calibration's board points fell, which distances and tilts the poses span, and what to capture next.

``coverage_report`` summarises the used poses of a calibration per camera (every point each camera detected counts,
also those the other camera did not see: they say where that camera was looked at) and turns the gaps into plain
sentences (``guidance``). Where the gap is an image corner or a tilt, it builds the missing pose from the used
ones (a used board moved towards the empty corner, or turned about the vertical or horizontal axis), keeps it if
both cameras would see enough of it, and predicts the extrinsic's 1-sigma after adding it from the current
covariance plus that pose's information (the extrinsic block of its Gauss-Newton normal equations, the board
pose marginalised out; the residual variance and the jackknife factor as in the calibration).
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from gtforge.core.geometry import invert_T, perturb_left, transform_points
from gtforge.core.schema import GTModel
from gtforge.core.targets.models import collinear

GRID_COLS, GRID_ROWS = 8, 6  # the coverage map's cells per image
CORNER_RADIUS_FRAC = 0.12  # "no points within R of an image corner", R as a share of the image diagonal
MIN_TILT_DEG = 20.0  # poses should reach this tilt about each axis (both signs are not needed)
MIN_DISTANCE_RATIO = 1.25  # farthest / nearest board distance
CORNER_NAMES = ("top-left", "top-right", "bottom-right", "bottom-left")


class CameraCoverage(GTModel):
    camera: Literal["mech", "zed"]
    width_px: int
    height_px: int
    n_points: int
    counts_grid: list[list[int]]  # GRID_ROWS x GRID_COLS: points per cell, row 0 at the image top
    nearest_to_corner_px: dict[str, float]  # image corner -> distance (px) of the nearest point to it
    # the points themselves, for the report's map; not written into the calibration file
    points_uv: list[list[float]] = Field(default_factory=list, exclude=True)


class PredictedPose(GTModel):
    """One more pose as guidance proposes it, and the extrinsic's 1-sigma predicted with it."""

    description: str
    n_points_common: int
    sigma_rot_deg: float
    sigma_trans_mm: float


class CoverageResult(GTModel):
    cameras: list[CameraCoverage]
    distance_mm_min: float  # board centre's depth in the ZED-left camera, over the used poses
    distance_mm_max: float
    tilt_vertical_axis_deg: list[float]  # [min, max]: board turned about the ZED's vertical (y) axis
    tilt_horizontal_axis_deg: list[float]  # [min, max]: about its horizontal (x) axis
    guidance: list[str]
    predictions: list[PredictedPose] = Field(default_factory=list)


def _camera_coverage(name: str, cam, pts: np.ndarray) -> CameraCoverage:
    W, H = cam.width_px, cam.height_px
    gx = np.clip((pts[:, 0] / W * GRID_COLS).astype(int), 0, GRID_COLS - 1)
    gy = np.clip((pts[:, 1] / H * GRID_ROWS).astype(int), 0, GRID_ROWS - 1)
    grid = np.zeros((GRID_ROWS, GRID_COLS), int)
    np.add.at(grid, (gy, gx), 1)
    corners = np.array([[0, 0], [W - 1, 0], [W - 1, H - 1], [0, H - 1]], float)
    near = {n: float(np.min(np.linalg.norm(pts - c, axis=1))) if len(pts) else float("inf")
            for n, c in zip(CORNER_NAMES, corners)}
    return CameraCoverage(camera=name, width_px=W, height_px=H, n_points=len(pts), counts_grid=grid.tolist(),
                          nearest_to_corner_px=near, points_uv=pts.tolist())


def _tilts_deg(T_zed_from_board: np.ndarray) -> tuple[float, float]:
    """(about the vertical axis, about the horizontal axis) of the board normal in the ZED frame (0: facing it)."""
    n = T_zed_from_board[:3, 2]
    return float(np.degrees(np.arctan2(n[0], n[2]))), float(np.degrees(np.arctan2(n[1], n[2])))


def _visible(cam, pc: np.ndarray, margin_px: float = 3.0) -> np.ndarray:
    ok = pc[:, 2] > 1.0
    uv = np.full((len(pc), 2), -1e9)
    uv[ok] = cam.project(pc[ok])
    return ok & (uv[:, 0] >= margin_px) & (uv[:, 1] >= margin_px) & (uv[:, 0] <= cam.width_px - 1 - margin_px) & \
        (uv[:, 1] <= cam.height_px - 1 - margin_px)


def pose_information(T_zed_from_mech: np.ndarray, T_mech_from_board: np.ndarray, X: np.ndarray, mech, zed_cam,
                     sigma_px: float) -> np.ndarray:
    """6x6 information on the extrinsic (left perturbation, rad then mm: ``CalibrationFile.cov_extrinsic_rad_mm``)
    from one pose whose points ``X`` both cameras see, its board pose marginalised out (Schur complement)."""

    def res(x):
        T_zed_from_mech_x = perturb_left(T_zed_from_mech, x[:6])
        T_mech_from_board_x = perturb_left(T_mech_from_board, x[6:])
        return np.concatenate([mech.project(transform_points(T_mech_from_board_x, X)).ravel(),
                               zed_cam.project(transform_points(T_zed_from_mech_x @ T_mech_from_board_x, X)).ravel()])

    x0 = np.zeros(12)
    f0 = res(x0)
    J = np.empty((len(f0), 12))
    for k in range(12):
        h = 1e-6 if k in (0, 1, 2, 6, 7, 8) else 1e-4
        d = x0.copy()
        d[k] = h
        J[:, k] = (res(d) - f0) / h
    A = J.T @ J / sigma_px ** 2
    Aee, Aeb, Abb = A[:6, :6], A[:6, 6:], A[6:, 6:]
    return Aee - Aeb @ np.linalg.solve(Abb, Aeb.T)


def _predict(cov: np.ndarray, info: np.ndarray) -> tuple[float, float]:
    c = np.linalg.inv(np.linalg.inv(cov) + info)
    return float(np.degrees(np.sqrt(max(np.trace(c[:3, :3]), 0.0)))), float(np.sqrt(max(np.trace(c[3:, 3:]), 0.0)))


def coverage_report(used, T_mech_from_board: list[np.ndarray], T_zed_from_mech: np.ndarray, mech, zed_cam, board,
                    cov: np.ndarray | None = None, rms_px: float | None = None, jack_scale: float | None = None,
                    min_common: int = 6) -> CoverageResult:
    """Coverage of the used poses (``PoseObs`` with their refined ``T_mech_from_board``) and what to capture next."""
    X_all = board.corners_board()
    cams = []
    for name, cam, attr, obs_attr in (("zed", zed_cam, "det_zed", "zed_uv"), ("mech", mech, "det_mech", "mech_uv")):
        pts = [getattr(o, attr).corners_uv if getattr(o, attr) is not None else getattr(o, obs_attr) for o in used]
        cams.append(_camera_coverage(name, cam, np.concatenate(pts) if pts else np.zeros((0, 2))))
    T_zed_from_boards = [T_zed_from_mech @ T_mech_from_board_k for T_mech_from_board_k in T_mech_from_board]
    centre_b = X_all.mean(0)
    dist = np.array([transform_points(T_zed_from_board, centre_b[None])[0, 2]
                     for T_zed_from_board in T_zed_from_boards])
    tilts = np.array([_tilts_deg(T_zed_from_board) for T_zed_from_board in T_zed_from_boards])
    guidance: list[str] = []
    gaps: list[tuple[str, str]] = []  # (kind, detail) for the proposals
    for c in cams:
        R = CORNER_RADIUS_FRAC * np.hypot(c.width_px, c.height_px)
        R = float(np.ceil(R / 10) * 10)
        label = "ZED" if c.camera == "zed" else "structured-light"
        for corner, d in c.nearest_to_corner_px.items():
            if d > R:
                guidance.append(f"no board points within {R:.0f} px of the {label} image's {corner} corner")
                gaps.append(("corner", f"{c.camera}:{corner}"))
    for k, axis in ((0, "vertical"), (1, "horizontal")):
        m = float(np.max(np.abs(tilts[:, k])))
        if m < MIN_TILT_DEG:
            guidance.append(f"the board was never tilted more than {m:.0f} deg about the {axis} axis; add poses "
                            f"turned {MIN_TILT_DEG:.0f}-40 deg about it")
            gaps.append(("tilt", axis))
    if dist.max() / dist.min() < MIN_DISTANCE_RATIO:
        guidance.append(f"all boards were {dist.min():.0f}-{dist.max():.0f} mm from the ZED; add poses nearer "
                        f"({0.8 * dist.min():.0f} mm) and farther ({1.2 * dist.max():.0f} mm)")
    predictions: list[PredictedPose] = []
    if cov is not None and np.all(np.isfinite(cov)) and rms_px:
        # per-coordinate residual sigma (rms_px is per point, over u and v), times the jackknife factor the
        # covariance was scaled by: the new pose's information is then on the covariance's footing
        sigma_px = max(float(rms_px), 1e-3) / np.sqrt(2.0) * np.sqrt(jack_scale or 1.0)
        for kind, detail in gaps:
            best = None
            for _, T_zed_from_board in _sources(kind, detail, T_mech_from_board, T_zed_from_boards, centre_b, mech,
                                                zed_cam):
                for T_zed_from_board_new, text in _proposals(kind, detail, T_zed_from_board, T_zed_from_mech, centre_b,
                                                             mech, zed_cam):
                    T_mech_from_board_new = invert_T(T_zed_from_mech) @ T_zed_from_board_new
                    vis = (_visible(mech, transform_points(T_mech_from_board_new, X_all))
                           & _visible(zed_cam, transform_points(T_zed_from_board_new, X_all)))
                    if vis.sum() < min_common:
                        continue

                    if collinear(X_all[vis]):
                        continue
                    info = pose_information(T_zed_from_mech, T_mech_from_board_new, X_all[vis], mech, zed_cam, sigma_px)
                    sr, st = _predict(cov, info)
                    if best is None or sr + st / 10 < best.sigma_rot_deg + best.sigma_trans_mm / 10:
                        best = PredictedPose(description=text, n_points_common=int(vis.sum()), sigma_rot_deg=sr,
                                             sigma_trans_mm=st)
            if best is not None:
                predictions.append(best)
        if predictions:
            now_r = float(np.degrees(np.sqrt(np.trace(cov[:3, :3]))))
            now_t = float(np.sqrt(np.trace(cov[3:, 3:])))
            for p in predictions:
                guidance.append(f"one more pose ({p.description}, {p.n_points_common} points in both images) is "
                                f"predicted to bring the extrinsic's 1-sigma from {now_r:.4f} deg / {now_t:.3f} mm to "
                                f"{p.sigma_rot_deg:.4f} deg / {p.sigma_trans_mm:.3f} mm")
    return CoverageResult(cameras=cams, distance_mm_min=float(dist.min()), distance_mm_max=float(dist.max()),
                          tilt_vertical_axis_deg=[float(tilts[:, 0].min()), float(tilts[:, 0].max())],
                          tilt_horizontal_axis_deg=[float(tilts[:, 1].min()), float(tilts[:, 1].max())],
                          guidance=guidance, predictions=predictions)


def _sources(kind: str, detail: str, T_mech_from_boards, T_zed_from_boards, centre_b, mech, zed_cam, n: int = 3):
    """The used poses a proposal starts from (at most ``n``: the cost stays a fraction of the calibration's): for a
    corner gap the poses whose board centre is imaged nearest that corner, for a tilt the first ``n``."""
    pairs = list(zip(T_mech_from_boards, T_zed_from_boards))
    if kind != "corner":
        return pairs[:n]
    cam_name, corner = detail.split(":")
    cam = zed_cam if cam_name == "zed" else mech
    k = {"top-left": (0, 0), "top-right": (1, 0), "bottom-right": (1, 1), "bottom-left": (0, 1)}[corner]
    c = np.array([k[0] * (cam.width_px - 1), k[1] * (cam.height_px - 1)])
    d = [np.linalg.norm(cam.project(transform_points(T_mech_from_board if cam_name == "mech" else T_zed_from_board,
                                                     centre_b[None]))[0] - c)
         for T_mech_from_board, T_zed_from_board in pairs]
    return [pairs[i] for i in np.argsort(d)[:n]]


def _proposals(kind: str, detail: str, T_zed_from_board: np.ndarray, T_zed_from_mech: np.ndarray,
               centre_b: np.ndarray, mech, zed_cam):
    """Candidate ``T_zed_from_board`` for one gap, derived from a used pose (same distance)."""
    c_zed = transform_points(T_zed_from_board, centre_b[None])[0]
    if kind == "tilt":
        for sign in (1, -1):
            ang = np.radians(30.0 * sign)
            axis = np.array([0.0, 1.0, 0.0]) if detail == "vertical" else np.array([1.0, 0.0, 0.0])
            import cv2

            R = cv2.Rodrigues(axis * ang)[0]
            T_zed_from_board_turned = T_zed_from_board.copy()
            T_zed_from_board_turned[:3, :3] = R @ T_zed_from_board[:3, :3]
            T_zed_from_board_turned[:3, 3] = c_zed - T_zed_from_board_turned[:3, :3] @ centre_b  # about its own centre
            yield T_zed_from_board_turned, f"a board turned {30 * sign:+d} deg about the {detail} axis"
        return
    cam_name, corner = detail.split(":")
    cam = zed_cam if cam_name == "zed" else mech
    k = {"top-left": (0.08, 0.08), "top-right": (0.92, 0.08), "bottom-right": (0.92, 0.92),
         "bottom-left": (0.08, 0.92)}[corner]
    target = np.array([[k[0] * cam.width_px, k[1] * cam.height_px]])
    xy = cam.undistort_to_normalized(target)[0]
    if not np.all(np.isfinite(xy)):
        return
    if cam_name == "zed":
        depth = c_zed[2]
        p = np.array([xy[0], xy[1], 1.0]) * depth
    else:
        T_mech_from_board = invert_T(T_zed_from_mech) @ T_zed_from_board
        depth = transform_points(T_mech_from_board, centre_b[None])[0, 2]
        p = transform_points(T_zed_from_mech, (np.array([xy[0], xy[1], 1.0]) * depth)[None])[0]
    T_zed_from_board_moved = T_zed_from_board.copy()
    T_zed_from_board_moved[:3, 3] = p - T_zed_from_board[:3, :3] @ centre_b
    label = "ZED" if cam_name == "zed" else "structured-light"
    yield T_zed_from_board_moved, f"a board centred near the {label} image's {corner} corner, cut by its border"
