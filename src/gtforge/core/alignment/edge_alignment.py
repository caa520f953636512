"""Refine ``T_color_from_depth`` from one capture or many by putting the depth map's silhouettes (and the depth
camera's own image's edges) on the colour image's edges.

Photometric alignment (``gtforge.refine``) needs a texture that looks like the colour image; a depth camera's own
infrared image often does not (an Azure Kinect's infrared and colour images differ too much for local
normalisation, docs/cameras.md). Depth discontinuities need no texture: where the depth jumps, the colour image
almost always has an edge too (a different surface behind). This module (its pieces:
``gtforge.core.alignment.edge_features``)

1. renders each capture's depth into the undistorted colour camera at the starting (factory) extrinsic, finds the
   foreground side of every depth jump there and carries it back into the depth camera as a 3-D point
   (``depth_edges``); with the depth camera's own image (infrared, a structured-light camera's 2-D texture), its
   edges on surfaces too (``texture_edges``);
2. undistorts each colour image into a pinhole camera and makes edge-strength images ``|dI/dx|``, ``|dI/dy|``,
   Gaussian-blurred (``edge_strength``);
3. scores a candidate pose by the mean colour edge strength at the projected edges of every capture together
   (``edge_scores``): the captures share one extrinsic, so their edges together determine what one cannot;
4. searches the two rotations that shift the image on a coarse grid (wide blur) whose range doubles (with its step
   and blur) while the best point lies on its border, up to ``max_search_px`` (beyond: "not determined", said so),
   then walks back down to the fine step around the best point;
5. fits every fitted parameter **jointly** from there (Nelder-Mead, then Newton steps on a one-pixel-wide quadratic
   model), and computes the cluster-robust sandwich covariance ``H^-1 B H^-1`` (one connected edge structure, a
   contour, is one observation); then **selection by the joint covariance**: while a free parameter's 1-sigma
   moves the image by more than ``max_sigma_px`` (or there are too few structures for the free parameters), the
   least determined one is held at its factory value and the rest are fitted again;
6. **decides** on the determined parameters together: the correction is applied when it is significant against the
   factory value (its chi-square against the joint covariance, as an equivalent two-sided normal sigma, above
   ``apply_z``); otherwise the factory extrinsic is kept and the result says "not significant";
7. measures, per capture and for all together, the pixel offset between the depth edges and the colour edges
   before (factory) and after (``edge_offset_px``: the measure of ``tests/io/test_real_frame.py``); a capture whose
   offset after the fit exceeds ``disagree_px`` is flagged (a knocked rig, a moved object).

Internally the parameters are scaled to pixels: a rotation by ``1 / f`` rad and a translation by ``Z_median / f`` mm
move the image by about one pixel, so that one step size, one tolerance and one threshold fit all six.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from gtforge.core.alignment.edge_features import (
    DepthEdges,
    EdgeOffset,
    depth_edges,
    edge_offset_px,
    edge_strength,
    points_offset_px,
    project_edges,
    render_depth,
    texture_edges,
    undistort_image,
)
from gtforge.core.alignment.edge_fit import _Cap, _maximise, _Problem, _sandwich, _significance_sigma
from gtforge.core.camera import PinholeCamera
from gtforge.core.geometry import rotation_angle_deg
from gtforge.core.schema import GTModel, matrix4_field
from gtforge.errors import InputError
from gtforge.infra import defaults

PARAMETER_NAMES = ("omega_x", "omega_y", "omega_z", "delta_t_x", "delta_t_y", "delta_t_z")
Status = Literal["determined", "estimated", "not determined", "not fitted"]
Decision = Literal["applied", "not significant", "not determined"]


MAX_SEARCH_PX = 48.0  # the coarse search's widest range (px), and the most a first range may be


class EdgeAlignmentParams(GTModel):
    """Settings of ``align_color_to_depth``; the defaults are the measure of ``tests/io/test_real_frame.py``."""

    jump_ratio: float = Field(1.05, gt=1.0)  # a depth edge: the far side >= 5 % farther than the foreground
    gap_px: int = Field(8, ge=0)  # ... found across at most this many invalid depth pixels
    blur_sigma_px: float = Field(1.0, gt=0)  # Gaussian blur of the colour gradients (fine stage, and the score)
    coarse_blur_sigma_px: float = Field(2.0, gt=0)  # ... of the coarse grid search (doubled with its range)
    # coarse grid: image shifts within +-search_px first (at most MAX_SEARCH_PX: the first grid has (2 r / step + 1)^2
    # points, and --search-px 1e9 allocated 30 GB, 100 ran for minutes, inf raised a traceback) ...
    search_px: float = Field(defaults.EDGE_SEARCH_PX, gt=0, le=MAX_SEARCH_PX)
    search_step_px: float = Field(0.5, gt=0)  # ... in these steps; range, step and blur double while the best
    max_search_px: float = Field(MAX_SEARCH_PX, gt=0)  # point is on the border, up to this range
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
    # applied when the determined correction is more than this many (equivalent normal) sigma from the factory value
    # (3, not 2: a factory value has earned a prior; the silhouettes of curved objects are biased by a few tenths of
    # a pixel, which the exact pose of tests/stages/test_align_depth.py would otherwise see as a 2.7-sigma roll)
    apply_z: float = Field(defaults.EDGE_APPLY_Z, ge=0)
    # the silhouette placement rule's own sub-pixel bias (a curved object's limb seen from two viewpoints, the depth
    # grid): added to every determined parameter's 1-sigma in quadrature (measured: up to ~0.05 px, synthetic)
    edge_bias_px: float = Field(0.05, ge=0)
    # align-depth's scenes when none are named: at most this many, evenly spread over the session (None: every scene;
    # every board capture too): a 0.5x scene takes about 1.1 s and 19 MB, and the estimate did not move from 12 scenes
    # to 40 (benchmarks/RESULTS.md, round 22)
    max_scenes: int | None = Field(defaults.MAX_SCENES, ge=1)
    disagree_px: float = Field(1.0, gt=0)  # a capture whose offset after the fit exceeds this is flagged
    min_gradient: float = Field(2.0, ge=0)  # a colour image whose strongest blurred gradient is below: blank


class CaptureAlignment(GTModel):
    """One capture in the fit: its edges, and the pixel offset (colour edges minus depth edges, ``(dx, dy)`` px,
    ``gtforge.core.alignment.edge_features.EdgeOffset``) with the factory extrinsic and with the result's."""

    name: str
    excluded: str = ""  # why the capture took no part ("": used)
    n_edges: int = 0
    n_structures: int = 0
    offset_before_px: list[float] | None = None
    offset_after_px: list[float] | None = None
    offset_after_interior: bool = True  # False: the peak is on the border of the widest search (at least that far)
    disagrees: bool = False  # |offset after| > disagree_px: this capture does not share the others' extrinsic


class EdgeAlignmentResult(GTModel):
    """What ``align_color_to_depth`` / ``align_captures`` found. Per parameter, in ``PARAMETER_NAMES`` order (omega in
    deg, delta_t in mm, the left perturbation ``T_color_from_depth = [exp(omega) R_initial | t_initial + delta_t]``):
    ``status`` "determined" (fitted jointly with the others determined, its 1-sigma below ``max_sigma_px`` in
    pixels), "estimated" (its 1-sigma above ``max_sigma_px`` but its joint estimate more than ``apply_z`` sigma off
    the initial value: the estimate is the better guess, its sigma is in the covariance), "not determined" (fitted
    but the data do not pin it down: held at its initial value) or "not fitted";
    ``omega_deg``/``delta_t_mm`` the estimate (0 where not determined) and ``sigma_*`` its 1-sigma from the joint
    covariance of the determined parameters (inf elsewhere). ``decision`` says what ``T_color_from_depth`` holds:
    the estimate ("applied": significant against the factory value, ``significance_sigma`` > ``apply_z``), or the
    factory extrinsic ("not significant", "not determined", with ``reason``). ``covariance_rad_mm``: the 6x6
    covariance of the applied left perturbation (rad, mm; zero rows where nothing was applied)."""

    T_color_from_depth_initial: list[list[float]]
    T_color_from_depth: list[list[float]]
    omega_deg: list[float] = Field(min_length=3, max_length=3)
    delta_t_mm: list[float] = Field(min_length=3, max_length=3)
    status: list[Status] = Field(min_length=6, max_length=6)
    sigma_omega_deg: list[float] = Field(min_length=3, max_length=3)  # inf: not determined or not fitted
    sigma_delta_t_mm: list[float] = Field(min_length=3, max_length=3)
    decision: Decision = "not determined"
    reason: str = ""
    significance_sigma: float | None = None  # the determined correction against the factory value
    covariance_rad_mm: list[list[float]] = Field(default_factory=lambda: np.zeros((6, 6)).tolist())
    rotation_deg: float  # angle of the applied correction
    n_edges: int
    n_structures: int  # edge structures of >= 10 samples (the covariance's observations)
    edge_kinds: list[Literal["silhouettes", "texture"]]  # what the edges were
    score_initial: float  # mean colour edge strength at the depth edges (grey levels / px), factory extrinsic
    score_final: float  # ... at the result's extrinsic
    f_px: float  # the colour pinhole's mean focal length (the pixel scale of the parameters)
    median_depth_mm: float  # median depth of the edges (the pixel scale of the translations)
    search_px: float = 0.0  # the coarse search's final range (+-px)
    search_interior: bool = True  # False: its best point was on the border of the widest range
    # every capture's edges together: (dx, dy) px, colour edges minus depth edges
    offset_before_px: list[float] = Field(default_factory=lambda: [0.0, 0.0])
    offset_after_px: list[float] = Field(default_factory=lambda: [0.0, 0.0])
    captures: list[CaptureAlignment] = Field(default_factory=list)
    warnings: list[str] = Field(default_factory=list)

    @field_validator("T_color_from_depth_initial", "T_color_from_depth", mode="before")
    @classmethod
    def _T4(cls, v):
        return matrix4_field(v)


@dataclass
class EdgeCapture:
    """One capture for ``align_captures``: the depth (float mm, NaN invalid) on ``depth_cam``'s grid, the colour
    image, and optionally the depth camera's own image (pixel-aligned with the depth)."""

    name: str
    depth_mm: np.ndarray
    depth_cam: PinholeCamera
    color_rgb: np.ndarray
    texture: np.ndarray | None = None


# ---- the estimator -----------------------------------------------------------------------------
def _prepare(cap: EdgeCapture, color_cam: PinholeCamera, T_color_from_depth_initial: np.ndarray, kinds: list[str],
             params: EdgeAlignmentParams) -> _Cap:
    """A capture's edges (at the factory extrinsic) and undistorted colour image; InputError for a blank image."""
    und, pinhole = undistort_image(cap.color_rgb, color_cam)
    if max(float(g.max()) for g in edge_strength(und, params.blur_sigma_px)) < params.min_gradient:
        raise InputError(None, "colour image", f"edges (a blurred gradient of >= {params.min_gradient} grey levels)",
                         "none: a blank image", "is the colour image exposed and from this capture?")
    edges = DepthEdges(np.zeros((0, 3)), np.zeros(0, np.int8), np.zeros(0, np.int8), np.zeros(0, np.int64))
    rendered = render_depth(cap.depth_mm, cap.depth_cam, T_color_from_depth_initial, pinhole)
    if "silhouettes" in kinds:
        edges = edges + depth_edges(cap.depth_mm, cap.depth_cam, T_color_from_depth_initial, pinhole,
                                    params.jump_ratio, params.gap_px, rendered)
    if "texture" in kinds:
        edges = edges + texture_edges(cap.texture, cap.depth_mm, cap.depth_cam, T_color_from_depth_initial, pinhole,
                                      params.texture_top_fraction, params.texture_max_relief,
                                      params.texture_min_length_px, rendered_z_mm=rendered)
    return _Cap(cap.name, edges, und)


def _coarse_search(problem: _Problem, params: EdgeAlignmentParams) -> tuple[np.ndarray, float, bool]:
    """The best image shift ``(theta_0, theta_1)`` (px) on a grid whose range, step and blur double while the best
    point is on its border (up to ``max_search_px``), then refined back down to ``search_step_px`` around it.
    Returns (shift, the final range, whether the best point was interior)."""
    n = sum(len(c.edges) for c in problem.caps)
    stride = max(1, -(-n // 8000))  # a grid of hundreds of points on wide blur: every stride-th edge is enough
    problem = _Problem([_Cap(c.name, c.edges.subset(slice(None, None, stride)), c.undistorted, c.strengths)
                        for c in problem.caps], problem.pinhole, problem.T_color_from_depth_initial, problem.scale)
    r, s, b = params.search_px, params.search_step_px, params.coarse_blur_sigma_px
    levels = []
    while True:
        ticks = np.arange(-r, r + 0.5 * s, s)
        grid = [(float(problem.scores(np.array([x, y, 0, 0, 0, 0.0]), b).mean()), x, y) for y in ticks for x in ticks]
        _, bx, by = max(grid)
        levels.append((s, b))
        interior = max(abs(bx), abs(by)) < r - 0.5 * s
        if interior or r >= params.max_search_px:
            break
        r, s, b = min(2 * r, params.max_search_px), 2 * s, 2 * b
    centre = np.array([bx, by])
    for k in range(len(levels) - 2, -1, -1):  # back down: +-2 steps of the level above, at this level's step
        s, b = levels[k]
        ticks = np.arange(-2 * levels[k + 1][0], 2 * levels[k + 1][0] + 0.5 * s, s)
        grid = [(float(problem.scores(np.array([centre[0] + x, centre[1] + y, 0, 0, 0, 0.0]), b).mean()), x, y)
                for y in ticks for x in ticks]
        _, bx, by = max(grid)
        centre = centre + [bx, by]
    return centre, float(r), bool(interior)


def align_captures(captures: list[EdgeCapture], color_cam: PinholeCamera, T_color_from_depth: np.ndarray,
                   params: EdgeAlignmentParams = EdgeAlignmentParams()) -> EdgeAlignmentResult:
    """Refine ``T_color_from_depth`` (shared by every capture) from the edges of all ``captures`` together (the
    module docstring says how). A capture with a blank colour image takes no part (its ``excluded`` says why); a
    depth map or image of another size than its intrinsics is an ``InputError``, so are too few edges in all."""
    T_color_from_depth_initial = np.asarray(T_color_from_depth, np.float64)
    matrix4_field(T_color_from_depth_initial)
    if not captures:
        raise InputError(None, "captures", "at least one capture", "none", "select board or scene captures")
    caps, reports, kinds_used = [], [], set()
    for c in captures:
        c.depth_cam.check_image_size(np.shape(c.depth_mm), None, f"depth map of capture {c.name}")
        color_cam.check_image_size(np.shape(c.color_rgb), None, f"colour image of capture {c.name}")
        kinds = {"auto": ["silhouettes", "texture"] if c.texture is not None else ["silhouettes"],
                 "silhouettes": ["silhouettes"], "texture": ["texture"],
                 "both": ["silhouettes", "texture"]}[params.edges]
        if "texture" in kinds and c.texture is None:
            raise InputError(None, "texture", f"the depth camera's own image for edges={params.edges!r}",
                             "none given", "pass the infrared / 2-D texture image, or use edges='silhouettes'")
        try:
            caps.append(_prepare(c, color_cam, T_color_from_depth_initial, kinds, params))
            kinds_used |= set(kinds)
            reports.append(CaptureAlignment(name=c.name))
        except InputError as e:
            if len(captures) == 1:
                raise
            reports.append(CaptureAlignment(name=c.name, excluded=str(e)))
    pinhole = color_cam.model_copy(update={"dist_coeffs": []})
    # keep the edges that project inside the image with a margin for the blur (a fixed set: a smooth objective)
    margin = 3 * params.coarse_blur_sigma_px + 2
    for c in caps:
        uv = project_edges(c.edges, T_color_from_depth_initial, pinhole)
        c.edges = c.edges.subset((uv[:, 0] > margin) & (uv[:, 0] < pinhole.width_px - 1 - margin)
                                 & (uv[:, 1] > margin) & (uv[:, 1] < pinhole.height_px - 1 - margin))
    n_edges = sum(len(c.edges) for c in caps)
    if n_edges < params.min_edges:
        raise InputError(None, "depth", f"at least {params.min_edges} depth edges inside the colour image",
                         f"{n_edges}", "a scene with objects in front of a background, seen by both cameras")
    caps = [c for c in caps if len(c.edges)]
    base = [(r.name, r.excluded) for r in reports]
    res = _fit(caps, base, T_color_from_depth_initial, pinhole, params, kinds_used, {})
    # a capture that disagrees with the others after the joint fit (a knocked rig, a moved object) pulls the fit
    # towards itself: left out, and the others fitted again (it is still measured and reported)
    bad = {c.name: c.offset_after_px for c in res.captures if c.disagrees and not c.excluded}
    if bad and res.decision == "applied" and len(caps) - len(bad) >= 2:
        left_out = {n: f"left out of the fit: its edges lay ({o[0]:+.2f}, {o[1]:+.2f}) px off after the joint fit "
                       f"with the others (> {params.disagree_px:g} px: a knocked rig or a moved object?)"
                    for n, o in bad.items()}
        res = _fit(caps, base, T_color_from_depth_initial, pinhole, params, kinds_used, left_out)
    return res


def _fit(all_caps: list[_Cap], base: list[tuple[str, str]], T_color_from_depth_initial: np.ndarray,
         pinhole: PinholeCamera, params: EdgeAlignmentParams, kinds_used: set, left_out: dict[str, str]
         ) -> EdgeAlignmentResult:
    """The fit on the captures not ``left_out`` (name -> why); every capture measured and reported."""
    reports = [CaptureAlignment(name=n, excluded=e or left_out.get(n, "")) for n, e in base]
    caps = [c for c in all_caps if c.name not in left_out]
    n_edges = sum(len(c.edges) for c in caps)
    f_px = 0.5 * (pinhole.fx_px + pinhole.fy_px)
    z_med = float(np.median(np.concatenate([c.edges.pts_depth_mm[:, 2] for c in caps])))
    scale = np.array([1 / f_px] * 3 + [z_med / f_px] * 3)
    problem = _Problem(caps, pinhole, T_color_from_depth_initial, scale)
    fine, coarse = params.blur_sigma_px, params.coarse_blur_sigma_px
    _, sizes = np.unique(problem.structure, return_counts=True)
    n_structures = int((sizes >= 10).sum())

    # coarse: the two rotations that shift the image, on a grid that widens until its best point is interior
    start, search_r, interior = _coarse_search(problem, params)
    for c in caps:  # the wider blurs of the search are done with (a session's dozens of captures hold the rest)
        c.strengths = {b: v for b, v in c.strengths.items() if b in (fine, coarse)}
    fitted = np.array([True] * 3 + [params.fit_translation] * 3)
    theta = np.array([start[0], start[1], 0, 0, 0, 0.0])
    free = fitted.copy()
    warnings: list[str] = []
    reason = ""
    if interior:
        # a joint start: every fitted parameter together, then selection by the joint covariance
        theta = _maximise(problem, coarse, theta, free, polish=False)
        theta = _maximise(problem, fine, theta, free, polish=True)
        # selection by the joint covariance: while a free parameter's 1-sigma exceeds max_sigma_px (or there are too
        # few structures for the free parameters), the least determined one that the data do not show to be off the
        # factory value (within apply_z sigma of it) is held there and the rest fitted again; a weak parameter whose
        # joint estimate is more than apply_z sigma off the factory value stays free ("estimated": the factory value
        # is the worse guess; its sigma goes into the covariance)
        while free.any():
            sig = np.sqrt(np.abs(np.diag(_sandwich(problem, theta, fine, free))))
            enough = n_structures >= free.sum() + params.min_extra_structures
            weak = free & ~(sig <= params.max_sigma_px)
            significant = free & (np.abs(theta) > params.apply_z * sig) & enough
            if not (weak & ~significant).any() and enough:
                break
            pool = (weak & ~significant) if enough else free
            worst = int(np.flatnonzero(pool)[np.argmax(np.where(np.isfinite(sig[pool]), sig[pool], 1e300))])
            free[worst] = False
            theta[worst] = 0.0
            if free.any():
                theta = _maximise(problem, fine, theta, free, polish=True)
        theta = np.where(free, theta, 0.0)
        if not free.any():
            reason = (f"no parameter has a 1-sigma under {params.max_sigma_px} px with {n_structures} edge structures "
                      f"(>= {params.min_extra_structures} more than the parameters needed)")
    else:
        free[:] = False
        theta = np.zeros(6)
        reason = (f"the edges' best image shift lies on the border of the widest search (+-{search_r:g} px): the "
                  "factory extrinsic is further off than that, or the captures' edges do not match")
    determined = free
    cov_px = _sandwich(problem, theta, fine, determined) if determined.any() else np.full((6, 6), np.inf)
    estimated = determined & ~(np.sqrt(np.abs(np.diag(cov_px))) <= params.max_sigma_px)
    # what the edges' scatter cannot show: the silhouette placement's own bias (edge_bias_px), and, with three or
    # more captures, how much the captures' offsets at the estimate scatter (a random offset per capture, averaged
    # over them), each added to every determined parameter's variance (pixel units)
    T_color_from_depth_estimate = problem.pose(theta)
    per_cap = {c.name: edge_offset_px(c.edges, T_color_from_depth_estimate, pinhole, c.strength(fine)) for c in caps}
    floor_var = params.edge_bias_px ** 2
    if len(caps) >= 3:
        off = np.array([[o.dx_px, o.dy_px] for o in per_cap.values()])
        floor_var += float(off.var(axis=0, ddof=1).max()) / len(caps)
    cov_px = cov_px + np.diag(np.where(determined, floor_var, 0.0))
    sigma = np.where(determined, np.sqrt(np.abs(np.diag(cov_px))), np.inf)
    significance = None
    decision: Decision = "not determined"
    applied_theta = np.zeros(6)
    cov_rad_mm = np.zeros((6, 6))
    if determined.any():
        idx = np.flatnonzero(determined)
        significance = _significance_sigma(theta[idx], cov_px[np.ix_(idx, idx)])
        if significance > params.apply_z:
            decision, applied_theta = "applied", theta
            cov_rad_mm[np.ix_(idx, idx)] = cov_px[np.ix_(idx, idx)] * np.outer(scale[idx], scale[idx])
            reason = f"the correction is {significance:.1f} sigma from the factory value (> {params.apply_z:g})"
        else:
            decision = "not significant"
            reason = f"the correction is {significance:.1f} sigma from the factory value (<= {params.apply_z:g}): kept"
    T_color_from_depth = problem.pose(applied_theta)
    # the pixel offsets, per capture (the left-out ones too) and all together (those fitted), before and after
    fine_strengths = [c.strength(fine) for c in caps]
    applied = decision == "applied"
    R0 = int(np.ceil(np.abs(start).max())) + 4  # the factory pose's offset: at least as far as the coarse search's
    per_cap.update({c.name: edge_offset_px(c.edges, T_color_from_depth_estimate, pinhole, c.strength(fine), R0)
                    for c in all_caps if c.name in left_out})
    per_cap_before = {c.name: edge_offset_px(c.edges, T_color_from_depth_initial, pinhole, c.strength(fine), R0)
                      for c in all_caps}
    per_cap_after = per_cap if applied else per_cap_before  # (the pose applied is the estimate or the factory one)
    one = len(caps) == 1
    before_all = (per_cap_before[caps[0].name] if one
                  else _offset_all(caps, T_color_from_depth_initial, pinhole, fine_strengths, R0))
    after_all = per_cap_after[caps[0].name] if one else _offset_all(caps, T_color_from_depth, pinhole, fine_strengths)
    by_name = {c.name: c for c in all_caps}
    for r in reports:
        c = by_name.get(r.name)
        if c is None:
            if not r.excluded:
                r.excluded = "no depth edges inside the colour image"
            continue
        b, a = per_cap_before[c.name], per_cap_after[c.name]
        _, sz = np.unique(c.edges.structure, return_counts=True)
        r.n_edges, r.n_structures = len(c.edges), int((sz >= 10).sum())
        r.offset_before_px, r.offset_after_px = [b.dx_px, b.dy_px], [a.dx_px, a.dy_px]
        r.offset_after_interior = a.interior
        r.disagrees = a.magnitude_px > params.disagree_px or not a.interior
        if r.name in left_out:
            warnings.append(f"capture {r.name}: {left_out[r.name]}; after the others' fit ({a.dx_px:+.2f}, "
                            f"{a.dy_px:+.2f}) px")
        elif r.disagrees:
            warnings.append(f"capture {r.name}: its edges lie ({a.dx_px:+.2f}, {a.dy_px:+.2f}) px off the colour "
                            f"edges after the fit (> {params.disagree_px:g} px): a knocked rig or a moved object?")
    if decision != "applied" and before_all.magnitude_px > params.disagree_px:
        warnings.append(f"the factory extrinsic is kept ({decision}) although the depth edges lie "
                        f"({before_all.dx_px:+.2f}, {before_all.dy_px:+.2f}) px off the colour edges")
    value = theta * scale
    sigma_phys = sigma * scale
    return EdgeAlignmentResult(
        T_color_from_depth_initial=T_color_from_depth_initial, T_color_from_depth=T_color_from_depth,
        omega_deg=np.degrees(value[:3]).tolist(), delta_t_mm=value[3:].tolist(),
        status=["estimated" if e else "determined" if d else "not determined" if f else "not fitted"
                for d, e, f in zip(determined, estimated, fitted)],
        sigma_omega_deg=np.degrees(sigma_phys[:3]).tolist(), sigma_delta_t_mm=sigma_phys[3:].tolist(),
        decision=decision, reason=reason, significance_sigma=significance, covariance_rad_mm=cov_rad_mm.tolist(),
        rotation_deg=rotation_angle_deg(T_color_from_depth[:3, :3] @ T_color_from_depth_initial[:3, :3].T),
        n_edges=n_edges, n_structures=n_structures,
        edge_kinds=[k for k in ("silhouettes", "texture") if k in kinds_used],
        score_initial=float(problem.scores(np.zeros(6), fine).mean()),
        score_final=float(problem.scores(applied_theta, fine).mean()), f_px=f_px, median_depth_mm=z_med,
        search_px=search_r, search_interior=interior, offset_before_px=[before_all.dx_px, before_all.dy_px],
        offset_after_px=[after_all.dx_px, after_all.dy_px], captures=reports, warnings=warnings)


def _offset_all(caps: list[_Cap], T_color_from_depth: np.ndarray, pinhole: PinholeCamera, strengths,
                radius_px: int = 4) -> EdgeOffset:
    """The offset of every capture's edges together (each capture's edges read its own colour image)."""
    return points_offset_px([(project_edges(c.edges, T_color_from_depth, pinhole), c.edges.axis, st)
                             for c, st in zip(caps, strengths)], radius_px)


def align_color_to_depth(depth_mm: np.ndarray, depth_cam: PinholeCamera, color_rgb: np.ndarray,
                         color_cam: PinholeCamera, T_color_from_depth: np.ndarray,
                         params: EdgeAlignmentParams = EdgeAlignmentParams(),
                         texture: np.ndarray | None = None) -> EdgeAlignmentResult:
    """Refine ``T_color_from_depth`` from one capture (``align_captures`` with one): ``depth_mm`` (float, NaN
    invalid) on ``depth_cam``'s grid; ``color_rgb`` from ``color_cam`` (lens model applied here); ``texture`` the
    depth camera's own image (infrared, or a structured-light camera's 2-D image), pixel-aligned with the depth.
    ``params.edges`` says which edges are used."""
    return align_captures([EdgeCapture("frame", depth_mm, depth_cam, color_rgb, texture)], color_cam,
                          T_color_from_depth, params)


