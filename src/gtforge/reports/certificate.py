"""The dataset certificate of ``gtforge run``: ``certificate.json`` (``records.certificate.Certificate``) and its page
``index.html``, one page saying how good the labels are and why to believe it. Every figure is read from a stage's own
file (``source_file`` + ``source_field``, a dotted path into it) and links to that stage's report; nothing is typed
in by hand."""
from __future__ import annotations

import datetime as _dt
import html
import json
import math
from pathlib import Path
from statistics import median
from typing import Any


import gtforge
from gtforge.core.schema import load_yaml
from gtforge.infra.digest import blake3_hex
from gtforge.records.certificate import CertFigure, Certificate, CertSection, CertStage
from gtforge.records.run import STAGES, RunState
from gtforge.reports.html import CSS, fmt_value

CALIBRATION_REPORT = "calibration_report/calibration_report.html"


def load(path: Path) -> Any:
    """A stage's JSON or YAML file as plain data (None when it is not there)."""
    if not path.is_file():
        return None
    text = path.read_text()
    return json.loads(text) if path.suffix == ".json" else load_yaml(text)


def field_value(doc: Any, dotted: str) -> Any:
    """``doc``'s value at a dotted path (list items by index): what a figure's ``source_field`` names."""
    for part in dotted.split("."):
        doc = doc[int(part)] if isinstance(doc, list) else doc[part]
    return doc


class _Figures:
    def __init__(self, out: Path, file: str, link: str | None):
        self.file, self.link = file, link
        self.doc = load(out / file)
        self.items: list[CertFigure] = []

    def add(self, name: str, dotted: str, unit: str = "", sigma: str | None = None, status: Any = None) -> None:
        try:
            v = field_value(self.doc, dotted)
        except (KeyError, IndexError, TypeError):
            return
        if v is None:  # not measured (e.g. no held-out scenes): left out
            return
        s = None
        if sigma is not None:
            try:
                s = field_value(self.doc, sigma)
            except (KeyError, IndexError, TypeError):
                s = None
        self.items.append(CertFigure(name=name, value=v, unit=unit, sigma=s, status=status, source_file=self.file,
                                     source_field=dotted, link=self.link))


def _pf(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def _sigma_coverage(ds: Path, man: dict, session_root: Path | None) -> list[CertFigure]:
    """On a synthetic session (``truth/`` beside the captures): the share of GT pixels within 1 and 2 sigma of the exact
    disparity, over every scene's pixels the depth camera saw (an honest sigma: about 68 % and 95 %)."""
    import numpy as np

    from gtforge.io.formats import read_pfm

    truth = Path(session_root) / "truth" if session_root is not None else None
    if truth is None or not truth.is_dir():
        return []
    k1 = k2 = n = 0
    for sid, meta in man["scenes"].items():
        t = truth / f"scene_{sid}.npz"
        sig_path = ds / "scenes" / sid / "disp0GT_sigma.pfm"
        if not t.is_file() or not sig_path.is_file():
            continue
        with np.load(t) as z:
            exact, seen = z["zed_disparity_px"], z["seen_by_mech"]
        if meta.get("crop_xywh"):
            x0, y0, w, h = meta["crop_xywh"]
            exact, seen = exact[y0:y0 + h, x0:x0 + w], seen[y0:y0 + h, x0:x0 + w]
        gt, sig = read_pfm(ds / "scenes" / sid / "disp0GT.pfm"), read_pfm(sig_path)
        ok = seen & np.isfinite(gt) & np.isfinite(sig) & np.isfinite(exact) & (sig > 0)
        r = np.abs(gt[ok] - exact[ok]) / sig[ok]
        k1, k2, n = k1 + int((r <= 1).sum()), k2 + int((r <= 2).sum()), n + int(ok.sum())
    if not n:
        return []
    src = "session truth/scene_*.npz (zed_disparity_px) vs dataset/scenes/*/disp0GT.pfm and disp0GT_sigma.pfm"
    return [CertFigure(name=f"GT within {k} sigma of the exact disparity (synthetic truth)",
                       value=round(100.0 * c / n, 2), unit="%", source_file="dataset/manifest.json",
                       derivation=f"{src}, over the {n} pixels the depth camera saw, every scene",
                       link="dataset/build_report.html") for k, c in ((1, k1), (2, k2))]


def build_certificate(out: Path, state: RunState, session_root: Path | None = None) -> Certificate:
    """The certificate of the run in ``out`` (its ``state``): the files of the stages that ran this time or before,
    never those a stage that no longer applies left behind."""
    st = state.stages
    sections: list[CertSection] = []

    def ran(stage: str) -> bool:  # a stage that did not apply may have left an earlier run's file: not read
        return stage in st and st[stage].status == "done"

    # board accuracy and the ZED's rows (validate)
    val = _Figures(out, "validation/validation.json", "validation/validation.html")
    if not ran("validate"):
        val.doc = None
    if val.doc is not None:
        d = val.doc
        val.add("board XY reprojection error, mean", "xy_mean_px", "px", status=_pf(d["pass_xy"]))
        val.add("XY threshold", "thresholds.xy_px", "px")
        val.add("corner detectors' noise floor (XY error their noise alone gives)", "xy_noise_floor_px", "px")
        val.add("XY error with the detectors' noise removed (board models)", "xy_model_mean_px", "px")
        val.add("board Z geometric error, mean", "z_error_mean_pct", "%", status=_pf(d["pass_z"]))
        val.add("Z threshold", "thresholds.z_pct", "%")
        val.add("board flatness RMS", "flatness_rms_mm", "mm")
        val.add("published reference XY", "reference.xy_px", "px")
        val.add("published reference Z", "reference.z_pct", "%")
        held = st["validate"].options.get("holdout")
        what = ([f"validated on the last {held} board capture(s) ({', '.join(p['capture'] for p in d['poses'])}) with "
                 "a calibration made without them (validation/holdout_calibration.yaml; run --holdout): the dataset's "
                 "calibration uses every capture"] if held else [])
        sections.append(CertSection(title="Board accuracy (validate)", verdict=_pf(d["passed"]), figures=val.items,
                                    notes=what + list(d.get("warnings") or []), link=val.link))
        if d.get("gauges"):
            sections.append(_gauges(out, "validation/validation.json", "gauges."))
    elif ran("validate") and (out / "validation" / "gauges.json").is_file():
        sections.append(_gauges(out, "validation/gauges.json", ""))

    rows = []
    given = st["calibrate"].detail.get("given") if "calibrate" in st and not ran("calibrate") else None
    cal = _Figures(out, given, None) if given else _Figures(out, "calibration.yaml", CALIBRATION_REPORT)
    if not ran("calibrate") and not given:
        cal.doc = None
    if cal.doc is not None:
        sr = cal.doc.get("zed_self_rectification")
        if sr:
            cal.add("self-rectification", "zed_self_rectification.status")
            cal.add("median |vertical disparity| of left-right matches before", "zed_self_rectification."
                    "median_abs_before_px", "px")
            cal.add("... after self-rectification", "zed_self_rectification.median_abs_after_px", "px")
        rows += cal.items
    if val.doc is not None and val.doc.get("rectification"):
        v2 = _Figures(out, "validation/validation.json", "validation/validation.html")
        v2.add("board corners' |vertical disparity|, mean (detected)", "rectification.overall.mean_abs_px", "px")
        v2.add("... of the fitted corners (detector noise removed)", "rectification.overall.fit_mean_abs_px", "px")
        v2.add("warning threshold", "rectification.threshold_px", "px")
        rows += v2.items
    if rows:
        sections.append(CertSection(title="ZED rows after self-rectification", figures=rows,
                                    link=cal.link if cal.doc is not None else None))

    if cal.doc is not None:
        c = _Figures(out, cal.file, cal.link)
        c.add("board reprojection RMS", "rms_px", "px")
        c.items.append(CertFigure(name="poses used", value=len(cal.doc["captures_used"]),
                                  source_file=cal.file, derivation="number of captures_used", link=c.link))
        c.add("extrinsic 1-sigma rotation", "sigma_rot_deg", "deg")
        c.add("extrinsic 1-sigma translation", "sigma_trans_mm", "mm")
        c.add("leave-one-pose-out transfer error, mean", "loo_transfer_mean_px", "px")
        sections.append(CertSection(title="Calibration (given with -c)" if given else "Calibration (calibrate)",
                                    verdict=cal.doc.get("verdict"),
                                    figures=c.items, notes=list(cal.doc.get("verdict_reasons") or []), link=c.link))

    al = _Figures(out, "aligned.yaml", "aligned_report.html")
    if ran("align-depth") and al.doc is not None and al.doc.get("depth_alignment"):
        r = al.doc["depth_alignment"]["result"]
        key = "depth_alignment.result."
        al.add("decision", key + "decision")
        for i, axis in enumerate(("omega_x", "omega_y", "omega_z")):
            al.add(f"{axis} correction", f"{key}omega_deg.{i}", "deg", status=r["status"][i],
                   sigma=f"{key}sigma_omega_deg.{i}" if math.isfinite(r["sigma_omega_deg"][i]) else None)
        for when in ("before", "after"):
            for i, axis in enumerate(("x", "y")):
                al.add(f"edge offset (colour - depth) {axis}, {when}", f"{key}offset_{when}_px.{i}", "px")
        al.add("edges", key + "n_edges")
        sections.append(CertSection(title="Depth camera pose (align-depth)", figures=al.items, link=al.link,
                                    notes=[n for n in (r.get("reason"), "edges: " + " and ".join(
                                        r.get("edge_kinds", [])), *r.get("warnings", [])) if n]))

    sc = _Figures(out, "scaled.yaml", "scaled.yaml")
    if ran("calibrate-scale") and sc.doc is not None and sc.doc.get("scale_calibration"):
        reasons = []
        for name, t in sc.doc["scale_calibration"]["terms"].items():
            unit = name.rsplit("_", 1)[-1] if name.rsplit("_", 1)[-1] in ("mm", "deg", "px") else ""
            sc.add(f"{name}: estimate (all terms free)", f"scale_calibration.terms.{name}.estimate", unit,
                   sigma=f"scale_calibration.terms.{name}.sigma", status=t["status"])
            sc.add(f"{name}: applied", f"scale_calibration.terms.{name}.value", unit)
            if t.get("reason"):
                reasons.append(f"{name}: {t['reason']}")
        sc.add("baseline in the ZED file", "scale_calibration.baseline_file_mm", "mm")
        sc.add("baseline used", "rig.zed.baseline_mm", "mm")
        sections.append(CertSection(title="Scale terms (calibrate-scale)", figures=sc.items, link=sc.link,
                                    notes=["a term is applied when its estimate with the other terms held is beyond 2 "
                                           "sigma of 0 (the figures that decided it follow); the others stay 0 and "
                                           "their sigma goes into the per-pixel sigma", *reasons]))

    rf = _Figures(out, "refined.yaml", "refined.yaml")
    if ran("refine") and rf.doc is not None and rf.doc.get("refinement"):
        rf.add("extrinsic moved by (rotation)", "refinement.change_rot_deg", "deg")
        rf.add("extrinsic moved by (translation)", "refinement.change_trans_mm", "mm")
        rf.add("held-out scenes' |texture shift| before", "refinement.heldout_shift_before_mean_px", "px")
        rf.add("... after", "refinement.heldout_shift_after_mean_px", "px")
        sections.append(CertSection(title="Refinement from the scenes (refine)", figures=rf.items, link=rf.link,
                                    notes=[f"scene {k} left out: {v}" for k, v in
                                           rf.doc["refinement"].get("scenes_excluded", {}).items()]))

    cert_scenes: dict[str, Any] = {}
    man = load(out / "dataset" / "manifest.json") if ran("build-dataset") else None
    layouts: list[str] = []
    splits: dict[str, int] = {}
    if man is not None:
        sig = [m["sigma"] for m in man["scenes"].values() if m.get("sigma")]
        figs = []
        for region in ("all", "fruit"):
            vals = [s[region] for s in sig if s.get(region) and s[region].get("median_px") is not None]
            for key, label, unit in (("median_px", "median", "px"), ("p95_px", "95th percentile", "px"),
                                     ("over_0_1_px_pct", "share of pixels over 0.1 px", "%")):
                xs = [v[key] for v in vals if v.get(key) is not None]
                if xs:
                    figs.append(CertFigure(name=f"GT sigma, {region}: {label} (median over scenes)",
                                           value=float(median(xs)), unit=unit, source_file="dataset/manifest.json",
                                           derivation=f"median over scenes of scenes.*.sigma.{region}.{key}",
                                           link="dataset/build_report.html"))
        n_inc = sum(bool(m.get("sigma_extrinsic_included")) for m in man["scenes"].values())
        figs.append(CertFigure(name="scenes whose sigma includes the calibration's covariance", value=n_inc,
                               source_file="dataset/manifest.json",
                               derivation="count of scenes.*.sigma_extrinsic_included",
                               link="dataset/build_report.html"))
        figs += _sigma_coverage(out / "dataset", man, session_root)
        sections.append(CertSection(title="Per-pixel ground-truth sigma (disp0GT_sigma.pfm)", figures=figs,
                                    link="dataset/build_report.html",
                                    notes=["each GT pixel's 1-sigma from the depth noise, the calibration's covariance "
                                           "and the scale terms' sigmas; on synthetic truth about two thirds of the "
                                           "pixels lie within 1 sigma of the truth and 95 % within 2 "
                                           "(docs/pipeline.md), pooled over calibrations drawn from their "
                                           "covariance. One session is one draw of the calibration's error, shared "
                                           "by every pixel: a session's share within 1 sigma (given on synthetic "
                                           "sessions) is well above 68 % when its calibration came out better than "
                                           "its sigma, below when worse"]))
        cert_scenes = {"built": sorted(man["scenes"]), "flagged": man.get("flagged", {}),
                       "quarantined": man.get("quarantined", []), "failures": man.get("failures", {})}
        ds = out / "dataset"
        for rel, what in (("scenes", "Middlebury-style scenes/<id>/ (im0, im1, disp0GT.pfm, calib.txt)"),
                          ("kitti", "KITTI 2015 layout"), ("eth3d", "ETH3D two-view layout"),
                          ("views", "per-split views (Middlebury, ETH3D, KITTI) for training repositories"),
                          ("filenames", "split lists (filenames/*.txt)")):
            if (ds / rel).is_dir():
                layouts.append(f"dataset/{rel}: {what}")
        splits = {k: len(v) for k, v in man.get("splits", {}).items()}
        vfig = []
        for s, r in sorted(cert_scenes["flagged"].items()):
            vfig.append(CertFigure(name=f"scene {s} flagged", value="; ".join(r), source_file="dataset/manifest.json",
                                   source_field=f"flagged.{s}", link="dataset/verification.html"))
        if man.get("compensated"):  # issue 37 (only then: the other certificates stay as they were)
            vfig.append(CertFigure(name="scenes whose fruit moved between the exposures, ground truth rebuilt with the "
                                   f"fruit moved (motion compensated: {', '.join(man['compensated'])})",
                                   value=len(man["compensated"]), source_file="dataset/manifest.json",
                                   derivation="number of compensated", link="dataset/verification.html"))
        vrec = st.get("verify")
        sections.append(CertSection(
            title="Scenes: built, flagged, quarantined", verdict=vrec.verdict if vrec else None, figures=[
                CertFigure(name="scenes built", value=len(man["scenes"]), source_file="dataset/manifest.json",
                           derivation="number of scenes", link="dataset/build_report.html"),
                CertFigure(name="scenes flagged by verification", value=len(cert_scenes["flagged"]),
                           source_file="dataset/manifest.json", derivation="number of flagged",
                           link="dataset/verification.html"),
                CertFigure(name="scenes quarantined (left out of the split lists)",
                           value=len(cert_scenes["quarantined"]), source_file="dataset/manifest.json",
                           derivation="number of quarantined", link="dataset/verification.html"),
                CertFigure(name="scenes failed", value=len(cert_scenes["failures"]),
                           source_file="dataset/manifest.json",
                           derivation="number of failures", link="dataset/build_report.html"), *vfig],
            notes=[f"scene {s} failed: {r}" for s, r in cert_scenes["failures"].items()]
            + _split_notes(splits), link="dataset/verification.html"))

    stages = [CertStage(stage=n, status=st[n].status, verdict=st[n].verdict,
                        reasons=st[n].verdict_reasons or ([st[n].reason] if st[n].reason else []))
              for n in STAGES if n in st]
    fails = [f"{s.stage}: {r}" for s in stages if s.verdict == "FAIL" for r in (s.reasons or ["FAIL"])]
    warns = [f"{s.stage}: {r}" for s in stages if s.verdict == "WARN" for r in (s.reasons or ["WARN"])]
    verdict = "FAIL" if fails else ("WARN" if warns else "PASS")
    # the session's files by their path in it, a file from elsewhere (a calibration given with -c) by its own
    inputs = {k.removeprefix("session/").removeprefix("file:"): v for rec in st.values()
              for k, v in rec.inputs.items() if k.startswith(("session/", "file:"))}
    inputs = dict(sorted(inputs.items()))
    digest = blake3_hex("".join(f"{k} {v}\n" for k, v in inputs.items()).encode())
    return Certificate(gtforge_version=gtforge.__version__,
                       created=_dt.datetime.now().astimezone().isoformat(timespec="seconds"),
                       session_dir=state.session_dir, verdict=verdict, verdict_reasons=fails + warns, stages=stages,
                       sections=sections, scenes_built=cert_scenes.get("built", []),
                       scenes_flagged=cert_scenes.get("flagged", {}),
                       scenes_quarantined=cert_scenes.get("quarantined", []),
                       scenes_failed=cert_scenes.get("failures", {}), layouts=layouts, splits=splits,
                       inputs_blake3=inputs, inputs_digest=digest)


def _split_notes(splits: dict[str, int]) -> list[str]:
    empty = [k for k, n in splits.items() if n == 0]
    line = "splits: " + ", ".join(f"{k} {n}" for k, n in splits.items())
    if empty:
        line += (f" ({', '.join(empty)} empty: normal for a small session, scenes of one fruit stay in one split; "
                 "add scenes of more fruit for a held-out split)")
    return [line]


def _gauges(out: Path, file: str, prefix: str) -> CertSection:
    g = _Figures(out, file, "validation/gauges.html")
    doc = field_value(g.doc, prefix[:-1]) if prefix else g.doc
    for k, r in enumerate(doc["gauges"]):
        p = f"{prefix}gauges.{k}.gt."
        for j, _ in enumerate(r["gt"].get("spheres") or []):
            g.add(f"gauge {r['capture']} sphere {j}: size error PS", f"{p}spheres.{j}.size_error_mm", "mm",
                  status=r["status"])
            g.add(f"gauge {r['capture']} sphere {j}: form PF", f"{p}spheres.{j}.form_range_mm", "mm")
        g.add(f"gauge {r['capture']}: sphere spacing error SD", f"{p}spacing_error_mm", "mm", status=r["status"])
        g.add(f"gauge {r['capture']}: flatness F", f"{p}flatness_mm", "mm", status=r["status"])
    return CertSection(title="Gauge objects (VDI/VDE 2634-2, from the GT)", verdict=doc["status"], figures=g.items,
                       link=g.link)


def _cls(v: str | None) -> str:
    return {"PASS": "pass", "WARN": "warn", "FAIL": "fail"}.get(v or "", "")


def _a(link: str | None, text: str) -> str:
    return f'<a href="{html.escape(link)}">{html.escape(text)}</a>' if link else html.escape(text)


def write_certificate_html(cert: Certificate, path: Path) -> Path:
    from gtforge.infra.atomic import atomic_write_text

    e = html.escape
    banner = {"PASS": "#e6f4e6", "WARN": "#fdf0dc", "FAIL": "#fbe4e4"}[cert.verdict]
    p = [f"<!doctype html><html><head><meta charset='utf-8'><title>Dataset certificate: {cert.verdict}</title>"
         f"<style>{CSS}\ndiv.banner{{font-size:2em;font-weight:bold;padding:.4em .7em;border-radius:6px;"
         f"background:{banner}}}</style></head><body><h1>Dataset certificate</h1>",
         f'<div class="banner"><span class="{_cls(cert.verdict)}">{cert.verdict}</span></div>']
    if cert.verdict_reasons:
        p.append("<ul>" + "".join(f"<li>{e(r)}</li>" for r in cert.verdict_reasons) + "</ul>")
    p.append(f'<table class="header"><tr><th>session</th><td>{e(cert.session_dir)}</td></tr>'
             f"<tr><th>gtforge version</th><td>{e(cert.gtforge_version)}</td></tr>"
             f"<tr><th>written</th><td>{e(cert.created)}</td></tr>"
             f"<tr><th>inputs (BLAKE3 of every input's hash)</th><td>{e(cert.inputs_digest)}</td></tr></table>")
    p.append("<h2>Stages</h2><table><thead><tr><th>stage</th><th>status</th><th>verdict</th><th>why</th></tr></thead>"
             "<tbody>" + "".join(f"<tr><td>{e(s.stage)}</td><td>{e(s.status)}</td><td>"
                                 f"<span class=\"{_cls(s.verdict)}\">{e(s.verdict or '')}</span></td>"
                                 f"<td style='text-align:left'>{e('; '.join(s.reasons))}"
                                 f"</td></tr>" for s in cert.stages) + "</tbody></table>")
    for sec in cert.sections:
        cls = f' class="{_cls(sec.verdict)}"' if sec.verdict else ""
        head = sec.title + (f" {sec.verdict}" if sec.verdict else "")
        p.append(f"<h2{cls}>{e(head)}</h2>")
        if sec.link:
            p.append(f'<p class="note">report: {_a(sec.link, sec.link)}</p>')
        rows = []
        for f in sec.figures:
            val = e(fmt_value(f.value)) + (f" &plusmn; {e(fmt_value(f.sigma))}" if f.sigma is not None else "")
            src = f.source_file + (f": {f.source_field}" if f.source_field else f" ({f.derivation})")
            rows.append(f"<tr><td>{e(f.name)}</td><td>{val}</td><td>{e(f.unit)}</td>"
                        f"<td><span class=\"{_cls(f.status)}\">{e(f.status or '')}</span></td>"
                        f"<td style='text-align:left'>{_a(f.link, src)}</td></tr>")
        if rows:
            p.append("<table><thead><tr><th>figure</th><th>value</th><th>unit</th><th>status</th><th>source</th></tr>"
                     "</thead><tbody>" + "".join(rows) + "</tbody></table>")
        for n in sec.notes:
            p.append(f'<p class="note">{e(n)}</p>')
    if cert.layouts:
        p.append("<h2>Training-ready layouts written</h2><ul>" + "".join(f"<li>{e(x)}</li>" for x in cert.layouts)
                 + "</ul>")
    p.append(f"<h2>Inputs ({len(cert.inputs_blake3)} files, BLAKE3)</h2><details><summary>list</summary><table>"
             + "".join(f"<tr><td>{e(k)}</td><td style='font-family:monospace'>{e(v)}</td></tr>"
                       for k, v in cert.inputs_blake3.items()) + "</table></details>")
    p.append("</body></html>")
    return atomic_write_text(path, "\n".join(p))


def write_certificate(out: Path, state: RunState, session_root: Path | None = None) -> Certificate:
    """``out/certificate.json`` and ``out/index.html`` for the run recorded in ``state`` (``session_root``: where a
    synthetic session's ``truth/`` is looked for)."""
    cert = build_certificate(Path(out), state, session_root)
    cert.write(Path(out) / "certificate.json")
    write_certificate_html(cert, Path(out) / "index.html")
    return cert
