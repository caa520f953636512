"""One scene's ground truth in the rectified ZED-left image: the depth camera's depth reprojected (``StereoDepth``),
the region labels and the fruit mask. build-dataset writes it; refine, calibrate-scale and the gauges recompute it."""
from __future__ import annotations

import numpy as np

from gtforge.core.camera import Rig
from gtforge.core.ground_truth.regions import fruit_regions
from gtforge.core.ground_truth.reproject import reproject_to_zed
from gtforge.records.dataset import BuildParams


def build_scene_arrays(depth_mm: np.ndarray, rig: Rig, params: BuildParams, user_mask: np.ndarray | None = None):
    """Ground-truth depth/disparity/occlusion in the ZED-left image, region labels and the fruit mask."""
    depth_mm = rig.corrected_depth_mm(depth_mm)  # (itself without calibrate-scale's depth correction)
    sd = reproject_to_zed(depth_mm, rig.depth_camera, rig.T_zed_from_depth, rig.zed, params.reproject_params(),
                          params.occlusion_rel_tol, left_span=params.sigma and params.mode == "mesh")
    region, fruit = fruit_regions(sd.depth_mm, rig.zed, params, user_mask)
    return sd, region, fruit
