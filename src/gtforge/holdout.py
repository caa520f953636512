"""Hold-out validation, a recipe of two stages: calibrate on all board captures but the last K, then validate that
calibration on the K it never saw (``gtforge validate --holdout K``)."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

from gtforge.calibrate import calibrate
from gtforge.core.targets.models import BoardModel
from gtforge.errors import InputError
from gtforge.io.captures import open_session
from gtforge.records.calibration import CalibrateParams
from gtforge.records.validation import ValidateParams, ValidationResult
from gtforge.reports.validation import write_validation_report
from gtforge.validate import check_report_folder, validate

log = logging.getLogger("gtforge.validate")

MIN_CALIBRATION_POSES = 3  # the captures that must remain to calibrate
HOLDOUT_CALIBRATION = "holdout_calibration.yaml"  # the calibration of the other captures, in the report folder


def validate_holdout(session_dir: str | Path, holdout: int, out_dir: str | Path | None = None,
                     params: ValidateParams | None = None, captures: list[str] | None = None,
                     progress: Callable[[str], None] | None = None, gauges: bool = True) -> ValidationResult:
    """Calibrate on every board capture but the last ``holdout`` of ``captures`` (default: all), written to
    ``out_dir/holdout_calibration.yaml``, and validate it on those ``holdout`` (``gtforge.validate.validate``)."""
    params = params or ValidateParams()
    session = open_session(session_dir)
    if out_dir is not None:
        check_report_folder(session, out_dir)
    dirs = session.select("board", captures)
    if len(dirs) <= MIN_CALIBRATION_POSES:  # nothing can be held out: say so, not "1 to -1 poses"
        raise InputError(session_dir, "holdout", f"more than {MIN_CALIBRATION_POSES} board captures to hold any out "
                         f"({MIN_CALIBRATION_POSES} must remain to calibrate)",
                         f"{len(dirs)}" + (" (--captures)" if captures else ""),
                         "list more captures with --captures, or capture more board poses")
    if not 1 <= holdout <= len(dirs) - MIN_CALIBRATION_POSES:
        raise InputError(session_dir, "holdout", f"1 to {len(dirs) - MIN_CALIBRATION_POSES} held-out poses of "
                         f"{len(dirs)} ({MIN_CALIBRATION_POSES} must remain to calibrate)", str(holdout),
                         "captures where the board is not found do not count among the 3, so fewer may be needed")
    held = [d.name for d in dirs[-holdout:]]
    calib_path = Path(out_dir or ".") / HOLDOUT_CALIBRATION
    made = not calib_path.exists()
    cal = calibrate(session_dir, calib_path, CalibrateParams(board=params.board or BoardModel()), exclude=held,
                    progress=progress)
    try:
        rep = validate(session_dir, calib_path, out_dir, params, captures=held, progress=progress, gauges=gauges)
    except InputError as exc:
        if exc.field != "board captures":
            raise
        if made:  # (this command's own file, of a hold-out that validated nothing)
            calib_path.unlink(missing_ok=True)
        raise InputError(session_dir, "holdout", "held-out captures where both cameras see the board",
                         f"none of the last {holdout} ({', '.join(held)}; each one's reason is above)",
                         "hold out more captures (--holdout K), or leave those out with --captures") from None
    # said, in the report too: a hold-out validated on fewer poses than it held out, and its calibration's WARN
    said = []
    if len(rep.poses) < len(held):
        said.append(f"validated on {len(rep.poses)} of the {len(held)} held-out captures ("
                    + "; ".join(f"{k}: {v}" for k, v in rep.skipped.items()) + ")"
                    + (": the figures rest on a single board pose" if len(rep.poses) == 1 else ""))
    if cal.verdict != "PASS":
        said.append(f"the hold-out calibration ({calib_path.name}) is {cal.verdict}: "
                    + "; ".join(cal.verdict_reasons))
    for line in said:
        log.warning(line)
    if said:
        rep.warnings = said + rep.warnings
        if out_dir is not None:
            write_validation_report(rep, Path(out_dir), cal.rig.zed.left)
    return rep
