"""The ground truth's region labels (``region.png``): where there is no ground truth, background, the fruit's centre
and its edge; the fruit found from geometry, the SGRA loss weights, sigma statistics and evaluation masks by region,
and the occlusion mask's encoding."""
from __future__ import annotations

from typing import Protocol

import cv2
import numba
import numpy as np

from gtforge.core.camera import RectifiedStereo
from gtforge.core.geometry import finite_box, fit_plane_robust, mask_bounding_box
from gtforge.core.ground_truth.uncertainty import SigmaStats, sigma_stats_by_label


class RegionSettings(Protocol):
    """The fields of the build's settings (``gtforge.records.dataset.BuildParams``) that the regions and weights use;
    any object with them will do."""

    fruit_height_mm: float  # points this far above the table plane are fruit
    plane_threshold_mm: float  # RANSAC inlier distance of the table plane
    min_component_frac: float  # keep fruit components at least this share of the largest
    erosion_px: int  # fruit centre = fruit eroded by this; edge = the rest
    lambda_edge: float
    lambda_center: float
    lambda_bg: float


REGION_NONE, REGION_BG, REGION_CENTRE, REGION_EDGE = 0, 1, 2, 3



@numba.njit(cache=True)
def _gt_region(depth):
    """``region.png``'s first labels, REGION_BG where ``depth`` is finite and REGION_NONE elsewhere (uint8), and the
    bounding box of the finite values (None where there are none): one pass over the box (``finite_box``), zeros
    around it."""
    H, W = depth.shape
    region = np.zeros((H, W), np.uint8)
    y0, y1, x0, x1 = finite_box(depth)
    for v in range(y0, y1):
        zs, rs = depth[v, x0:x1], region[v, x0:x1]
        for u in range(x1 - x0):
            rs[u] = np.uint8(REGION_BG) if abs(zs[u]) < np.inf else np.uint8(REGION_NONE)  # (NaN compares false)
    return region, ((y0, y1, x0, x1) if y1 > y0 else None)


@numba.njit(cache=True)
def _gt_pixels(depth, y0, y1, x0, x1):
    """``np.flatnonzero(np.isfinite(depth[y0:y1, x0:x1]))``: the box's finite pixels, raster order (branch-free
    compaction)."""
    w = x1 - x0
    flat = np.empty((y1 - y0) * w, np.int64)
    n = 0
    for v in range(y0, y1):
        zs = depth[v, x0:x1]
        base = (v - y0) * w
        for u in range(w):
            flat[n] = base + u
            n += abs(zs[u]) < np.inf
    return flat[:n]


@numba.njit(cache=True, error_model="numpy")
def _above_plane(depth, y0, x0, a, b, thr):
    """Fruit candidates on the box from ``(y0, x0)``, ``len(b)`` rows by ``len(a)`` columns: ``(a[u] + b[v]) * depth
    > thr`` where the depth is finite: the plane height ``n . p`` of each GT pixel (``a[u] + b[v]`` = n . ray) against
    ``thr`` (float64, the same expressions as numpy's broadcast)."""
    h, w = b.shape[0], a.shape[0]
    fg = np.empty((h, w), np.bool_)
    for v in range(h):
        zs, out, bv = depth[y0 + v, x0:x0 + w], fg[v], b[v]
        for u in range(w):
            z = np.float64(zs[u])
            out[u] = ((a[u] + bv) * z > thr) & (abs(z) < np.inf)
    return fg


def fruit_regions(depth_mm: np.ndarray, zed: RectifiedStereo, params: RegionSettings,
                  user_mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(region labels uint8, fruit mask bool). Fruit from geometry: RANSAC plane of the table in the GT
    point cloud, points more than ``fruit_height_mm`` above it, the largest components."""
    depth_mm = np.asarray(depth_mm)
    # REGION_BG where there is GT (a finite depth), REGION_NONE (0) elsewhere; the GT's bounding box (None: no GT)
    region, box = _gt_region(depth_mm)
    fruit_box = None  # the fruit's bounding box, where known without a search
    if user_mask is not None:
        fruit = user_mask & np.isfinite(depth_mm)
        fruit_box = mask_bounding_box(fruit)
    else:
        fruit = np.zeros(depth_mm.shape, bool)
        flat = _gt_pixels(depth_mm, *box) if box else ()  # GT pixels of the box, raster order
        if len(flat) >= 100:
            y0, y1, x0, x1 = box
            # the plane from 20000 random GT pixels: only their 3-D points are built
            rng = np.random.default_rng(0)
            v, u = np.divmod(flat[rng.choice(len(flat), min(len(flat), 20000), replace=False)], x1 - x0)
            v, u = v + y0, u + x0
            cam = zed.left
            z = depth_mm[v, u].astype(np.float64)
            sub = cam.unproject(np.stack([u, v], axis=1), z)
            n, c, _ = fit_plane_robust(sub, params.plane_threshold_mm, iterations=300, rng=rng)
            if c > 0:  # orient the normal towards the camera (origin): height = n.p - c > 0 in front
                n, c = -n, -c
            # height n.p - c with p = z * ray, the ray linear in u and v: n . ray = a[u] + b[v] (float64), times the
            # depth and compared in one compiled pass over the box, no point cloud
            ray_x = (np.arange(x0, x1) - cam.cx_px) / cam.fx_px
            ray_y = (np.arange(y0, y1) - cam.cy_px) / cam.fy_px
            fg = _above_plane(depth_mm, y0, x0, n[0] * ray_x, n[1] * ray_y + n[2], c + params.fruit_height_mm)
            fg_box = mask_bounding_box(fg)  # connected components on the foreground's bounding box: the same ones
            if fg_box:
                fy0, fy1, fx0, fx1 = fg_box
                n_cc, labels, stats, _ = cv2.connectedComponentsWithStats(
                    fg[fy0:fy1, fx0:fx1].view(np.uint8), connectivity=8)
                areas = stats[1:, cv2.CC_STAT_AREA]
                keep = np.zeros(n_cc, bool)
                keep[1:] = (areas >= params.min_component_frac * areas.max()) & (areas >= 50)
                kept = keep[labels]
                fruit[y0 + fy0:y0 + fy1, x0 + fx0:x0 + fx1] = kept
                fruit_box = mask_bounding_box(kept)  # the fruit lies in this window: its box from the window's
                if fruit_box:
                    fruit_box = (fruit_box[0] + y0 + fy0, fruit_box[1] + y0 + fy0, fruit_box[2] + x0 + fx0,
                                 fruit_box[3] + x0 + fx0)
    box = fruit_box
    if box:  # erode and label the fruit's bounding box plus the element's radius only: the same result
        k = 2 * params.erosion_px + 1
        r = k // 2
        y0, y1 = max(box[0] - r, 0), min(box[1] + r, fruit.shape[0])
        x0, x1 = max(box[2] - r, 0), min(box[3] + r, fruit.shape[1])
        f = fruit[y0:y1, x0:x1]  # within the GT
        centre = cv2.erode(f.view(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).view(bool)
        region[y0:y1, x0:x1][f] = REGION_EDGE
        region[y0:y1, x0:x1][centre] = REGION_CENTRE  # the erosion keeps fruit pixels only
    return region, fruit



def sgra_weights(region: np.ndarray, params: RegionSettings) -> np.ndarray:
    """``weight.tiff``: the SGRA loss weight of each pixel's region (0 where no GT), float32."""
    lut = np.zeros(256, np.float32)  # by region label: one table look-up pass instead of three masked writes
    lut[[REGION_BG, REGION_CENTRE, REGION_EDGE]] = params.lambda_bg, params.lambda_center, params.lambda_edge
    return cv2.LUT(np.ascontiguousarray(region, np.uint8), lut)



def region_sigma_stats(sigma: np.ndarray, region: np.ndarray) -> dict[str, SigmaStats]:
    """Sigma statistics for all GT pixels, the fruit, its centre and edge, and the background (one pass)."""
    return sigma_stats_by_label(sigma, region, {
        "all": (REGION_BG, REGION_CENTRE, REGION_EDGE), "fruit": (REGION_CENTRE, REGION_EDGE),
        "fruit_centre": (REGION_CENTRE,), "fruit_edge": (REGION_EDGE,), "background": (REGION_BG,)})



def occlusion_mask(disp: np.ndarray, nonoccluded: np.ndarray) -> np.ndarray:
    """``mask?nocc.png`` values: 255 non-occluded, 128 occluded in the other view, 0 no ground truth."""
    return _occlusion_mask(disp, nonoccluded)



@numba.njit(cache=True)
def _occlusion_mask(disp, nonoccluded):
    H, W = disp.shape
    mask = np.empty((H, W), np.uint8)
    for v in range(H):
        for u in range(W):
            mask[v, u] = 255 if nonoccluded[v, u] else (128 if abs(disp[v, u]) < np.inf else 0)
    return mask


def region_masks(region: np.ndarray, nocc: np.ndarray) -> dict[str, np.ndarray]:
    """The pixels each evaluation region scores, from ``region.png`` and ``mask0nocc.png`` (``occlusion_mask``)."""
    return {"all": nocc > 0, "nonoccluded": nocc == 255,
            "fruit": (region == REGION_CENTRE) | (region == REGION_EDGE), "fruit_edge": region == REGION_EDGE,
            "fruit_centre": region == REGION_CENTRE, "background": region == REGION_BG}
