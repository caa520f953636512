"""Rigid transforms (4x4 float64, named ``T_dst_from_src``) and small geometry helpers."""
from __future__ import annotations

import numba
import numpy as np


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a 4x4 transform from a 3x3 rotation and a 3-vector translation (mm)."""
    T_dst_from_src = np.eye(4)
    T_dst_from_src[:3, :3] = np.asarray(R, dtype=np.float64)
    T_dst_from_src[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T_dst_from_src


def mask_bounding_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(y0, y1, x0, x1)`` (ends exclusive) of a 2-D mask's True pixels; None where there are none."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    return (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1) if len(rows) else None


@numba.njit(cache=True)
def _n_finite(row, lo, hi):
    """How many of ``row[lo:hi]`` are finite: a branch-free count, vectorised."""
    n = 0
    part = row[lo:hi]  # a slice from index 0: plain loads
    for u in range(hi - lo):
        n += abs(part[u]) < np.inf  # (NaN compares false)
    return n


@numba.njit(cache=True)
def finite_rows(a):
    """``(y0, y1)`` (end exclusive) of the rows of a 2-D float array holding a finite value, ``(0, 0)`` where none
    does: rows counted from the top down to the first such row and from the bottom up to the last (the rows between
    are not read)."""
    H, W = a.shape
    y0 = 0
    while y0 < H and _n_finite(a[y0], 0, W) == 0:
        y0 += 1
    if y0 == H:
        return 0, 0
    y1 = H
    while _n_finite(a[y1 - 1], 0, W) == 0:  # row y0 holds one: stops there at the latest
        y1 -= 1
    return y0, y1


@numba.njit(cache=True)
def finite_box(a):
    """``(y0, y1, x0, x1)`` (ends exclusive) of a 2-D float array's finite values; ``(0, 0, 0, 0)`` where there are
    none. The image-sized passes of a build run on this box only: a depth camera narrower than the ZED fills about a
    third of its image (the benchmark's scenes: 37 % of 2208x1242). It reads little more than what lies outside the
    box: rows from the top and from the bottom until one holds a finite value, then in each row between them only the
    columns left of the leftmost and right of the rightmost finite value found so far (vectorised counts; a scalar
    search only where one is there)."""
    H, W = a.shape
    y0, y1 = finite_rows(a)
    if y1 == 0:
        return 0, 0, 0, 0
    x0, x1 = W, 0  # the columns of the finite values found so far: [x0, x1)
    for v in range(y0, y1):
        row = a[v]
        if _n_finite(row, 0, x0):
            u = 0
            while not abs(row[u]) < np.inf:
                u += 1
            x0 = u
        if _n_finite(row, max(x1, x0), W):
            u = W - 1
            while not abs(row[u]) < np.inf:
                u -= 1
            x1 = u + 1
    return y0, y1, x0, x1


def T_from_rotvec(rotvec_rad: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation  # here, not at import: importing scipy slows every process start

    return make_T(Rotation.from_rotvec(np.asarray(rotvec_rad, float).reshape(3)).as_matrix(), t_mm)


def invert_T(T_dst_from_src: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform: ``T_src_from_dst = invert_T(T_dst_from_src)``."""
    R = T_dst_from_src[:3, :3]
    t = T_dst_from_src[:3, 3]
    return make_T(R.T, -R.T @ t)


def transform_points(T_dst_from_src: np.ndarray, pts_src: np.ndarray) -> np.ndarray:
    """Apply a transform to an ``(N, 3)`` point list."""
    pts = np.asarray(pts_src, dtype=np.float64)
    return pts @ T_dst_from_src[:3, :3].T + T_dst_from_src[:3, 3]


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix (deg)."""
    c = (np.trace(R[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def pose_difference(T_dst_from_src_a: np.ndarray, T_dst_from_src_b: np.ndarray) -> tuple[float, float]:
    """(rotation angle deg, translation distance mm) between two transforms of the same frames."""
    return (rotation_angle_deg(T_dst_from_src_a[:3, :3].T @ T_dst_from_src_b[:3, :3]),
            float(np.linalg.norm(T_dst_from_src_a[:3, 3] - T_dst_from_src_b[:3, 3])))


def look_at_T_cam_from_world(cam_pos_mm: np.ndarray, target_mm: np.ndarray,
                             up_world: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera (OpenCV axes) at ``cam_pos_mm`` looking at ``target_mm``; image 'up' towards ``up_world``."""
    c = np.asarray(cam_pos_mm, float)
    z = np.asarray(target_mm, float) - c
    z /= np.linalg.norm(z)
    up = np.asarray(up_world, float)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_world_from_cam = np.stack([x, y, z], axis=1)
    return invert_T(make_T(R_world_from_cam, c))


def fit_plane(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through ``(N, 3)`` points: unit normal n and offset c with n.p = c."""
    centroid = pts.mean(axis=0)
    _, _, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    n = vt[-1]
    return n, float(n @ centroid)


@numba.njit(cache=True)
def _inlier_counts(x, y, z, normals, offsets, threshold_mm):
    """For each plane ``k``: how many points ``(x[i], y[i], z[i])`` have ``|n_k . p - c_k| < threshold_mm``. Four planes
    a pass over the points (each point's coordinates loaded once for four tests, the same expression for each), the
    last ones one at a time."""
    K = len(normals)
    counts = np.zeros(K, np.int64)
    k = 0
    while k + 4 <= K:
        a0, a1, a2, ac = normals[k, 0], normals[k, 1], normals[k, 2], offsets[k]
        b0, b1, b2, bc = normals[k + 1, 0], normals[k + 1, 1], normals[k + 1, 2], offsets[k + 1]
        c0, c1, c2, cc = normals[k + 2, 0], normals[k + 2, 1], normals[k + 2, 2], offsets[k + 2]
        d0, d1, d2, dc = normals[k + 3, 0], normals[k + 3, 1], normals[k + 3, 2], offsets[k + 3]
        ma = mb = mc = md = 0
        for i in range(len(x)):
            xi, yi, zi = x[i], y[i], z[i]
            ma += abs(xi * a0 + yi * a1 + zi * a2 - ac) < threshold_mm
            mb += abs(xi * b0 + yi * b1 + zi * b2 - bc) < threshold_mm
            mc += abs(xi * c0 + yi * c1 + zi * c2 - cc) < threshold_mm
            md += abs(xi * d0 + yi * d1 + zi * d2 - dc) < threshold_mm
        counts[k], counts[k + 1], counts[k + 2], counts[k + 3] = ma, mb, mc, md
        k += 4
    for j in range(k, K):
        n0, n1, n2, c = normals[j, 0], normals[j, 1], normals[j, 2], offsets[j]
        m = 0
        for i in range(len(x)):
            m += abs(x[i] * n0 + y[i] * n1 + z[i] * n2 - c) < threshold_mm
        counts[j] = m
    return counts


def fit_plane_robust(pts: np.ndarray, threshold_mm: float = 1.0, iterations: int = 200,
                     rng: np.random.Generator | None = None) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane followed by a least-squares refit on the inliers.

    Returns (normal, offset, inlier mask). Requires at least 3 points.
    """
    pts = np.asarray(pts, dtype=np.float64)
    n_pts = len(pts)
    if n_pts < 3:
        raise ValueError(f"fit_plane_robust needs >= 3 points, got {n_pts}")
    rng = rng or np.random.default_rng(0)
    # every hypothesis at once (three distinct points each), all scored against all points in one compiled pass
    idx = np.stack([rng.choice(n_pts, 3, replace=False) for _ in range(iterations)])
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    ok = norm > 1e-12
    normals, a = normals[ok] / norm[ok, None], a[ok]
    offsets = np.einsum("ij,ij->i", normals, a)
    best = None
    if len(normals):
        xyz = np.ascontiguousarray(pts.T)
        counts = _inlier_counts(xyz[0], xyz[1], xyz[2], normals, offsets, float(threshold_mm))
        j = int(np.argmax(counts))  # the first of the best hypotheses
        if counts[j] >= 3:
            best = np.abs(pts @ normals[j] - offsets[j]) < threshold_mm
    if best is None:
        best = np.ones(n_pts, bool)
    n, off = fit_plane(pts[best])
    for _ in range(3):  # refit on the plane's inliers, three times at most
        inliers = np.abs(pts @ n - off) < threshold_mm
        if inliers.sum() < 3:
            inliers = np.ones(n_pts, bool)
        if np.array_equal(inliers, best):
            break  # a fixed point: every further refit returns this plane again
        best = inliers
        n, off = fit_plane(pts[best])
    return n, off, best


def perturb_left(T_dst_from_src: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``[exp(omega) R | t + delta_t]`` for ``T_dst_from_src = [R | t]`` and ``x = (omega_rad (3), delta_t_mm (3))``:
    the left perturbation every covariance of gtforge is written in (``cov_extrinsic_rad_mm``)."""
    from scipy.spatial.transform import Rotation  # here, not at import: importing scipy costs every process start

    return make_T(Rotation.from_rotvec(x[:3]).as_matrix() @ T_dst_from_src[:3, :3], T_dst_from_src[:3, 3] + x[3:])


def rotvec_between(T_dst_from_src_a: np.ndarray, T_dst_from_src_b: np.ndarray) -> np.ndarray:
    """``omega`` (rad) with ``R_b = exp(omega) R_a``: the rotation part of the left perturbation (``perturb_left``)
    that takes ``T_dst_from_src_a`` (rotation ``R_a``) to ``T_dst_from_src_b`` (``R_b``)."""
    from scipy.spatial.transform import Rotation  # here, not at import: importing scipy costs every process start

    return Rotation.from_matrix(T_dst_from_src_b[:3, :3] @ T_dst_from_src_a[:3, :3].T).as_rotvec()

