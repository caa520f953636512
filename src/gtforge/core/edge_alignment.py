"""Refine ``T_color_from_depth`` from one capture by putting the depth map's silhouettes (and the depth camera's own
image's edges) on the colour image's edges.

Photometric alignment (``gtforge.refine``) needs a texture that looks like the colour image; a depth camera's own
infrared image often does not (an Azure Kinect's infrared and colour images differ too much for local
normalisation, docs/cameras.md). Depth discontinuities need no texture: where the depth jumps, the colour image
almost always has an edge too (a different surface behind). This module

1. renders the depth into the undistorted colour camera at the starting extrinsic (gtforge's mesh reprojection, the
   surfaces ground truth is built from), finds the foreground side of every depth jump there, places it where the
   silhouette lies on average and carries it back into the depth camera as a 3-D point (``depth_edges``); with the
   depth camera's own image (infrared, a structured-light camera's 2-D texture: pixel-aligned with the depth), its
   edges on surfaces too (``texture_edges``; docs/cameras.md measures both on the real Azure Kinect frame);
2. undistorts the colour image into a pinhole camera and makes two edge-strength images, ``|dI/dx|`` for the
   silhouettes between horizontal neighbours and ``|dI/dy|`` for those between vertical neighbours, Gaussian-blurred
   (``edge_strength``);
3. for a candidate pose, projects the 3-D edge points into the pinhole camera and scores the mean edge strength
   there (``edge_scores``): the same measure ``tests/io/test_real_frame.py`` uses to report the misalignment;
4. maximises the score over a small left perturbation ``T = [exp(omega) R | t + delta_t]`` (docs/conventions.md)
   of the factory extrinsic, rotation only by default (``align_color_to_depth``): a coarse grid search
   (``scipy.optimize.brute``) over the two rotations that shift the image, with wider blur, then Nelder-Mead and
   Newton steps on a one-pixel-wide quadratic model of the score;
5. says which parameters the one capture determines: the cluster-robust sandwich covariance
   ``H^-1 B H^-1`` of the score's maximiser (H: the score's Hessian; B: the outer products of the per-edge score
   gradients summed over each connected edge structure, because one contour's samples share that contour's
   offset and are one observation, not hundreds). Parameters are chosen one at a time (forward selection) while every chosen one keeps its
   1-sigma within ``max_sigma_px``; a parameter never chosen is "not determined" and held at the factory value,
   never guessed.

Internally the parameters are scaled to pixels: a rotation by ``1 / f`` rad and a translation by ``Z_median / f`` mm
move the image by about one pixel, so that one step size, one tolerance and one threshold fit all six.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from pydantic import Field, field_validator

from gtforge.core.camera import PinholeCamera
from gtforge.core.geometry import invert_T, perturb_left, rotation_angle_deg, transform_points
from gtforge.core.photometric import to_gray
from gtforge.core.reproject import ReprojectParams, project_depth_to_camera
from gtforge.core.schema import GTModel, matrix4_field
from gtforge.errors import InputError

PARAMETER_NAMES = ("omega_x", "omega_y", "omega_z", "delta_t_x", "delta_t_y", "delta_t_z")
Status = Literal["determined", "not determined", "not fitted"]


class EdgeAlignmentParams(GTModel):
    """Settings of ``align_color_to_depth``; the defaults are the measure of ``tests/io/test_real_frame.py``."""

    jump_ratio: float = Field(1.05, gt=1.0)  # a depth edge: the far side >= 5 % farther than the foreground
    gap_px: int = Field(8, ge=0)  # ... found across at most this many invalid depth pixels
    blur_sigma_px: float = Field(1.0, gt=0)  # Gaussian blur of the colour gradients (fine stage, and the score)
    coarse_blur_sigma_px: float = Field(2.0, gt=0)  # ... of the coarse grid search
    search_px: float = Field(6.0, gt=0)  # coarse grid: image shifts within +-search_px ...
    search_step_px: float = Field(0.5, gt=0)  # ... in these steps
    fit_translation: bool = False  # one capture rarely separates a translation from a rotation
    # which edges: the depth silhouettes, the depth camera's own texture (texture_edges), or both; "auto": both
    # when a texture is given, else silhouettes
    edges: Literal["auto", "silhouettes", "texture", "both"] = "auto"
    texture_top_fraction: float = Field(0.2, gt=0, le=1)  # texture edges: the strongest gradients kept
    texture_max_relief: float = Field(0.02, gt=0)  # ... on surfaces whose depth changes < 2 % across the edge
    texture_min_length_px: int = Field(20, ge=1)  # ... in contours of at least this many pixels (not speckle)
    max_sigma_px: float = Field(0.3, gt=0)  # "determined": 1 sigma moves the image by at most this much
    min_edges: int = Field(50, gt=0)
    # the covariance counts an edge structure (of >= 10 samples) as one observation, and G structures leave at most
    # G - 1 directions in the sandwich's B: k parameters are determined only from k + this many structures
    min_extra_structures: int = Field(3, ge=1)


class EdgeAlignmentResult(GTModel):
    """What ``align_color_to_depth`` found. Per parameter, in ``PARAMETER_NAMES`` order (omega in deg, delta_t in
    mm, the left perturbation ``T_color_from_depth = [exp(omega) R_initial | t_initial + delta_t]``):
    ``status`` "determined" (fitted and its 1-sigma below the threshold), "not determined" (fitted but the capture
    does not pin it down: held at its initial value) or "not fitted"; ``sigma_*`` the 1-sigma in the model fitted
    (the other parameters held), ``sigma_*_6dof`` with all six free: what this capture could determine."""

    T_color_from_depth_initial: list[list[float]]
    T_color_from_depth: list[list[float]]
    omega_deg: list[float] = Field(min_length=3, max_length=3)
    delta_t_mm: list[float] = Field(min_length=3, max_length=3)
    status: list[Status] = Field(min_length=6, max_length=6)
    sigma_omega_deg: list[float] = Field(min_length=3, max_length=3)  # inf: not determined or not fitted
    sigma_delta_t_mm: list[float] = Field(min_length=3, max_length=3)
    rotation_deg: float  # angle of the applied correction
    n_edges: int
    n_structures: int  # edge structures of >= 10 samples (the covariance's observations)
    edge_kinds: list[Literal["silhouettes", "texture"]]  # what the edges were
    score_initial: float  # mean colour edge strength at the depth edges (grey levels / px), factory extrinsic
    score_final: float
    f_px: float  # the colour pinhole's mean focal length (the pixel scale of the parameters)
    median_depth_mm: float  # median depth of the edges (the pixel scale of the translations)

    @field_validator("T_color_from_depth_initial", "T_color_from_depth", mode="before")
    @classmethod
    def _T4(cls, v):
        return matrix4_field(v)


# ---- pieces ------------------------------------------------------------------------------------
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

    def subset(self, keep: np.ndarray) -> "DepthEdges":
        return DepthEdges(self.pts_depth_mm[keep], self.axis[keep], self.side[keep], self.structure[keep])

    def __add__(self, other: "DepthEdges") -> "DepthEdges":
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
    # structures: the connected components of the edge pixels (8-connected, across one-pixel breaks)
    vu = np.concatenate(pix)
    return DepthEdges(transform_points(invert_T(T_color_from_depth), pts_color), np.concatenate(axes),
                      np.concatenate(sides), _edge_components(vu, z.shape))


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


def edge_scores(edges: DepthEdges, T_color_from_depth: np.ndarray, pinhole: PinholeCamera,
                strength: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """``(N,)`` colour edge strength at each projected edge point, bilinear (``cv2.remap``); 0 outside the
    image. Each edge reads the strength image of its own direction."""
    uv = project_edges(edges, T_color_from_depth, pinhole)
    out = np.zeros(len(uv), np.float64)
    for axis in (0, 1):
        m = edges.axis == axis
        x = uv[m, 0] - (0.5 if axis == 0 else 0.0)  # the x image's [v, u] sits at u + 0.5
        y = uv[m, 1] - (0.5 if axis == 1 else 0.0)
        if not m.any():  # (cv2.remap refuses an empty map)
            continue
        # cv2.remap takes maps under 32767 rows and columns: the samples go in as rows of 1024
        n = len(x)
        rows = -(-n // 1024)
        xm, ym = (np.pad(a.astype(np.float32), (0, rows * 1024 - n)).reshape(rows, 1024) for a in (x, y))
        out[m] = cv2.remap(strength[axis], xm, ym, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT).ravel()[:n]
    return out


# ---- the estimator -----------------------------------------------------------------------------
@dataclass
class _Problem:
    """One capture's edges and strength images; ``theta`` (6,) the perturbation in pixel units."""

    edges: DepthEdges
    pinhole: PinholeCamera
    T0: np.ndarray
    scale: np.ndarray  # (6,) theta * scale = (omega rad, delta_t mm)

    def pose(self, theta: np.ndarray) -> np.ndarray:
        p = np.asarray(theta, float) * self.scale
        return perturb(self.T0, p[:3], p[3:])

    def scores(self, theta: np.ndarray, strength) -> np.ndarray:
        return edge_scores(self.edges, self.pose(theta), self.pinhole, strength)


def _quadratic_model(f, theta: np.ndarray, step_px: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Gradient and Hessian of ``f`` (a scalar, or a vector per edge for the gradient) by central differences
    one pixel wide, on purpose: the score is a mean of bilinear samples, kinked at every pixel and flat-topped
    where structures disagree by a pixel or two, and ``tests/io/test_real_frame.py`` locates its peak the same way
    (a parabola through the maximum and its neighbours one pixel away). An adaptive differentiation
    (``scipy.differentiate``) would chase the kinks."""
    n, h = len(theta), step_px
    E = np.eye(n) * h
    f0 = f(theta)
    fp = [f(theta + E[k]) for k in range(n)]
    fm = [f(theta - E[k]) for k in range(n)]
    grad = np.stack([(fp[k] - fm[k]) / (2 * h) for k in range(n)], axis=-1)
    H = np.zeros((n, n) + np.shape(f0))
    for k in range(n):
        H[k, k] = (fp[k] - 2 * f0 + fm[k]) / h**2
        for m in range(k):
            H[k, m] = H[m, k] = (f(theta + E[k] + E[m]) - f(theta + E[k] - E[m]) - f(theta - E[k] + E[m])
                                 + f(theta - E[k] - E[m])) / (4 * h**2)
    return grad, H


def _restrict(f, theta: np.ndarray, idx: np.ndarray):
    def g(t):
        full = theta.copy()
        full[idx] = t
        return f(full)
    return g


def _sandwich(problem: _Problem, theta: np.ndarray, strength, free: np.ndarray) -> np.ndarray:
    """Covariance (pixel units, 6x6, inf outside ``free``) of the score maximiser over the ``free`` parameters,
    the others held: the cluster-robust sandwich ``H^-1 B H^-1`` of an M-estimator. ``H`` is the Hessian of the
    summed score; ``B`` sums, over the connected edge structures (one contour each: its samples see the same colour
    edge and share its offset, so a contour is one observation, not hundreds), the outer product of the
    structure's summed per-edge score gradient. Structures that disagree (a table edge whose colour transition
    lies 3 px below its depth silhouette beside a window sill that matches) make the variance large. A direction
    in which the score does not curve down (``H`` not negative definite) gets an infinite variance."""
    idx = np.flatnonzero(free)
    per_edge = _restrict(lambda t: problem.scores(t, strength), theta, idx)
    J, _ = _quadratic_model(per_edge, theta[idx])
    _, H = _quadratic_model(lambda t: per_edge(t).sum(), theta[idx])
    _, label = np.unique(problem.edges.structure, return_inverse=True)
    G = np.zeros((label.max() + 1, len(idx)))
    np.add.at(G, label, J)
    n_clusters = len(G)
    B = G.T @ G * n_clusters / max(n_clusters - 1, 1)  # the usual small-sample factor
    w, V = np.linalg.eigh(-H)  # a maximum: -H positive definite
    good = w > 1e-6 * max(w.max(), 1e-30)
    Hinv = (V[:, good] / w[good]) @ V[:, good].T
    cov = Hinv @ B @ Hinv
    undetermined = (np.abs(V[:, ~good]) > 0.05).any(axis=1)  # loads on a direction without curvature
    cov[undetermined, :] = np.inf
    cov[:, undetermined] = np.inf
    full = np.full((6, 6), np.inf)
    full[np.ix_(idx, idx)] = cov
    return full


def _maximise(problem: _Problem, strength, theta0: np.ndarray, free: np.ndarray, polish: bool) -> np.ndarray:
    """Nelder-Mead on the mean score over the ``free`` parameters (1 px initial steps); with ``polish``, then
    Newton steps on the one-pixel quadratic model (``_quadratic_model``), which find the centre of a flat top where
    Nelder-Mead stops anywhere on it."""
    from scipy.optimize import minimize  # here, not at import: importing scipy slows every process start

    idx = np.flatnonzero(free)
    score = _restrict(lambda t: problem.scores(t, strength).mean(), theta0, idx)
    simplex = theta0[idx] + np.vstack([np.zeros(len(idx)), np.eye(len(idx))])
    t = minimize(lambda t: -score(t), theta0[idx], method="Nelder-Mead",
                 options=dict(initial_simplex=simplex, xatol=0.005, fatol=1e-7, maxiter=4000)).x
    for _ in range(10 if polish else 0):
        g, H = _quadratic_model(score, t)
        w = np.linalg.eigvalsh(H)
        if w.max() >= 0:  # not a maximum of the quadratic model: keep Nelder-Mead's point
            break
        step = -np.linalg.solve(H, g)
        if np.abs(step).max() > 1.0:  # beyond the pixel the model describes
            break
        t = t + step
        if np.abs(step).max() < 0.005:
            break
    out = theta0.copy()
    out[idx] = t
    return out


def align_color_to_depth(depth_mm: np.ndarray, depth_cam: PinholeCamera, color_rgb: np.ndarray,
                         color_cam: PinholeCamera, T_color_from_depth: np.ndarray,
                         params: EdgeAlignmentParams = EdgeAlignmentParams(),
                         texture: np.ndarray | None = None) -> EdgeAlignmentResult:
    """Refine ``T_color_from_depth`` so that the depth map's silhouettes (and, with ``texture``, the edges of the
    depth camera's own image) land on the colour image's edges.

    ``depth_mm`` (float, NaN invalid) on ``depth_cam``'s grid; ``color_rgb`` from ``color_cam`` (lens model
    applied here); ``T_color_from_depth`` the starting (factory) extrinsic; ``texture`` the depth camera's own image
    (infrared, or a structured-light camera's 2-D image), pixel-aligned with the depth. ``params.edges`` says which
    edges are used. The module docstring says how; the result says which parameters the capture determined (the
    others are held at their initial values)."""
    from scipy.optimize import brute  # here, not at import: importing scipy slows every process start

    T0 = np.asarray(T_color_from_depth, np.float64)
    matrix4_field(T0)
    kinds = {"auto": ["silhouettes", "texture"] if texture is not None else ["silhouettes"],
             "silhouettes": ["silhouettes"], "texture": ["texture"],
             "both": ["silhouettes", "texture"]}[params.edges]
    if "texture" in kinds and texture is None:
        raise InputError(None, "texture", f"the depth camera's own image for edges={params.edges!r}", "none given",
                         "pass the infrared / 2-D texture image, or use edges='silhouettes'")
    und, pinhole = undistort_image(color_rgb, color_cam)
    edges = DepthEdges(np.zeros((0, 3)), np.zeros(0, np.int8), np.zeros(0, np.int8), np.zeros(0, np.int64))
    rendered = render_depth(depth_mm, depth_cam, T0, pinhole)
    if "silhouettes" in kinds:
        edges = edges + depth_edges(depth_mm, depth_cam, T0, pinhole, params.jump_ratio, params.gap_px, rendered)
    if "texture" in kinds:
        edges = edges + texture_edges(texture, depth_mm, depth_cam, T0, pinhole, params.texture_top_fraction,
                                      params.texture_max_relief, params.texture_min_length_px,
                                      rendered_z_mm=rendered)
    # keep the edges that stay inside the image over the whole search (a fixed set: a smooth objective)
    uv = project_edges(edges, T0, pinhole)
    margin = params.search_px + 3 * params.coarse_blur_sigma_px + 2
    keep = ((uv[:, 0] > margin) & (uv[:, 0] < pinhole.width_px - 1 - margin)
            & (uv[:, 1] > margin) & (uv[:, 1] < pinhole.height_px - 1 - margin))
    edges = edges.subset(keep)
    if len(edges) < params.min_edges:
        raise InputError(None, "depth", f"at least {params.min_edges} depth edges inside the colour image",
                         f"{len(edges)}", "a scene with objects in front of a background, seen by both cameras")
    f_px = 0.5 * (pinhole.fx_px + pinhole.fy_px)
    z_med = float(np.median(edges.pts_depth_mm[:, 2]))
    scale = np.array([1 / f_px] * 3 + [z_med / f_px] * 3)
    problem = _Problem(edges, pinhole, T0, scale)
    fine = edge_strength(und, params.blur_sigma_px)
    coarse = edge_strength(und, params.coarse_blur_sigma_px)
    score_initial = float(problem.scores(np.zeros(6), fine).mean())

    # coarse: the two rotations that shift the image, on a grid of +-search_px
    def coarse_cost(t):
        return -problem.scores(np.array([t[0], t[1], 0, 0, 0, 0.0]), coarse).mean()

    r, s = params.search_px, params.search_step_px
    start = np.asarray(brute(coarse_cost, (slice(-r, r + 0.5 * s, s), slice(-r, r + 0.5 * s, s)), finish=None))
    # fine: forward selection. Each round fits every candidate parameter together with those already chosen and
    # keeps the candidate that raises the score most among those whose fit leaves every chosen parameter
    # determined (1-sigma <= max_sigma_px); it stops when none does. What is never chosen stays at its initial value.
    _, structure_sizes = np.unique(edges.structure, return_counts=True)
    n_structures = int((structure_sizes >= 10).sum())
    fitted = np.array([True] * 3 + [params.fit_translation] * 3)
    initial = np.array([start[0], start[1], 0, 0, 0, 0.0])
    determined = np.zeros(6, bool)
    theta, sigma = np.zeros(6), np.full(6, np.inf)
    while True:
        best = None
        for k in np.flatnonzero(fitted & ~determined):
            free = determined.copy()
            free[k] = True
            if n_structures < free.sum() + params.min_extra_structures:  # too few observations for the sandwich
                continue
            t = np.where(determined, theta, 0.0)
            t[k] = initial[k]
            t = _maximise(problem, coarse, t, free, polish=False)
            t = _maximise(problem, fine, t, free, polish=True)
            sig = np.sqrt(np.diag(_sandwich(problem, t, fine, free)))
            score = float(problem.scores(t, fine).mean())
            if sig[free].max() <= params.max_sigma_px and (best is None or score > best[0]):
                best = (score, free, t, sig)
        if best is None:
            break
        _, determined, theta, sigma = best
    status = ["determined" if d else ("not determined" if f else "not fitted") for d, f in zip(determined, fitted)]
    value = theta * scale
    sigma_phys = np.where(determined, sigma, np.inf) * scale
    T = problem.pose(theta)
    return EdgeAlignmentResult(
        T_color_from_depth_initial=T0, T_color_from_depth=T,
        omega_deg=np.degrees(value[:3]).tolist(), delta_t_mm=value[3:].tolist(), status=status,
        sigma_omega_deg=np.degrees(sigma_phys[:3]).tolist(), sigma_delta_t_mm=sigma_phys[3:].tolist(),
        rotation_deg=rotation_angle_deg(T[:3, :3] @ T0[:3, :3].T), n_edges=len(edges), n_structures=n_structures, edge_kinds=kinds,
        score_initial=score_initial, score_final=float(problem.scores(theta, fine).mean()),
        f_px=f_px, median_depth_mm=z_med)
