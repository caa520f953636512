"""``verification.html``: every scene's checks of its ground truth against its own images, worst first."""
from __future__ import annotations

import datetime
import html
from pathlib import Path

import numpy as np

import gtforge
from gtforge.records.verification import SceneVerification, VerificationResult
from gtforge.reports.html import fig_to_img_tag, table, write_html


def _f(v, fmt="{:+.3f}"):
    return "-" if v is None else fmt.format(v)


def _fn(v, noise, fmt="{:+.3f}"):
    """A figure with its noise floor (1 sigma, what exact labels give on this scene): ``+0.012 ± 0.004``."""
    return _f(v, fmt) if v is None or noise is None else f"{fmt.format(v)} ± {noise:.3f}"


def _sort_key(item):
    sid, v = item
    order = {"flagged": 0, "not verifiable": 1, "ok": 2}[v.status]
    w = v.worst_shift_px
    return order, -(w if np.isfinite(w) else 0.0), sid


def _shift_map(sid: str, v: SceneVerification) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([[np.nan if x is None else x for x in row] for row in v.texture_tiles], float)
    if not len(t) or not np.isfinite(t[:, 2]).any():
        return ""
    fig, ax = plt.subplots(figsize=(5.2, 3.4))
    ok = np.isfinite(t[:, 2])
    mag = np.hypot(t[ok, 2], t[ok, 3])
    scale = 0.08 * (t[:, 0].max() * 2) / max(float(mag.max()), 0.05)
    ax.quiver(t[ok, 0], t[ok, 1], t[ok, 2] * scale, t[ok, 3] * scale, mag, angles="xy", scale_units="xy", scale=1,
              cmap="viridis", width=0.006)
    for (x, y, dx, dy) in t[ok]:
        ax.annotate(f"{np.hypot(dx, dy):.2f}", (x, y), fontsize=7, ha="center", va="bottom")
    W, H = t[:, 0].max() * 2 * len(np.unique(t[:, 0])) / max(len(np.unique(t[:, 0])) * 2 - 1, 1), t[:, 1].max() * 2
    ax.set_xlim(0, W)
    ax.set_ylim(H, 0)
    ax.set_aspect("equal")
    ax.set_xlabel("u (ZED-left px)")
    ax.set_ylabel("v (px)")
    ax.set_title(f"{sid}: texture shift per tile (px, arrows scaled; labels = |shift|)", fontsize=9)
    return fig_to_img_tag(fig, "520px")


def write_verification_html(rep: VerificationResult, out: Path) -> Path:
    p = rep.params
    items = sorted(rep.scenes.items(), key=_sort_key)
    n_flag = sum(v.status == "flagged" for v in rep.scenes.values())
    n_nv = sum(v.status == "not verifiable" for v in rep.scenes.values())
    head = (f"<p>{len(rep.scenes)} scene(s): <b class='{'fail' if n_flag else 'pass'}'>{n_flag} flagged</b>, "
            f"{n_nv} not verifiable, {len(rep.scenes) - n_flag - n_nv} ok. gtforge {gtforge.__version__}, "
            f"{datetime.datetime.now().strftime('%Y-%m-%d %H:%M')}, dataset {html.escape(rep.dataset_dir)}.</p>"
            "<p>Texture shift = where the ZED-left image shows a structure minus where the ground truth puts it "
            "(the structured-light texture rendered through the GT geometry, both locally normalised, aligned by "
            "Lucas-Kanade). Correlation: normalised cross-correlation after alignment. Stereo: the disparity bias "
            "and vertical offset that best explain ZED-right warped through the GT disparity; bad-match = share of "
            "textured pixels whose match is clearly better within +-1 px than at the GT (docs/pipeline.md). "
            "Each figure is followed by its noise floor (± 1 sigma: what exact labels give on this scene, from the "
            "spread of the figure over 16 bands of its pixels); a figure within 2-3 of it is a measurement artefact, "
            "not an error of the ground truth.</p>")
    thresholds = table(["threshold", "value"], [
        ["texture shift, whole area or fruit (px)", p.max_shift_px],
        ["texture correlation, at least", p.min_correlation],
        ["stereo disparity bias, any region (px)", p.max_disparity_bias_px],
        ["stereo vertical misalignment (px)", p.max_vertical_px],
        ["bad matches (% of textured pixels)", p.max_bad_match_pct]])
    rows = []
    for sid, v in items:
        st = v.stereo.get("all")
        sf = v.stereo.get("fruit")
        ta, tf = v.texture_all, v.texture_fruit
        rows.append([sid, v.status.upper() if v.status == "flagged" else
                     v.status + v.compensated_label,
                     _fn(ta.dx_px, ta.dx_noise_px) + " / " + _fn(ta.dy_px, ta.dy_noise_px),
                     _fn(tf.dx_px, tf.dx_noise_px) + " / " + _fn(tf.dy_px, tf.dy_noise_px),
                     _fn(ta.correlation, ta.correlation_noise, "{:.2f}") + " / "
                     + _fn(tf.correlation, tf.correlation_noise, "{:.2f}"),
                     _fn(st.disparity_bias_px, st.disparity_bias_noise_px) if st else _f(None),
                     _fn(sf.disparity_bias_px, sf.disparity_bias_noise_px) if sf else _f(None),
                     _fn(st.vertical_px, st.vertical_noise_px) if st else _f(None),
                     _f(st.bad_match_pct if st else None, "{:.1f}"), "; ".join(v.reasons)])
    body = table(["scene", "status", "shift all dx / dy (px)", "shift fruit dx / dy (px)", "correlation all / fruit",
                  "disparity bias all (px)", "disparity bias fruit (px)", "vertical (px)", "bad matches (%)",
                  "reasons"], rows)
    flagged_parts = []
    for sid, v in items:
        if v.status != "flagged":
            continue
        overlay = out / "verification" / f"{sid}_overlay.jpg"
        img = (f"<a href='verification/{sid}_overlay.jpg'><img style='max-width:640px' "
               f"src='verification/{sid}_overlay.jpg'/></a>") if overlay.exists() else ""
        flagged_parts.append(f"<h3>{html.escape(sid)}</h3><p>{html.escape('; '.join(v.reasons))}</p>"
                             f"<div style='display:flex;gap:12px;align-items:flex-start'>"
                             f"{_shift_map(sid, v)}{img}</div>"
                             "<p class='note'>Overlay: ZED-left (green) and the texture rendered through the ground "
                             "truth (magenta), both locally normalised; where they agree the image is grey, a shift "
                             "shows as green/magenta fringes.</p>")
    sections = [("Summary", head + thresholds), ("Per scene, worst first", body),
                ("Flagged scenes", "".join(flagged_parts) or "<p>none</p>")]
    motion = _motion_section(items, out)
    if motion:  # only where a scene's fruit moved (the other datasets' pages stay as they were)
        sections.append(("Fruit motion between the exposures", motion))
    return write_html(out / "verification.html", "gtforge verification", sections)


def _v3(x, signed: bool = True) -> str:
    return "-" if x is None else " / ".join(f"{a:{'+' if signed else ''}.3f}" for a in x)


def _motion_section(items, out: Path) -> str:
    """The scenes verification flagged for fruit motion: what the compensation did, per fruit, with the before/after
    overlays of a compensated scene (docs/design/motion-compensation.md)."""
    parts = []
    for sid, v in items:
        mc = v.motion_compensation
        if mc is None:
            continue
        rows = [[f.component, f.status, _v3(f.translation_mm), _v3(f.sigma_translation_mm, signed=False),
                 _v3(f.rotvec_deg), _v3(f.sigma_rot_deg, signed=False), _f(f.disparity_sigma_px, "{:.4f}"),
                 _f(f.chi2_still, "{:.1f}"), f.n_pixels, html.escape(f.reason)] for f in mc.fruit]
        imgs = "".join(f"<figure><a href='verification/{sid}_motion_{w}.jpg'><img style='max-width:520px' "
                       f"src='verification/{sid}_motion_{w}.jpg'/></a><figcaption>{w}</figcaption></figure>"
                       for w in ("before", "after") if (out / "verification" / f"{sid}_motion_{w}.jpg").exists())
        before = (f"<p>Before: {html.escape('; '.join(mc.before.reasons))}</p>" if mc.before is not None else "")
        parts.append(f"<h3>{html.escape(sid)}: {mc.status}</h3>"
                     + (f"<p>{html.escape('; '.join(mc.reasons))}</p>" if mc.reasons else "") + before
                     + table(["fruit", "status", "translation x / y / z (mm)", "1 sigma (mm)",
                              "rotation vector (deg)", "1 sigma (deg)", "disparity sigma p95 (px)",
                              "chi2 from still", "pixels", "why"], rows)
                     + (f"<div style='display:flex;gap:12px'>{imgs}</div>" if imgs else ""))
    if not parts:
        return ""
    return ("<p>A fruit that moved between the structured-light exposure and the ZED exposure: each fruit's rigid "
            "motion (ZED-left frame, about the centroid of its measured points) estimated from the ZED pair's "
            "photo-consistency and the texture; a scene is <b>compensated</b> (its ground truth rebuilt with the "
            "fruit moved, the motion's covariance in its sigma map) only when every moved fruit's motion is "
            "determined and within the limits and the rebuilt scene passes verification; otherwise it stays flagged, "
            "with the reason. Overlays: as above, of the ground truth as first built (before) and rebuilt "
            "(after).</p>" + "".join(parts))


def write_verification_report(report: VerificationResult, out_dir: str | Path) -> Path:
    """``verification.json`` + ``verification.html`` in ``out_dir``; ``verification/<id>_overlay.jpg`` of a scene the
    report does not flag is removed (overlays are of flagged scenes only: a scene flagged by an earlier build or
    verify and passing now kept one, showing a flag the dataset no longer had)."""

    out = Path(out_dir)
    for sid, v in report.scenes.items():
        if v.status != "flagged":
            (out / "verification" / f"{sid}_overlay.jpg").unlink(missing_ok=True)
    report.write(out / "verification.json")
    return write_verification_html(report, out)
