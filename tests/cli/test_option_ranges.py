"""Every numeric option refuses a value out of its range (NaN and infinity included) before any work: one line naming
the option the user typed, exit code 2, nothing written (docs/conventions.md "Errors"). In-process and cheap: each
command line here is refused before it reads its inputs, which need not exist."""
from __future__ import annotations

import pytest
from typer.testing import CliRunner

from gtforge.cli.commands import app
from gtforge.errors import InputError


def refused_option(args, tmp_path) -> str:
    """The option ``gtforge ARGS`` names when it refuses them: an ``InputError``'s field, or the option Click's own
    range check names (exit code 2 both); fails when the command does anything else."""
    r = CliRunner().invoke(app, [str(a) for a in args])
    assert not list(tmp_path.iterdir()), f"wrote {list(tmp_path.iterdir())}"
    if isinstance(r.exception, InputError):
        return r.exception.field
    assert r.exit_code == 2 and isinstance(r.exception, SystemExit), (r.exit_code, r.exception, r.output)
    return r.output


BOARD_CASES = [("--square-mm", "inf"), ("--square-mm", "nan"), ("--square-mm", "1e300"), ("--marker-mm", "inf"),
               ("--circle-mm", "inf"), ("--circle-mm", "nan")]


@pytest.mark.parametrize("option,value", BOARD_CASES)
@pytest.mark.parametrize("command", ["calibrate", "import", "synth"])
def test_board_sizes_must_be_finite(command, option, value, tmp_path):
    """An infinite square reached calibrate's solver (a traceback) and was written by import into session.yaml as
    null; 1e300 mm overflowed the solver."""
    where = {"calibrate": [tmp_path / "session", "-o", tmp_path / "c.yaml"],
             "import": [tmp_path / "rec.bag", "-o", tmp_path / "s"], "synth": [tmp_path / "s"]}[command]
    assert refused_option([command, *where, option, value], tmp_path) == option


@pytest.mark.parametrize("value", ["inf", "nan", "2000"])
def test_validate_square_mm_must_be_finite(value, tmp_path):
    assert refused_option(["validate", tmp_path / "session", "-o", tmp_path / "va", "--square-mm", value],
                          tmp_path) == "--square-mm"


@pytest.mark.parametrize("option", ["--max-shift-px", "--max-disparity-bias-px"])
@pytest.mark.parametrize("value", [float("inf"), float("nan"), -1.0])
def test_verify_thresholds_must_be_finite(option, value):
    """verify --max-shift-px inf was accepted: the workers got it as JSON null (a pydantic traceback). (verify builds
    its thresholds with ``_options`` from the manifest's; the library call keeps the test free of a dataset.)"""
    from gtforge.cli.commands import _options
    from gtforge.records.verification import VerifyParams

    with pytest.raises(InputError) as e:
        _options(VerifyParams, **{option[2:].replace("-", "_"): value})
    assert e.value.field == option


@pytest.mark.parametrize("option", ["--xy-threshold-px", "--z-threshold-pct"])
@pytest.mark.parametrize("value", ["inf", "nan", "-1", "0"])
def test_validate_thresholds_must_be_finite(option, value, tmp_path):
    """validate --xy-threshold-px inf was accepted: it validated, then failed in the report's plot (a traceback)."""
    assert refused_option(["validate", tmp_path / "session", "-o", tmp_path / "va", option, value],
                          tmp_path) == option


@pytest.mark.parametrize("option,value", [("--max-skew-ms", "inf"), ("--still-threshold", "inf"),
                                          ("--still-threshold", "256"), ("--max-skew-ms", "nan"),
                                          ("--still-threshold", "-1")])
def test_import_pairing_thresholds_must_be_finite(option, value, tmp_path):
    """import --max-skew-ms inf was accepted (written into import.json as Infinity, which is no JSON); a still
    threshold above 255 grey levels takes every frame for still."""
    assert refused_option(["import", tmp_path / "rec.bag", "-o", tmp_path / "s", option, value], tmp_path) == option


@pytest.mark.parametrize("value", ["inf", "1e9", "100", "nan"])
def test_align_depth_search_range_is_at_most_the_widest_search(value, tmp_path):
    """align-depth --search-px 1e9 allocated 30 GB (a traceback), inf raised one, 100 ran for minutes: the first range
    is at most the range the search widens itself to (48 px)."""
    assert refused_option(["align-depth", tmp_path / "session", "-c", tmp_path / "c.yaml", "-o", tmp_path / "a.yaml",
                           "--search-px", value], tmp_path) == "--search-px"


@pytest.mark.parametrize("option", ["--max-disp", "--max-gt-sigma"])
@pytest.mark.parametrize("value", ["inf", "nan", "-1", "0"])
def test_evaluate_limits_must_be_finite(option, value, tmp_path):
    """evaluate --max-disp inf was accepted and written into results.json as Infinity (no JSON); the limits are now
    checked before the dataset is read."""
    assert refused_option(["evaluate", tmp_path / "ds", "--sgbm", "-o", tmp_path / "ev", option, value],
                          tmp_path) == option


@pytest.mark.parametrize("option,value", [("--depth-noise-mm", "inf"), ("--baseline-error-pct", "nan"),
                                          ("--baseline-error-pct", "-100"), ("--baseline-error-pct", "1000"),
                                          ("--right-yaw-deg", "nan"), ("--depth-scale-error-pct", "nan"),
                                          ("--depth-scale-error-pct", "-100"), ("--depth-offset-mm", "nan"),
                                          ("--depth-offset-mm", "inf"), ("--moved-fruit-mm", "inf")])
def test_synth_rig_errors_must_be_finite(option, value, tmp_path):
    """synth rendered a session with each of these (a NaN rig, infinite noise, a baseline of zero) and exit code 0;
    --baseline-error-pct 1000 raised a traceback after writing part of the session."""
    assert refused_option(["synth", tmp_path / "s", option, value], tmp_path) == option


@pytest.mark.parametrize("args,option", [(["synth", "--seed", "-1"], "'--seed'"),
                                         (["demo", "--seed", "-1"], "'--seed'"),
                                         (["demo", "--scenes", "0"], "'--scenes'"),
                                         (["demo", "--scenes", "-1"], "'--scenes'")])
def test_synth_and_demo_counts_and_seeds(args, option, tmp_path):
    """--seed -1 raised numpy's traceback; demo --scenes 0 (or -1) calibrated, then failed at calibrate-scale on a
    session without scenes/."""
    assert option in refused_option([args[0], tmp_path / "o", *args[1:]], tmp_path)
