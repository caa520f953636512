"""Evaluation tables (Markdown, CSV) and ``results.html``."""
from __future__ import annotations

import csv
import io
from pathlib import Path

from gtforge.evaluate import EvalReport, TABLE_REGIONS
from gtforge.io.atomic import atomic_write_text


def write_eval_html(rep: EvalReport, out: Path, max_scenes: int = 12) -> Path:
    """``results.html``: the table, per-scene figures (worst EPE first) and the error heat maps."""
    import base64

    from gtforge.reports.html import table, write_html

    rows = [[r, m.epe_px, m.rmse_px, m.bad_0_5_pct, m.bad_1_0_pct, m.bad_2_0_pct, m.coverage_pct, m.depth_mae_mm]
            for r, m in rep.pooled.items()]
    fmt_rows = [[v if v is not None else "-" for v in r] for r in rows]
    head = ["region", "EPE (px)", "RMSE (px)", "Bad-0.5 (%)", "Bad-1.0 (%)", "Bad-2.0 (%)", "coverage (%)", "depth MAE (mm)"]
    worst = sorted(rep.per_scene, key=lambda s: -(s.metrics["all"].epe_px or 0.0))
    scene_rows = [[s.scene, s.metrics["all"].epe_px or float("nan"), s.metrics["fruit"].epe_px or float("nan"),
                   s.metrics["fruit"].depth_mae_mm or float("nan"), s.time_ms] for s in worst]
    imgs = []
    for s in worst[:max_scenes]:
        tags = []
        for kind, label in (("disp_error", "disparity error, 0-2 px"), ("depth_error", "fruit depth error, 0-1 mm")):
            p = out / "heatmaps" / f"{s.scene}_{kind}.png"
            if p.exists():
                b64 = base64.b64encode(p.read_bytes()).decode("ascii")
                tags.append(f'<figure style="display:inline-block;margin:4px"><img style="width:420px" '
                            f'src="data:image/png;base64,{b64}"/><figcaption>{s.scene}: {label}</figcaption></figure>')
        imgs.append("".join(tags))
    missing = table(["scene", "reason"], list(rep.missing.items())) if rep.missing else "<p>none</p>"
    return write_html(out / "results.html", f"gtforge evaluation: {rep.model}", [
        (f"{rep.model} ({rep.provider}), {len(rep.scenes)} scenes, median {rep.time_ms_median or 0:.1f} ms/frame",
         table(head, fmt_rows)),
        ("Per scene, worst first", table(["scene", "EPE all", "EPE fruit", "depth MAE fruit (mm)", "time (ms)"], scene_rows)),
        ("Error maps (turbo colour map; black = no ground truth)", "".join(imgs)),
        ("Excluded scenes", missing)])


def _rows(reports: list[EvalReport]):
    for rep in reports:
        for r in TABLE_REGIONS:
            m = rep.pooled[r]
            yield [rep.model, r, m.epe_px, m.rmse_px, m.bad_0_5_pct, m.bad_1_0_pct, m.bad_2_0_pct, m.coverage_pct,
                   m.depth_mae_mm, rep.time_ms_median]


HEADERS = ["model", "region", "EPE (px)", "RMSE (px)", "Bad-0.5 (%)", "Bad-1.0 (%)", "Bad-2.0 (%)", "coverage (%)",
           "depth MAE (mm)", "time (ms)"]


def tables_markdown(reports: list[EvalReport]) -> str:
    def cell(v):
        return "-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))

    lines = ["| " + " | ".join(HEADERS) + " |", "|" + "---|" * len(HEADERS)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in _rows(reports)]
    return "\n".join(lines) + "\n\nPooled over pixels; invalid predictions excluded from the error figures and " \
                              "counted against coverage (docs/metrics.md).\n"


def write_tables(reports: list[EvalReport], out: Path, stem: str = "results") -> None:
    atomic_write_text(out / f"{stem}.md", tables_markdown(reports))
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(HEADERS)
    for row in _rows(reports):
        w.writerow(["" if v is None else v for v in row])
    atomic_write_text(out / f"{stem}.csv", buf.getvalue())
