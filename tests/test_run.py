"""``gtforge run`` (gtforge.run): the chain in one command gives the same files as the six commands by hand; a rerun
redoes nothing; an edited scene redoes exactly what depends on it; Ctrl-C leaves a run that resumes; the certificate's
figures are the stage files' figures.

One session for the module: the shipped example (3 scenes) plus a fourth scene (a copy of scene 000) that
calibrate-scale and refine do not use (``calibration_scenes``), so that editing it must redo only its own build and
verification. The tests after the first share the run folder and follow each other."""
from __future__ import annotations

import importlib.util
import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile
import yaml
from typer.testing import CliRunner

from gtforge.cli.commands import app
from gtforge.errors import INTERRUPTED, InputError, Interrupted
from gtforge.records.calibration import CalibrationFile
from gtforge.records.certificate import Certificate
from gtforge.records.run import RunState
from gtforge.reports.certificate import field_value
from gtforge.run import RunOptions, run_session

from conftest import gtforge, one_line_error

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "calib_data_examples" / "session"
CAL_SCENES = ["000", "001", "002"]
OPTS = RunOptions(loo=False, calibration_scenes=CAL_SCENES, workers=1)

pytestmark = pytest.mark.slow


def _compare_module():
    spec = importlib.util.spec_from_file_location("compare_outputs", ROOT / "scripts" / "compare_outputs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    base = tmp_path_factory.mktemp("run")
    sess = base / "session"
    shutil.copytree(EXAMPLE, sess, ignore=shutil.ignore_patterns("truth"))
    shutil.copytree(sess / "scenes" / "000", sess / "scenes" / "003")
    said: list[str] = []
    res = run_session(sess, base / "run", OPTS, say=said.append)
    return {"base": base, "session": sess, "out": base / "run", "first": res, "said": said}


def _edit_depth(path: Path) -> None:
    d = tifffile.imread(path)
    ok = np.argwhere(np.isfinite(d))[len(np.argwhere(np.isfinite(d))) // 2]
    d[tuple(ok)] += 0.5
    tifffile.imwrite(path, d)


def test_run_equals_the_six_commands_by_hand(chain):
    res, out, sess = chain["first"], chain["out"], chain["session"]
    assert res.redone == ["calibrate", "validate", "calibrate-scale", "refine", "build-dataset", "verify"]
    hand = chain["base"] / "hand"
    scenes = ",".join(CAL_SCENES)
    for args in (["calibrate", sess, "-o", hand / "calibration.yaml", "--no-loo"],
                 ["validate", sess, "-c", hand / "calibration.yaml", "-o", hand / "validation"],
                 ["calibrate-scale", sess, "-c", hand / "calibration.yaml", "-o", hand / "scaled.yaml", "--scenes",
                  scenes],
                 ["refine", sess, "-c", hand / "scaled.yaml", "-o", hand / "refined.yaml", "--no-loo", "--scenes",
                  scenes],
                 ["build-dataset", sess, "-c", hand / "refined.yaml", "-o", hand / "dataset", "--workers", "1"],
                 ["verify", hand / "dataset", "--workers", "1"]):
        r = CliRunner().invoke(app, [str(a) for a in args])
        assert r.exit_code == 0, (args[0], r.output, r.exception)
    logging.getLogger().handlers.clear()  # CliRunner's captured stderr is closed now
    diffs = _compare_module().compare(out, hand)
    run_only = {f"only in {out}: {p}" for p in ("run_state.json", "certificate.json", "index.html")}
    # (verify by hand computed every scene's figures; the run took its build's: the same files)
    assert [d for d in diffs if d not in run_only] == []
    st = RunState.read(out / "run_state.json").stages
    assert st["verify"].detail["checked_by_build"] == st["verify"].detail["verified"] == ["000", "001", "002", "003"]
    assert "      4 of them with the figures build-dataset's checks gave (verify computes the same from their files)" \
        in chain["said"], chain["said"]
    assert res.exit_code == 0 and res.certificate.verdict in ("PASS", "WARN")


def test_certificate_figures_are_the_stage_files_figures(chain):
    out = chain["out"]
    cert = Certificate.read(out / "certificate.json")
    n = 0
    for sec in cert.sections:
        for f in sec.figures:
            assert (out / f.source_file).is_file(), f.source_file
            if f.source_field is None:
                assert f.derivation, f.name
                continue
            text = (out / f.source_file).read_text()
            doc = json.loads(text) if f.source_file.endswith(".json") else yaml.safe_load(text)
            assert f.value == field_value(doc, f.source_field), f.name
            n += 1
    assert n >= 20
    # and read by name from the stage reports, as a reader of both would
    val = json.loads((out / "validation" / "validation.json").read_text())
    scaled = yaml.safe_load((out / "scaled.yaml").read_text())["scale_calibration"]
    figs = {f.name: f for s in cert.sections for f in s.figures}
    assert figs["board XY reprojection error, mean"].value == val["xy_mean_px"]
    assert figs["corner detectors' noise floor (XY error their noise alone gives)"].value == val["xy_noise_floor_px"]
    assert figs["board Z geometric error, mean"].value == val["z_error_mean_pct"]
    notes = [n for s in cert.sections for n in s.notes]
    for name, t in scaled["terms"].items():
        est = figs[f"{name}: estimate (all terms free)"]
        assert est.value == t["estimate"] and est.sigma == t["sigma"] and est.status == t["status"]
        unit = {"mm": "mm", "deg": "deg"}.get(name.rsplit("_", 1)[-1], "")  # _frac: a fraction, no unit
        assert est.unit == unit and figs[f"{name}: applied"].unit == unit
        assert not t["reason"] or f"{name}: {t['reason']}" in notes  # the figures that decided it
    man = json.loads((out / "dataset" / "manifest.json").read_text())
    assert cert.scenes_built == sorted(man["scenes"]) and cert.splits == {k: len(v) for k, v in man["splits"].items()}
    assert any(k.endswith("scenes/003/DepthMap.tiff") for k in cert.inputs_blake3)
    page = (out / "index.html").read_text()
    assert f'<span class="{cert.verdict.lower()}">{cert.verdict}</span>' in page
    assert 'href="validation/validation.html"' in page and 'href="dataset/verification.html"' in page


def test_rerun_edit_and_interrupt(chain):
    sess, out = chain["session"], chain["out"]
    # nothing changed: nothing redone, and it says so
    said: list[str] = []
    stamps = {f: (out / f).stat().st_mtime_ns for f in ("calibration.yaml", "index.html", "certificate.json")}
    res = run_session(sess, out, OPTS, say=said.append)
    assert res.redone == [] and len(res.skipped) == 6
    assert any("nothing to redo" in s for s in said)
    assert {f: (out / f).stat().st_mtime_ns for f in stamps} == stamps  # the certificate too: not rewritten

    # a scene calibrate-scale and refine do not read: its build and its verification only
    _edit_depth(sess / "scenes" / "003" / "DepthMap.tiff")
    said = []
    res = run_session(sess, out, OPTS, say=said.append)
    assert res.redone == ["build-dataset", "verify"]
    st = RunState.read(out / "run_state.json").stages
    assert st["build-dataset"].detail["built"] == ["003"] and st["verify"].detail["verified"] == ["003"]
    assert st["verify"].detail["checked_by_build"] == ["003"]
    # the file as the user's folder names it (the state's "session/..." key was printed before)
    assert any(f"build-dataset: running ({(sess / 'scenes/003/DepthMap.tiff').as_posix()} changed)" in s
               for s in said), said
    assert any("built 003 (its inputs changed)" in s for s in said)
    assert any(f"verify: running ({(out / 'dataset/scenes/003/meta.json').as_posix()} changed)" in s for s in said)

    # a scene they read: calibrate-scale, refine and so every scene; Ctrl-C after calibrate-scale, then resume
    _edit_depth(sess / "scenes" / "001" / "DepthMap.tiff")

    def stop(name):
        if name == "calibrate-scale":
            raise KeyboardInterrupt

    said = []
    with pytest.raises(KeyboardInterrupt):
        run_session(sess, out, OPTS, say=said.append, after_stage=stop)
    assert any("interrupted during" in s and "run the same command again" in s for s in said)
    said = []
    res = run_session(sess, out, OPTS, say=said.append)
    assert res.redone == ["refine", "build-dataset", "verify"]
    # (calibrate-scale came to the same terms: scaled.yaml kept as it was, so the depth file is refine's one reason)
    assert any(f"refine: running ({(sess / 'scenes/001/DepthMap.tiff').as_posix()} changed)" in s for s in said), said
    st = RunState.read(out / "run_state.json").stages
    assert st["build-dataset"].detail["built"] == ["000", "001", "002", "003"]
    assert st["verify"].detail["verified"] == ["000", "001", "002", "003"]
    assert run_session(sess, out, OPTS, say=said.append).redone == []

    # the command's Ctrl-C (Interrupted): one message, the command's to print, with what the stage said was complete
    for exc, words in [(Interrupted(INTERRUPTED), "interrupted during or right after refine: every stage recorded"),
                       (Interrupted("interrupted: 2 scene(s) ...", detail="2 scene(s) built in this run and complete"),
                        "interrupted during or right after refine (2 scene(s) built in this run and complete): ")]:
        def stop_cli(name, exc=exc):
            if name == "refine":
                raise exc

        said = []
        with pytest.raises(Interrupted) as raised:
            run_session(sess, out, OPTS, say=said.append, after_stage=stop_cli)
        assert str(raised.value).startswith(words) and "run the same command again to resume" in str(raised.value)
        assert str(raised.value).count("interrupted") == 1 and not any("interrupted" in s for s in said)


def test_holdout_validates_on_captures_the_calibration_never_saw(chain, tmp_path):
    """run --holdout K (a newcomer's run-through, round 4: run's validation warned "optimistic; use --holdout K", which
    run had no way to take): validate alone is redone, on the last K board captures with a calibration made without
    them, and the certificate says so; the dataset's calibration is the run's. Without it again: validated as before,
    the hold-out's calibration gone."""
    out = tmp_path / "run"
    shutil.copytree(chain["out"], out, symlinks=True)
    said: list[str] = []
    res = run_session(chain["session"], out, OPTS.model_copy(update={"holdout": 1}), say=said.append)
    assert res.redone == ["validate"], said
    doc = json.loads((out / "validation" / "validation.json").read_text())
    assert [p["capture"] for p in doc["poses"]] == ["004"]
    assert doc["calibration_path"] == str((out / "validation" / "holdout_calibration.yaml").resolve())
    assert not any("optimistic" in w for w in doc["warnings"]), doc["warnings"]
    held = CalibrationFile.read(out / "validation" / "holdout_calibration.yaml")
    assert "004" not in held.captures_used and "004" in CalibrationFile.read(out / "calibration.yaml").captures_used
    cert = Certificate.read(out / "certificate.json")
    notes = [n for s in cert.sections if s.title == "Board accuracy (validate)" for n in s.notes]
    assert notes[0].startswith("validated on the last 1 board capture(s) (004) with a calibration made without them")
    assert any("on the last 1 board capture(s), calibrated without them" in s for s in said), said
    res = run_session(chain["session"], out, OPTS, say=said.append)
    assert res.redone == ["validate"] and not (out / "validation" / "holdout_calibration.yaml").exists()
    doc = json.loads((out / "validation" / "validation.json").read_text())
    assert any("optimistic" in w for w in doc["warnings"])
    # with -c: refused (the run would use the file given, not the one the hold-out validates)
    with pytest.raises(InputError) as e:
        run_session(chain["session"], tmp_path / "run2",
                    OPTS.model_copy(update={"holdout": 1, "calibration": str(out / "calibration.yaml")}))
    assert e.value.field == "--holdout" and not (tmp_path / "run2").exists()


def test_run_without_boards_needs_a_calibration(tmp_path):
    sess = tmp_path / "s"
    shutil.copytree(EXAMPLE, sess, ignore=shutil.ignore_patterns("truth", "board"))
    r = gtforge("run", sess, "-o", tmp_path / "out")
    assert r.returncode == 2 and one_line_error(r) and "-c FILE" in r.stderr


def test_run_refuses_its_session_as_output_and_leaves_no_folder_on_bad_input(tmp_path):
    sess = tmp_path / "s"
    shutil.copytree(EXAMPLE, sess, ignore=shutil.ignore_patterns("truth"))
    before = sorted(p.relative_to(sess) for p in sess.rglob("*"))
    r = gtforge("run", sess, "-o", sess)  # the session's root holds its capture folders
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "expected a path outside the session folder" in r.stderr and "got the session folder itself" in r.stderr
    assert sorted(p.relative_to(sess) for p in sess.rglob("*")) == before  # nothing written into it
    r = gtforge("run", sess, "--calibration-scenes", "999", "-o", tmp_path / "out")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "[--calibration-scenes]" in r.stderr and "got 999" in r.stderr  # the option the user gave, by its name
    assert not (tmp_path / "out").exists()  # a run stopped before writing anything leaves no empty folder
    r = gtforge("run", sess, "--workers", "0", "-o", tmp_path / "out")  # Click's own check: one line too
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert r.stderr.startswith("error: gtforge run: Invalid value for '--workers'") and "gtforge run --help" in r.stderr
    assert not (tmp_path / "out").exists()


def test_changed_dataset_files_are_built_again(chain):
    """A scene's labels or a view replaced since the run wrote them (the dataset's files are recorded by size and
    time, too many to hash back) make the next run build those scenes again, and only them: the files are the
    build's again, and the run after that redoes nothing (verify's own rewrites of the manifest and split lists are
    not changes)."""
    sess, out = chain["session"], chain["out"]
    ds = out / "dataset"
    pfm = ds / "scenes" / "002" / "disp0GT.pfm"
    kitti = ds / "kitti" / "training" / "disp_occ_0" / "000_10.png"
    before = {f: f.read_bytes() for f in (pfm, kitti)}
    shutil.copyfile(ds / "scenes" / "001" / "disp0GT.pfm", pfm)
    shutil.copyfile(ds / "kitti" / "training" / "disp_occ_0" / "001_10.png", kitti)
    said: list[str] = []
    res = run_session(sess, out, OPTS, say=said.append)
    assert res.redone == ["build-dataset", "verify"], said
    assert any("its output " in s and "changed since" in s for s in said), said
    assert "      built 000 (its dataset files changed since the last run)" in said
    assert "      built 002 (its dataset files changed since the last run)" in said
    assert not any(s.startswith("      built 001") or s.startswith("      built 003") for s in said), said
    assert {f: f.read_bytes() for f in before} == before
    said = []
    assert run_session(sess, out, OPTS, say=said.append).redone == [], said


def test_an_edit_of_fruit_ids_redoes_only_the_dataset(chain):
    """session.yaml's fruit_ids say which scenes show one fruit (the splits keep them together); no stage before
    build-dataset reads them, so editing them redoes the build (which rebuilds no scene, only their meta and the
    splits) and the verification of the scenes whose meta changed, and nothing else; another field of session.yaml
    still redoes everything."""
    sess, out = chain["session"], chain["out"]
    ds = out / "dataset"
    yml = sess / "session.yaml"
    original = yml.read_text()
    content = yaml.safe_load(original)
    content["fruit_ids"]["003"] = "fruit07"
    yml.write_text(yaml.safe_dump(content))
    try:
        said: list[str] = []
        res = run_session(sess, out, OPTS, say=said.append)
        assert res.redone == ["build-dataset", "verify"], said
        st = RunState.read(out / "run_state.json").stages
        assert st["build-dataset"].detail["built"] == [] and st["verify"].detail["verified"] == ["003"], said
        # 003 was regrouped, not rebuilt (the line said "checking 003 (rebuilt)": the docs run-through, session 18)
        assert "      checking 003 (meta.json changed; the other scenes as verified before)" in said, said
        assert json.loads((ds / "scenes" / "003" / "meta.json").read_text())["fruit_id"] == "fruit07"
        said = []
        assert run_session(sess, out, OPTS, say=said.append).redone == [], said
        content["zed_conf_reading"] = "neg-x"  # read by calibrate (and, through its file, by every stage after)
        yml.write_text(yaml.safe_dump(content))
        said = []

        def stop_when_calibrate_starts(line: str) -> None:  # (its decision is the point; running it costs time)
            said.append(line)
            if "calibrate: running" in line:
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            run_session(sess, out, OPTS, say=stop_when_calibrate_starts)
        assert any(f"calibrate: running ({yml.as_posix()} changed)" in s for s in said), said
    finally:
        yml.write_text(original)
    said = []
    res = run_session(sess, out, OPTS, say=said.append)
    assert res.redone == ["build-dataset", "verify"], said  # calibrate never ran on the edit: nothing else to redo
    assert json.loads((ds / "scenes" / "003" / "meta.json").read_text())["fruit_id"] is None


def test_deleted_outputs_are_written_again_and_a_removed_scene_leaves_the_dataset(chain):
    """Files a run wrote and the user deleted are noticed and written again (a scene's disparity, a KITTI view, the
    calibration report); calibrate run again to the same result leaves calibration.yaml as it was, so the stages
    after it are not redone; no hidden temporary file stays in the views; a scene taken out of the session leaves
    every folder of the dataset; the certificate is withdrawn while stages run and written again."""
    sess, out = chain["session"], chain["out"]
    ds = out / "dataset"
    cal_bytes = (out / "calibration.yaml").read_bytes()
    gone = [ds / "scenes" / "002" / "disp0GT.pfm", ds / "kitti" / "training" / "disp_occ_0" / "001_10.png",
            out / "calibration_report" / "calibration_report.json", ds / "filenames" / "train.txt",
            ds / "build_report.html", ds / "verification.html"]
    for f in gone:
        f.unlink()
    said: list[str] = []
    res = run_session(sess, out, OPTS, say=said.append)
    assert res.redone == ["calibrate", "build-dataset", "verify"], said
    assert all(f.is_file() for f in gone)
    assert (out / "calibration.yaml").read_bytes() == cal_bytes
    assert not [p for p in out.rglob(".*") if p.is_file()]
    assert (out / "index.html").is_file()

    # 003 leaves the session as 003_b (an id it is a prefix of) joins: 003_b's files stay
    moved = chain["base"] / "scene_003_moved_away"
    shutil.move(sess / "scenes" / "003", moved)
    shutil.copytree(sess / "scenes" / "000", sess / "scenes" / "003_b")
    try:
        said = []
        run_session(sess, out, OPTS, say=said.append)
        assert any("removed from the dataset (no longer in the session): 003" in s for s in said)
        left = [p for p in ds.rglob("*003*") if "003_b" not in p.as_posix()]
        assert left == [] and "scenes/003/" not in (ds / "filenames" / "train.txt").read_text() + \
            (ds / "filenames" / "val.txt").read_text() + (ds / "filenames" / "test.txt").read_text()
        assert (ds / "report" / "003_b_sigma.jpg").is_file() and (ds / "scenes" / "003_b" / "meta.json").is_file()
    finally:
        shutil.rmtree(sess / "scenes" / "003_b")
        shutil.move(moved, sess / "scenes" / "003")


def test_run_refuses_a_folder_of_the_users_own(tmp_path):
    """-o at an existing folder that is no earlier run's (no run_state.json): refused before anything is written; the
    user's calibration.yaml was replaced before."""
    sess = tmp_path / "s"
    shutil.copytree(EXAMPLE, sess, ignore=shutil.ignore_patterns("truth"))
    mine = tmp_path / "mine"
    (mine / "dataset").mkdir(parents=True)
    (mine / "calibration.yaml").write_text("mine\n")
    (mine / "dataset" / "readme.txt").write_text("keep\n")
    r = gtforge("run", sess, "-o", mine)
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert f"{mine} [--output]: expected a new or empty folder (or one with run_state.json), got a folder with 2 " \
           "entries" in r.stderr
    assert sorted(str(p.relative_to(mine)) for p in mine.rglob("*")) == ["calibration.yaml", "dataset",
                                                                       "dataset/readme.txt"]
    assert (mine / "calibration.yaml").read_text() == "mine\n"


def test_a_calibration_given_with_c_is_in_the_certificate(chain, tmp_path):
    """-c FILE: the certificate shows the given calibration's figures (read from that file), lists its BLAKE3 among
    the inputs, and takes its verdict: a FAIL calibration fails the run's certificate."""
    sess = chain["session"]
    doc = yaml.safe_load((chain["out"] / "calibration.yaml").read_text())
    doc["verdict"], doc["verdict_reasons"] = "FAIL", ["made to fail for the test"]
    given = tmp_path / "given.yaml"
    given.write_text(yaml.safe_dump(doc))
    said: list[str] = []
    out = tmp_path / "out"  # an earlier run's folder: its calibration no longer applies, and is not left beside
    shutil.copytree(chain["out"], out, symlinks=True)
    assert (out / "calibration.yaml").is_file() and (out / "calibration_report").is_dir()
    res = run_session(sess, out, RunOptions(loo=False, calibration_scenes=CAL_SCENES, workers=1,
                                            calibration=str(given)), say=said.append)
    assert not (out / "calibration.yaml").exists() and not (out / "calibration_report").exists()
    cert = res.certificate
    assert cert.verdict == "FAIL" and "calibrate: made to fail for the test" in cert.verdict_reasons
    sec = {s.title: s for s in cert.sections}["Calibration (given with -c)"]
    rms = {f.name: f for f in sec.figures}["board reprojection RMS"]
    assert rms.value == doc["rms_px"] and rms.source_file == str(given.resolve())
    assert str(given.resolve()) in cert.inputs_blake3


def test_a_refined_calibration_given_with_c_is_not_scale_corrected_again(chain, tmp_path):
    """-c a refined calibration: calibrate-scale does not apply (refine fitted its extrinsic through the uncorrected
    depth; the terms it would find now would correct a second time what refine took up), nor refine again, each saying
    which file to give; the run builds with the given calibration."""
    from gtforge.records.calibration import CalibrationFile, RefinementInfo

    # refine run on the board calibration itself (skipping calibrate-scale)
    board = CalibrationFile.read(chain["out"] / "calibration.yaml")
    info = RefinementInfo(refined_from="calibration.yaml", scenes_used=CAL_SCENES, change_rot_deg=0.01,
                          change_trans_mm=0.2)
    given = board.model_copy(update={"refinement": info}).write(tmp_path / "refined.yaml")
    said: list[str] = []
    res = run_session(chain["session"], tmp_path / "out", RunOptions(loo=False, calibration_scenes=CAL_SCENES,
                                                                     workers=1, calibration=str(given)),
                      say=said.append)
    st = RunState.read(tmp_path / "out" / "run_state.json").stages
    assert st["calibrate-scale"].status == "not applicable"
    assert st["calibrate-scale"].reason == ("refined.yaml is refined; calibrate-scale runs before refine: give -c the "
                                            "calibration refine started from (calibration.yaml) to correct the scale")
    assert st["refine"].status == "not applicable"
    assert st["refine"].reason == ("refined.yaml is already refined; give -c the calibration refine started from "
                                   "(calibration.yaml) to refine again")
    assert not (tmp_path / "out" / "scaled.yaml").exists() and not (tmp_path / "out" / "refined.yaml").exists()
    assert f"file:{given}" in st["build-dataset"].inputs  # the run went on with the calibration given
    assert res.exit_code == 0, said


def test_another_sessions_run_folder_is_refused(chain, tmp_path):
    """-o at the run folder of another session (a mistyped -o) is refused before anything is written: that run's
    calibration and dataset are the other session's (they were replaced, with one line of notice)."""
    from gtforge.errors import InputError

    import cv2

    other = tmp_path / "other"
    shutil.copytree(EXAMPLE, other, ignore=shutil.ignore_patterns("truth"))
    for png in sorted(other.glob("*/*/*.png")):  # other captures: the same names, other files
        cv2.imwrite(str(png), cv2.imread(str(png), cv2.IMREAD_UNCHANGED), [cv2.IMWRITE_PNG_COMPRESSION, 0])
    out = chain["out"]
    before = {p: p.read_bytes() for p in (out / "run_state.json", out / "calibration.yaml", out / "certificate.json")}
    with pytest.raises(InputError, match=r"\[--output\].*the run folder of another session .*, whose captures are "
                                         r"not this session's.*delete the folder first"):
        run_session(other, out, OPTS)
    assert {p: p.read_bytes() for p in before} == before


def test_a_session_moved_with_its_run_resumes_there(chain, tmp_path):
    """A lab moves a session and its run folder to another disk: the run resumes there, redoing nothing (it was
    refused: "delete the folder first", and every stage ran again); the certificate names the new place."""
    run_session(chain["session"], chain["out"], OPTS, say=lambda s: None)  # up to date with the earlier tests' edits
    sess, out = tmp_path / "moved" / "session", tmp_path / "moved" / "run"
    shutil.copytree(chain["session"], sess, symlinks=True)
    shutil.copytree(chain["out"], out, symlinks=True)
    said: list[str] = []
    res = run_session(sess, out, OPTS, say=said.append)
    assert res.redone == [], said
    assert f"{out}: the run of {chain['session'].resolve()}, whose captures are this session's (moved or copied): " \
           "resumed here" in said
    assert RunState.read(out / "run_state.json").session_dir == str(sess.resolve())
    assert Certificate.read(out / "certificate.json").session_dir == str(sess.resolve())
    assert all(not k.startswith(str(chain["session"].resolve())) for k in RunState.read(out / "run_state.json").hashes)


def test_a_calibration_in_the_run_folder_is_refused_before_any_stage(tmp_path):
    """-c OUT/aligned.yaml (an earlier run's file given back to it): align-depth, not applying to an aligned
    calibration, removed the file as a stale output, and validate stopped on a FileNotFoundError traceback; -c
    OUT/refined.yaml got as far as refine, which refused to replace its input. Now refused before anything, the file
    kept; a copy beside the run is the way (the hint names it)."""
    out = tmp_path / "out"
    out.mkdir()
    given = out / "aligned.yaml"
    shutil.copy(EXAMPLE / "zed_calibration.yaml", given)  # (refused by its place: never read)
    data = given.read_bytes()
    for spelled in (given, out / ".." / "out" / "refined.yaml"):
        with pytest.raises(InputError) as e:
            run_session(EXAMPLE, out, RunOptions(calibration=str(spelled)))
        assert str(e.value).startswith(f"{spelled} [--calibration]: expected a calibration outside the run's folder "
                                       f"(its stages write and remove calibration.yaml, aligned.yaml, scaled.yaml and "
                                       f"refined.yaml there), got a file in {out} (the run's own {spelled.name}) "
                                       f"(hint: copy it beside the run and give the copy: cp {spelled} "
                                       f"{tmp_path / ('given-' + spelled.name)})"), str(e.value)
    assert given.read_bytes() == data and sorted(p.name for p in out.iterdir()) == ["aligned.yaml"]


def test_a_calibration_of_another_rig_is_refused_before_any_stage(tmp_path):
    """-c with another rig's calibration: one line naming the camera's size, before any stage is announced (it was
    found at validate or calibrate-scale, after align-depth had been skipped as not applying because the other rig
    had one camera, on an Azure Kinect session)."""
    import numpy as np

    from gtforge.core.camera import Rig
    from gtforge.core.targets.models import BoardModel
    from gtforge.io.captures import open_session
    from gtforge.records.calibration import CalibrationFile

    s = open_session(EXAMPLE)
    other = s.mech.model_copy(update={"width_px": s.mech.width_px * 2, "height_px": s.mech.height_px * 2})
    given = tmp_path / "other_rig.yaml"
    CalibrationFile(rig=Rig(zed=s.zed, mech=other, T_zed_from_mech=np.eye(4)), board=BoardModel(), captures_used=[],
                    rms_px=0.1, max_px=0.2, sigma_rot_xyz_deg=[0.01] * 3, sigma_trans_xyz_mm=[0.1] * 3,
                    sigma_rot_deg=0.01, sigma_trans_mm=0.1, poses=[]).write(given)
    said = []
    with pytest.raises(InputError) as e:
        run_session(EXAMPLE, tmp_path / "out", RunOptions(calibration=str(given)), say=said.append)
    assert str(e.value).startswith(f"{given} [rig.mech]: expected 480x300 px (the session's camera), got 960x600 px "
                                   "(hint: "), str(e.value)
    assert said == [] and not (tmp_path / "out").exists()


def test_a_session_yaml_given_as_the_calibration_is_called_another_kind_of_file(tmp_path):
    """-c session.yaml: one short line saying the file is of another kind (it listed 26 problems field by field)."""
    r = gtforge("run", EXAMPLE, "-o", tmp_path / "out", "-c", EXAMPLE / "session.yaml")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "got a file of another kind (its fields: mech_intrinsics" in r.stderr and "missing: rig" in r.stderr
    assert "problems" not in r.stderr and len(r.stderr) < 600
    assert not (tmp_path / "out").exists()
    # the stereo camera's file (one field of its own: zed) for the calibration (a run-through: 11 problems listed)
    r = gtforge("validate", EXAMPLE, "-c", EXAMPLE / "zed_calibration.yaml", "-o", tmp_path / "v")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "got a file of another kind (its fields: zed; missing: rig" in r.stderr and "problems" not in r.stderr
    assert not (tmp_path / "v").exists()
    # a report with a field of the calibration's name but another content (validation.json's poses): 142 nested
    # problems made a 15 kB "line" (a run-through); it is another kind of file
    from gtforge.errors import InputError
    from gtforge.records.calibration import CalibrationFile

    report = tmp_path / "validation.json"
    report.write_text(json.dumps({"schema_version": 1, "poses": [{"capture": f"{k:03d}", "xy_rms_px": 0.5}
                                                                 for k in range(40)], "verdict": "PASS",
                                  "xy": {"mean_px": 0.5}, "z": {"mean_pct": 0.1}}))
    with pytest.raises(InputError) as err:
        CalibrationFile.read(report)
    assert "got a file of another kind (its fields: xy, z; missing: rig" in str(err.value)
    assert len(str(err.value)) < 600


def test_a_run_stopped_in_its_first_stage_names_no_state_file(tmp_path):
    """Ctrl-C during calibrate, before any stage was recorded: the run's new folder is removed on the way out, so the
    message does not send the user to OUT/run_state.json (it did); the next run starts from nothing."""
    def stop(msg):
        raise Interrupted(INTERRUPTED)

    out = tmp_path / "out"
    with pytest.raises(Interrupted) as raised:
        run_session(EXAMPLE, out, OPTS, say=lambda s: None, progress=stop)
    assert str(raised.value) == ("interrupted during or right after calibrate: no stage was recorded yet; run the same "
                                 "command again to start the run")
    assert not out.exists()
