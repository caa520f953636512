"""Fruit size, volume and grade in ``results.md``/``results.html``/``comparison.*``
(``gtforge.core.measure.fruit_size``)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from gtforge.infra.atomic import atomic_write_text
from gtforge.reports.html import Section, note, table

if TYPE_CHECKING:
    from gtforge.core.measure.fruit_size import FruitSizeResult, GradeAgreement
    from gtforge.records.evaluation import EvalResult

FRUIT_NOTE = ("Per fruit (connected fruit components of region.png): an ellipsoid resting on the table (one axis "
              "along the table's normal, lowest point on the table; the table fitted to the same source's background "
              "around the fruit) is fitted to the visible surface's 3-D points, Z = f*B/(d + doffs), from the ground "
              "truth and from the prediction on the same pixels. Diameter: equatorial, 2 sqrt(a b); volume: of the "
              "fitted ellipsoid. Diameter error in mm (prediction - GT), volume error in % of the GT volume; "
              "'GT vs truth': the ground truth against the generator's exact fruit (synthetic sessions only). "
              "docs/metrics.md, 'Fruit size, volume and grade'.")
POOLED_HEADERS = ["model", "fruit", "diameter MAE (mm)", "diameter max (mm)", "volume MAPE (%)", "volume max (%)",
                  "grade changed (%)", "GT vs truth: diameter MAE (mm)", "GT vs truth: volume MAPE (%)"]


def pooled_rows(reports: list["EvalResult"], labels: list[str] | None = None) -> list[list]:
    rows = []
    for k, rep in enumerate(reports):
        f = rep.fruit_size
        if f is None:
            continue
        d, v = f.diameter_model_vs_gt, f.volume_model_vs_gt
        dt, vt = f.diameter_gt_vs_truth, f.volume_gt_vs_truth
        rows.append([labels[k] if labels else rep.model, d.n if d else 0, d.mae_mm if d else None,
                     d.max_abs_mm if d else None, v.mape_pct if v else None, v.max_abs_pct if v else None,
                     f.grades_model_vs_gt.changed_pct if f.grades_model_vs_gt else None,
                     dt.mae_mm if dt else None, vt.mape_pct if vt else None])
    return rows


def fruit_markdown(reports: list["EvalResult"], labels: list[str] | None = None) -> str:
    """The pooled fruit-size table (empty string when no result has one)."""
    rows = pooled_rows(reports, labels)
    if not rows:
        return ""

    def cell(v):
        return "-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))

    lines = ["| " + " | ".join(POOLED_HEADERS) + " |", "|" + "---|" * len(POOLED_HEADERS)]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    for k, rep in enumerate(reports):
        g = rep.fruit_size.grades_model_vs_gt if rep.fruit_size else None
        if g is not None:
            lines += ["", f"{labels[k] if labels else rep.model}: grades by {g.bins.quantity} "
                      f"({', '.join(g.labels)}); rows GT grade, columns model grade", "",
                      confusion_markdown(g)]
    return "\n".join(lines) + "\n\n" + FRUIT_NOTE + "\n"


def confusion_markdown(g: "GradeAgreement") -> str:
    h = ["GT \\ model"] + g.labels
    lines = ["| " + " | ".join(h) + " |", "|" + "---|" * len(h)]
    lines += ["| " + " | ".join([lab] + [str(x) for x in row]) + " |" for lab, row in zip(g.labels, g.confusion)]
    return "\n".join(lines)


def _scatter(f: "FruitSizeResult") -> str:
    from matplotlib.figure import Figure

    gt = [r.gt.diameter_mm for r in f.fruit if r.gt.ok and r.pred is not None and r.pred.ok]
    pr = [r.pred.diameter_mm for r in f.fruit if r.gt.ok and r.pred is not None and r.pred.ok]
    tr = [(r.truth.diameter_mm, r.gt.diameter_mm) for r in f.fruit if r.truth is not None and r.gt.ok]
    fig = Figure(figsize=(4.6, 4.2))
    ax = fig.add_subplot(111)
    ax.scatter(gt, pr, s=14, label="model vs GT")
    if tr:
        ax.scatter([a for a, _ in tr], [b for _, b in tr], s=14, marker="x", label="GT vs generator truth")
    vals = gt + pr + [x for p in tr for x in p]
    if vals:
        lo, hi = min(vals), max(vals)
        pad = 0.05 * (hi - lo + 1)
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k--", lw=0.8, label="y = x")
    if f.grades_model_vs_gt is not None and f.grades_model_vs_gt.bins.quantity == "diameter_mm":
        for e in f.grades_model_vs_gt.bins.edges:
            ax.axvline(e, color="0.7", lw=0.6)
            ax.axhline(e, color="0.7", lw=0.6)
    ax.set_xlabel("reference diameter (mm): GT, or truth for x")
    ax.set_ylabel("measured diameter (mm): model, or GT for x")
    ax.legend(fontsize=7)
    ax.set_aspect("equal", adjustable="datalim")
    return svg_img_tag(fig, "predicted vs GT fruit diameter")


def svg_img_tag(fig, alt: str) -> str:
    """A figure inlined as SVG (a scatter plot: small and sharp; results.html keeps raster images to its JPEG map
    previews)."""
    import base64
    import html
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
    b64 = base64.b64encode(buf.getvalue()).decode("ascii")
    return f'<img style="max-width:460px" alt="{html.escape(alt)}" src="data:image/svg+xml;base64,{b64}"/>'


def fruit_section(rep: "EvalResult") -> Section | None:
    f = rep.fruit_size
    if f is None:
        return None
    body = table(POOLED_HEADERS[1:], [r[1:] for r in pooled_rows([rep])])
    body += note(FRUIT_NOTE + (f" Measuring the fruit added {f.time_ms_per_scene:.0f} ms per scene (median)."
                               if f.time_ms_per_scene is not None else ""))
    if f.n_not_measurable_gt or f.n_not_measurable_pred:
        body += note(f"not measurable: {f.n_not_measurable_gt} fruit from the GT, {f.n_not_measurable_pred} from the "
                     "prediction (reasons in the per-fruit table)")
    body += _scatter(f)
    for title, g in (("grade: model vs GT", f.grades_model_vs_gt),
                     ("grade: GT vs generator truth", f.grades_gt_vs_truth)):
        if g is not None:
            body += table([f"{title} ({g.bins.quantity}); rows: reference"] + g.labels,
                          [[lab] + row for lab, row in zip(g.labels, g.confusion)])
            body += note(f"{g.n} fruit graded; grade changed for {g.changed_pct:.1f} %" if g.changed_pct is not None
                         else "no fruit graded")

    def size(s):
        if s is None:
            return [None] * 3
        return [s.diameter_mm, s.height_mm, s.volume_ml] if s.ok else [f"not measurable: {s.reason}", None, None]

    rows = [[r.scene, r.fruit, *size(r.gt), *size(r.pred), r.diameter_error_mm, r.volume_error_pct,
             r.truth.diameter_mm if r.truth else None, r.gt_diameter_error_mm, r.grade_gt, r.grade_pred]
            for r in f.fruit]
    body += table(["scene", "fruit", "GT diameter (mm)", "GT height (mm)", "GT volume (mL)", "model diameter (mm)",
                   "model height (mm)", "model volume (mL)", "diameter error (mm)", "volume error (%)",
                   "truth diameter (mm)", "GT - truth diameter (mm)", "GT grade", "model grade"], rows)
    return Section("Fruit size, volume and grade", body)


def comparison_section(reports: list["EvalResult"], labels: list[str]) -> Section | None:
    rows = pooled_rows(reports, labels)
    if not rows:
        return None
    return Section("Fruit size, volume and grade", table(POOLED_HEADERS, rows) + note(FRUIT_NOTE))


FRUIT_CSV_HEADERS = ["scene", "fruit", "n_pixels", "gt_ok", "gt_diameter_mm", "gt_length_mm", "gt_width_mm",
                     "gt_height_mm", "gt_volume_ml", "pred_ok", "pred_diameter_mm", "pred_height_mm", "pred_volume_ml",
                     "diameter_error_mm", "volume_error_pct", "truth_diameter_mm", "truth_volume_ml",
                     "gt_diameter_error_mm", "gt_volume_error_pct", "grade_gt", "grade_pred", "grade_truth", "reason"]


def write_fruit_csv(rep: "EvalResult", path) -> None:
    """``fruit_size.csv``: one row per fruit (what results.json's ``fruit_size.fruit`` holds)."""
    import csv
    import io


    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(FRUIT_CSV_HEADERS)
    for r in rep.fruit_size.fruit:
        p, t = r.pred, r.truth
        reason = "; ".join(x for x in (r.gt.reason and f"GT: {r.gt.reason}", p and p.reason and f"model: {p.reason}")
                           if x)
        w.writerow(["" if v is None else v for v in [
            r.scene, r.fruit, r.n_pixels, r.gt.ok, r.gt.diameter_mm, r.gt.length_mm, r.gt.width_mm, r.gt.height_mm,
            r.gt.volume_ml, p.ok if p else None, p.diameter_mm if p else None, p.height_mm if p else None,
            p.volume_ml if p else None, r.diameter_error_mm, r.volume_error_pct, t.diameter_mm if t else None,
            t.volume_ml if t else None, r.gt_diameter_error_mm, r.gt_volume_error_pct, r.grade_gt, r.grade_pred,
            r.grade_truth, reason]])
    atomic_write_text(path, buf.getvalue())
