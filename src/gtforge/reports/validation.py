"""``validation.html`` / ``.json``: the XY and Z accuracy of the ground truth on board captures.

The page is the list ``SECTIONS``: each entry maps ``(report, ZED-left camera)`` to a
:class:`~gtforge.reports.html.Section` (or ``None``). A new section is one function appended to the list.
"""
from __future__ import annotations

import html
from pathlib import Path
from typing import Callable

import numpy as np

from gtforge.core.camera import PinholeCamera
from gtforge.infra.atomic import atomic_path
from gtforge.records.validation import REFERENCE_SOURCE, REFERENCE_XY_PX, REFERENCE_Z_PCT, ValidationResult
from gtforge.reports import rectification as rectification_report
from gtforge.reports.gauges import gauge_sections
from gtforge.reports.html import (
    Section,
    fig_to_img_tag,
    nice_ceil,
    note,
    standard_header,
    table,
    verdict_badge,
    write_html,
)

THRESHOLD_COLOUR = "#c00000"
REFERENCE_COLOUR = "#777777"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _legend_below(ax, ncol: int = 3) -> None:
    """A legend under the axes, where it cannot hide a line or a bar."""
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.22), ncol=ncol, fontsize=8, frameon=False)


# ---- sections -----------------------------------------------------------------------------------
def verdict_section(rep: ValidationResult, zed_cam: PinholeCamera) -> Section:
    def ok(flag: bool):
        return verdict_badge("pass" if flag else "fail")

    summary = table(["check", "ours", "published", "threshold", "verdict"], [
        ["XY reprojection error, mean over corners (px)", rep.xy_mean_px, REFERENCE_XY_PX, rep.thresholds["xy_px"],
         ok(rep.pass_xy)],
        ["Z geometric error, mean over poses (%)", rep.z_error_mean_pct, REFERENCE_Z_PCT, rep.thresholds["z_pct"],
         ok(rep.pass_z)],
        ["XY median / RMS / max (px)", f"{rep.xy_median_px:.3f} / {rep.xy_rms_px:.3f} / {rep.xy_max_px:.3f}",
         "", "", ""],
        ["XY the corner detectors' noise alone gives, mean (px)", rep.xy_noise_floor_px, "", "", ""],
        ["XY with the detectors' noise removed (per-pose board models), mean (px)", rep.xy_model_mean_px, "", "", ""],
        ["Z max over poses (%)", rep.z_error_max_pct, "", "", ""],
        ["board flatness RMS (mm)", rep.flatness_rms_mm, "", "", ""],
        ["scale error (%)", rep.scale_error_pct, "", "", ""],
    ], fmt=[None, "{:.4f}", "{:.4g}", "{:.4g}", None])
    warn = "".join(f'<p class="warn">warning: {html.escape(w)}</p>' for w in rep.warnings)
    status = "pass" if rep.passed else "fail"
    return Section(f"Verdict: {'PASS' if rep.passed else 'FAIL'}", warn + summary + note(
        f"PASS when both means are at or below their thresholds. Published: {REFERENCE_SOURCE}. "
        "XY: structured-light corners lifted to 3-D by the "
        "depth and mapped into the ZED-left image, against the ZED detections. Z: the board diagonal measured in the "
        "generated ZED-left depth against its true length (docs/pipeline.md, validate). The detectors' noise floor "
        "is the part of XY that two corner detectors' own noise makes; XY with it removed compares per-pose board "
        "models fitted to each camera's corners instead, what is left for the calibration and the depth."),
        status=status)


def per_pose_section(rep: ValidationResult, zed_cam: PinholeCamera) -> Section:
    """Per-pose means against the thresholds (the thresholds apply to means, not to single corners)."""
    plt = _plt()
    poses = rep.poses
    names = [p.capture for p in poses]
    x = np.arange(len(poses))
    fig, ax = plt.subplots(1, 2, figsize=(12.5, 3.8))
    for a, vals, thr, ref, mean, unit, title in (
            (ax[0], [p.xy_mean_px for p in poses], rep.thresholds["xy_px"], REFERENCE_XY_PX, rep.xy_mean_px, "px",
             "XY reprojection error, mean per pose"),
            (ax[1], [p.z_error_pct for p in poses], rep.thresholds["z_pct"], REFERENCE_Z_PCT, rep.z_error_mean_pct, "%",
             "Z geometric error per pose (board diagonal)")):
        colours = ["#4a7ab5" if v <= thr else "#d9534f" for v in vals]
        a.bar(x, vals, color=colours, width=0.5, label=f"pose ({unit})")
        a.set_xlim(-0.75, max(len(vals), 6) - 0.25)
        a.axhline(thr, color=THRESHOLD_COLOUR, ls="--", lw=1.5, label=f"threshold {thr:g} {unit}")
        a.axhline(ref, color=REFERENCE_COLOUR, ls=":", lw=1.5, label=f"published {ref:g} {unit}")
        a.axhline(mean, color="k", lw=1.0, label=f"this run's mean {mean:.3g} {unit}")
        a.set_xticks(x, names, rotation=45 if len(names) > 8 else 0, fontsize=8)
        a.set_xlabel("capture")
        a.set_ylabel(f"error ({unit})")
        a.set_ylim(0, max(max(vals, default=0), thr, ref) * 1.12)
        a.set_title(title, fontsize=10)
        _legend_below(a, 2)
    fig.tight_layout()
    return Section("Per pose against the thresholds", fig_to_img_tag(fig, alt="per-pose means"))


def field_of_view_section(rep: ValidationResult, zed_cam: PinholeCamera) -> Section | None:
    if not rep.corner_errors:
        return None

    plt = _plt()
    v = np.array(rep.corner_errors)
    e = np.linalg.norm(v[:, 2:], axis=1)
    W, H = zed_cam.width_px, zed_cam.height_px
    key_px = nice_ceil(float(np.percentile(e, 95)))
    scale = 0.05 * W / key_px
    fig = plt.figure(figsize=(12.5, 12.5 * 0.55 * H / W + 1.2))
    gs = fig.add_gridspec(1, 2, width_ratios=[2.2, 1])
    a0 = fig.add_subplot(gs[0])
    q = a0.quiver(v[:, 0], v[:, 1], v[:, 2] * scale, v[:, 3] * scale, e, cmap="viridis", clim=(0, key_px),
                  angles="xy", scale_units="xy", scale=1, width=0.003)
    a0.quiverkey(q, 0.82, 0.06, key_px * scale, f"{key_px:g} px", coordinates="axes", labelpos="W",
                 fontproperties={"size": 8})
    a0.set_xlim(0, W)
    a0.set_ylim(H, 0)
    a0.set_aspect("equal")
    a0.set_xlabel("u (px)")
    a0.set_ylabel("v (px)")
    a0.set_title(f"XY error per corner over the ZED-left image (arrows x{scale:.0f})", fontsize=10)
    fig.colorbar(q, ax=a0, label="XY error (px)", shrink=0.8)
    a1 = fig.add_subplot(gs[1])
    a1.hist(e, bins=40, color="#4a7ab5")
    a1.set_xlabel("XY error per corner (px)")
    a1.set_ylabel("corners")
    a1.set_title("Per-corner distribution", fontsize=10)
    fig.tight_layout()
    return Section("Where in the field of view", fig_to_img_tag(fig, alt="XY error field") + note(
        "Each arrow points from the ZED detection to where the structured-light corner lands; colour and the key "
        "arrow give its length. The thresholds apply to means (plot above), not to single corners."))


def poses_section(rep: ValidationResult, zed_cam: PinholeCamera) -> Section:
    rows = [[p.capture, "yes" if p.used_for_calibration else "no", p.n_corners, p.xy_mean_px, p.xy_median_px,
             p.xy_rms_px, p.xy_max_px, p.z_diagonal_calc_mm, p.z_diagonal_true_mm, p.z_error_pct,
             p.z_pairs_mean_abs_pct, p.flatness_rms_mm]
            for p in sorted(rep.poses, key=lambda p: -p.xy_mean_px)]
    head = ["capture", "in calibration", "corners", "XY mean (px)", "XY median (px)", "XY RMS (px)", "XY max (px)",
            "D calc (mm)", "D true (mm)", "E_z (%)", "pairs mean |E| (%)", "flatness RMS (mm)"]
    fmt = [None, None, None, "{:.3f}", "{:.3f}", "{:.3f}", "{:.3f}", "{:.2f}", "{:.2f}", "{:.4f}", "{:.4f}", "{:.4f}"]
    return Section("Per pose (worst XY first)", table(head, rows, fmt=fmt) + note(
        "D calc: distance between the first and last board corner measured in the generated depth; D true: the "
        "board's; E_z = |D calc - D true| / D true. Pairs: every corner pair's distance error."))


def skipped_section(rep: ValidationResult, zed_cam: PinholeCamera) -> Section:
    body = table(["capture", "reason"], list(rep.skipped.items())) if rep.skipped else "<p>none</p>"
    return Section("Skipped captures", body)


def rectification_section(rep: ValidationResult, zed_cam: PinholeCamera) -> Section | None:
    """Vertical disparity of the board corners in both rectified ZED images."""
    return rectification_report.rectification_section(getattr(rep, "rectification", None), None, zed_cam.width_px,
                                                      zed_cam.height_px)


SectionBuilder = Callable[[ValidationResult, PinholeCamera], "Section | None"]
def gauges_section(rep: ValidationResult, zed_cam: PinholeCamera) -> Section | None:
    """The gauge objects' VDI/VDE 2634-2 figures (gauges.html has the residual maps and histograms)."""
    if rep.gauges is None:
        return None

    parts = gauge_sections(rep.gauges)
    body = parts[0].body + "".join(f"<h3>{html.escape(p.heading)}</h3>{p.body}" for p in parts[1:])
    body += note('Residual maps and histograms: <a href="gauges.html">gauges.html</a>.')
    return Section(parts[0].heading, body, status=parts[0].status)


SECTIONS: list[SectionBuilder] = [verdict_section, per_pose_section, field_of_view_section, poses_section,
                                  skipped_section, rectification_section, gauges_section]


def write_validation_report(rep: ValidationResult, out: Path, zed_cam: PinholeCamera,
                            sections: list[SectionBuilder] | None = None) -> Path:
    """``validation.json`` and a self-contained ``validation.html`` built from ``sections`` (default ``SECTIONS``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    built = [s for s in (f(rep, zed_cam) for f in (sections or SECTIONS)) if s is not None]
    board = getattr(rep, "board", None)
    header = standard_header(("session", rep.session_dir), ("calibration", rep.calibration_path),
                             *((("board (inner corners, square)", f"{board.cols} x {board.rows}, "
                                 f"{board.square_size_mm:g} mm"),) if board is not None else ()))
    # validation.json, the result a script reads, lands once the page is written: a run stopped (Ctrl-C) before leaves
    # no new validation.json without its page
    with atomic_path(out / "validation.json") as staged:
        rep.write(staged)
        return write_html(out / "validation.html", "gtforge validation", built, header=header)
