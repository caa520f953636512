"""``validation.html`` / ``.json``: the XY and Z accuracy of the ground truth on board captures."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gtforge.camera import PinholeCamera
from gtforge.validate import REFERENCE_XY_PX, REFERENCE_Z_PCT, ValidationReport


def write_validation_report(rep: ValidationReport, out: Path, zed_cam: PinholeCamera) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gtforge.reports.html import fig_to_img_tag, table, write_html

    out.mkdir(parents=True, exist_ok=True)
    rep.write(out / "validation.json")
    v = np.array(rep.corner_errors)
    e = np.linalg.norm(v[:, 2:], axis=1)
    fig, ax = plt.subplots(1, 2, figsize=(13, 4.2))
    sc = ax[0].scatter(v[:, 0], v[:, 1], c=e, s=12, cmap="viridis")
    scale = 0.05 * zed_cam.width_px / max(float(e.max()), 1e-6)
    ax[0].quiver(v[:, 0], v[:, 1], v[:, 2] * scale, v[:, 3] * scale, angles="xy", scale_units="xy", scale=1,
                 width=0.002, color="k")
    ax[0].set_xlim(0, zed_cam.width_px)
    ax[0].set_ylim(zed_cam.height_px, 0)
    ax[0].set_title("XY error per corner over the ZED-left image (px; arrows scaled)")
    fig.colorbar(sc, ax=ax[0])
    ax[1].hist(e, bins=40)
    ax[1].axvline(rep.thresholds["xy_px"], color="r", ls="--", label="threshold")
    ax[1].axvline(REFERENCE_XY_PX, color="gray", ls=":", label="published 0.56 px")
    ax[1].set_xlabel("XY error (px)")
    ax[1].legend()
    img = fig_to_img_tag(fig)

    def verdict(ok):
        return '<span class="pass">PASS</span>' if ok else '<span class="fail">FAIL</span>'

    summary = table(["check", "ours", "published", "threshold", "verdict"], [
        ["XY reprojection mean (px)", rep.xy_mean_px, REFERENCE_XY_PX, rep.thresholds["xy_px"], "PASS" if rep.pass_xy else "FAIL"],
        ["Z geometric error mean (%)", rep.z_error_mean_pct, REFERENCE_Z_PCT, rep.thresholds["z_pct"], "PASS" if rep.pass_z else "FAIL"],
        ["XY median / RMS / max (px)", f"{rep.xy_median_px:.3f} / {rep.xy_rms_px:.3f} / {rep.xy_max_px:.3f}", "", "", ""],
        ["Z max (%)", rep.z_error_max_pct, "", "", ""],
        ["board flatness RMS (mm)", rep.flatness_rms_mm, "", "", ""],
        ["scale error (%)", rep.scale_error_pct, "", "", ""],
    ])
    warn = "".join(f'<p class="warn">warning: {w}</p>' for w in rep.warnings)
    rows = [[p.capture, "yes" if p.used_for_calibration else "no", p.xy_mean_px, p.xy_median_px, p.xy_rms_px, p.xy_max_px,
             p.z_diagonal_calc_mm, p.z_diagonal_true_mm, p.z_error_pct, p.z_pairs_mean_abs_pct, p.flatness_rms_mm]
            for p in sorted(rep.poses, key=lambda p: -p.xy_mean_px)]
    poses = table(["capture", "in calib", "XY mean", "XY median", "XY RMS", "XY max", "D calc mm", "D true mm", "E_z %",
                   "pairs |E| %", "flatness mm"], rows)
    skipped = table(["capture", "reason"], list(rep.skipped.items())) if rep.skipped else "<p>none</p>"
    write_html(out / "validation.html", "gtforge validation", [
        ("Verdict: " + ("PASS" if rep.passed else "FAIL"), verdict(rep.passed) + warn + summary),
        ("Where in the field of view", img), ("Per pose (worst first)", poses), ("Skipped captures", skipped)])
