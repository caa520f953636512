"""``calibration_report.html`` / ``.json``: what ``gtforge calibrate`` found, for a person to read.

The page is the list ``SECTIONS``: each entry maps the calibration to a :class:`~gtforge.reports.html.Section`
(or ``None`` to leave it out). A new section is one function appended to the list.

Which solve each figure describes: ``calibrate`` always runs the joint reprojection solve (both cameras); its
residuals give the histogram, the region table, the arrows and the leave-one-out figures. With ``--use-depth``
the depth method's extrinsic is the one written; the summary shows that method's RMS in the ZED image, and its
sigmas when the file carries the written extrinsic's covariance (``cov_extrinsic_rad_mm``).
"""
from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Callable

import numpy as np

from gtforge.core.targets.coverage import GRID_COLS, GRID_ROWS
from gtforge.infra.atomic import atomic_write_text
from gtforge.records.calibration import CalibrationFile, MethodResult
from gtforge.reports import rectification as rectification_report
from gtforge.reports.html import Raw, Section, fig_to_img_tag, nice_ceil, note, standard_header, table, write_html

METHOD_TEXT = {
    "reprojection": "reprojection: joint refinement of every corner's reprojection in both cameras",
    "depth": "depth: the depth camera's 3-D board corners, one 3D-to-2D solve into the ZED-left image",
}
ARROW_LENGTH_FRAC = 0.05  # the 95th-percentile residual is drawn this long (share of the image width), every view
AMBIGUITY_TEXT = {  # how each target's point order is made the same in both cameras (docs/targets.md)
    "checkerboard": "none: cols + rows odd, the pattern fixes the corner order",
    "charuco": "none: every corner has an id from its markers",
    "circles_asymmetric": "none: the staggered rows fix the order",
    "circles_symmetric": "resolved per pose: the ZED numbering whose board x axis agrees with the texture camera's",
}
REGION_ROWS = ("top", "middle", "bottom")
REGION_COLS = ("left", "centre", "right")


def _method(calib: CalibrationFile, name: str) -> MethodResult | None:
    return next((m for m in calib.methods if m.method == name), None)


def written_rms_zed_px(calib: CalibrationFile) -> float | None:
    """RMS (px) in the ZED-left image of the method whose extrinsic was written."""
    m = _method(calib, calib.method)
    if m is not None:
        return m.rms_zed_px
    if calib._residuals:
        r = np.concatenate([v["res_zed"] for v in calib._residuals.values()])
        return float(np.sqrt(np.mean(np.sum(r ** 2, axis=1))))
    return None


def sigma_method(calib: CalibrationFile) -> str:
    """The solve the 1-sigma figures come from: the written one when the file has its covariance."""
    return calib.method if getattr(calib, "cov_extrinsic_rad_mm", None) is not None else "reprojection"


def _matrix(T_dst_from_src) -> Raw:
    rows = ["  ".join(f"{x:+.6f}" if j < 3 else f"{x:+10.3f}" for j, x in enumerate(r))
            for r in np.asarray(T_dst_from_src)]
    return Raw("<pre style='margin:0;text-align:left'>" + "\n".join(rows) + "</pre>")


# ---- sections -----------------------------------------------------------------------------------
def verdict_section(calib: CalibrationFile) -> Section | None:
    verdict = getattr(calib, "verdict", None)
    if verdict is None:
        return None
    reasons = list(getattr(calib, "verdict_reasons", []) or [])
    body = "".join(f'<p class="{"fail" if verdict == "FAIL" else "warn"}">{html.escape(r)}</p>'
                   for r in reasons) if reasons else \
        "<p>No warning from calibrate's checks.</p>"
    body += note("Criteria: docs/pipeline.md (calibrate, 'Verdict'). The figures below say how well the extrinsic "
                 "fits these captures; `gtforge validate` on captures not used here says how good the ground truth is.")
    return Section(f"Verdict: {verdict}", body, status=verdict.lower())


def summary_section(calib: CalibrationFile) -> Section:
    n_skip = sum(p.status == "skipped" for p in calib.poses)
    n_out = sum(p.status == "outlier" for p in calib.poses)
    sm = sigma_method(calib)
    loo = "\u2013 (not run)" if calib.loo_transfer_mean_px is None else \
        f"{calib.loo_transfer_mean_px:.3f} / {calib.loo_transfer_max_px:.3f}"
    b = calib.board
    rows = [
        ["calibration written", METHOD_TEXT.get(calib.method, calib.method)],
        ["RMS residual in the ZED-left image, written calibration (px)", written_rms_zed_px(calib)],
        [f"1-sigma rotation x / y / z (deg), {sm} solve", " / ".join(f"{v:.4f}" for v in calib.sigma_rot_xyz_deg)],
        [f"1-sigma translation x / y / z (mm), {sm} solve", " / ".join(f"{v:.3f}" for v in calib.sigma_trans_xyz_mm)],
        ["leave-one-pose-out transfer mean / max (px), reprojection solve", loo],
        ["poses used / skipped / outliers", f"{len(calib.captures_used)} / {n_skip} / {n_out}"],
        ["board (inner corners, square)", f"{b.cols} x {b.rows}, {b.square_size_mm:g} mm"] if b.kind == "checkerboard"
        else ["board", b.describe()],
        ["board's 180-degree ambiguity", AMBIGUITY_TEXT.get(b.kind, "")],
    ]
    measured = getattr(calib, "square_size_measured_mm", None)
    if measured is not None:
        rows.append(["square size measured in the depth (mm)", measured])
    rows.append(["T_zed_from_mech written (rotation | translation mm)", _matrix(calib.rig.T_zed_from_mech)])
    body = table(["quantity", "value"], rows, fmt="{:.4f}", cls="kv")
    if calib.method != "reprojection":
        body += note(f"The extrinsic written is the {calib.method} method's; the residual figures below (histogram, "
                     "regions, arrows) and the leave-one-out figures come from the reprojection solve, which is "
                     "always run (see 'Methods side by side' for how far apart the two are).")
    return Section("Summary", body)


def reprojection_section(calib: CalibrationFile) -> Section:
    rep = _method(calib, "reprojection")
    rows = [["RMS residual, both cameras (px)", calib.rms_px],
            ["RMS residual, ZED-left image (px)", rep.rms_zed_px if rep else None],
            ["worst corner residual, both cameras (px)", calib.max_px]]
    if calib.method != "reprojection" and len(calib.methods) > 1:
        m = _method(calib, calib.method)
        rows.append(["differs from the written calibration by (deg / mm)",
                     f"{m.rot_diff_to_primary_deg:.4f} / {m.trans_diff_to_primary_mm:.3f}"])
    written = " (the calibration written)" if calib.method == "reprojection" else ""
    return Section(f"Reprojection solve{written}", table(["quantity", "value"], rows, fmt="{:.4f}"))


def methods_section(calib: CalibrationFile) -> Section | None:
    if len(calib.methods) < 2:
        return None
    rows = [[m.method, "yes" if m.method == calib.method else "no", m.rms_zed_px, m.rot_diff_to_primary_deg,
             m.trans_diff_to_primary_mm] for m in calib.methods]
    return Section("Methods side by side", table(
        ["method", "written", "RMS ZED-left (px)", "rotation vs reprojection (deg)",
         "translation vs reprojection (mm)"],
        rows, fmt=[None, None, "{:.4f}", "{:.4f}", "{:.3f}"]))


def poses_section(calib: CalibrationFile) -> Section:
    rows = [[p.capture, p.status, p.reason or "", p.rms_mech_px, p.rms_zed_px, p.max_px, p.loo_transfer_mean_px,
             p.loo_transfer_max_px, p.sharpness_mech_px, p.sharpness_zed_px, "yes" if p.blurred else "no"]
            for p in calib.poses]
    head = ["capture", "status", "reason", "RMS mech (px)", "RMS ZED (px)", "max (px)", "LOO mean (px)", "LOO max (px)",
            "edge width mech (px)", "edge width ZED (px)", "blurred"]
    return Section("Poses, worst first", table(head, rows, fmt=[None, None, None] + ["{:.3f}"] * 5 + ["{:.2f}"] * 2)
                   + note("RMS/max: residuals of the reprojection solve. LOO: the pose's corners transferred by the "
                          "extrinsic solved without it. Edge width: cv2.estimateChessboardSharpness (blurred above "
                          "4 px); \u2013 there for a used pose: OpenCV could not measure it (it needs the board's "
                          "squares at least 10 px across in that image: a small or distant board; not counted as "
                          "blurred). Other \u2013: not computed for that pose (skipped, an outlier, or LOO not run)."))


def histogram_section(calib: CalibrationFile) -> Section | None:
    if not calib._residuals:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rm = np.concatenate([np.linalg.norm(v["res_mech"], axis=1) for v in calib._residuals.values()])
    rz = np.concatenate([np.linalg.norm(v["res_zed"], axis=1) for v in calib._residuals.values()])
    fig, ax = plt.subplots(figsize=(7, 3.2))
    bins = np.linspace(0, max(rm.max(), rz.max()) * 1.02, 50)
    ax.hist(rm, bins=bins, histtype="step", lw=1.5,
            label=f"structured-light texture (RMS {np.sqrt(np.mean(rm**2)):.3f})")
    ax.hist(rz, bins=bins, histtype="step", lw=1.5, label=f"ZED left (RMS {np.sqrt(np.mean(rz**2)):.3f})")
    ax.set_xlabel("corner residual (px)")
    ax.set_ylabel("corners")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.9)
    return Section("Residual histogram (reprojection solve)", fig_to_img_tag(fig, "70%", alt="residual histogram"))


def regions_section(calib: CalibrationFile) -> Section | None:
    r = calib.residuals_by_region_px
    if not r:
        return None
    rows = [[row] + [r.get(f"{row}-{col}") for col in REGION_COLS] for row in REGION_ROWS]
    return Section("Residual by ZED-left image region", table(
        ["", *REGION_COLS], rows, fmt="{:.3f}",
        caption="RMS (px) of the ZED-left residuals of the reprojection solve, by third of the image; "
                "\u2013: no corner there."))


def vectors_section(calib: CalibrationFile) -> Section | None:
    if not calib._residuals:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    names = [p.capture for p in calib.poses if p.capture in calib._residuals]
    W, H = calib.rig.zed.left.width_px, calib.rig.zed.left.height_px
    allz = np.concatenate([np.linalg.norm(calib._residuals[n]["res_zed"], axis=1) for n in names])
    key_px = nice_ceil(float(np.percentile(allz, 95)))
    scale = ARROW_LENGTH_FRAC * W / key_px  # image px drawn per px of residual, the same in every view
    ncol = min(3, len(names))
    nrow = int(np.ceil(len(names) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(5.0 * ncol, (5.0 * H / W + 0.9) * nrow), squeeze=False)
    q = None
    for ax, name in zip(axes.ravel(), names):
        r = calib._residuals[name]
        e = np.linalg.norm(r["res_zed"], axis=1)
        q = ax.quiver(r["zed_uv"][:, 0], r["zed_uv"][:, 1], r["res_zed"][:, 0] * scale, r["res_zed"][:, 1] * scale,
                      e, cmap="viridis", clim=(0, key_px), angles="xy", scale_units="xy", scale=1, width=0.004)
        ax.set_xlim(0, W)
        ax.set_ylim(H, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{name}: RMS {np.sqrt(np.mean(e ** 2)):.3f} px, max {e.max():.3f} px", fontsize=9)
        ax.set_xlabel("u (px)", fontsize=8)
        ax.set_ylabel("v (px)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.quiverkey(q, 0.80, 0.06, key_px * scale, f"{key_px:g} px", coordinates="axes", labelpos="W",
                     fontproperties={"size": 8})
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    body = note(f"Arrows: residual of each ZED-left corner (reprojection solve), drawn {scale:.0f} times longer than "
                f"it is, the same in every view; the key arrow at the bottom right of each view is {key_px:g} px. "
                "Colour: residual length (px). Axes: ZED-left image pixels.")
    return Section("ZED-left residual vectors per view", body + fig_to_img_tag(fig, dpi=80, alt="residual vectors"))


def rectification_section(calib: CalibrationFile) -> Section | None:
    """Vertical disparity of the board corners in both rectified ZED images; the SN.conf reading chosen."""
    z = calib.rig.zed.left
    return rectification_report.rectification_section(getattr(calib, "rectification", None),
                                                      getattr(calib, "zed_conf", None), z.width_px, z.height_px)


def self_rectification_section(calib: CalibrationFile) -> Section | None:
    """The ZED self-rectification: the fit, the decision, and every capture's rows before and after."""
    return rectification_report.self_rectification_section(calib.zed_self_rectification)


def coverage_section(calib: CalibrationFile) -> Section | None:
    """Where each camera's board points fell (all detected points of the used poses), the poses' distances and
    tilts, and what to capture next (gtforge.core.targets.coverage)."""
    cov = getattr(calib, "coverage", None)
    if cov is None:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    fig, axes = plt.subplots(1, len(cov.cameras), figsize=(5.5 * len(cov.cameras), 4.0), squeeze=False)
    for ax, c in zip(axes.ravel(), cov.cameras):
        grid = np.asarray(c.counts_grid, float)
        ax.imshow(grid > 0, extent=(0, c.width_px, c.height_px, 0), cmap="Greens", vmin=0, vmax=2.5, alpha=0.6,
                  interpolation="nearest", aspect="equal")
        pts = np.asarray(c.points_uv).reshape(-1, 2)
        if len(pts):
            ax.plot(pts[:, 0], pts[:, 1], ".", ms=2, color="k")
        for gx in range(1, GRID_COLS):
            ax.axvline(gx * c.width_px / GRID_COLS, color="0.8", lw=0.5)
        for gy in range(1, GRID_ROWS):
            ax.axhline(gy * c.height_px / GRID_ROWS, color="0.8", lw=0.5)
        ax.set_xlim(0, c.width_px)
        ax.set_ylim(c.height_px, 0)
        ax.set_title(f"{'ZED-left' if c.camera == 'zed' else 'structured-light texture'}: {c.n_points} points, "
                     f"{int((grid > 0).sum())}/{grid.size} cells", fontsize=9)
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    body = note("Dots: every board point each camera detected in the used poses (also those the other camera did not "
                "see); green: cells of the 8x6 grid with at least one point. "
                f"Board distance from the ZED {cov.distance_mm_min:.0f}-{cov.distance_mm_max:.0f} mm; tilt about the "
                f"vertical axis {cov.tilt_vertical_axis_deg[0]:+.0f} to {cov.tilt_vertical_axis_deg[1]:+.0f} deg, "
                f"about the horizontal axis {cov.tilt_horizontal_axis_deg[0]:+.0f} to "
                f"{cov.tilt_horizontal_axis_deg[1]:+.0f} deg.")
    body += fig_to_img_tag(fig, dpi=80, alt="coverage map")
    if cov.guidance:
        body += ("<p><b>Capture next:</b></p><ul>" + "".join(f"<li>{html.escape(g)}</li>" for g in cov.guidance)
                 + "</ul>")
    else:
        body += "<p>No gap found: the points reach every image corner, the poses span tilts and distances.</p>"
    return Section("Coverage and what to capture next", body)


SectionBuilder = Callable[[CalibrationFile], "Section | None"]
SECTIONS: list[SectionBuilder] = [verdict_section, summary_section, reprojection_section, methods_section,
                                  poses_section, histogram_section, regions_section, vectors_section,
                                  coverage_section, rectification_section, self_rectification_section]


def write_calibration_report(calib: CalibrationFile, out_dir: str | Path,
                             sections: list[SectionBuilder] | None = None) -> Path:
    """``calibration_report.json`` (the calibration + per-corner residuals) and a self-contained
    ``calibration_report.html`` built from ``sections`` (default ``SECTIONS``)."""

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = calib.model_dump(mode="json")
    data["residuals"] = {k: {kk: np.asarray(vv).tolist() for kk, vv in v.items()} for k, v in calib._residuals.items()}
    atomic_write_text(out / "calibration_report.json", json.dumps(data, indent=1))
    built = [s for s in (f(calib) for f in (sections or SECTIONS)) if s is not None]
    header = standard_header(("session", calib.session_dir or None), ("method written", calib.method),
                             ("solve time (s)", f"{calib.time_s:.1f}"))
    return write_html(out / "calibration_report.html", "gtforge calibration report", built, header=header)


def scale_term_lines(info) -> list[str]:
    """calibrate-scale's terms as the console shows them (``gtforge calibrate-scale``, ``gtforge run``): each term's
    estimate with its sigma, whatever its status, and what was applied (a term not significant shows its estimate and
    "not applied", never a bare 0)."""
    lines = []
    for name, t in info.terms.items():
        est = "not estimated" if t.estimate is None else "estimate " + f"{t.estimate:+.4g}" + (
            f" +- {t.sigma:.3g}" if t.sigma is not None else "")
        applied = f", value applied {t.value:+.4g}" if t.status == "applied" else ""
        lines.append(f"{name}: {est} [{t.status}]{applied}" + (f" ({t.reason})" if t.reason else "")
                     + (f"; from {', '.join(t.sources)}" if t.sources else ""))
    return lines
