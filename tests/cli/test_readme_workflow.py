"""The README's step-by-step workflow, exactly as written there, on the shipped example (calib_data_examples): every
line runs and exits 0 (issue #36: the example could not run it, refine needing 3 scenes)."""
from __future__ import annotations

import logging
import re
import shlex
from pathlib import Path

import pytest

from typer.testing import CliRunner

from gtforge.cli.commands import app

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "calib_data_examples" / "session"


def readme_workflow() -> list[list[str]]:
    """The command lines of the README's block after "The same chain step by step", comments dropped."""
    text = (ROOT / "README.md").read_text()
    block = re.search(r"The same chain step by step.*?```bash\n(.*?)```", text, re.S).group(1)
    return [shlex.split(line.split("#", 1)[0]) for line in block.splitlines() if line.startswith("gtforge ")]


def test_the_readme_workflow_is_the_run_chain():
    assert [c[1] for c in readme_workflow()] == ["calibrate", "validate", "calibrate-scale", "refine", "build-dataset",
                                                 "verify"]


@pytest.mark.slow
def test_the_readme_workflow_runs_on_the_shipped_example(tmp_path, monkeypatch):
    """In this process (the same command-line app, without six interpreter start-ups); SESSION is the example."""
    monkeypatch.chdir(tmp_path)
    for cmd in readme_workflow():
        args = [str(EXAMPLE) if a == "SESSION" else a for a in cmd[1:]]
        r = CliRunner().invoke(app, args)
        assert r.exit_code == 0, (cmd, r.output[-2000:], r.exception)
    logging.getLogger().handlers.clear()  # CliRunner's captured stderr is closed now
    assert (tmp_path / "refined.yaml").is_file() and (tmp_path / "dataset" / "verification.json").is_file()
