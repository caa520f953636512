"""``build_report.html``: what build-dataset made, per scene: coverage, disparity range, verification verdict and the
ground truth's uncertainty (sigma heat maps)."""
from __future__ import annotations

import datetime
import html
from pathlib import Path

import cv2
import numpy as np

import gtforge
from gtforge.io.formats import write_image
from gtforge.reports.html import table, write_html


def _f(v, fmt="{:.4f}"):
    return "-" if v is None else fmt.format(v)


def write_build_report(manifest, out: Path, sigma_vmax_px: float = 0.1) -> Path:
    """``manifest``: the dataset's ``gtforge.records.dataset.Manifest``."""
    scenes = manifest.scenes
    head = (f"<p>{len(scenes)} scene(s) built, {len(manifest.failures)} failed, {len(manifest.flagged)} flagged by "
            f"verification (<a href='verification.html'>verification.html</a>){', ' if manifest.quarantined else ''}"
            f"{f'{len(manifest.quarantined)} quarantined' if manifest.quarantined else ''}"
            + (f", {len(manifest.compensated)} with fruit motion compensated (their ground truth rebuilt with the "
               f"fruit where the ZED saw it; filenames/compensated.txt)" if manifest.compensated else "") + ". "
            + f"gtforge {gtforge.__version__}, {datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}; calibration "
            f"{html.escape(manifest.calibration_path)}; session {html.escape(manifest.session_dir)}.</p>"
            "<p>sigma: the 1-sigma uncertainty of each GT disparity (disp0GT_sigma.pfm), from the calibration's "
            "covariance, the depth camera's noise model, the mesh interpolation and the verification's texture shift "
            "(docs/dataset-format.md)"
            + ("; on a compensated scene's moved fruit also the motion's covariance" if manifest.compensated else "")
            + ". Per region: median / 95th percentile (px) and the share above 0.1 px.</p>")
    rows = []
    for sid, m in sorted(scenes.items()):
        sg = m.sigma or {}

        def cell(region):
            s = sg.get(region)
            return "-" if s is None or s.median_px is None else \
                f"{s.median_px:.4f} / {s.p95_px:.4f} / {s.over_0_1_px_pct:.1f} %"

        v = m.verification
        rows.append([sid, m.fruit_id or "", _f(m.stats.valid_pct, "{:.1f}"), _f(m.stats.fruit_pct, "{:.1f}"),
                     f"{_f(m.stats.disp_min_px, '{:.1f}')} - {_f(m.stats.disp_max_px, '{:.1f}')}",
                     "-" if v is None else v.status + v.compensated_label,
                     cell("all"), cell("fruit_centre"), cell("fruit_edge"),
                     cell("background"),
                     "" if m.sigma_extrinsic_included or not m.sigma else "no calibration covariance"])
    stats = table(["scene", "fruit", "GT valid (%)", "fruit (%)", "disparity (px)", "verification",
                   "sigma all", "sigma fruit centre", "sigma fruit edge", "sigma background", "note"], rows)
    thumbs = []
    for sid in sorted(scenes):
        p = out / "report" / f"{sid}_sigma.jpg"
        if p.exists():
            thumbs.append(f"<figure style='display:inline-block;margin:4px'><a href='report/{sid}_sigma.jpg'>"
                          f"<img style='width:300px' src='report/{sid}_sigma.jpg'/></a>"
                          f"<figcaption>{html.escape(sid)}</figcaption></figure>")
    legend = (f"<p>Colour: turbo, 0 (blue) to {sigma_vmax_px} px (red) and above; black = no ground truth.</p>")
    return write_html(out / "build_report.html", "gtforge dataset", [
        ("Summary", head), ("Per scene", stats),
        ("Ground-truth uncertainty (sigma) per scene", legend + ("".join(thumbs) or "<p>no sigma maps</p>"))])


def write_sigma_thumbnail(path: Path, sigma: np.ndarray, vmax_px: float = 0.1) -> None:
    """A small heat map of a scene's GT sigma for build_report.html (turbo, 0 to ``vmax_px``; black: no GT)."""
    s = np.asarray(sigma, np.float32)
    scale = min(1.0, 640 / s.shape[1])
    if scale < 1.0:  # nearest neighbour: the thumbnail's pixels are values of the map (inf stays inf)
        s = cv2.resize(s, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    finite = np.isfinite(s)
    g = np.where(finite, s, np.float32(0.0))  # (float32 throughout, as s; in place: one temporary array)
    g /= vmax_px
    np.clip(g, 0, 1, out=g)
    g *= 255
    grey = np.rint(g, out=g).astype(np.uint8)
    bgr = cv2.applyColorMap(grey, cv2.COLORMAP_TURBO)
    bgr = cv2.copyTo(bgr, finite.view(np.uint8), np.zeros_like(bgr))  # black where no GT (OpenCV's masked
    # copy: a multiply by the mask broadcast over the channels, or a boolean-mask assignment, is several times slower)
    write_image(path, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
