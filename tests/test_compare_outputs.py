"""scripts/compare_outputs.py, the check that a restructuring kept every output: it must see a changed byte of a map
or a changed value of a record, and must not see what only records when a run happened."""
from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

from gtforge.io.formats import write_pfm

ROOT = Path(__file__).resolve().parents[1]


def _compare():
    spec = importlib.util.spec_from_file_location("compare_outputs", ROOT / "scripts" / "compare_outputs.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("compare_outputs", mod)
    spec.loader.exec_module(mod)
    return mod.compare


def _run(root: Path, disp: np.ndarray, epe: float, time_s: float, date: str) -> Path:
    (root / "scenes" / "000").mkdir(parents=True)
    write_pfm(root / "scenes" / "000" / "disp0GT.pfm", disp)
    (root / "meta.json").write_text(json.dumps({"scene": "000", "epe_px": epe, "time_s": time_s,
                                                "session_dir": str(root / "session")}))
    (root / "results.md").write_text(f"written {date}\n\n| model | EPE (px) | time (ms/frame) |\n|---|---|---|\n"
                                     f"| SGBM | {epe} | {time_s * 1000:.1f} |\n")
    return root


def test_only_times_dates_and_folders_may_differ(tmp_path):
    compare = _compare()
    disp = np.linspace(10, 20, 48, dtype=np.float32).reshape(6, 8)
    a = _run(tmp_path / "a", disp, 0.125, 1.5, "2026-12-02 14:00")
    b = _run(tmp_path / "b", disp, 0.125, 9.25, "2026-12-03 09:30")
    assert compare(a, b) == []
    changed = disp.copy()
    changed[3, 4] = np.nextafter(changed[3, 4], np.float32(np.inf))  # one ulp of one pixel
    c = _run(tmp_path / "c", changed, 0.125, 1.5, "2026-12-02 14:00")
    assert compare(a, c) == ["scenes/000/disp0GT.pfm: bytes differ"]
    d = _run(tmp_path / "d", disp, 0.126, 1.5, "2026-12-02 14:00")
    diffs = compare(a, d)
    assert [x.split(":")[0] for x in diffs] == ["meta.json", "results.md"]


def test_folders_given_relative_are_replaced_in_both_forms(tmp_path, monkeypatch):
    """A run folder given relative to the working directory appears in its files as an absolute path too (stages
    record resolved paths); both forms must read as the same folder, whatever order a set iterates them in."""
    compare = _compare()
    disp = np.linspace(10, 20, 48, dtype=np.float32).reshape(6, 8)
    _run(tmp_path / "a", disp, 0.125, 1.5, "2026-12-02 14:00")
    _run(tmp_path / "bb", disp, 0.125, 1.5, "2026-12-02 14:00")
    monkeypatch.chdir(tmp_path)
    assert compare(Path("a"), Path("bb")) == []
    text = sys.modules["compare_outputs"]._text(Path("a") / "meta.json", Path("a"))
    assert "RUN/session" in text and str(tmp_path) not in text


def test_a_short_folder_name_is_replaced_only_where_it_is_a_path(tmp_path, monkeypatch):
    """Run folders 'r2' and 'rI4' holding the same report: 'r2' was replaced everywhere in the text, inside embedded
    base64 images and words too, so the same page read as different ('text differs at line 20')."""
    compare = _compare()
    disp = np.linspace(10, 20, 48, dtype=np.float32).reshape(6, 8)
    for name in ("r2", "rI4"):
        root = _run(tmp_path / name, disp, 0.125, 1.5, "2026-12-02 14:00")
        (root / "report.html").write_text(f'<p>see {root}/meta.json and {name}/meta.json</p>'
                                          '<img src="data:image/png;base64,iVBORw0Kr2AAAEr2/r2+r2=="/><p>er2 r2d2</p>'
                                          f'<p>dataset {root}.</p>')
    monkeypatch.chdir(tmp_path)
    assert compare(Path("r2"), Path("rI4")) == []
    text = sys.modules["compare_outputs"]._text(Path("r2") / "report.html", Path("r2"))
    # a folder that ends a sentence is a path too (verification.html's summary: "dataset /abs/out.")
    assert text == ('<p>see RUN/meta.json and RUN/meta.json</p>'
                    '<img src="data:image/png;base64,iVBORw0Kr2AAAEr2/r2+r2=="/><p>er2 r2d2</p>'
                    '<p>dataset RUN.</p>')
    (Path("r2") / "notes.txt").write_text("r2.png r2.")
    assert sys.modules["compare_outputs"]._text(Path("r2") / "notes.txt", Path("r2")) == "r2.png RUN."


def test_a_runs_state_file_differs_only_in_its_own_outputs_digests(tmp_path):
    """Two identical `gtforge run`s: run_state.json holds the digests of the run's own files, which differ where a
    file records a time (a calibration's solve time); those files are compared themselves, so their digests are not.
    An input's digest (the session's) still counts."""
    compare = _compare()

    def state(root: Path, out_digest: str, session_digest: str) -> Path:
        root.mkdir()
        rec = {"stage": "refine", "time_s": 1.0, "outputs": {"out/refined.yaml": out_digest},
               "inputs": {"session/session.yaml": session_digest, "out/calibration.yaml": out_digest}}
        (root / "run_state.json").write_text(json.dumps({
            "schema_version": 1, "stages": {"refine": rec},
            "hashes": {str(root / "refined.yaml"): {"blake3": out_digest, "size_bytes": 10},
                       "/data/session/session.yaml": {"blake3": session_digest, "size_bytes": 5}}}))
        return root

    a = state(tmp_path / "a", "aa11", "5e55")
    assert compare(a, state(tmp_path / "b", "bb22", "5e55")) == []
    assert compare(a, state(tmp_path / "c", "aa11", "5e56")) == ["run_state.json: data differ beyond time fields"]
