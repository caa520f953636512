"""What ``gtforge align-depth`` found and applied (``CalibrationFile.depth_alignment``): a separate depth camera's
pose ``T_mech_from_depth`` refined by putting every capture's depth edges on the texture camera's edges
(``gtforge.core.alignment.edge_alignment``)."""
from __future__ import annotations

from pydantic import Field, field_validator

from gtforge.core.alignment.edge_alignment import EdgeAlignmentParams, EdgeAlignmentResult
from gtforge.core.schema import GTModel, matrix4_field


class DepthAlignment(GTModel):
    """Stored in the calibration file. ``rig.T_mech_from_depth`` holds the result's pose (the factory pose when
    the decision is not "applied"); ``T_mech_from_depth_file`` the pose before. The sigma map adds the applied
    rotation's covariance (``result.covariance_rad_mm``, the left perturbation of ``T_mech_from_depth``: rad, mm)
    through ``gtforge.core.zed.scale_corrections.depth_pose_jacobian_image``, as for calibrate-scale's rotation."""

    method: str = "edge alignment: depth silhouettes on the texture camera's edges, every capture together"
    calibrated_from: str
    T_mech_from_depth_file: list[list[float]]
    params: EdgeAlignmentParams = Field(default_factory=EdgeAlignmentParams)
    result: EdgeAlignmentResult
    scenes_not_selected: int = 0  # the session's scenes beyond params.max_scenes (those used evenly spread)
    time_s: float = 0.0

    @field_validator("T_mech_from_depth_file", mode="before")
    @classmethod
    def _T4(cls, v):
        return matrix4_field(v)
