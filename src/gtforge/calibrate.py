"""Stage 1: ``T_zed_from_mech`` from checkerboard captures.

Per pose: corners in the structured-light texture and the rectified ZED-left image (consistent
order from the pattern), PnP in each, ``T_zed_from_mech_i = T_zed_from_board_i @ inv(T_mech_from_board_i)``.
Fusion: rotation mean on SO(3) with median/MAD outlier rejection, then joint refinement of the
extrinsic and every board pose over all corner reprojections in both cameras
(``scipy.optimize.least_squares``, Huber loss), 1-sigma uncertainty from the Jacobian, and
leave-one-pose-out cross-validation. ``use_depth`` adds a 3D-to-2D solve through the depth camera's
own measurement of the board.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, ClassVar, Literal

import cv2
import numpy as np
from pydantic import Field, PrivateAttr, model_serializer

from gtforge.core.board import Detection, detect_corners
from gtforge.core.camera import PinholeCamera, RectifiedStereo, Rig
from gtforge.errors import InputError
from gtforge.core.geometry import fit_plane_robust, invert_T, make_T, pose_difference, transform_points
from gtforge.core.rectification import RectificationQuality, ZedConfChoice
from gtforge.core.selfcal import SelfRectifyParams, ZedRightCorrection, ZedSelfRectification, self_rectify
from gtforge.scale_calibration import ScaleCalibration
from gtforge.core.schema import GTModel, VersionedFile
from gtforge.synthetic import BoardSpec

# scipy is imported inside the functions that use it: it adds about 0.4 s to every process start, and the
# build-dataset workers, which import this module for CalibrationFile, never need it

log = logging.getLogger("gtforge.calibrate")

LOO_WARN_PX = 0.3  # verdict WARN when the leave-one-pose-out transfer error exceeds this


from gtforge.core.coverage import CoverageReport  # noqa: E402
from gtforge.core.targets import BoardModel  # noqa: E402  (the board declaration; re-exported here as before)


class CalibrateParams(GTModel):
    board: BoardModel = Field(default_factory=BoardModel)
    use_depth: bool = False
    huber_px: float = 1.0
    outlier_k: float = 4.0  # median + k * 1.4826 * MAD rule on the per-pose extrinsic estimates
    outlier_floor_deg: float = 0.1
    outlier_floor_mm: float = 1.0
    blur_sharpness_px: float = 4.0  # flag poses whose edge width exceeds this
    min_poses: int = 3
    leave_one_out: bool = True
    # the board's squares measured in the depth must match square_size_mm within this (%); 0 switches it off
    square_check_pct: float = Field(3.0, ge=0)
    # --use-depth: the two methods may differ by at most max(these floors, 5 sigma) before the verdict is FAIL
    methods_agree_deg: float = 0.1
    methods_agree_mm: float = 1.0
    # the ZED right camera's residual rotation from left-right matches over every capture (gtforge.core.selfcal)
    self_rectify: bool = True


class PoseReport(GTModel):
    capture: str
    status: Literal["used", "skipped", "outlier"]
    reason: str = ""
    rms_mech_px: float | None = None
    rms_zed_px: float | None = None
    max_px: float | None = None
    sharpness_mech_px: float | None = None
    sharpness_zed_px: float | None = None
    blurred: bool = False
    init_rot_dev_deg: float | None = None
    init_trans_dev_mm: float | None = None
    loo_transfer_mean_px: float | None = None
    loo_transfer_max_px: float | None = None
    # ChArUco / circle grids (gtforge.core.targets): board points found in each image and in both (None: checkerboard)
    n_points_mech: int | None = None
    n_points_zed: int | None = None
    n_points_common: int | None = None

    @model_serializer(mode="wrap")
    def _compact(self, handler):
        d = handler(self)
        return {k: v for k, v in d.items() if not (k.startswith("n_points_") and v is None)}


class MethodResult(GTModel):
    method: Literal["reprojection", "depth"]
    T_zed_from_mech: list[list[float]]
    rms_zed_px: float
    rot_diff_to_primary_deg: float = 0.0
    trans_diff_to_primary_mm: float = 0.0


class SceneRefinement(GTModel):
    scene: str
    status: Literal["used", "excluded", "not usable"]
    reason: str = ""
    n_points: int = 0
    shift_before_px: float | None = None  # |texture shift| (whole area) with the starting calibration
    shift_after_px: float | None = None  # with the refined calibration
    fruit_shift_after_px: float | None = None
    heldout_shift_px: float | None = None  # refined WITHOUT this scene, measured on it (cross-validation)


class RefinementInfo(GTModel):
    """Provenance of a refined calibration (stored in the calibration file)."""

    refined_from: str  # the starting calibration file
    method: str = "scene texture alignment (direct photometric, Huber IRLS)"
    scenes_used: list[str]
    scenes_excluded: dict[str, str] = Field(default_factory=dict)
    change_rot_deg: float
    change_trans_mm: float
    heldout_shift_before_mean_px: float | None = None
    heldout_shift_after_mean_px: float | None = None
    sigma_jackknife_rot_deg: float | None = None
    sigma_jackknife_trans_mm: float | None = None
    scenes: list[SceneRefinement] = Field(default_factory=list)


class CalibrationFile(VersionedFile):
    """Output of ``gtforge calibrate``; ``rig`` is what every later stage uses."""

    KIND: ClassVar[str] = "gtforge calibration file (from gtforge calibrate)"

    @classmethod
    def read(cls, path: str | Path) -> "CalibrationFile":
        """Read a calibration file; a folder holding ``calibration.yaml`` (what ``calibrate -o DIR/`` writes) means
        that file."""
        p = Path(path)
        if p.is_dir() and (p / "calibration.yaml").is_file():
            p = p / "calibration.yaml"
        return super().read(p)

    @classmethod
    def known_extrinsic(cls, rig: Rig, sigma_rot_deg: float = 0.0, sigma_trans_mm: float = 0.0) -> "CalibrationFile":
        """A calibration file for a rig whose extrinsic is known (synthetic truth, benchmarks), reported with
        ``sigma_rot_deg`` / ``sigma_trans_mm`` per axis (the covariance's diagonal, independent axes; no covariance
        when both are 0)."""
        cov = None
        if sigma_rot_deg or sigma_trans_mm:
            cov = np.diag([np.radians(sigma_rot_deg) ** 2] * 3 + [sigma_trans_mm ** 2] * 3).tolist()
        return cls(rig=rig, board=BoardModel(), captures_used=[], rms_px=0.0, max_px=0.0,
                   sigma_rot_xyz_deg=[sigma_rot_deg] * 3, sigma_trans_xyz_mm=[sigma_trans_mm] * 3,
                   sigma_rot_deg=float(np.sqrt(3) * sigma_rot_deg), sigma_trans_mm=float(np.sqrt(3) * sigma_trans_mm),
                   poses=[], cov_extrinsic_rad_mm=cov)

    rig: Rig
    board: BoardModel
    method: Literal["reprojection", "depth"] = "reprojection"
    session_dir: str = ""
    captures_used: list[str]
    rms_px: float
    max_px: float
    sigma_rot_xyz_deg: list[float]
    sigma_trans_xyz_mm: list[float]
    sigma_rot_deg: float
    sigma_trans_mm: float
    loo_transfer_mean_px: float | None = None
    loo_transfer_max_px: float | None = None
    poses: list[PoseReport]
    methods: list[MethodResult] = Field(default_factory=list)
    residuals_by_region_px: dict[str, float] = Field(default_factory=dict)
    # Full covariance of the written extrinsic, parameterised as a left perturbation:
    # T_zed_from_mech = [exp(omega) R | t + delta_t] with omega (rad, 3) then delta_t (mm, 3); rows/columns in
    # that order (omega_x, omega_y, omega_z, t_x, t_y, t_z). sigma_* above are the square roots of its diagonal.
    cov_extrinsic_rad_mm: list[list[float]] | None = None
    # the factor the leave-one-out jackknife scaled cov_extrinsic_rad_mm by (>= 1): over board poses (calibrate) or,
    # in a refined file, over scenes (refine --loo); None: no jackknife was run for this covariance
    cov_jackknife_scale: float | None = None
    square_size_measured_mm: float | None = None  # from the depth camera's view of the board (median over poses)
    verdict: Literal["PASS", "WARN", "FAIL"] = "PASS"
    verdict_reasons: list[str] = Field(default_factory=list)
    refinement: RefinementInfo | None = None  # set by gtforge refine: the extrinsic was refined from scenes
    coverage: CoverageReport | None = None  # where the board points fell and what to capture next (gtforge.core.coverage)
    # set by gtforge calibrate-scale: baseline scale, right-camera yaw, depth scale/offset (applied in rig)
    scale_calibration: ScaleCalibration | None = None

    @property
    def zed_conf_reading(self) -> str | None:
        """The SN.conf reading later stages rectify raw ZED images with (None: not a raw + SN.conf session)."""
        return self.zed_conf.reading if self.zed_conf is not None else None

    @property
    def zed_right_correction(self) -> ZedRightCorrection | None:
        """The right camera's correction later stages rectify with (None: none was applied)."""
        s = self.zed_self_rectification
        return s.correction if s is not None and s.status == "applied" else None

    def open_session(self, session_dir: str | Path):
        """The session as this calibration sees it: raw ZED images rectified with the recorded SN.conf reading and
        the self-rectification's correction."""
        from gtforge.io.captures import open_session

        return open_session(session_dir, zed_conf_reading=self.zed_conf_reading,
                            zed_right_correction=self.zed_right_correction)
    # the ZED pair's rectification (board corners in both rectified images) and, for raw images + SN.conf,
    # the conf reading chosen from the board images (gtforge.core.rectification; later stages rectify with it)
    rectification: RectificationQuality | None = None
    zed_conf: ZedConfChoice | None = None
    # the ZED pair's self-rectification (gtforge.core.selfcal): when applied, every later stage rectifies with its correction
    zed_self_rectification: ZedSelfRectification | None = None
    time_s: float = 0.0
    # per-corner residuals for the report (not written into the calibration file)
    _residuals: dict = PrivateAttr(default_factory=dict)
    _coverage_inputs: dict = PrivateAttr(default_factory=dict)

    def attach_coverage(self) -> "CalibrationFile":
        """Fill ``coverage`` (where the points fell, distances, tilts, what to capture next: gtforge.core.coverage) from
        the poses this calibration used; ``calibrate`` does it, ``calibrate_observations`` leaves it to the caller
        (a few tenths of a second)."""
        from gtforge.core.coverage import coverage_report

        if self._coverage_inputs:
            self.coverage = coverage_report(**self._coverage_inputs)
        return self


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


# ---- PnP ------------------------------------------------------------------------------------
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


# ---- fusion ---------------------------------------------------------------------------------
def robust_initial_extrinsic(Ts: list[np.ndarray], params: CalibrateParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rotation mean on SO(3) + translation mean over poses kept by a median/MAD rule.

    Returns (T, inlier mask, rotation deviation deg, translation deviation mm)."""
    from scipy.spatial.transform import Rotation
    Rs = Rotation.from_matrix(np.stack([T[:3, :3] for T in Ts]))
    ts = np.stack([T[:3, 3] for T in Ts])
    keep = np.ones(len(Ts), bool)
    for _ in range(3):
        R_mean = Rs[keep].mean()
        t_med = np.median(ts[keep], axis=0)
        rot_dev = np.degrees((R_mean.inv() * Rs).magnitude())
        tr_dev = np.linalg.norm(ts - t_med, axis=1)
        new_keep = np.ones(len(Ts), bool)
        for dev, floor in ((rot_dev, params.outlier_floor_deg), (tr_dev, params.outlier_floor_mm)):
            med = np.median(dev[keep])
            mad = 1.4826 * np.median(np.abs(dev[keep] - med))
            new_keep &= dev <= med + params.outlier_k * max(mad, floor)
        if new_keep.sum() < 2 or np.array_equal(new_keep, keep):
            keep = new_keep if new_keep.sum() >= 2 else keep
            break
        keep = new_keep
    R_mean = Rs[keep].mean()
    T = make_T(R_mean.as_matrix(), ts[keep].mean(axis=0))
    rot_dev = np.degrees((R_mean.inv() * Rs).magnitude())
    tr_dev = np.linalg.norm(ts - T[:3, 3], axis=1)
    return T, keep, rot_dev, tr_dev


def _project_many(cam: PinholeCamera, pts: np.ndarray) -> np.ndarray:
    return cam.project(pts.reshape(-1, 3)).reshape(pts.shape[:-1] + (2,))


def _perturbed(T0: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``T = [exp(x[:3]) R0 | t0 + x[3:]]`` (small-perturbation parametrisation)."""
    from scipy.spatial.transform import Rotation
    return make_T(Rotation.from_rotvec(x[:3]).as_matrix() @ T0[:3, :3], T0[:3, 3] + x[3:])


@dataclass
class Refined:
    T_zed_from_mech: np.ndarray
    T_mech_from_board: list[np.ndarray]
    res_mech: np.ndarray  # (P, N, 2)
    res_zed: np.ndarray  # (P, N, 2)
    cov_extrinsic: np.ndarray  # (6, 6): rotation perturbation (rad), translation (mm)
    n_iter: int


def joint_refine(obs: list[PoseObs], mech: PinholeCamera, zed_cam: PinholeCamera, board: BoardSpec,
                 T_zed_from_mech0: np.ndarray, huber_px: float = 1.0,
                 T_mech_from_board0: list[np.ndarray] | None = None) -> Refined:
    """Minimise every corner's reprojection error in both cameras over the extrinsic and the board poses."""
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix
    if any(o.ids is not None for o in obs):
        return _joint_refine_ragged(obs, mech, zed_cam, board, T_zed_from_mech0, huber_px, T_mech_from_board0)
    P = len(obs)
    X = board.corners_board()
    N = len(X)
    Tb0 = T_mech_from_board0 or [o.T_mech_from_board for o in obs]
    uv_m = np.stack([o.mech_uv for o in obs])
    uv_z = np.stack([o.zed_uv for o in obs])

    def unpack(x):
        Te = _perturbed(T_zed_from_mech0, x[:6])
        Tbs = [_perturbed(Tb0[i], x[6 + 6 * i: 12 + 6 * i]) for i in range(P)]
        return Te, Tbs

    def residuals(x):
        Te, Tbs = unpack(x)
        pm = np.stack([transform_points(T, X) for T in Tbs])
        pz = np.stack([transform_points(Te @ T, X) for T in Tbs])
        rm = _project_many(mech, pm) - uv_m
        rz = _project_many(zed_cam, pz) - uv_z
        return np.concatenate([rm.reshape(P, -1), rz.reshape(P, -1)], axis=1).ravel()

    m = P * N * 4
    sp = lil_matrix((m, 6 + 6 * P), dtype=int)
    for i in range(P):
        rows = slice(i * N * 4, (i + 1) * N * 4)
        sp[rows, 6 + 6 * i: 12 + 6 * i] = 1
        sp[i * N * 4 + N * 2: (i + 1) * N * 4, :6] = 1
    x0 = np.zeros(6 + 6 * P)
    sol = least_squares(residuals, x0, jac_sparsity=sp, loss="huber", f_scale=huber_px, x_scale="jac",
                        method="trf", xtol=1e-8, ftol=1e-8, gtol=1e-8, max_nfev=200)
    Te, Tbs = unpack(sol.x)
    r = sol.fun.reshape(P, 4 * N)
    res_m = r[:, :2 * N].reshape(P, N, 2)
    res_z = r[:, 2 * N:].reshape(P, N, 2)
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    dof = max(m - len(x0), 1)
    s2 = float(np.sum(sol.fun ** 2) / dof)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov = np.full((len(x0), len(x0)), np.nan)
    return Refined(Te, Tbs, res_m, res_z, cov[:6, :6], int(sol.nfev))


def _joint_refine_ragged(obs: list[PoseObs], mech: PinholeCamera, zed_cam: PinholeCamera, board,
                         T_zed_from_mech0: np.ndarray, huber_px: float = 1.0,
                         T_mech_from_board0: list[np.ndarray] | None = None) -> Refined:
    """``joint_refine`` for poses with different point sets (ChArUco partial views): the same residuals with each
    pose's own board points (all mech residuals, then all ZED residuals); ``res_mech``/``res_zed`` are lists."""
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix
    P = len(obs)
    Xs = [o.board_points(board) for o in obs]
    Ns = np.array([len(X) for X in Xs])
    starts = np.concatenate([[0], np.cumsum(Ns)])
    n_pts = int(starts[-1])
    Xh = np.concatenate([np.column_stack([X, np.ones(len(X))]) for X in Xs])
    pose_of = np.repeat(np.arange(P), Ns)
    uv_m = np.concatenate([o.mech_uv for o in obs])
    uv_z = np.concatenate([o.zed_uv for o in obs])
    Tb0 = T_mech_from_board0 or [o.T_mech_from_board for o in obs]

    def unpack(x):
        Te = _perturbed(T_zed_from_mech0, x[:6])
        Tbs = [_perturbed(Tb0[i], x[6 + 6 * i: 12 + 6 * i]) for i in range(P)]
        return Te, Tbs

    def residuals(x):
        Te, Tbs = unpack(x)
        Tm = np.stack(Tbs)[pose_of]  # (n, 4, 4): each point's board pose
        pm = np.einsum("nij,nj->ni", Tm[:, :3], Xh)
        pz = pm @ Te[:3, :3].T + Te[:3, 3]
        return np.concatenate([(mech.project(pm) - uv_m).ravel(), (zed_cam.project(pz) - uv_z).ravel()])

    m = 4 * n_pts
    sp = lil_matrix((m, 6 + 6 * P), dtype=int)
    for i in range(P):
        rows_m = slice(2 * starts[i], 2 * starts[i + 1])
        rows_z = slice(2 * n_pts + 2 * starts[i], 2 * n_pts + 2 * starts[i + 1])
        sp[rows_m, 6 + 6 * i: 12 + 6 * i] = 1
        sp[rows_z, 6 + 6 * i: 12 + 6 * i] = 1
        sp[rows_z, :6] = 1
    x0 = np.zeros(6 + 6 * P)
    sol = least_squares(residuals, x0, jac_sparsity=sp, loss="huber", f_scale=huber_px, x_scale="jac",
                        method="trf", xtol=1e-8, ftol=1e-8, gtol=1e-8, max_nfev=200)
    Te, Tbs = unpack(sol.x)
    rm, rz = sol.fun[:2 * n_pts].reshape(-1, 2), sol.fun[2 * n_pts:].reshape(-1, 2)
    res_m = [rm[starts[i]:starts[i + 1]] for i in range(P)]
    res_z = [rz[starts[i]:starts[i + 1]] for i in range(P)]
    J = sol.jac.toarray() if hasattr(sol.jac, "toarray") else np.asarray(sol.jac)
    s2 = float(np.sum(sol.fun ** 2) / max(m - len(x0), 1))
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov = np.full((len(x0), len(x0)), np.nan)
    return Refined(Te, Tbs, res_m, res_z, cov[:6, :6], int(sol.nfev))


# ---- depth-based corners ----------------------------------------------------------------------
def board_corners_from_depth(o: PoseObs, mech: PinholeCamera, board: BoardSpec, depth_cam: PinholeCamera | None = None,
                             T_mech_from_depth: np.ndarray | None = None) -> np.ndarray | None:
    """3D corners (mech frame) measured by the depth camera: a robust plane through the board's depth, intersected
    with the texture camera's corner rays. The board's area in the depth image comes from the texture camera's PnP
    pose mapped into the depth camera (the same camera, and the detected corners, when there is one camera)."""
    if o.depth_mm is None:
        return None
    depth_cam = depth_cam or mech
    T_md = np.eye(4) if T_mech_from_depth is None else np.asarray(T_mech_from_depth, float)
    X_depth = transform_points(invert_T(T_md) @ o.T_mech_from_board, o.board_points(board))
    uv_depth = depth_cam.project(X_depth)
    if not np.all(np.isfinite(uv_depth)):
        return None
    hull = cv2.convexHull(uv_depth.astype(np.float32)).reshape(-1, 2)
    centre = hull.mean(0)
    hull = centre + 0.92 * (hull - centre)  # stay off the board edge
    mask = np.zeros(o.depth_mm.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(hull).astype(np.int32)], 1)
    v, u = np.nonzero((mask > 0) & np.isfinite(o.depth_mm))
    if len(v) < 50:
        return None
    rays = depth_cam.ray_grid()[v, u]
    z = o.depth_mm[v, u].astype(np.float64)
    pts = transform_points(T_md, np.stack([rays[:, 0] * z, rays[:, 1] * z, z], axis=1))
    n, c, _ = fit_plane_robust(pts, threshold_mm=1.0)
    xy = mech.undistort_to_normalized(o.mech_uv)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    t = c / (d @ n)
    return d * t[:, None]


def measured_square_size_mm(corners_mech: np.ndarray, board: BoardSpec, ids: np.ndarray | None = None) -> float:
    """Median distance between neighbouring corners of one pose (mm); with ``ids`` (ChArUco, circle grids) the
    neighbours' distances scaled to the declared spacing (asymmetric grids' nearest neighbours are sqrt(2) apart)."""
    if ids is not None:
        from gtforge.core.targets import neighbour_pairs

        a, b = neighbour_pairs(board, ids)
        Xb = board.corners_board()[ids]
        ratio = np.linalg.norm(corners_mech[a] - corners_mech[b], axis=1) / np.linalg.norm(Xb[a] - Xb[b], axis=1)
        return float(np.median(ratio) * board.square_size_mm)
    g = corners_mech.reshape(board.rows, board.cols, 3)
    d = np.concatenate([np.linalg.norm(np.diff(g, axis=1), axis=2).ravel(),
                        np.linalg.norm(np.diff(g, axis=0), axis=2).ravel()])
    return float(np.median(d))


# ---- main entry -------------------------------------------------------------------------------
def detect_pose(name: str, texture: np.ndarray, depth_mm: np.ndarray | None, zed_left: np.ndarray,
                mech: PinholeCamera, zed: RectifiedStereo, board: BoardSpec,
                blur_px: float) -> tuple[PoseObs | None, PoseReport]:
    if getattr(board, "kind", "checkerboard") != "checkerboard":
        from gtforge.core.targets import detect_pose_target

        return detect_pose_target(name, texture, depth_mm, zed_left, mech, zed, board, blur_px)
    dm = detect_corners(texture, board)
    dz = detect_corners(zed_left, board)
    if dm is None or dz is None:
        which = " and ".join(w for w, d in (("structured-light", dm), ("ZED", dz)) if d is None)
        log.warning("capture %s: board not found in the %s image; skipped", name, which)
        return None, PoseReport(capture=name, status="skipped", reason=f"board not found in the {which} image")
    X = board.corners_board()
    T_mb = solve_pnp(X, dm.corners_uv, mech)
    T_zb = solve_pnp(X, dz.corners_uv, zed.left)
    blurred = bool(dm.sharpness_px > blur_px or dz.sharpness_px > blur_px)  # NaN (unmeasurable) is not blurred
    if blurred:
        log.warning("capture %s: blurred board (edge width %.1f / %.1f px)", name, dm.sharpness_px, dz.sharpness_px)
    def finite_or_none(x: float) -> float | None:
        return x if np.isfinite(x) else None

    rep = PoseReport(capture=name, status="used", sharpness_mech_px=finite_or_none(dm.sharpness_px),
                     sharpness_zed_px=finite_or_none(dz.sharpness_px), blurred=blurred)
    return PoseObs(name, dm.corners_uv, dz.corners_uv, T_mb, T_zb, depth_mm, dm, dz), rep


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(a.reshape(-1, 2) ** 2, axis=1))))


def jackknife_scale(T: np.ndarray, T_loo: list[np.ndarray], cov: np.ndarray) -> float | None:
    """``max(1, rms_i(C_jack[i, i] / cov[i, i]))`` over the six parameters, where ``C_jack`` is the jackknife
    covariance of the leave-one-out solutions ``T_loo`` around ``T`` (parameterised as ``cov``). None below 4.

    Measured (benchmarks/bench_uncertainty.py, tests/test_uncertainty.py): the normalised squared error of the
    extrinsic averages 10.9 with the Jacobian covariance on rendered boards (correlated detector errors) and 7.6 once
    scaled; with independent corner noise 5.7 unscaled and 4.5 scaled (6 is right). The mean ratio gave 8.5 / 4.7,
    the largest 4.5 / 3.5."""
    from scipy.spatial.transform import Rotation
    n = len(T_loo)
    if n < 4 or not np.all(np.isfinite(cov)):
        return None
    xs = np.array([np.concatenate([Rotation.from_matrix(Ti[:3, :3] @ T[:3, :3].T).as_rotvec(), Ti[:3, 3] - T[:3, 3]])
                   for Ti in T_loo])
    d = xs - xs.mean(axis=0)
    c_jack = (n - 1) / n * (d.T @ d)
    ratio = float(np.sqrt(np.mean((np.diag(c_jack) / np.maximum(np.diag(cov), 1e-30)) ** 2)))
    return max(1.0, ratio)


def transfer_error(o: PoseObs, T_zed_from_mech: np.ndarray, zed_cam: PinholeCamera, board: BoardSpec) -> np.ndarray:
    """Per-corner error (px) of mech-PnP board corners mapped into the ZED-left image."""
    X = transform_points(T_zed_from_mech @ o.T_mech_from_board, o.board_points(board))
    return np.linalg.norm(zed_cam.project(X) - o.zed_uv, axis=1)


def calibrate_observations(obs: list[PoseObs], reports: list[PoseReport], mech: PinholeCamera,
                           zed: RectifiedStereo, params: CalibrateParams,
                           progress: Callable[[str], None] | None = None, depth_cam: PinholeCamera | None = None,
                           T_mech_from_depth: np.ndarray | None = None) -> CalibrationFile:
    """Fuse and refine the extrinsic from detected poses (``obs``); ``reports`` is updated in place.
    ``depth_cam``/``T_mech_from_depth``: the depth map's camera when it is not the texture camera."""
    t0 = time.perf_counter()
    board = params.board.spec()
    if len(obs) < params.min_poses:
        raise InputError(None, "captures", f"at least {params.min_poses} poses where both cameras see the board",
                         f"{len(obs)} usable", "add board captures, or check the board size (--cols/--rows)")
    Ts = [o.T_zed_from_board @ invert_T(o.T_mech_from_board) for o in obs]
    T0, keep, rot_dev, tr_dev = robust_initial_extrinsic(Ts, params)
    rep_by_name = {r.capture: r for r in reports}
    for o, k, rd, td in zip(obs, keep, rot_dev, tr_dev):
        r = rep_by_name[o.name]
        r.init_rot_dev_deg, r.init_trans_dev_mm = float(rd), float(td)
        if not k:
            r.status, r.reason = "outlier", f"per-pose extrinsic off by {rd:.2f} deg / {td:.1f} mm"
            log.warning("capture %s: rejected as an outlier (%s)", o.name, r.reason)
    used = [o for o, k in zip(obs, keep) if k]
    if len(used) < params.min_poses:
        raise InputError(None, "captures", f"at least {params.min_poses} consistent poses", f"{len(used)}",
                         "the per-pose estimates disagree; check the board size and the image pairing")
    # the depth camera's own view of each board: its square size, and the --use-depth solve
    corners_depth = {}
    for o in used:
        X = board_corners_from_depth(o, mech, board, depth_cam, T_mech_from_depth)
        if X is not None and np.all(np.isfinite(X)):
            corners_depth[o.name] = X
    square_measured = None
    if len(corners_depth) >= 2:
        ids_of = {o.name: o.ids for o in used}
        square_measured = float(np.median([measured_square_size_mm(X, board, ids_of[n]) for n, X in corners_depth.items()]))
        dev_pct = (square_measured / board.square_size_mm - 1.0) * 100.0
        if params.square_check_pct and abs(dev_pct) > params.square_check_pct:
            raise InputError(None, "--square-mm", f"the board's square size as the depth camera measures it "
                             f"(within {params.square_check_pct:g} %)",
                             f"{board.square_size_mm:g} mm declared, {square_measured:.2f} mm measured in the depth "
                             f"of {len(corners_depth)} poses ({dev_pct:+.1f} %)",
                             f"pass --square-mm {square_measured:.1f} if that is the board; if the board is right, the "
                             "depth is off (depth_unit / depth_scale_mm in session.yaml)")
    if progress:
        progress("joint refinement")
    ref = joint_refine(used, mech, zed.left, board, T0, params.huber_px)
    allres = []
    region_res: dict[str, list[float]] = {}
    for i, o in enumerate(used):
        r = rep_by_name[o.name]
        r.rms_mech_px, r.rms_zed_px = _rms(ref.res_mech[i]), _rms(ref.res_zed[i])
        e = np.concatenate([np.linalg.norm(ref.res_mech[i], axis=1), np.linalg.norm(ref.res_zed[i], axis=1)])
        r.max_px = float(e.max())
        allres.append(e)
        # errors by ZED image region (3x3 grid)
        gx = np.clip((o.zed_uv[:, 0] / zed.left.width_px * 3).astype(int), 0, 2)
        gy = np.clip((o.zed_uv[:, 1] / zed.left.height_px * 3).astype(int), 0, 2)
        for k, en in enumerate(np.linalg.norm(ref.res_zed[i], axis=1)):
            region_res.setdefault(f"{['top', 'middle', 'bottom'][gy[k]]}-{['left', 'centre', 'right'][gx[k]]}", []).append(en)
    allres = np.concatenate(allres)
    cov = ref.cov_extrinsic
    loo_means, loo_maxs, loo_T = [], [], []
    if params.leave_one_out and len(used) > params.min_poses:
        for i, o in enumerate(used):
            if progress:
                progress(f"leave-one-out {i + 1}/{len(used)}")
            rest = [u for j, u in enumerate(used) if j != i]
            Tb = [t for j, t in enumerate(ref.T_mech_from_board) if j != i]
            ref_i = joint_refine(rest, mech, zed.left, board, ref.T_zed_from_mech, params.huber_px, Tb)
            e = transfer_error(o, ref_i.T_zed_from_mech, zed.left, board)
            r = rep_by_name[o.name]
            r.loo_transfer_mean_px, r.loo_transfer_max_px = float(e.mean()), float(e.max())
            loo_means.append(e.mean())
            loo_maxs.append(e.max())
            loo_T.append(ref_i.T_zed_from_mech)
    T_final = ref.T_zed_from_mech
    # The Jacobian covariance assumes independent corner errors; a detector's errors are not (perspective and
    # blur bias whole poses). The leave-one-pose-out solutions' jackknife spread sees that: where it is larger (the
    # RMS ratio over the six parameters), the covariance is scaled up by the ratio (never down).
    jack_scale = jackknife_scale(T_final, loo_T, ref.cov_extrinsic)
    cov = cov * (jack_scale or 1.0)
    methods = [MethodResult(method="reprojection", T_zed_from_mech=T_final.tolist(),
                            rms_zed_px=_rms(np.concatenate([np.reshape(r, (-1, 2)) for r in ref.res_zed])))]
    method = "reprojection"
    verdict_reasons: list[str] = []
    fail = False
    if params.use_depth:
        T_d, rms_d, cov_d = _depth_method(used, corners_depth, zed, T_final)
        if T_d is not None:
            dr, dt = pose_difference(T_final, T_d)
            methods.append(MethodResult(method="depth", T_zed_from_mech=T_d.tolist(), rms_zed_px=rms_d,
                                        rot_diff_to_primary_deg=dr, trans_diff_to_primary_mm=dt))
            sr = float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))))
            st = float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0)))
            lim_deg, lim_mm = max(params.methods_agree_deg, 5 * sr), max(params.methods_agree_mm, 5 * st)
            if dr > lim_deg or dt > lim_mm:
                fail = True
                verdict_reasons.append(
                    f"--use-depth: the depth method differs from the reprojection method by {dr:.3f} deg / {dt:.2f} mm "
                    f"(allowed {lim_deg:.3f} deg / {lim_mm:.2f} mm): the depth's scale or bias, or the board size, "
                    "is off")
            T_final, method = T_d, "depth"
            if cov_d is not None:
                cov = cov_d * (jack_scale or 1.0)  # the ZED corners' correlated errors affect both solves
        else:
            verdict_reasons.append("--use-depth: fewer than 2 poses with board depth; the reprojection method was used")
    sig_r = np.degrees(np.sqrt(np.clip(np.diag(cov)[:3], 0, None)))
    sig_t = np.sqrt(np.clip(np.diag(cov)[3:], 0, None))
    n_bad = sum(r.status != "used" for r in reports)
    if n_bad:
        verdict_reasons.append(f"{n_bad} capture(s) skipped or rejected as outliers (see poses)")
    if any(r.blurred for r in reports if r.status == "used"):
        verdict_reasons.append("some used poses are blurred")
    if len(used) < 6:
        verdict_reasons.append(f"only {len(used)} poses: 6 or more give a better-constrained extrinsic")
    loo_mean = float(np.mean(loo_means)) if loo_means else None
    if loo_mean is not None and loo_mean > LOO_WARN_PX:
        verdict_reasons.append(f"leave-one-out transfer {loo_mean:.3f} px > {LOO_WARN_PX} px")
    rig = Rig(zed=zed, mech=mech, T_zed_from_mech=T_final, depth_cam=depth_cam,
              T_mech_from_depth=None if T_mech_from_depth is None else np.asarray(T_mech_from_depth).tolist())
    result = CalibrationFile(
        rig=rig, board=params.board, method=method, captures_used=[o.name for o in used],
        rms_px=float(np.sqrt(np.mean(allres ** 2))), max_px=float(allres.max()),
        sigma_rot_xyz_deg=sig_r.tolist(), sigma_trans_xyz_mm=sig_t.tolist(),
        sigma_rot_deg=float(np.sqrt(np.sum(sig_r ** 2))), sigma_trans_mm=float(np.sqrt(np.sum(sig_t ** 2))),
        loo_transfer_mean_px=loo_mean,
        loo_transfer_max_px=float(np.max(loo_maxs)) if loo_maxs else None,
        poses=sorted(reports, key=lambda r: -(r.max_px or 0.0)),
        methods=methods, cov_extrinsic_rad_mm=cov.tolist() if np.all(np.isfinite(cov)) else None,
        cov_jackknife_scale=jack_scale,
        square_size_measured_mm=square_measured,
        verdict="FAIL" if fail else ("WARN" if verdict_reasons else "PASS"), verdict_reasons=verdict_reasons,
        residuals_by_region_px={k: float(np.sqrt(np.mean(np.square(v)))) for k, v in region_res.items()},
        time_s=time.perf_counter() - t0)
    # what gtforge.core.coverage needs (calibrate() attaches the coverage report; other callers may: attach_coverage)
    result._coverage_inputs = dict(used=used, T_mech_from_board=ref.T_mech_from_board, T_zed_from_mech=ref.T_zed_from_mech,
                                   mech=mech, zed_cam=zed.left, board=board,
                                   cov=cov if np.all(np.isfinite(cov)) else None,
                                   rms_px=float(np.sqrt(np.mean(allres ** 2))), jack_scale=jack_scale)
    result._residuals = {o.name: dict(mech_uv=o.mech_uv, res_mech=ref.res_mech[i], zed_uv=o.zed_uv, res_zed=ref.res_zed[i])
                         for i, o in enumerate(used)}
    return result


def _depth_method(used: list[PoseObs], corners_depth: dict[str, np.ndarray], zed: RectifiedStereo,
                  T_init: np.ndarray) -> tuple[np.ndarray | None, float, np.ndarray | None]:
    """3D-2D solve: the depth camera's board corners (mech frame) against the ZED detections, all poses at once.
    Returns (T_zed_from_mech, RMS px, 6x6 covariance in the CalibrationFile parameterisation)."""
    from scipy.optimize import least_squares
    P3 = [corners_depth[o.name] for o in used if o.name in corners_depth]
    P2 = [o.zed_uv for o in used if o.name in corners_depth]
    if len(P3) < 2:
        log.warning("--use-depth: fewer than 2 poses with board depth; depth method skipped")
        return None, float("nan"), None
    P3, P2 = np.concatenate(P3), np.concatenate(P2)

    def residuals(x):
        return (zed.left.project(transform_points(_perturbed(T_init, x), P3)) - P2).ravel()

    sol = least_squares(residuals, np.zeros(6), method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    T = _perturbed(T_init, sol.x)
    res = sol.fun.reshape(-1, 2)
    # re-linearise at the solution so the covariance is in the parameterisation around the written T
    J = least_squares(lambda x: (zed.left.project(transform_points(_perturbed(T, x), P3)) - P2).ravel(),
                      np.zeros(6), max_nfev=1, method="lm").jac
    s2 = float(np.sum(res ** 2) / max(res.size - 6, 1))
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        cov = None
    return T, _rms(res), cov


def calibrate(session_dir: str | Path, out_path: str | Path | None = None, params: CalibrateParams | None = None,
              captures: list[str] | None = None, exclude: list[str] | None = None,
              progress: Callable[[str], None] | None = None) -> CalibrationFile:
    """Calibrate from a capture session's ``board/`` captures; writes ``out_path`` (YAML) when given
    (an existing folder, or a path ending in ``/``, gets ``calibration.yaml`` inside it)."""
    from gtforge.io.captures import open_session

    from gtforge.core.targets import check_board_model

    params = params or CalibrateParams()
    session = open_session(session_dir)
    params = params.model_copy(update={"board": session_board(session, params.board, "board" in params.model_fields_set)})
    check_board_model(params.board)
    board = params.board.spec()
    if out_path is not None:
        out_path = calibration_output_path(out_path)
        session.refuse_output_inside_captures(out_path)
    dirs = session.select("board", captures, exclude)
    from gtforge.core.rectification import RectificationMeter, rectified_by, settle_zed_conf_reading

    checker = params.board.kind == "checkerboard"
    # raw ZED images + SN.conf: the conf reading comes from the board images (re-opens the session with it);
    # the rectification is measured on full checkerboards only (other targets: not yet, docs/targets.md)
    session, zed_conf = settle_zed_conf_reading(session, dirs, board, progress=progress) if checker else (session, None)
    selfcal = None
    if params.self_rectify:
        # every capture with both images: the scenes' texture constrains the rows as well as the boards
        scene_root = session.root / session.config.scenes_dir
        scene_dirs = session.capture_dirs("scenes") if scene_root.is_dir() and any(scene_root.iterdir()) else []
        selfcal = self_rectify(session, dirs + scene_dirs, SelfRectifyParams(), progress)
        if selfcal.correction is not None:
            session = open_session(session_dir, zed_conf_reading=zed_conf.reading if zed_conf else None,
                                   zed_right_correction=selfcal.correction)
    meter = RectificationMeter(board, session.zed.left, rectified_by(session)) if checker else None
    obs, reports = [], []
    for k, d in enumerate(dirs):
        if progress:
            progress(f"detect {d.name} ({k + 1}/{len(dirs)})")
        cap = session.load_capture(d, need_right=False)
        o, rep = detect_pose(d.name, cap.mech_texture, cap.mech_depth_mm, cap.zed_left, session.mech, session.zed,
                             board, params.blur_sharpness_px)
        reports.append(rep)
        if o is not None:
            obs.append(o)
            if meter is not None:
                meter.add(d.name, cap.zed_right, left_uv=o.zed_uv)
    result = calibrate_observations(obs, reports, session.mech, session.zed, params, progress, session.depth_cam,
                                    session.T_mech_from_depth)
    result.attach_coverage()
    result.session_dir = str(Path(session_dir).resolve())
    result.zed_conf, result.rectification = zed_conf, (meter.result() if meter is not None else None)
    result.zed_self_rectification = selfcal
    stereo_warnings = (zed_conf.warnings if zed_conf else []) + (result.rectification.warnings if result.rectification else [])
    if selfcal is not None and selfcal.status == "not determined":
        stereo_warnings.append(selfcal.summary_line())
    if stereo_warnings:
        result.verdict_reasons = result.verdict_reasons + stereo_warnings
        result.verdict = "WARN" if result.verdict == "PASS" else result.verdict
    if out_path is not None:
        result.write(out_path)
    return result



def session_board(session, given: BoardModel, given_explicitly: bool) -> BoardModel:
    """The board to use: session.yaml's ``board:`` when there is one, with the fields given explicitly (CLI options,
    ``given.model_fields_set``) overriding it; else ``given``."""
    declared = getattr(session.config, "board", None)
    if declared is None:
        return given
    if not given_explicitly:
        return declared
    return BoardModel.model_validate({**declared.model_dump(), **{k: getattr(given, k) for k in given.model_fields_set}})


def check_rig_matches_session(rig: Rig, session, calib_path: str | Path,
                              hint: str = "was this calibration made for another session?") -> None:
    """The calibration's cameras have the session's image sizes (a calibration of another rig or resolution would
    otherwise fail deep inside a stage)."""
    for name, a, b in (("mech", rig.mech, session.mech), ("zed", rig.zed.left, session.zed.left),
                       ("depth_cam", rig.depth_camera, session.depth_camera)):
        if (a.width_px, a.height_px) != (b.width_px, b.height_px):
            raise InputError(calib_path, f"rig.{name}", f"{b.width_px}x{b.height_px} px (the session's camera)",
                             f"{a.width_px}x{a.height_px} px", hint)


def open_calibrated_session(session_dir: str | Path, calibration: str | Path, out_path: str | Path | None,
                            example_name: str):
    """The prologue of the stages that turn a calibration into a new one (refine, calibrate-scale): the calibration,
    the session as it sees it (``CalibrationFile.open_session``), checked against it, and the output path, which may
    be neither inside the captures nor the input file. Returns ``(calib, session, out_path or None)``."""
    calib_path = Path(calibration)
    calib = CalibrationFile.read(calib_path)
    session = calib.open_session(session_dir)
    check_rig_matches_session(calib.rig, session, calib_path)
    if out_path is not None:
        out_path = calibration_output_path(out_path)
        session.refuse_output_inside_captures(out_path)
        if Path(out_path).resolve() == calib_path.resolve():
            raise InputError(out_path, "--output", "a new file (the input calibration stays as it is)",
                             "the input calibration", f"write the new calibration beside it, e.g. {example_name}")
    return calib, session, out_path


def calibration_output_path(out_path: str | Path) -> Path:
    """``-o DIR/`` or an existing folder means ``DIR/calibration.yaml``."""
    p = Path(out_path)
    if p.is_dir() or str(out_path).endswith(("/", "\\")):
        return p / "calibration.yaml"
    return p
