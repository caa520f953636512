"""How a stage opens a capture session with a calibration file: the session as the calibration sees it, checked
against it, and the checks on the stage's output path. The calibration is any object with ``CalibrationFile``'s fields
(``gtforge.records.calibration``), read by the caller: this module sits below the records."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from gtforge.core.camera import Rig
from gtforge.core.targets.models import BoardModel
from gtforge.errors import InputError
from gtforge.io.captures import Session, open_session
from gtforge.io.outputs import free_path, require_output_file


def open_with_calibration(session_dir: str | Path, calib: Any, right_yaw: bool = True) -> Session:
    """The session as ``calib`` (a ``CalibrationFile``) sees it: raw ZED images rectified with the recorded SN.conf
    reading, and the right image corrected for the self-rectification and calibrate-scale's yaw
    (``rig.scale_corrections``) in one resampling (``gtforge.core.zed.selfcal.corrected_right``): the right image every
    stage reads is the dataset's im1, and no stage resamples it again. ``right_yaw=False``: without the yaw (the right
    image as calibrate-scale measured the yaw on, and as validate measures the rectification)."""
    return open_session(session_dir, zed_conf_reading=calib.zed_conf_reading,
                        zed_right_correction=calib.zed_right_correction,
                        zed_right_yaw_deg=calib.rig.zed_right_yaw_deg if right_yaw else 0.0)


def session_board(session, given: BoardModel, given_explicitly: bool) -> BoardModel:
    """The board to use: session.yaml's ``board:`` when there is one, with the fields given explicitly (CLI options,
    ``given.model_fields_set``) overriding it; else ``given``."""
    declared = getattr(session.config, "board", None)
    if declared is None:
        return given
    if not given_explicitly:
        return declared
    return BoardModel.model_validate({**declared.model_dump(),
                                      **{k: getattr(given, k) for k in given.model_fields_set}})


def check_rig_matches_session(rig: Rig, session, calib_path: str | Path,
                              hint: str = "was this calibration made for another session?") -> None:
    """The calibration's cameras have the session's image sizes (a calibration of another rig or resolution would
    otherwise fail deep inside a stage)."""
    for name, a, b in (("mech", rig.mech, session.mech), ("zed", rig.zed.left, session.zed.left),
                       ("depth_cam", rig.depth_camera, session.depth_camera)):
        if (a.width_px, a.height_px) != (b.width_px, b.height_px):
            raise InputError(calib_path, f"rig.{name}", f"{b.width_px}x{b.height_px} px (the session's camera)",
                             f"{a.width_px}x{a.height_px} px", hint)
    # the ZED baseline: the session's, or calibrate-scale's correction of it (at most MAX_SCALE_CORRECTION_FRAC)
    b_rig, b_session = rig.zed.baseline_mm, session.zed.baseline_mm
    if abs(b_rig / b_session - 1.0) > BASELINE_TOL_FRAC:
        raise InputError(calib_path, "rig.zed.baseline_mm", f"{b_session:g} mm (the session's "
                         f"{session.config.zed_calibration}), within {BASELINE_TOL_FRAC:.0%}", f"{b_rig:g} mm",
                         "a length in another unit (metres?), or " + hint)
    # the structured-light unit's cameras are the session's files' as calibrate read them: other intrinsics mean the
    # files changed after calibrating (the extrinsic was solved with the old ones) or another unit's session
    files = {"mech": session.config.mech_intrinsics, "depth_cam": session.config.depth_intrinsics
             or session.config.mech_intrinsics}
    for name, a, b in (("mech", rig.mech, session.mech), ("depth_cam", rig.depth_camera, session.depth_camera)):
        differs = _intrinsics_difference(a, b)
        if differs is not None:
            field, theirs, ours = differs
            raise InputError(calib_path, f"rig.{name}.{field}", f"{ours} (the session's {files[name]})", theirs,
                             "the session's intrinsics changed since this calibration (calibrate again), or " + hint)


# how far a calibration's ZED baseline may lie from the session's: calibrate-scale's largest correction
# (ScaleParams.max_scale_correction_frac, 5 %) with a margin
BASELINE_TOL_FRAC = 0.1
# how far a calibration's copy of an intrinsic may lie from the session's file: rounding when a file is re-exported
# (6 decimals), far below anything a pose or a label feels
INTRINSICS_TOL_PX = 1e-3
DIST_COEFF_TOL = 1e-6


def _intrinsics_difference(a, b) -> tuple[str, str, str] | None:
    """The first intrinsic in which camera ``a`` differs from ``b`` (field, a's value, b's value), or None."""
    for field in ("fx_px", "fy_px", "cx_px", "cy_px"):
        if abs(getattr(a, field) - getattr(b, field)) > INTRINSICS_TOL_PX:
            return field, f"{getattr(a, field):.6g}", f"{getattr(b, field):.6g}"
    da, db = list(a.dist_coeffs), list(b.dist_coeffs)
    n = max(len(da), len(db))  # (OpenCV's trailing zeros: (k1, k2, p1, p2) is (k1, k2, p1, p2, 0))
    da, db = da + [0.0] * (n - len(da)), db + [0.0] * (n - len(db))
    for k in range(n):
        if abs(da[k] - db[k]) > DIST_COEFF_TOL:
            return f"dist_coeffs[{k}]", f"{da[k]:.6g}", f"{db[k]:.6g}"
    return None


def open_calibrated_session(session_dir: str | Path, calib: Any, calib_path: str | Path,
                            out_path: str | Path | None, example_name: str) -> tuple[Session, Path | None]:
    """The prologue of the stages that turn a calibration into a new one (refine, calibrate-scale): the session as
    ``calib`` (read from ``calib_path``) sees it (``open_with_calibration``), checked against it, and the output path,
    which may be neither inside the captures nor the input file. Returns ``(session, out_path or None)``."""
    calib_path = Path(calib_path)
    session = open_with_calibration(session_dir, calib)
    check_rig_matches_session(calib.rig, session, calib_path)
    if out_path is not None:
        out_path = calibration_output_path(out_path, example_name, session)
        if Path(out_path).resolve() == calib_path.resolve():
            raise InputError(out_path, "--output", "a new file (the input calibration stays as it is)",
                             "the input calibration", "write the new calibration beside it, e.g. "
                             f"{free_path(Path(out_path).parent, example_name)}")
    return session, out_path


def calibration_output_file(out_path: str | Path, name: str) -> Path:
    """The file ``-o`` names for a stage's calibration: ``DIR/name`` for an existing folder or a path ending in ``/``,
    else the path itself."""
    p = Path(out_path)
    return p / name if p.is_dir() or str(out_path).endswith(("/", "\\")) else p


def calibration_output_path(out_path: str | Path, name: str = "calibration.yaml", session: Session | None = None
                            ) -> Path:
    """``-o DIR/`` or an existing folder means ``DIR/name`` (each stage its own name: a refinement written into
    calibrate's folder never replaces calibrate's file). With ``session``: a path its inputs or folder hold is refused
    first (``Session.refuse_output_over_inputs``: a session's own file named as such). An existing file there is
    replaced only when it is a gtforge calibration (an earlier run's); any other file (a report, a user's notes) is
    refused."""
    p = calibration_output_file(out_path, name)
    if session is not None:
        session.refuse_output_over_inputs(p)
    p = require_output_file(p, "--output")  # (before any work: a read-only folder is not found by the write)
    if p.is_file() and not _is_calibration_file(p):
        raise InputError(p, "--output", "a new file, or a gtforge calibration to replace", "an existing file that is "
                         "not a gtforge calibration (it would be lost)",
                         f"give a new file name, e.g. {free_path(p.parent, name)}")
    return p


def _is_calibration_file(p: Path) -> bool:
    """Whether ``p`` reads as a YAML mapping with a calibration's top-level fields (cheap: not validated)."""
    import yaml

    try:
        with open(p, "rb") as f:
            head = f.read(1 << 20)
        d = yaml.safe_load(head)
    except (OSError, yaml.YAMLError, UnicodeDecodeError):
        return False
    return isinstance(d, dict) and "rig" in d and "schema_version" in d
