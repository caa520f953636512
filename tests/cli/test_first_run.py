"""What a first-time user meets on the way through the chain (issue #36, items 3-6): the console shows each scale
term's estimate, a file with several problems names them all in one line, mistyped paths say so with a hint, the help
lists the commands in workflow order without breaking a line mid-sentence, a capture with a missing file is skipped
like a capture without the board."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from gtforge.cli.commands import app
from gtforge.errors import InputError
from gtforge.records.calibration import ScaleTerm

from conftest import gtforge, one_line_error

EXAMPLE = Path(__file__).resolve().parents[2] / "calib_data_examples" / "session"


def test_help_lists_the_workflow_in_order_and_whole_sentences():
    r = CliRunner().invoke(app, ["--help"], terminal_width=200)
    assert r.exit_code == 0
    order = ["run", "calibrate", "validate", "calibrate-scale", "refine", "build-dataset", "verify", "evaluate"]
    listed = [ln.split()[1] for ln in r.output.splitlines() if ln.startswith("\u2502 ") and ln[2] != " "]
    assert [c for c in listed if c in order] == order, r.output
    demo = " ".join(CliRunner().invoke(app, ["demo", "--help"]).output.split())
    assert "calibrate -> validate -> calibrate-scale -> refine -> build-dataset" in demo
    # each command's help paragraph is one line, which the help wraps to the terminal (never at the source's line ends)
    import typer.main

    group = typer.main.get_command(app)
    for name, cmd in group.commands.items():
        for para in (cmd.help or "").split("\n\n"):
            assert "\n" not in para, (name, para)


def test_scale_terms_show_their_estimate_whatever_their_status():
    from types import SimpleNamespace

    from gtforge.reports.calibration import scale_term_lines

    info = SimpleNamespace(terms={
        "zed_baseline_frac": ScaleTerm(value=0.0, estimate=-0.000376, sigma=0.000338, status="not significant",
                                       reason="within 2 sigma of 0: not applied"),
        "zed_right_yaw_deg": ScaleTerm(value=0.0399, estimate=0.0399, sigma=0.0006, status="applied"),
        "depth_offset_mm": ScaleTerm(value=0.0, estimate=None, sigma=None, status="not determined")})
    a, b, c = scale_term_lines(info)
    assert "estimate -0.000376 +- 0.000338 [not significant]" in a and "+0 " not in a
    assert "[applied], value applied +0.0399" in b and "not estimated [not determined]" in c
    # a term without an estimate says so once ("estimate not estimated" read as a contradiction)
    assert c.startswith("depth_offset_mm: not estimated [not determined]") and "estimate" not in c.replace(
        "not estimated", "")
    assert a.startswith("zed_baseline_frac: estimate -0.000376") and b.startswith("zed_right_yaw_deg: estimate +0.0399")


def test_a_file_with_several_problems_names_them_all(tmp_path):
    from gtforge.records.validation import ValidateParams
    from gtforge.core.schema import VersionedFile

    class F(VersionedFile):
        a: float
        b: int
        params: ValidateParams

    with pytest.raises(InputError) as e:
        F.from_dict({"b": "x", "params": {"xy_threshold_px": -1}}, tmp_path / "f.yaml")
    msg = str(e.value)
    assert "3 problems" in msg and "a: Field required (got missing)" in msg and "b: " in msg
    assert "params.xy_threshold_px" in msg and "{" not in msg.split("got", 1)[1].split("problems")[0]
    with pytest.raises(InputError) as e:
        F.from_dict({"b": 1, "params": {}}, tmp_path / "f.yaml")
    assert str(e.value).endswith("got missing (hint: add a)") and e.value.field == "a"


def test_mistyped_paths_say_so_with_a_hint(tmp_path):
    from gtforge.predictors import PredictionFolder
    from gtforge.verify import verify_dataset

    with pytest.raises(InputError, match="no such folder.*hint: check the path.*<id>.pfm"):
        PredictionFolder(tmp_path / "nowhere")
    with pytest.raises(InputError, match="no such folder"):
        verify_dataset(tmp_path / "datset")


@pytest.mark.slow
def test_a_capture_with_a_missing_file_is_skipped_with_a_hint(tmp_path):
    sess = tmp_path / "s"
    shutil.copytree(EXAMPLE, sess, ignore=shutil.ignore_patterns("truth", "scenes"))
    (sess / "board" / "003" / "DepthMap.tiff").unlink()
    r = gtforge("calibrate", sess, "-o", tmp_path / "c.yaml", "--no-loo", "--no-self-rectify")
    assert r.returncode == 0, r.stderr
    assert "capture 003 skipped" in r.stderr and "--captures" in r.stderr and r.stderr.count("\n") <= 3
    poses = {p["capture"]: p for p in yaml.safe_load((tmp_path / "c.yaml").read_text())["poses"]}
    assert poses["003"]["status"] == "skipped" and "DepthMap.tiff" in poses["003"]["reason"]
    # a file that is there but wrong still stops calibrate (one line, exit 2), the hint naming --captures
    (sess / "board" / "001" / "2DImage.png").write_bytes(b"not a png")
    r = gtforge("calibrate", sess, "-o", tmp_path / "c2.yaml", "--no-loo", "--no-self-rectify")
    assert r.returncode == 2 and "2DImage.png" in r.stderr and "leave capture 001 out with --captures" in r.stderr
    # the same with the self-rectification on (the default), which reads every capture first: the same hint
    r = gtforge("calibrate", sess, "-o", tmp_path / "c2.yaml", "--no-loo")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "2DImage.png" in r.stderr and "leave capture 001 out with --captures" in r.stderr
