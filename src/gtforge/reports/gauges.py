"""``gauges.html`` and the gauge section of ``validation.html``: VDI/VDE 2634-2 figures of the ground truth on
gauge objects, with each gauge's residual map on the ZED-left image and the residuals' histogram."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gtforge.reports.html import Section, fig_to_img_tag, note, standard_header, table, write_html

if TYPE_CHECKING:
    from gtforge.core.measure.gauges import GaugeResult, GaugesResult

GAUGE_NOTE = ("Ground truth (gt): the GT disparity turned back into 3-D, Z = f*B/(d + doffs), in the ZED-left frame; "
              "raw: the structured-light depth mapped into the same frame. Size error PS = fitted - calibrated "
              "diameter; "
              "form error PF = range of the radial residuals (RMS beside it); sphere-spacing error SD = fitted - "
              "calibrated centre distance; flatness F = range of the distances to the fitted plane. 'predicted': the "
              "form figures the per-pixel sigma map states (depth noise and mesh interpolation; the extrinsic term "
              "moves the object rigidly and changes none of these figures); for size and spacing the 1-sigma of the "
              "fitted "
              "figure from the same per-point sigmas (the mesh's chord bias is not in it). docs/metrics.md, "
              "'Gauge objects'.")

_STATUS = {"PASS": "pass", "WARN": "warn", "FAIL": "fail", "NOT MEASURABLE": "warn"}


def figure_rows(g: "GaugeResult") -> list[list]:
    rows = []
    for src in (g.gt, g.raw):
        if src is None:
            continue
        if not src.measurable:
            rows.append([src.source, "not measurable", src.reason, None, None, None, None])
            continue
        for k, s in enumerate(src.spheres):
            name = "sphere" if len(src.spheres) == 1 else f"sphere {k + 1}"
            rows.append([src.source, f"{name}: size error PS (mm)", s.size_error_mm, s.size_sigma_predicted_mm,
                         s.n_points, f"diameter {s.diameter_mm:.3f}", None])
            rows.append([src.source, f"{name}: form error PF (mm)", s.form_range_mm, s.form_range_predicted_mm,
                         s.n_points, f"RMS {s.form_rms_mm:.4f}", s.form_rms_predicted_mm])
        if src.spacing_error_mm is not None:
            rows.append([src.source, "sphere-spacing error SD (mm)", src.spacing_error_mm,
                         src.spacing_sigma_predicted_mm,
                         sum(s.n_points for s in src.spheres), f"distance {src.centre_distance_mm:.3f}", None])
        if src.flatness_mm is not None:
            rows.append([src.source, "flatness F (mm)", src.flatness_mm, src.flatness_predicted_mm, src.n_points,
                         f"RMS {src.plane_rms_mm:.4f}", src.plane_rms_predicted_mm])
    return rows


HEADERS = ["source", "figure", "measured", "predicted from sigma (form: range; size, spacing: 1-sigma)", "points",
           "detail", "predicted RMS (mm)"]


def _plots(res: np.ndarray | None) -> str:
    if res is None or not np.isfinite(res).any():
        return ""
    from matplotlib.figure import Figure

    v, u = np.nonzero(np.isfinite(res))
    m = 6
    crop = res[max(v.min() - m, 0):v.max() + m + 1, max(u.min() - m, 0):u.max() + m + 1]
    vals = res[np.isfinite(res)]
    top = float(np.percentile(np.abs(vals), 99)) or 1e-3
    fig = Figure(figsize=(8.4, 3.2))
    ax = fig.add_subplot(121)
    im = ax.imshow(crop, cmap="coolwarm", vmin=-top, vmax=top, interpolation="nearest")
    ax.set_title("GT residual on the ZED-left image (mm)", fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    fig.colorbar(im, ax=ax, fraction=0.046)
    ax = fig.add_subplot(122)
    ax.hist(vals, bins=60, color="#4a78b0")
    ax.set_xlabel("signed residual (mm)")
    ax.set_ylabel("points")
    ax.set_title(f"{vals.size} points", fontsize=9)
    fig.tight_layout()
    return fig_to_img_tag(fig, width="840px", alt="gauge residual map and histogram")


def gauge_sections(rep: "GaugesResult", maps: dict | None = None) -> list[Section]:
    lim = rep.limits
    limits = table(["figure", "PASS up to (mm)", "WARN up to (mm)"], [
        ["size error |PS|", lim.size_pass_mm, lim.size_warn_mm], ["form error PF", lim.form_pass_mm, lim.form_warn_mm],
        ["sphere-spacing error |SD|", lim.spacing_pass_mm, lim.spacing_warn_mm],
        ["flatness F", lim.flatness_pass_mm, lim.flatness_warn_mm]])
    out = [Section(f"Gauge objects (VDI/VDE 2634-2): {rep.status}", limits + note(GAUGE_NOTE),
                   status=_STATUS[rep.status])]
    for g in rep.gauges:
        body = table(HEADERS, figure_rows(g), fmt="{:.4f}")
        if g.reasons:
            body += "".join(note(r) for r in g.reasons)
        body += _plots((maps or {}).get(g.capture, {}).get("residual_gt_mm"))
        out.append(Section(f"{g.capture} ({g.kind}): {g.status}", body, status=_STATUS[g.status]))
    return out


def write_gauges_html(rep: "GaugesResult", maps: dict | None, path: Path) -> Path:
    header = standard_header(("session", rep.session_dir), ("calibration", rep.calibration_path))
    return write_html(path, "gtforge gauge validation", gauge_sections(rep, maps), header=header)
