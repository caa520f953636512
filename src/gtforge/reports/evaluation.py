"""Evaluation reports: the tables (Markdown, CSV), ``results.html``, ``comparison.html`` and the error maps.

``results.html`` stays small whatever the image size: the error maps are inlined as small JPEG previews
(cropped to the scored pixels, colour bar below) that link to the full-size maps in ``heatmaps/``.
"""
from __future__ import annotations

import csv
import functools
import html
import io
import os
from pathlib import Path
from typing import Callable

import numpy as np

from gtforge.core.measure.metrics import Metrics
from gtforge.infra.atomic import atomic_write_text
from gtforge.records.evaluation import DEPTH_ERROR_MAP_PERCENTILE, DISP_ERROR_MAP_MAX_PX, TABLE_REGIONS, EvalResult
from gtforge.reports.fruit_size import comparison_section, fruit_markdown, fruit_section
from gtforge.reports.html import Section, note, pct_text, standard_header, table, write_html

ERROR_CMAP = "turbo"
PREVIEW_MAX_WH = (360, 250)  # preview size limit (px); crops smaller than this are enlarged at most 4x
PREVIEW_MIN_W = 320  # narrower previews are padded so the colour bar below stays readable
PREVIEW_JPEG_QUALITY = 72
MAX_SCENES_SHOWN = 8  # error maps of the worst scenes in results.html (the rest: heatmaps/)

DEPTH_NOTE = ("Depth MAE is computed on the fruit regions only (fruit, fruit_edge, fruit_centre: region.png 2 and "
              "3), the surfaces the dataset is built to measure; the other rows show a dash because no depth error "
              "is computed there.")
POOLED_NOTE = ("Pooled over every scored pixel of every scene. EPE, RMSE and Bad-x are over ground-truth pixels with "
               "a valid prediction; invalid predictions lower coverage instead (docs/metrics.md).")


# ---- error maps ---------------------------------------------------------------------------------
@functools.lru_cache(maxsize=4)
def _colour_table(name: str) -> tuple[int, np.ndarray]:
    """``(N, (N, 3) uint8)``: a colour map's entries as ``heatmap_rgb`` writes them (``(rgba[:3] * 255)`` cast)."""
    import matplotlib

    cmap = matplotlib.colormaps[name]
    return cmap.N, (cmap(np.arange(cmap.N))[:, :3] * 255).astype(np.uint8)


def heatmap_rgb(err: np.ndarray, vmax: float) -> np.ndarray:
    """``(H, W)`` errors -> RGB ``uint8`` in the ``turbo`` colour map over ``[0, vmax]``; NaN -> black.

    The entry is chosen as matplotlib's ``Colormap.__call__`` chooses it for values in ``[0, 1]`` (times ``N`` in the
    values' own type, 1 to the last entry, truncated), and looked up in the map's table already cast to bytes: the same
    pixels as ``(cmap(x)[..., :3] * 255).astype(uint8)``, without the float RGBA image in between (a third of the
    time of an error map; ``tests/reports/test_reports.py`` compares the two)."""
    n, table = _colour_table(ERROR_CMAP)
    x = np.clip(np.nan_to_num(err, nan=0.0) / vmax, 0, 1)
    x *= n
    x[x == n] = n - 1
    rgb = table[x.astype(np.intp)]
    rgb[~np.isfinite(err)] = 0
    return rgb


def colorbar_strip(width_px: int, vmax: float, label: str, height_px: int | None = None) -> np.ndarray:
    """A horizontal colour bar ``0 .. vmax`` (``turbo``, arrow = values above) as an RGB ``uint8`` strip (a copy of
    the one drawn for the same arguments before: every scene's disparity map has the same bar, and the previews' bars
    differ only in width and scale top; drawing one takes matplotlib about 50 ms)."""
    return _colorbar_strip(int(width_px), float(vmax), label, None if height_px is None else int(height_px)).copy()


@functools.lru_cache(maxsize=64)
def _colorbar_strip(width_px: int, vmax: float, label: str, height_px: int | None) -> np.ndarray:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    h = height_px or max(56, int(round(0.03 * width_px)))
    dpi = 100
    fs = 8.5 * h / 56
    fig = Figure(figsize=(width_px / dpi, h / dpi), dpi=dpi, facecolor="white")
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.06, 0.62, 0.88, 0.28))
    cb = fig.colorbar(ScalarMappable(Normalize(0.0, vmax), ERROR_CMAP), cax=ax, orientation="horizontal",
                      extend="max")
    cb.ax.tick_params(labelsize=fs, length=2, pad=1)
    cb.set_label(f"{label}; black: not scored", fontsize=fs, labelpad=1)
    canvas.draw()
    strip = np.asarray(canvas.buffer_rgba())[..., :3].copy()
    if strip.shape[1] != width_px:  # figure size rounding
        import cv2

        strip = cv2.resize(strip, (width_px, strip.shape[0]), interpolation=cv2.INTER_AREA)
    return strip


def error_map_images(err: np.ndarray, vmax: float, label: str) -> tuple[np.ndarray, np.ndarray]:
    """(full-size map with a colour bar below: its top ``H`` rows are pixel-aligned with ``im0.png``,
    a preview cropped to the scored pixels with its own colour bar)."""
    import cv2

    rgb = heatmap_rgb(err, vmax)
    full = np.vstack([rgb, colorbar_strip(rgb.shape[1], vmax, label)])
    v, u = np.nonzero(np.isfinite(err))
    if len(v):
        m = 12
        v0, v1 = max(v.min() - m, 0), min(v.max() + m + 1, rgb.shape[0])
        u0, u1 = max(u.min() - m, 0), min(u.max() + m + 1, rgb.shape[1])
        crop = rgb[v0:v1, u0:u1]
    else:
        crop = rgb
    ch, cw = crop.shape[:2]
    s = min(PREVIEW_MAX_WH[0] / cw, PREVIEW_MAX_WH[1] / ch, 4.0)
    size = (max(int(round(cw * s)), 1), max(int(round(ch * s)), 1))
    prev = cv2.resize(crop, size, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_NEAREST)
    if prev.shape[1] < PREVIEW_MIN_W:
        pad = PREVIEW_MIN_W - prev.shape[1]
        prev = cv2.copyMakeBorder(prev, 0, 0, pad // 2, pad - pad // 2, cv2.BORDER_CONSTANT, value=(255, 255, 255))
    return full, np.vstack([prev, colorbar_strip(prev.shape[1], vmax, label, 56)])


def preview_jpeg(rgb: np.ndarray) -> bytes:
    """A preview encoded for results.html (JPEG at ``PREVIEW_JPEG_QUALITY``: about 20-30 kB each)."""
    import cv2

    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, PREVIEW_JPEG_QUALITY])
    if not ok:
        raise RuntimeError("JPEG encode failed")
    return buf.tobytes()


# ---- tables -------------------------------------------------------------------------------------
def _uses_sigma(reports: list[EvalResult]) -> bool:
    return any(r.max_gt_sigma_px is not None for r in reports)


def _uses_params(reports: list[EvalResult]) -> bool:
    return any(r.params_count is not None for r in reports)


def _left_out_text(m: Metrics) -> str:
    total = m.n_gt + m.n_gt_sigma_left_out
    return f"{m.n_gt_sigma_left_out} ({100.0 * m.n_gt_sigma_left_out / total:.1f} %)" if total else "0"


def headers(reports: list[EvalResult]) -> list[str]:
    h = ["model", "region", "GT pixels", "EPE (px)", "RMSE (px)", "Bad-0.5 (%)", "Bad-1.0 (%)", "Bad-2.0 (%)",
         "coverage (%)", "depth MAE (mm)", "time (ms/frame)"]
    if _uses_sigma(reports):
        h.insert(3, "GT left out by sigma")
    if _uses_params(reports):  # evaluate --params-count: the model's size beside its figures
        h.append("parameters")
    return h


def _rows(reports: list[EvalResult], labels: list[str] | None = None, regions=TABLE_REGIONS,
          left_out: Callable[[Metrics], object] = _left_out_text):
    sig, params = _uses_sigma(reports), _uses_params(reports)
    for k, rep in enumerate(reports):
        for r in regions:
            m = rep.pooled[r]
            row = [labels[k] if labels else rep.model, r, m.n_gt, m.epe_px, m.rmse_px, m.bad_0_5_pct, m.bad_1_0_pct,
                   m.bad_2_0_pct, m.coverage_pct, m.depth_mae_mm, rep.time_ms_median]
            if sig:
                row.insert(3, left_out(m) if rep.max_gt_sigma_px is not None else None)
            if params:
                row.append(rep.params_count)
            yield row


def _pct_cells(head: list[str], rows) -> list[list]:
    """The rows with their Bad-x and coverage shares as ``pct_text`` (the table's 4 significant digits showed a
    coverage of 99.997 % as 100)."""
    pct = [k for k, h in enumerate(head) if h.endswith("(%)")]
    return [[pct_text(v) if k in pct else v for k, v in enumerate(row)] for row in rows]


def _notes(reports: list[EvalResult]) -> list[str]:
    out = [POOLED_NOTE, DEPTH_NOTE]
    for rep in reports:
        if rep.max_gt_sigma_px is not None:
            out.append(f"{rep.model}: only ground-truth pixels with sigma < {rep.max_gt_sigma_px:g} px scored "
                       "(disp0GT_sigma.pfm); 'GT left out by sigma' counts the others (share of the region's GT).")
    return out


def tables_markdown(reports: list[EvalResult], labels: list[str] | None = None,
                    warnings: list[str] | None = None) -> str:
    def cell(v):
        return "-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))

    h = headers(reports)
    lines = [f"> warning: {w}" for w in warnings or []] + ([""] if warnings else [])
    lines += ["| " + " | ".join(h) + " |", "|" + "---|" * len(h)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in _pct_cells(h, _rows(reports, labels))]

    fruit = fruit_markdown(reports, labels)
    return "\n".join(lines) + "\n\n" + "\n\n".join(_notes(reports)) + "\n" + ("\n" + fruit if fruit else "")


def write_tables(reports: list[EvalResult], out: Path, stem: str = "results", labels: list[str] | None = None,
                 warnings: list[str] | None = None) -> None:
    atomic_write_text(out / f"{stem}.md", tables_markdown(reports, labels, warnings))
    buf = io.StringIO()
    w = csv.writer(buf)
    h = headers(reports)
    if _uses_sigma(reports):
        h[3] = "GT left out by sigma (pixels)"
    w.writerow(h)
    for row in _rows(reports, labels, left_out=lambda m: m.n_gt_sigma_left_out):
        w.writerow(["" if v is None else v for v in row])
    atomic_write_text(out / f"{stem}.csv", buf.getvalue())


# ---- results.html -------------------------------------------------------------------------------
def _report_header(rep: EvalResult) -> list[tuple[str, object]]:
    return [("written", rep.created or None), ("gtforge version", rep.gtforge_version or None),
            ("dataset", rep.dataset_dir), ("model", rep.model_source or rep.model),
            ("provider", rep.provider), ("split", rep.split or "every scene"),
            ("scenes scored / excluded", f"{len(rep.scenes)} / {len(rep.missing)}"),
            ("max disparity scored (px)", rep.max_disp_px), ("max GT sigma scored (px)", rep.max_gt_sigma_px)]


def _scene_maps(rep: EvalResult, out: Path, max_scenes: int) -> str:
    import base64

    worst = sorted(rep.per_scene, key=lambda s: -(s.metrics["all"].epe_px or 0.0))[:max_scenes]
    rows = []
    for s in worst:
        figs = []
        for kind, label, top in (("disp_error", "disparity error", s.disp_error_map_max_px),
                                 ("depth_error", "fruit depth error", s.depth_error_map_max_mm)):
            prev = out / "heatmaps" / "preview" / f"{s.scene}_{kind}.jpg"
            full = f"heatmaps/{s.scene}_{kind}.png"
            if not prev.is_file():
                continue
            unit = "px" if kind == "disp_error" else "mm"
            scale = f", scale 0\u2013{top:g} {unit}" if top is not None else ""
            b64 = base64.b64encode(prev.read_bytes()).decode("ascii")
            figs.append(f'<figure><a href="{html.escape(full)}"><img alt="{s.scene} {label}" '
                        f'src="data:image/jpeg;base64,{b64}"/></a><figcaption>{html.escape(s.scene)}: {label}{scale} '
                        f'(<a href="{html.escape(full)}">full size</a>)</figcaption></figure>')
        rows.append(f'<div class="maps">{"".join(figs)}</div>')
    intro = note(f"Worst {len(worst)} scene(s) by EPE, cropped to the scored pixels; click a map for the full-size PNG "
                 "in heatmaps/ (its top rows are pixel-aligned with im0.png, the colour bar is below). "
                 "Disparity error: "
                 f"the same scale for every scene, 0\u2013{DISP_ERROR_MAP_MAX_PX:g} px (the Bad-2.0 threshold). Fruit "
                 f"depth error: each scene's own scale, its {DEPTH_ERROR_MAP_PERCENTILE:g}th percentile rounded up, "
                 "so the map shows where the error is, not only that it exceeds a fixed limit.")
    return intro + "".join(rows)


def write_eval_html(rep: EvalResult, out: Path, max_scenes: int = MAX_SCENES_SHOWN) -> Path:
    """``results.html``: header, pooled table, per-scene table (worst EPE first), error-map previews."""
    # no model column (one model), no time or parameters column (in the heading)
    full = headers([rep])
    keep = [k for k, h in enumerate(full) if h not in ("model", "time (ms/frame)", "parameters")]
    head = [full[k] for k in keep]
    rows = _pct_cells(head, [[row[k] for k in keep] for row in _rows([rep], regions=tuple(rep.pooled))])
    main = table(head, rows, fmt="{:.4g}") + "".join(note(n) for n in _notes([rep]))
    worst = sorted(rep.per_scene, key=lambda s: -(s.metrics["all"].epe_px or 0.0))
    scene_rows = [[s.scene, s.metrics["all"].epe_px, s.metrics["all"].bad_2_0_pct, s.metrics["fruit"].epe_px,
                   s.metrics["fruit"].depth_mae_mm, s.metrics["all"].coverage_pct, s.time_ms] for s in worst]
    scene_head = ["scene", "EPE all (px)", "Bad-2.0 all (%)", "EPE fruit (px)", "depth MAE fruit (mm)", "coverage (%)",
                  "time (ms)"]
    sections = [
        Section(f"{rep.model}: {len(rep.scenes)} scene(s), median {rep.time_ms_median or 0:.1f} ms/frame "
                f"({rep.provider})" + (f", {rep.params_count:,} parameters" if rep.params_count is not None else ""),
                main),
        Section("Per scene, worst EPE first", table(scene_head, _pct_cells(scene_head, scene_rows))),
        Section("Error maps", _scene_maps(rep, out, max_scenes)),
    ]

    fruit = fruit_section(rep)
    if fruit is not None:
        sections.insert(2, fruit)
    if rep.suspect_scenes:
        sections.insert(0, Section(f"{len(rep.suspect_scenes)} scored scene(s) with suspect ground truth (verify)",
                                   table(["scene", "verify"], list(rep.suspect_scenes.items())), status="warn"))
    if rep.missing:
        sections.insert(0, Section(f"{len(rep.missing)} scene(s) excluded", table(
            ["scene", "reason"], list(rep.missing.items())), status="warn"))
    return write_html(out / "results.html", f"gtforge evaluation: {rep.model}", sections, header=_report_header(rep))


# ---- compare ------------------------------------------------------------------------------------
def row_labels(reports: list[EvalResult], files: list[Path]) -> list[str]:
    """Model names, with the result's folder added where two results share a name: as many of the folder's trailing
    path parts as tell those results apart (``SGBM [run1/evaluation]``, ``SGBM [run2/evaluation]``)."""
    names = [r.model for r in reports]
    folders = [Path(os.path.abspath(f)).parent.parts for f in files]
    labels = list(names)
    for name in set(names):
        idx = [i for i, n in enumerate(names) if n == name]
        if len(idx) < 2:
            continue
        depth = max(len(folders[i]) for i in idx)
        for k in range(1, depth + 1):
            tails = ["/".join(folders[i][-k:]) for i in idx]
            if len(set(tails)) == len(tails):
                break
        else:  # the same folder more than once: numbered
            tails = [f"{folders[i][-1] if folders[i] else ''} #{j + 1}" for j, i in enumerate(idx)]
        for i, tail in zip(idx, tails):
            labels[i] = f"{name} [{tail}]"
    return labels


def comparison_warnings(reports: list[EvalResult], files: list[Path]) -> list[str]:
    """Why a side-by-side table may mislead: different datasets / scenes / scoring limits, repeated model names."""
    w = []

    def differ(key: Callable[[EvalResult], object]) -> bool:
        return len({repr(key(r)) for r in reports}) > 1

    def listing(key: Callable[[EvalResult], object]) -> str:
        return "; ".join(f"{f}: {key(r)}" for r, f in zip(reports, files))

    content = [r.dataset_content_sha256 for r in reports]
    hashes = content if all(content) else [r.dataset_manifest_sha256 for r in reports]
    if all(hashes) and len(set(hashes)) > 1:
        w.append("the results come from different datasets (manifest.json differs" +
                 (", beyond where and when each was built" if all(content) else "") + "): " +
                 "; ".join(f"{f}: {r.dataset_dir} (manifest {h[:12]})" for r, f, h in zip(reports, files, hashes)))
    elif not all(hashes) and differ(lambda r: r.dataset_dir):
        w.append("the results come from different dataset folders: " + listing(lambda r: r.dataset_dir))
    if differ(lambda r: sorted(r.scenes)):
        w.append("the results score different scenes: " +
                 listing(lambda r: f"{len(r.scenes)} scene(s){', split ' + r.split if r.split else ''}"))
    if differ(lambda r: (r.max_disp_px, r.max_gt_sigma_px)):
        w.append("the results use different scoring limits: " +
                 listing(lambda r: f"max disparity {r.max_disp_px}, max GT sigma {r.max_gt_sigma_px}"))
    names = [r.model for r in reports]
    for n in sorted({n for n in names if names.count(n) > 1}):
        w.append(f"model name '{n}' is used by {names.count(n)} results "
                 f"({', '.join(str(f) for r, f in zip(reports, files) if r.model == n)}); their rows are labelled "
                 "with the result's folder (use evaluate --name to tell them apart)")
    return w


def write_comparison_html(reports: list[EvalResult], files: list[Path], labels: list[str], warnings: list[str],
                          path: Path) -> Path:

    sections = []
    if warnings:
        sections.append(Section("Warnings", "".join(f'<p class="warn">{html.escape(w)}</p>' for w in warnings),
                                status="warn"))
    h = headers(reports)
    sections.append(Section("Pooled results", table(h, _pct_cells(h, _rows(reports, labels))) +
                            "".join(note(n) for n in _notes(reports))))

    fruit = comparison_section(reports, labels)
    if fruit is not None:
        sections.append(fruit)
    src = [[lab, str(f), r.model_source or r.model, r.dataset_dir, r.split or "every scene", len(r.scenes),
            r.created or None]
           for lab, f, r in zip(labels, files, reports)]
    sections.append(Section("Results compared", table(["row label", "results.json", "model", "dataset", "split",
                                                       "scenes", "evaluated"], src)))
    return write_html(path, "gtforge comparison", sections, header=standard_header())

