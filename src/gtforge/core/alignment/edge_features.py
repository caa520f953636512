"""The pieces of ``gtforge.core.alignment.edge_alignment``: the depth camera's edges as 3-D points (``depth_edges``: the
depth map's silhouettes; ``texture_edges``: the depth camera's own image's edges on surfaces), the colour image
undistorted into a pinhole camera and its edge-strength images (``undistort_image``, ``edge_strength``), and the score
of a candidate pose (``edge_scores``) and the pixel offset that is left (``edge_offset_px``). The estimator that uses
them is ``gtforge.core.alignment.edge_alignment``; its module docstring says how they fit together."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from gtforge.core.camera import PinholeCamera
from gtforge.core.geometry import invert_T, perturb_left, transform_points
from gtforge.core.alignment.photometric import to_gray
from gtforge.core.ground_truth.reproject import ReprojectParams, project_depth_to_camera


@dataclass(frozen=True)
class DepthEdges:
    """Depth silhouettes as 3-D points in the depth camera (``pts_depth_mm`` (N, 3)); ``axis`` (N,) 0: between
    horizontal neighbours (read against ``|dI/dx|``), 1: between vertical neighbours (``|dI/dy|``); ``side`` (N,)
    +1 when the farther surface lies towards +u (+v), -1 towards -u (-v)."""

    pts_depth_mm: np.ndarray
    axis: np.ndarray
    side: np.ndarray
    structure: np.ndarray  # (N,) id of the connected edge structure (one contour) the point belongs to

    def __len__(self) -> int:
        return len(self.axis)

    def subset(self, keep: np.ndarray) -> DepthEdges:
        return DepthEdges(self.pts_depth_mm[keep], self.axis[keep], self.side[keep], self.structure[keep])

    def __add__(self, other: DepthEdges) -> DepthEdges:
        """Both sets; ``other``'s structures renumbered after this one's (a contour stays one observation)."""
        shift = int(self.structure.max()) + 1 if len(self) else 0
        return DepthEdges(np.concatenate([self.pts_depth_mm, other.pts_depth_mm]),
                          np.concatenate([self.axis, other.axis]), np.concatenate([self.side, other.side]),
                          np.concatenate([self.structure, other.structure + shift]))


def render_depth(depth_mm: np.ndarray, depth_cam: PinholeCamera, T_color_from_depth: np.ndarray,
                 pinhole: PinholeCamera) -> np.ndarray:
    """The depth rendered into ``pinhole`` at ``T_color_from_depth`` (mesh mode; ``rendered_z_mm`` of
    ``depth_edges`` and ``texture_edges``, which ``align_color_to_depth`` renders once for both)."""
    return project_depth_to_camera(depth_mm, depth_cam, T_color_from_depth, pinhole, ReprojectParams())


def _edge_components(vu: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(N,)`` label of each edge pixel ``vu`` (N, 2) ``(v, u)``: the connected components of the edge pixels
    (8-connected, across one-pixel breaks)."""
    mask = np.zeros(shape, np.uint8)
    mask[vu[:, 0], vu[:, 1]] = 1
    _, labels = cv2.connectedComponents(cv2.dilate(mask, np.ones((3, 3), np.uint8)), connectivity=8)
    return labels[vu[:, 0], vu[:, 1]]


def depth_edges(depth_mm: np.ndarray, depth_cam: PinholeCamera, T_color_from_depth: np.ndarray,
                pinhole: PinholeCamera, jump_ratio: float = 1.05, gap_px: int = 8,
                rendered_z_mm: np.ndarray | None = None) -> DepthEdges:
    """The foreground side of every depth silhouette the colour camera sees, as 3-D points in the depth camera.

    The depth is rendered into ``pinhole`` (the undistorted colour camera) at ``T_color_from_depth`` by gtforge's
    reprojection core (``project_depth_to_camera``, mesh mode): the same surfaces, cut at the same silhouettes,
    that ground truth built from this depth shows (a silhouette blurred over a few mixed depth pixels is cut where
    the mesh stops, and a foreground the colour camera cannot see is not an edge). A rendered pixel is an edge
    when the first rendered pixel beyond it (1 to ``gap_px + 1`` pixels away, across what the colour camera sees
    and the depth camera did not) is at least ``jump_ratio`` times farther. The renderer draws a surface up to its
    last depth-pixel centre, half a depth pixel inside the true silhouette, and a pixel centre lies on average
    half a pixel inside what is drawn: each edge is placed ``0.5 + 0.5 f_colour / f_depth`` px beyond the
    foreground pixel, back-projected at the foreground's depth and carried into the depth camera's frame, where it
    stays fixed while the pose is refined. ``tests/io/test_real_frame.py`` measures the misalignment with the same
    edges (its own copy of this rule)."""
    z = rendered_z_mm if rendered_z_mm is not None else render_depth(depth_mm, depth_cam, T_color_from_depth, pinhole)
    half_px = (0.5 * pinhole.fx_px / depth_cam.fx_px, 0.5 * pinhole.fy_px / depth_cam.fy_px)
    uv_all, z_all, axes, sides, pix = [], [], [], [], []
    for axis in (0, 1):
        zz = z if axis == 0 else z.T
        finite = np.isfinite(zz)
        for side in (1, -1):
            beyond = np.full(zz.shape, np.nan)  # the nearest rendered depth 1..gap_px+1 pixels away towards `side`
            for k in range(gap_px + 1, 0, -1):
                shifted = np.full(zz.shape, np.nan)
                if side == 1:
                    shifted[:, :-k] = zz[:, k:]
                else:
                    shifted[:, k:] = zz[:, :-k]
                beyond = np.where(np.isfinite(shifted), shifted, beyond)
            with np.errstate(invalid="ignore"):
                edge = finite & (beyond > zz * jump_ratio)
            r, c = np.nonzero(edge)
            along = c + side * (0.5 + half_px[axis])
            uv_all.append(np.column_stack([along, r]) if axis == 0 else np.column_stack([r, along]))
            z_all.append(zz[r, c])
            pix.append(np.column_stack([r, c]) if axis == 0 else np.column_stack([c, r]))  # (v, u)
            axes.append(np.full(len(r), axis, np.int8))
            sides.append(np.full(len(r), side, np.int8))
    pts_color = pinhole.unproject(np.concatenate(uv_all).astype(np.float64), np.concatenate(z_all))
    # structures: the connected components of the edge pixels (8-connected, across one-pixel breaks), each split by
    # direction and side: an object's left, right, upper and lower silhouettes meet different colour edges (a
    # board's or a fruit's one contour would otherwise be one observation of a 2-D shift)
    vu = np.concatenate(pix)
    axis, side = np.concatenate(axes), np.concatenate(sides)
    key = np.column_stack([_edge_components(vu, z.shape), axis, side])
    _, structure = np.unique(key, axis=0, return_inverse=True) if len(key) else (None, np.zeros(0, np.int64))
    return DepthEdges(transform_points(invert_T(T_color_from_depth), pts_color), axis, side, structure.ravel())


def texture_edges(texture: np.ndarray, depth_mm: np.ndarray, depth_cam: PinholeCamera,
                  T_color_from_depth: np.ndarray, pinhole: PinholeCamera, top_fraction: float = 0.2,
                  max_relief: float = 0.02, min_length_px: int = 20, tile_px: int = 16,
                  rendered_z_mm: np.ndarray | None = None) -> DepthEdges:
    """The edges of the depth camera's own image (an infrared image, a structured-light camera's 2-D texture:
    ``texture`` pixel-aligned with ``depth_mm``) as 3-D points in the depth camera.

    The texture's grey levels go through ``log1p`` (an infrared image spans four decades; a ratio is what a
    reflectance edge keeps from one camera to the other) and a 0.7 px blur. An edge between horizontal (vertical)
    neighbours is a local maximum along u (v) of ``|difference|`` among the ``top_fraction`` strongest, on a surface
    (both neighbours' depths valid and within ``max_relief`` of each other: a texture edge on a depth jump belongs to
    the silhouettes), placed by a parabola through the maximum and its neighbours, back-projected at the mean of the
    two depths. A point the colour camera does not see (the depth rendered into ``pinhole`` at
    ``T_color_from_depth`` is more than ``max_relief`` nearer at its pixel) is dropped, and so is a connected
    component of edge pixels shorter than ``min_length_px`` (speckle). Structures (the covariance's observations):
    a connected component's piece within one ``tile_px`` square of the depth image."""
    depth_cam.check_image_size(np.shape(texture), None, "texture (must be pixel-aligned with the depth)")
    grey = np.log1p(np.maximum(to_gray(texture).astype(np.float64), 0.0))
    grey = cv2.GaussianBlur(grey, (0, 0), 0.7)
    pts, axes, sides, pix = [], [], [], []
    for axis in (0, 1):
        g = np.diff(grey if axis == 0 else grey.T, axis=1)
        zz = depth_mm if axis == 0 else depth_mm.T
        a = np.abs(g)
        z0, z1 = zz[:, :-1].astype(np.float64), zz[:, 1:].astype(np.float64)
        with np.errstate(invalid="ignore"):
            surface = np.isfinite(z0) & np.isfinite(z1) & (np.abs(z1 - z0) < max_relief * np.minimum(z0, z1))
        if not surface.any():
            continue
        threshold = np.quantile(a[surface], 1.0 - top_fraction)
        peak = np.zeros_like(surface)
        peak[:, 1:-1] = (a[:, 1:-1] > a[:, :-2]) & (a[:, 1:-1] >= a[:, 2:]) & (a[:, 1:-1] > threshold)
        r, c = np.nonzero(surface & peak)
        f0, f1, f2 = a[r, c - 1], a[r, c], a[r, c + 1]
        curvature = f0 - 2 * f1 + f2
        with np.errstate(invalid="ignore", divide="ignore"):
            offset = np.where(curvature < 0, 0.5 * (f0 - f2) / curvature, 0.0)
        along = c + 0.5 + np.clip(offset, -0.5, 0.5)  # the difference [c] sits between pixels c and c + 1
        uv = np.column_stack([along, r]) if axis == 0 else np.column_stack([r, along])
        pts.append(depth_cam.unproject(uv.astype(np.float64), 0.5 * (z0[r, c] + z1[r, c])))
        axes.append(np.full(len(r), axis, np.int8))
        sides.append(np.where(g[r, c] > 0, 1, -1).astype(np.int8))
        pix.append(np.column_stack([r, c]) if axis == 0 else np.column_stack([c, r]))
    if not pts:
        return DepthEdges(np.zeros((0, 3)), np.zeros(0, np.int8), np.zeros(0, np.int8), np.zeros(0, np.int64))
    P, vu = np.concatenate(pts), np.concatenate(pix)
    component = _edge_components(vu, np.shape(depth_mm))
    _, inverse, counts = np.unique(component, return_inverse=True, return_counts=True)
    long_enough = counts[inverse] >= min_length_px  # speckle and noise make short pieces
    # one observation: a component's piece within one tile of tile_px. Texture edges join into networks that
    # span the image, and a handful of giant structures would leave the sandwich's B near 0 at the maximiser
    tile = (vu[:, 0] // tile_px) * (np.shape(depth_mm)[1] // tile_px + 1) + vu[:, 1] // tile_px
    _, structure = np.unique(np.column_stack([component, tile]), axis=0, return_inverse=True)
    edges = DepthEdges(P, np.concatenate(axes), np.concatenate(sides), structure.ravel()).subset(long_enough)
    P = edges.pts_depth_mm
    # seen by the colour camera: the rendered surface at its pixel is this one, not a nearer one
    z_color = transform_points(T_color_from_depth, P)[:, 2]
    uv = np.round(pinhole.project(transform_points(T_color_from_depth, P))).astype(np.int64)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < pinhole.width_px) & (uv[:, 1] >= 0) & (uv[:, 1] < pinhole.height_px)
    seen = np.zeros(len(P), bool)
    rendered = rendered_z_mm if rendered_z_mm is not None else render_depth(depth_mm, depth_cam, T_color_from_depth,
                                                                             pinhole)
    zr = rendered[uv[inside, 1], uv[inside, 0]]
    with np.errstate(invalid="ignore"):
        seen[inside] = np.abs(zr - z_color[inside]) < max_relief * z_color[inside]
    return edges.subset(seen)


def undistort_image(image: np.ndarray, cam: PinholeCamera) -> tuple[np.ndarray, PinholeCamera]:
    """The image resampled into the pinhole version of ``cam`` (same K, no distortion): every pinhole pixel's ray
    through gtforge's lens model into the raw image, bilinear (``cv2.remap``). Edges are scored in a pinhole
    camera so that projecting a candidate pose's points is one matrix product."""
    cam.check_image_size(image.shape, None, "colour image")
    pinhole = cam.model_copy(update={"dist_coeffs": []})
    if not cam.has_distortion:
        return image, pinhole
    rays = pinhole.ray_grid().reshape(-1, 2)
    uv = cam.project(np.column_stack([rays, np.ones(len(rays))]))
    uv = uv.reshape(pinhole.height_px, pinhole.width_px, 2).astype(np.float32)
    return cv2.remap(image, uv[..., 0], uv[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT), pinhole


def edge_strength(image: np.ndarray, blur_sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """``(|dI/dx|, |dI/dy|)`` of the grey image (grey levels / px), Gaussian-blurred by ``blur_sigma_px``. The x
    image's ``[v, u]`` sits at ``(u + 0.5, v)``, the y image's at ``(u, v + 0.5)`` (differences between
    neighbours). Direction matters: a silhouette between horizontal neighbours should meet a colour edge across x,
    not a horizontal texture line that happens to pass by. The blur makes the score smooth over a pixel or two."""
    grey = to_gray(image).astype(np.float32)
    gx = cv2.GaussianBlur(np.abs(np.diff(grey, axis=1)), (0, 0), blur_sigma_px)
    gy = cv2.GaussianBlur(np.abs(np.diff(grey, axis=0)), (0, 0), blur_sigma_px)
    return gx, gy


def perturb(T_color_from_depth: np.ndarray, omega_rad: np.ndarray, delta_t_mm: np.ndarray) -> np.ndarray:
    """The left perturbation of docs/conventions.md: ``[exp(omega) R | t + delta_t]`` (``geometry.perturb_left``)."""
    return perturb_left(np.asarray(T_color_from_depth, float), np.concatenate([np.asarray(omega_rad, float),
                                                                                 np.asarray(delta_t_mm, float)]))


def project_edges(edges: DepthEdges, T_color_from_depth: np.ndarray, pinhole: PinholeCamera) -> np.ndarray:
    """``(N, 2)`` pixels of the edge points in the (undistorted) colour camera."""
    return pinhole.project(transform_points(T_color_from_depth, edges.pts_depth_mm))


def sample_strength(strength: tuple[np.ndarray, np.ndarray], uv: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """``(N,)`` colour edge strength at pixels ``uv`` (N, 2), bilinear (``cv2.remap``), 0 outside the image; each
    point reads the strength image of its own direction ``axis`` (N,)."""
    return _ShiftedSamples(strength, uv, axis).at(0, 0)


class _ShiftedSamples:
    """``sample_strength`` of fixed points shifted by whole pixels, the points split by direction once (an edge
    offset scores hundreds of shifts of the same points): ``at(dx, dy)`` gives the same values as
    ``sample_strength(strength, uv + (dx, dy), axis)``."""

    def __init__(self, strength: tuple[np.ndarray, np.ndarray], uv: np.ndarray, axis: np.ndarray):
        self.strength, self.n = strength, len(uv)
        self.parts = []
        for ax in (0, 1):
            m = axis == ax
            if m.any():  # (cv2.remap refuses an empty map)
                self.parts.append((ax, m, uv[m, 0], uv[m, 1]))

    def at(self, dx: float, dy: float) -> np.ndarray:
        out = np.zeros(self.n, np.float64)
        for ax, m, u, v in self.parts:
            x = (u + dx) - (0.5 if ax == 0 else 0.0)  # the x image's [v, u] sits at u + 0.5
            y = (v + dy) - (0.5 if ax == 1 else 0.0)
            # cv2.remap takes maps under 32767 rows and columns: the samples go in as rows of 1024, zero-padded (into
            # zeroed buffers: np.pad's own overhead was a fifth of an align-depth fit)
            n = len(x)
            rows = -(-n // 1024)
            xm, ym = np.zeros((2, rows * 1024), np.float32)
            xm[:n], ym[:n] = x, y
            out[m] = cv2.remap(self.strength[ax], xm.reshape(rows, 1024), ym.reshape(rows, 1024), cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT).ravel()[:n]
        return out


def edge_scores(edges: DepthEdges, T_color_from_depth: np.ndarray, pinhole: PinholeCamera,
                strength: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """``(N,)`` colour edge strength at each projected edge point, bilinear (``cv2.remap``); 0 outside the
    image. Each edge reads the strength image of its own direction."""
    return sample_strength(strength, project_edges(edges, T_color_from_depth, pinhole), edges.axis)


@dataclass(frozen=True)
class EdgeOffset:
    """Where the colour edges lie minus where the depth edges lie (px, ``(dx, dy)``): the sub-pixel peak of the mean
    colour edge strength at the depth edges shifted by integer ``(dx, dy)`` (a parabola through the peak and its
    neighbours per axis), ``tests/io/test_real_frame.py``'s measure. ``interior``: the peak lies inside the searched
    square (``radius_px``, widened until it does or ``max_radius_px`` is reached); else the offsets are the border's
    and at least that large."""

    dx_px: float
    dy_px: float
    interior: bool
    radius_px: int
    peak_score: float

    @property
    def magnitude_px(self) -> float:
        return float(np.hypot(self.dx_px, self.dy_px))


def _parabola(f0: float, f1: float, f2: float) -> float:
    den = f0 - 2 * f1 + f2
    return 0.0 if den >= 0 else float(np.clip(0.5 * (f0 - f2) / den, -0.5, 0.5))


def edge_offset_px(edges: DepthEdges, T_color_from_depth: np.ndarray, pinhole: PinholeCamera,
                   strength: tuple[np.ndarray, np.ndarray], radius_px: int = 4, max_radius_px: int = 32) -> EdgeOffset:
    """The offset left between the depth edges at ``T_color_from_depth`` and the colour edges (``EdgeOffset``)."""
    return points_offset_px([(project_edges(edges, T_color_from_depth, pinhole), edges.axis, strength)], radius_px,
                            max_radius_px)


def points_offset_px(groups: list[tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]], radius_px: int = 4,
                     max_radius_px: int = 32) -> EdgeOffset:
    """``edge_offset_px`` of several captures' projected edges together: ``groups`` of ``(uv (N, 2), axis (N,),
    strength)``, each read against its own colour image's strength; the score is the mean over every point."""
    n = sum(len(g[0]) for g in groups)
    R = int(radius_px)
    cache: dict[tuple[int, int], float] = {}
    samples = [_ShiftedSamples(st, uv, ax) for uv, ax, st in groups]

    def score(dx: int, dy: int) -> float:
        if (dx, dy) not in cache:
            cache[(dx, dy)] = sum(float(s.at(dx, dy).sum()) for s in samples) / n if n else 0.0
        return cache[(dx, dy)]

    while True:
        best, ix, iy = max((score(dx, dy), dx, dy) for dy in range(-R, R + 1) for dx in range(-R, R + 1))
        interior = abs(ix) < R and abs(iy) < R
        if interior or R >= max_radius_px:
            break
        R = min(2 * R, int(max_radius_px))
    sx = ix + (_parabola(score(ix - 1, iy), best, score(ix + 1, iy)) if abs(ix) < R else 0.0)
    sy = iy + (_parabola(score(ix, iy - 1), best, score(ix, iy + 1)) if abs(iy) < R else 0.0)
    return EdgeOffset(float(sx), float(sy), bool(interior), R, float(best))
