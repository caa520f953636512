"""The certificate's verdict (reports.certificate): FAIL names the stage and check that failed, WARN what warned, and a
stage that no longer applies does not lend its old files to the page."""
from __future__ import annotations

import json

from gtforge.records.run import RunState, StageRecord
from gtforge.reports.certificate import build_certificate, write_certificate
from gtforge.run import RunResult


def _state(**verdicts) -> RunState:
    st = RunState(gtforge_version="x", session_dir="/s")
    for name, (verdict, reasons) in verdicts.items():
        st.stages[name] = StageRecord(stage=name, status="done", verdict=verdict, verdict_reasons=reasons)
    return st


def test_verdict_names_what_failed_and_what_warned(tmp_path):
    st = _state(calibrate=("WARN", ["only 4 poses"]), validate=("FAIL", ["board XY reprojection 0.4 px over 0.3"]))
    st.stages["refine"] = StageRecord(stage="refine", status="not applicable", reason="needs 3 scenes, has 2")
    cert = write_certificate(tmp_path, st)
    assert cert.verdict == "FAIL"
    assert cert.verdict_reasons == ["validate: board XY reprojection 0.4 px over 0.3", "calibrate: only 4 poses"]
    assert RunResult(st, cert, [], []).exit_code == 1
    assert [s.reasons for s in cert.stages if s.stage == "refine"] == [["needs 3 scenes, has 2"]]
    page = (tmp_path / "index.html").read_text()
    assert '<span class="fail">FAIL</span>' in page and "needs 3 scenes, has 2" in page
    assert json.loads((tmp_path / "certificate.json").read_text())["verdict"] == "FAIL"
    st = _state(calibrate=("WARN", ["only 4 poses"]), validate=("PASS", []))
    cert = build_certificate(tmp_path, st)
    assert cert.verdict == "WARN" and RunResult(st, cert, [], []).exit_code == 0


def test_files_of_a_stage_that_did_not_run_are_not_read(tmp_path):
    (tmp_path / "scaled.yaml").write_text("scale_calibration: {terms: {b: {estimate: 1.0, sigma: 0.1, value: 1.0, "
                                          "status: applied}}, baseline_file_mm: 63.0}\nrig: {zed: {baseline_mm: 63}}\n")
    st = _state()
    st.stages["calibrate-scale"] = StageRecord(stage="calibrate-scale", status="not applicable", reason="no scenes")
    assert not [s for s in build_certificate(tmp_path, st).sections if "Scale" in s.title]
    st.stages["calibrate-scale"] = StageRecord(stage="calibrate-scale", status="done", verdict="PASS")
    sec = [s for s in build_certificate(tmp_path, st).sections if "Scale" in s.title][0]
    assert sec.figures[0].value == 1.0 and sec.figures[0].sigma == 0.1 and sec.figures[0].status == "applied"


def test_a_figure_value_is_escaped_in_the_page(tmp_path):
    """A text value (a flagged scene's reason: "texture shift < ...") was written into index.html unescaped (a
    run-through): each value is escaped as every other text there."""
    from gtforge.records.certificate import Certificate, CertFigure, CertSection
    from gtforge.reports.certificate import write_certificate_html

    cert = build_certificate(tmp_path, _state(calibrate=("PASS", [])))
    cert.sections.append(CertSection(title="Scenes", figures=[CertFigure(name="scene 002", value="shift <b>0.4</b> px",
                                                                         source_file="dataset/manifest.json")]))
    page = write_certificate_html(Certificate.model_validate(cert.model_dump()), tmp_path / "index.html").read_text()
    assert "<td>shift &lt;b&gt;0.4&lt;/b&gt; px</td>" in page and "<b>0.4</b>" not in page
