"""``calibration_report.html`` / ``.json``: what ``gtforge calibrate`` found, for a person to read."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gtforge.calibrate import CalibrationFile


def write_calibration_report(calib: CalibrationFile, out_dir: str | Path) -> Path:
    """``calibration_report.json`` + self-contained ``calibration_report.html``: residual vectors per view,
    residual histogram, errors by image region, worst poses first, sigmas and cross-validation."""
    import json

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gtforge.io.atomic import atomic_write_text
    from gtforge.reports.html import fig_to_img_tag, table, write_html

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = calib.model_dump(mode="json")
    data["residuals"] = {k: {kk: np.asarray(vv).tolist() for kk, vv in v.items()} for k, v in calib._residuals.items()}
    atomic_write_text(out / "calibration_report.json", json.dumps(data, indent=1))
    sections = []
    T = calib.rig.T
    summary = table(["quantity", "value"], [
        ["method", calib.method], ["poses used", len(calib.captures_used)],
        ["poses skipped / outliers", sum(p.status != "used" for p in calib.poses)],
        ["RMS residual (px)", calib.rms_px], ["worst residual (px)", calib.max_px],
        ["sigma rotation x/y/z (deg)", " / ".join(f"{v:.4f}" for v in calib.sigma_rot_xyz_deg)],
        ["sigma translation x/y/z (mm)", " / ".join(f"{v:.3f}" for v in calib.sigma_trans_xyz_mm)],
        ["leave-one-out transfer mean / max (px)",
         "-" if calib.loo_transfer_mean_px is None else f"{calib.loo_transfer_mean_px:.3f} / {calib.loo_transfer_max_px:.3f}"],
        ["T_zed_from_mech", "<br>".join(" ".join(f"{x:+.6f}" for x in row) for row in T)],
    ])
    sections.append(("Summary", summary.replace("&lt;br&gt;", "<br>")))
    if len(calib.methods) > 1:
        sections.append(("Methods side by side", table(["method", "RMS ZED (px)", "rot diff (deg)", "trans diff (mm)"],
                         [[m.method, m.rms_zed_px, m.rot_diff_to_primary_deg, m.trans_diff_to_primary_mm] for m in calib.methods])))
    rows = [[p.capture, p.status, p.reason, p.rms_mech_px, p.rms_zed_px, p.max_px, p.loo_transfer_mean_px,
             p.sharpness_mech_px, p.sharpness_zed_px, "yes" if p.blurred else ""] for p in calib.poses]
    sections.append(("Poses, worst first", table(["capture", "status", "reason", "RMS mech", "RMS ZED", "max", "LOO mean",
                                                  "edge mech", "edge ZED", "blurred"], rows)))
    if calib._residuals:
        allr = np.concatenate([np.linalg.norm(np.concatenate([v["res_mech"], v["res_zed"]]), axis=1)
                               for v in calib._residuals.values()])
        fig, ax = plt.subplots(figsize=(6, 3.2))
        ax.hist(allr, bins=50)
        ax.set_xlabel("corner residual (px)")
        ax.set_ylabel("count")
        sections.append(("Residual histogram", fig_to_img_tag(fig, "60%")))
        sections.append(("Residual by ZED image region (RMS px)", table(["region", "RMS (px)"],
                                                                           sorted(calib.residuals_by_region_px.items()))))
        names = [p.capture for p in calib.poses if p.capture in calib._residuals]
        ncol = 4
        nrow = int(np.ceil(len(names) / ncol))
        fig, axes = plt.subplots(nrow, ncol, figsize=(16, 3.2 * nrow), squeeze=False)
        W, H = calib.rig.zed.left.width_px, calib.rig.zed.left.height_px
        for ax, name in zip(axes.ravel(), names):
            r = calib._residuals[name]
            sc = 0.04 * W / max(float(np.abs(r["res_zed"]).max()), 1e-6)
            ax.quiver(r["zed_uv"][:, 0], r["zed_uv"][:, 1], r["res_zed"][:, 0] * sc, r["res_zed"][:, 1] * sc,
                      angles="xy", scale_units="xy", scale=1, width=0.004)
            ax.set_xlim(0, W)
            ax.set_ylim(H, 0)
            ax.set_title(f"{name}: max {np.linalg.norm(r['res_zed'], axis=1).max():.3f} px", fontsize=9)
            ax.set_aspect("equal")
        for ax in axes.ravel()[len(names):]:
            ax.axis("off")
        sections.append(("ZED-left residual vectors per view (arrows scaled per view)", fig_to_img_tag(fig)))
    return write_html(out / "calibration_report.html", "gtforge calibration report", sections)
