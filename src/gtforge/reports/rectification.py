"""The "ZED rectification" report section (calibration and validation pages): vertical disparity of the
board corners in the two rectified ZED images and, for raw images + SN.conf, the conf reading chosen."""
from __future__ import annotations

import html

import numpy as np

from gtforge.core.zed.rectification import COLS, ROWS, RectificationQuality
from gtforge.core.zed.selfcal import ZedSelfRectification
from gtforge.io.zed_rectification import ZedConfChoice
from gtforge.reports.html import Section, fig_to_img_tag, note, table


def rectification_section(q: RectificationQuality | None, choice: ZedConfChoice | None,
                          width_px: int, height_px: int) -> Section | None:
    """``None`` when nothing was measured (no right image with the board in it, no SN.conf choice)."""
    if q is None and choice is None:
        return None
    warnings = (choice.warnings if choice else []) + (q.warnings if q else [])
    body = "".join(f'<p class="warn">{html.escape(w)}</p>' for w in warnings)
    if q is not None:
        o = q.overall
        body += table(["vertical disparity v_left - v_right (px)", "value"], [
            ["corners (poses)", f"{o.n_points} ({len(q.poses)})"],
            ["mean |.|, homography-fitted corners", o.fit_mean_abs_px],
            ["max |.|, homography-fitted", o.fit_max_abs_px],
            ["mean |.|, detected corners", o.mean_abs_px], ["max |.|, detected corners", o.max_abs_px],
            ["signed mean", o.mean_px], ["threshold (fitted mean)", q.threshold_px]], fmt="{:.3f}", cls="kv")
        body += note(f"Images rectified: {q.rectified_by}. Each board corner found in both rectified images; "
                     "'homography-fitted': each image's corners replaced by a homography fitted to all of them (the "
                     "rectification's own error, detector noise averaged out). A well-rectified pair stays below a "
                     "few hundredths of a pixel.")
        rows = [[p.capture, p.fit_mean_abs_px, p.fit_max_abs_px, p.mean_abs_px, p.max_abs_px, p.mean_px,
                 p.disparity_median_px] for p in q.poses]
        body += table(["capture", "fitted mean |.|", "fitted max |.|", "detected mean |.|", "detected max |.|",
                       "signed mean", "median disparity"], rows, fmt=[None] + ["{:.3f}"] * 5 + ["{:.1f}"],
                      caption="Per pose, worst first (px).")
        reg = [[r] + [q.by_region_left[f"{r}-{c}"].mean_px if f"{r}-{c}" in q.by_region_left else None for c in COLS]
               for r in ROWS]
        body += table(["", *COLS], reg, fmt="{:+.3f}",
                      caption="Signed mean vertical disparity (px) of the detected corners by third of the rectified "
                              "left image; \u2013: no corner there.")
        if q.skipped:
            body += table(["capture", "not measured because"], sorted(q.skipped.items()))
        if len(q._points):
            body += _scatter(q._points, width_px, height_px)
    if choice is not None:
        body += f"<p>SN.conf <code>{html.escape(choice.conf_file)}</code> ({html.escape(choice.resolution)}) read as " \
                f"<b>{html.escape(choice.reading)}</b>: {html.escape(choice.formula)}; " \
                f"chosen by {choice.chosen_by}.</p>"
        if choice.candidates:
            rows = [[c.reading, "yes" if c.eligible else "no (right camera at -x)", c.vertical.fit_mean_abs_px,
                     c.vertical.mean_abs_px, c.vertical.max_abs_px, c.formula] for c in choice.candidates]
            body += table(["reading", "eligible", "fitted mean |.| (px)", "detected mean |.| (px)",
                           "detected max |.| (px)", "formula"], rows,
                          fmt=[None, None, "{:.3f}", "{:.3f}", "{:.3f}", None],
                          caption=f"Every reading of the conf, scored on the raw board corners of "
                                  f"{len(choice.captures)} captures (best first; docs/conventions.md, 'ZED SN.conf').")
    status = "warn" if warnings else None
    return Section("ZED rectification: vertical disparity", body, status=status)


def _scatter(points: np.ndarray, width_px: int, height_px: int) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lim = max(float(np.percentile(np.abs(points[:, 2]), 98)), 0.05)
    fig, ax = plt.subplots(figsize=(7, 7 * height_px / width_px + 0.6))
    sc = ax.scatter(points[:, 0], points[:, 1], c=points[:, 2], s=10, cmap="coolwarm", vmin=-lim, vmax=lim)
    ax.set_xlim(0, width_px)
    ax.set_ylim(height_px, 0)
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    fig.colorbar(sc, ax=ax, label="v_left - v_right (px)", shrink=0.8)
    return fig_to_img_tag(fig, "70%", dpi=90, alt="vertical disparity over the image") + note(
        "Each detected corner at its place in the rectified left image, coloured by its vertical disparity.")


def self_rectification_section(s: ZedSelfRectification | None) -> Section | None:
    """``None`` when no self-rectification was run (``--no-self-rectify``)."""
    if s is None:
        return None
    w, sw = np.degrees(s.rotvec_rad), np.degrees(s.sigma_rotvec_rad)
    status = {"applied": "pass", "not needed": None, "not determined": "warn"}[s.status]
    body = f"<p><b>{html.escape(s.status)}</b>: {html.escape(s.reason)}.</p>"
    rows = [["matches (captures)", f"{s.n_matches} ({len(s.captures)}"
             + (f"; {s.scenes_not_matched} scene captures not matched, the matched ones evenly spread)"
                if s.scenes_not_matched else ")")],
            ["median |v_left - v_right| before (px)", s.median_abs_before_px],
            ["median |v_left - v_right| after (px)", s.median_abs_after_px],
            ["rotation about x (deg)", f"{w[0]:+.4f} \u00b1 {sw[0]:.4f}"],
            ["rotation about z (deg)", f"{w[2]:+.4f} \u00b1 {sw[2]:.4f}"],
            ["focal scale", f"{s.focal_scale:+.2e} \u00b1 {s.sigma_focal_scale:.1e}"],
            ["largest vertical move over the image (px)", s.max_vertical_move_px]]
    if s.omega_y_vertical_only_rad is not None:
        rows.append(["rotation about y, from vertical disparity alone (deg; not applied)",
                     f"{np.degrees(s.omega_y_vertical_only_rad):+.4f} \u00b1 "
                     f"{np.degrees(s.sigma_omega_y_vertical_only_rad or 0.0):.4f}"])
    body += table(["", "value"], rows, fmt="{:.3f}", cls="kv")
    body += note(f"Matched in the images as rectified {html.escape(s.rectified_by)}. The right camera's rectifying "
                 "rotation gets a small extra rotation and its focal length a scale, fitted to the rows of SIFT "
                 "matches "
                 "refined by Lucas-Kanade over every board capture and up to max_scenes scene captures, evenly "
                 "spread over the session. The rotation about the vertical axis "
                 "shifts every disparity by about f times its angle and shows in the rows only at second order: it is "
                 "reported, never applied here. A vertical principal-point offset is the rotation about x to first "
                 "order. 'After': the same matches with the correction applied.")
    if s.captures:
        body += table(["capture", "matches", "median v_l - v_r before", "median |.| before", "median |.| after",
                       "median after"],
                      [[c.capture, c.n_matches, c.median_before_px, c.median_abs_before_px, c.median_abs_after_px,
                        c.median_after_px] for c in s.captures],
                      fmt=[None, "{:d}", "{:+.3f}", "{:.3f}", "{:.3f}", "{:+.3f}"], caption="Per capture (px).")
    if s.skipped:
        body += table(["capture", "not used because"], sorted(s.skipped.items()))
    return Section("ZED self-rectification", body, status=status)


def summary_lines(q: RectificationQuality | None, choice: ZedConfChoice | None = None) -> list[str]:
    """The lines ``gtforge calibrate`` / ``validate`` print about the rectification."""
    lines = []
    if choice is not None:
        line = f"SN.conf read as '{choice.reading}' ({choice.formula}), chosen by {choice.chosen_by}"
        others = [c for c in choice.candidates if c.eligible and c.reading != choice.reading]
        mine = choice.score(choice.reading)
        if mine is not None:
            line += f": {mine.vertical.fit_mean_abs_px:.3f} px on the raw board corners"
            if others:
                line += f" (next: '{others[0].reading}' {others[0].vertical.fit_mean_abs_px:.3f} px)"
        lines.append(line)
    if q is not None:
        o = q.overall
        n = len(q.poses)
        lines.append(f"ZED vertical disparity on {n} pose{'' if n == 1 else 's'}: mean {o.fit_mean_abs_px:.3f} px "
                     "(fitted corners), "
                     f"{o.mean_abs_px:.3f} px (detected; max {o.max_abs_px:.3f} px); threshold {q.threshold_px} px")
    else:
        lines.append("ZED vertical disparity: not measured (the board was not found in any right image)")
    return lines
