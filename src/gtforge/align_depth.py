"""gtforge align-depth: a separate depth camera's pose ``T_mech_from_depth`` (Azure Kinect, Orbbec, PrimeSense-class
units: the depth map lies on another camera than the texture the board and ground truth are seen in) refined from
the captures' edges, every board and scene capture together (``gtforge.core.alignment.edge_alignment.align_captures``).

The factory pose in the calibration (from session.yaml) is the start. The result is written into a new calibration
file: ``rig.T_mech_from_depth`` holds the corrected pose when the correction is significant against the factory
value (else the factory pose, and the file says why), ``depth_alignment`` what was found: per parameter the estimate,
its sigma and status, the decision, the covariance of the applied rotation (the sigma map adds it, as calibrate-scale's
depth-pose terms), and per capture the pixel offset between its depth edges and the texture's edges before and after
(a capture that disagrees with the others, a knocked rig, is flagged). Every later stage (calibrate-scale, validate,
build-dataset, verify) reads the pose from that file. Run it after calibrate and before calibrate-scale.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gtforge.core.camera import Rig
from gtforge.core.alignment.edge_alignment import EdgeAlignmentParams, EdgeCapture, align_captures
from gtforge.errors import InputError
from gtforge.io.calibrated_session import open_calibrated_session
from gtforge.io.formats import read_image
from gtforge.records.calibration import CalibrationFile
from gtforge.records.depth_alignment import DepthAlignment


def align_depth(session_dir: str | Path, calibration: str | Path, out_path: str | Path | None = None,
                params: EdgeAlignmentParams | None = None, captures: list[str] | None = None,
                use_boards: bool = True, progress: Callable[[str], None] | None = None) -> CalibrationFile:
    """Refine the calibration's ``T_mech_from_depth`` from the session's captures (module docstring); ``captures``:
    the scene ids to use (default: ``params.max_scenes`` of them, evenly spread), ``use_boards``: the board captures
    too. Writes ``out_path`` when given (never the input file). Returns the new calibration file."""
    t0 = time.perf_counter()
    params = params or EdgeAlignmentParams()
    calib_path = Path(calibration)
    calib = CalibrationFile.read(calib_path)
    # the stages after align-depth estimate through the depth camera's pose: a pose changed under them would leave
    # their terms (calibrate-scale's depth scale, offset and pose, and its record of the pose it started from; refine's
    # extrinsic) fitted to another depth than the one the labels are built from
    for field, done, stage in (("scale_calibration", calib.scale_corrected, "calibrate-scale"),
                               ("refinement", calib.refinement is not None, "refine")):
        if done:
            raise InputError(calib_path, field, f"a calibration from before {stage} (align-depth runs after "
                             f"calibrate and before calibrate-scale and refine, which estimate through the depth "
                             f"camera's pose)", f"one {stage} wrote",
                             "run align-depth on the calibration calibrate wrote, then calibrate-scale and refine on "
                             "its output (docs/pipeline.md)")
    session, out_path = open_calibrated_session(session_dir, calib, calib_path, out_path, "aligned.yaml")
    rig = calib.rig
    if not rig.separate_depth_camera:
        raise InputError(calib_path, "rig.T_mech_from_depth", "a rig whose depth map lies on a separate depth camera",
                         "one camera (the depth is on the texture camera's grid)",
                         "align-depth is for units such as Azure Kinect / Orbbec; name depth_intrinsics and "
                         "T_mech_from_depth in session.yaml")
    if calib.depth_alignment is not None:
        raise InputError(calib_path, "depth_alignment", "a calibration whose depth camera pose is not aligned yet",
                         "one already aligned", "run align-depth on the calibration it was made from")
    dirs, not_selected = session.select_scenes(captures, params.max_scenes)
    board_root = session.root / session.config.board_dir
    if use_boards and board_root.is_dir():
        dirs = list(session.select("board", None)) + list(dirs)
    edge_caps = []
    for d in dirs:
        if progress:
            progress(f"reading {d.parent.name}/{d.name}")
        cap = session.load_capture(d, need_right=False)
        if cap.mech_texture is None:
            raise InputError(d, "mech_texture", "the texture camera's image", "none",
                             "each capture needs its 2-D image")
        texture = None if params.edges == "silhouettes" else _depth_texture(
            d / session.config.files.depth_texture, cap.depth_mm.shape, params.edges)
        edge_caps.append(EdgeCapture(f"{d.parent.name}/{d.name}", cap.depth_mm, rig.depth_camera, cap.mech_texture,
                                     texture))
    if not edge_caps:
        raise InputError(session.root, None, "board or scene captures", "none", "capture scenes with objects first")
    if progress:
        progress(f"aligning the depth edges of {len(edge_caps)} captures")
    T_mech_from_depth_file = rig.T_mech_from_depth_or_identity
    res = align_captures(edge_caps, rig.mech, T_mech_from_depth_file, params)
    new_rig = Rig.model_validate({**rig.model_dump(), "T_mech_from_depth": np.array(res.T_color_from_depth)})
    method = DepthAlignment.model_fields["method"].default
    if "texture" in res.edge_kinds:
        said = {"silhouettes": "depth silhouettes",
                "texture": f"the depth camera's own image's edges ({session.config.files.depth_texture})"}
        method = (f"edge alignment: {' and '.join(said[k] for k in res.edge_kinds)} on the texture camera's edges, "
                  "every capture together")
    info = DepthAlignment(method=method, calibrated_from=str(calib_path.resolve()),
                          T_mech_from_depth_file=T_mech_from_depth_file, params=params, result=res,
                          scenes_not_selected=not_selected, time_s=time.perf_counter() - t0)
    out = calib.model_copy(update={"rig": new_rig, "depth_alignment": info})
    out = CalibrationFile.model_validate(out.model_dump())
    if out_path is not None:
        out.write(out_path)
    return out


def _depth_texture(path: Path, shape: tuple[int, int], edges: str) -> np.ndarray | None:
    """A capture's depth camera image (``IR.png``: pixel-aligned with its depth), None where the capture has none and
    ``edges`` does not ask for it."""
    if not path.is_file():
        if edges in ("texture", "both"):
            raise InputError(path, None, f"the depth camera's own image for --edges {edges}", "no such file",
                             "use --edges auto or silhouettes, or name the image in session.yaml "
                             "(files.depth_texture)")
        return None
    img = read_image(path)
    if img.shape[:2] != tuple(shape):
        raise InputError(path, "size", f"{shape[1]}x{shape[0]} px (the depth map's: pixel-aligned with it)",
                         f"{img.shape[1]}x{img.shape[0]} px", "it must be the depth camera's own image, as "
                         "gtforge import writes it")
    return img


def summary_lines(info: DepthAlignment) -> list[str]:
    """The console report: the decision, each parameter, the offsets before/after, per capture."""
    r = info.result
    names = ("omega_x", "omega_y", "omega_z")
    lines = [f"depth camera pose: {r.decision} ({r.reason})", f"  edges: {' and '.join(r.edge_kinds)}"]
    if info.scenes_not_selected:
        lines.append(f"  {info.scenes_not_selected} more scene(s) of the session not used (--max-scenes: those used "
                     "evenly spread)")
    for k, n in enumerate(names):
        sig = f" +- {r.sigma_omega_deg[k]:.3f}" if np.isfinite(r.sigma_omega_deg[k]) else ""
        lines.append(f"  {n}: {r.omega_deg[k]:+.3f}{sig} deg [{r.status[k]}]")
    lines.append(f"  edge offset (colour - depth) all captures: before ({r.offset_before_px[0]:+.2f}, "
                 f"{r.offset_before_px[1]:+.2f}) px, after ({r.offset_after_px[0]:+.2f}, "
                 f"{r.offset_after_px[1]:+.2f}) px; {r.n_edges} edges, {r.n_structures} structures, "
                 f"search +-{r.search_px:g} px")
    for c in r.captures:
        if c.excluded:
            lines.append(f"  {c.name}: not used ({c.excluded})")
            continue
        flag = "  <- disagrees" if c.disagrees else ""
        lines.append(f"  {c.name}: before ({c.offset_before_px[0]:+.2f}, {c.offset_before_px[1]:+.2f}) px, after "
                     f"({c.offset_after_px[0]:+.2f}, {c.offset_after_px[1]:+.2f}) px, {c.n_edges} edges{flag}")
    lines += [f"warning: {w}" for w in r.warnings]
    return lines
