"""align-depth's page: the decision, each rotation with its sigma and status, and the pixel offsets between the depth
edges and the texture camera's edges before and after, for all captures together and per capture (a capture that
disagrees with the others, a knocked rig, is marked)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from gtforge.records.depth_alignment import DepthAlignment
from gtforge.reports.html import Section, esc, note, standard_header, table, verdict_badge, write_html

DECISION_BADGE = {"applied": "pass", "not significant": "pass", "not determined": "warn"}


def _xy(v) -> str:
    return "-" if v is None else f"({v[0]:+.2f}, {v[1]:+.2f})"


def write_depth_alignment_report(info: DepthAlignment, path: str | Path) -> Path:
    """Write the page to ``path`` (an ``.html`` file); returns it."""
    r = info.result
    path = Path(path)
    badge = verdict_badge(DECISION_BADGE.get(r.decision, "warn"), r.decision)
    summary = (f"<p>{badge} {esc(r.reason)}</p>"
               + table(["", "dx (px)", "dy (px)"],
                       [["all captures, before (factory pose)", r.offset_before_px[0], r.offset_before_px[1]],
                        ["all captures, after", r.offset_after_px[0], r.offset_after_px[1]]], fmt="{:+.2f}")
               + note(f"Offset = where the texture camera's edges lie minus where the depth edges put them, in the "
                      f"texture image (px). {r.n_edges} edge samples in {r.n_structures} structures; the coarse search "
                      f"covered +-{r.search_px:g} px"
                      f"{'' if r.search_interior else ' and its optimum lay on its border'}."
                      + (f" The correction is {r.significance_sigma:.1f} sigma from the factory pose."
                         if r.significance_sigma is not None else "")))
    rows = []
    for k, name in enumerate(("omega_x", "omega_y", "omega_z")):
        sig = r.sigma_omega_deg[k]
        rows.append([name, f"{r.omega_deg[k]:+.4f}", f"{sig:.4f}" if np.isfinite(sig) else "-", r.status[k]])
    params = table(["rotation (deg)", "estimate", "1 sigma", "status"], rows) + note(
        "The left perturbation of T_mech_from_depth (a rotation about the depth camera's centre, in the texture "
        "camera's axes); its covariance enters every GT pixel's sigma (disp0GT_sigma.pfm).")
    cap_rows = []
    for c in r.captures:
        state = f"not used: {c.excluded}" if c.excluded else ("disagrees with the others" if c.disagrees else "")
        cap_rows.append([c.name, _xy(c.offset_before_px), _xy(c.offset_after_px), c.n_edges, state])
    captures = table(["capture", "before (px)", "after (px)", "edges", ""], cap_rows)
    sections = [Section("Decision and offsets", summary, DECISION_BADGE.get(r.decision, "warn")),
                Section("Rotation", params),
                Section("Per capture", captures)]
    if r.warnings:
        sections.append(Section("Warnings", "".join(f"<p>{esc(w)}</p>" for w in r.warnings), "warn"))
    write_html(path, "Depth camera alignment (gtforge align-depth)", sections,
               header=standard_header(("calibration aligned", info.calibrated_from)))
    return path
