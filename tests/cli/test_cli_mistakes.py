"""Ordinary mistakes found by a newcomer's run-through (round 2), each through the real command: exit 2 and one
line naming the option or file, nothing written, or the right repair."""
import json
import shutil
import time

import pytest
import yaml
from conftest import gtforge, one_line_error, tree_digest

from gtforge.build_dataset import build_dataset
from gtforge.records.dataset import BuildParams
from gtforge.reports.evaluation import row_labels


@pytest.mark.slow
def test_synth_and_demo_never_write_into_an_existing_folder(tmp_path, session_dir):
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    before = tree_digest(sess)
    r = gtforge("synth", sess, "--boards", "1", "--scenes", "0", "--scale", "0.1")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "expected a new or empty folder" in r.stderr and "synth writes a whole new session" in r.stderr
    r = gtforge("demo", sess)
    assert r.returncode == 2 and one_line_error(r) and "session/truth/rig_truth.yaml" in r.stderr, r.stderr
    assert tree_digest(sess) == before
    r = gtforge("synth", tmp_path / "new", "--scale", "0")
    assert r.returncode == 2 and "--scale" in r.stderr and not (tmp_path / "new").exists()


def _foreign_session(session_dir, tmp_path, field="width_px", change=2):
    """The same captures with the texture camera's ``field`` changed by ``change`` (default: another image size): the
    test calibration is not this session's."""
    sess = tmp_path / "other"
    shutil.copytree(session_dir, sess)
    p = sess / "mech_intrinsics.yaml"
    d = yaml.safe_load(p.read_text())
    d["camera"][field] += change
    p.write_text(yaml.safe_dump(d))
    return sess


@pytest.mark.slow
def test_a_calibration_of_another_session_is_one_line(session_dir, true_calibration, dataset, tmp_path):
    other = _foreign_session(session_dir, tmp_path)
    for args in (("refine", other, "-c", true_calibration, "-o", tmp_path / "refined.yaml"),
                 ("build-dataset", other, "-c", true_calibration, "-o", tmp_path / "ds"),
                 ("verify", dataset[0], "--session", other)):
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r), (args[0], r.stderr)
        assert "[rig.mech]" in r.stderr and "(the session's camera)" in r.stderr, r.stderr
    assert not (tmp_path / "refined.yaml").exists() and not (tmp_path / "ds").exists()


@pytest.mark.slow
def test_a_calibration_made_with_other_intrinsics_is_one_line(session_dir, true_calibration, tmp_path):
    """The session's texture intrinsics edited after calibrating (fx 8 px more, the same image size): the extrinsic
    was solved with the old ones. validate and refine ran on without a word; now one line names the camera."""
    other = _foreign_session(session_dir, tmp_path, "fx_px", 8.0)
    for args in (("validate", other, "-c", true_calibration, "-o", tmp_path / "va"),
                 ("refine", other, "-c", true_calibration, "-o", tmp_path / "refined.yaml")):
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r), (args[0], r.stderr)
        assert "[rig.mech.fx_px]: expected " in r.stderr, r.stderr
        assert "(the session's mech_intrinsics.yaml), got " in r.stderr
        assert "the session's intrinsics changed since this calibration" in r.stderr
    assert not (tmp_path / "va").exists() and not (tmp_path / "refined.yaml").exists()


@pytest.mark.slow
def test_option_values_are_checked(session_dir, true_calibration, dataset, tmp_path):
    before = tree_digest(dataset[0])
    cases = [
        (("verify", dataset[0], "--max-shift-px", "-1"), "--max-shift-px"),
        (("evaluate", dataset[0], "--sgbm", "--max-disp", "-5", "-o", tmp_path / "ev"), "--max-disp"),
        (("validate", session_dir, "-c", true_calibration, "--xy-threshold-px", "-1", "-o", tmp_path / "va"),
         "--xy-threshold-px"),
        (("build-dataset", session_dir, "-c", true_calibration, "-o", tmp_path / "ds", "--crop", "5000x300"),
         "--crop"),
        (("calibrate", session_dir, "--captures", "000,999", "-o", tmp_path / "c.yaml"), "999"),
        (("refine", session_dir, "-c", true_calibration, "--scenes", "000,7", "-o", tmp_path / "r.yaml"),
         "--scenes]: expected capture names of scenes/"),
        (("calibrate", session_dir, "--square-mm", "-2", "-o", tmp_path / "c.yaml"),
         "--square-mm: expected a value greater than 0, got -2.0"),
        (("calibrate", session_dir, "--board", "hexagon", "-o", tmp_path / "c.yaml"), "--board: expected a value"),
        (("calibrate", session_dir, "--self-rectify-scenes", "-1", "-o", tmp_path / "c.yaml"),
         "'--self-rectify-scenes'"),  # Click's own range check
    ]
    for args, needle in cases:
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r), (args, r.stderr)
        assert needle in r.stderr, (needle, r.stderr)
    r = gtforge("build-dataset", session_dir, "-c", true_calibration, "-o", tmp_path / "ds", "--workers", "0")
    assert r.returncode == 2 and one_line_error(r) and "'--workers'" in r.stderr, r.stderr  # Click's own range check
    assert not [p for p in tmp_path.iterdir() if p.name != "c.yaml"] and not (tmp_path / "c.yaml").exists()
    assert tree_digest(dataset[0]) == before


@pytest.mark.slow
def test_outputs_must_be_folders_of_their_own(session_dir, true_calibration, dataset, tmp_path):
    before = tree_digest(dataset[0])
    a_file = tmp_path / "notes.txt"
    a_file.write_text("mine")
    for args, needle in (
            (("build-dataset", session_dir, "-c", true_calibration, "-o", a_file), "expected a folder"),
            (("evaluate", dataset[0], "--sgbm", "-o", a_file), "expected a folder"),
            (("evaluate", dataset[0], "--sgbm", "-o", dataset[0] / "scenes" / "000"), "inside the dataset's scenes/"),
            (("evaluate", dataset[0], "--sgbm", "-o", dataset[0]), "the dataset folder itself"),
            (("evaluate", session_dir, "--sgbm", "-o", tmp_path / "ev"), "no manifest.json")):
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r), (args, r.stderr)
        assert needle in r.stderr, (needle, r.stderr)
    assert a_file.read_text() == "mine" and tree_digest(dataset[0]) == before
    assert not (tmp_path / "ev").exists()


@pytest.mark.slow
def test_a_bad_scheduler_address_fails_fast_and_writes_nothing(session_dir, true_calibration, tmp_path):
    pytest.importorskip("distributed")
    for address, needle in (("foo", "the port is required"), ("tcp://no-such-host.invalid:8786", "not a known host")):
        t = time.time()
        r = gtforge("build-dataset", session_dir, "-c", true_calibration, "-o", tmp_path / "ds", "--scheduler", address)
        assert r.returncode == 2 and one_line_error(r), r.stderr
        assert needle in r.stderr and time.time() - t < 30
    assert not (tmp_path / "ds").exists()


@pytest.mark.slow
def test_calibration_option_takes_the_calibrate_output_folder(session_dir, true_calibration, tmp_path):
    folder = tmp_path / "calib"
    folder.mkdir()
    shutil.copy(true_calibration, folder / "calibration.yaml")
    r = gtforge("validate", session_dir, "-c", folder, "-o", tmp_path / "va")
    assert r.returncode == 0 and "XY reprojection" in r.stdout, r.stderr
    r = gtforge("build-dataset", session_dir, "-c", tmp_path, "-o", tmp_path / "ds2")
    assert r.returncode == 2 and one_line_error(r) and "got a folder" in r.stderr, r.stderr


@pytest.mark.slow
def test_resume_rebuilds_a_scene_with_a_deleted_file(session_dir, true_calibration, tmp_path):
    out = tmp_path / "ds"
    params = BuildParams(verification=False)
    s = build_dataset(session_dir, true_calibration, out, params, scenes=["000", "001"], workers=1)
    assert s.built == ["000", "001"]
    from gtforge.dataset.layout import scene_files

    assert sorted(p.name for p in (out / "scenes" / "000").iterdir()) == sorted(scene_files(params))
    (out / "scenes" / "001" / "disp0GT.pfm").unlink()
    s = build_dataset(session_dir, true_calibration, out, params, scenes=["000", "001"], workers=1)
    assert s.built == ["001"] and s.skipped_unchanged == ["000"]
    assert (out / "scenes" / "001" / "disp0GT.pfm").is_file()


@pytest.mark.slow
def test_verify_exits_1_when_a_scene_cannot_be_verified(session_dir, true_calibration, tmp_path):
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    out = tmp_path / "ds"
    assert build_dataset(sess, true_calibration, out, BuildParams(verification=False), scenes=["000"],
                         workers=1).built == ["000"]
    (out / "scenes" / "000" / "region.png").unlink()
    r = gtforge("verify", out)
    assert r.returncode == 1 and "1 not verifiable" in r.stdout, r.stdout + r.stderr
    assert json.loads((out / "verification.json").read_text())["scenes"]["000"]["status"] == "not verifiable"


def test_compare_tells_same_named_results_apart(tmp_path):
    class R:
        def __init__(self, model):
            self.model = model

    labels = row_labels([R("SGBM"), R("SGBM"), R("net")], [tmp_path / "run1" / "evaluation" / "results.json",
                                                            tmp_path / "run2" / "evaluation" / "results.json",
                                                            tmp_path / "results.json"])
    assert labels == ["SGBM [run1/evaluation]", "SGBM [run2/evaluation]", "net"]
    same = tmp_path / "evaluation" / "results.json"
    assert row_labels([R("SGBM"), R("SGBM")], [same, same]) == ["SGBM [evaluation #1]", "SGBM [evaluation #2]"]


def test_synth_refuses_a_depth_pose_error_it_cannot_render(tmp_path):
    """A malformed rotation, or one for a unit without a separate depth camera: one line naming the option, nothing
    written."""
    r = gtforge("synth", tmp_path / "a", "--scale", "0.1", "--depth-pose-error-deg", "0.1,0.2")
    assert r.returncode == 2 and one_line_error(r) and "--depth-pose-error-deg" in r.stderr, r.stderr
    assert "'0.1,0.2'" in r.stderr
    r = gtforge("synth", tmp_path / "a", "--scale", "0.1", "--depth-pose-error-deg", "0.1,0.2,0")
    assert r.returncode == 2 and one_line_error(r) and "add --separate-depth-camera" in r.stderr, r.stderr
    assert not (tmp_path / "a").exists()


@pytest.mark.slow
def test_output_places_are_checked_before_any_work(session_dir, true_calibration, tmp_path):
    """A calibrate whose report folder's name was taken by a file, or a validate given an existing file as its
    folder, crashed with FileExistsError after all the work (calibrate had written its calibration already); -c with
    --holdout was silently unused. Each is one line now, before anything is computed or written."""
    (tmp_path / "x_report").touch()
    cases = [(("calibrate", session_dir, "-o", tmp_path / "x.yaml", "--no-loo"),
              "x_report [--report-dir]: expected a folder (new or existing), got a file"),
             (("calibrate", session_dir, "-o", tmp_path / "x_report" / "c.yaml"),
              "c.yaml [--output]: expected a path whose parents are folders, got"),
             (("validate", session_dir, "-c", true_calibration, "-o", tmp_path / "x_report"),
              "x_report [--output]: expected a folder (new or existing), got a file"),
             (("validate", session_dir, "-c", true_calibration, "--holdout", "2", "-o", tmp_path / "v"),
              "[--calibration]: expected no calibration file with --holdout K")]
    for args, message in cases:
        t0 = time.perf_counter()
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r) and message in r.stderr, (args[0], r.stderr)
        assert time.perf_counter() - t0 < 60  # (refused at once: calibrate's work alone takes longer)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x_report"]


def test_an_unwritable_place_is_named_before_work_and_in_one_line_after(tmp_path, monkeypatch, capsys):
    """A read-only output folder: refused before the stage's work by the output checks, and, where the system says
    so only at the write (a full disk), one line naming the file (exit 2), not an OSError traceback."""
    import errno
    import os

    import gtforge.cli as cli
    import gtforge.cli.commands as commands
    from gtforge.errors import InputError
    from gtforge.io.outputs import require_output_file, require_output_folder

    (tmp_path / "gone").symlink_to(tmp_path / "nothing")  # a link to nothing: mkdir would fail with EEXIST
    with pytest.raises(InputError, match=r"gone/ds \[--output\]: expected a path whose folders exist or can be made, "
                                         r"got .*gone is a symbolic link to nothing"):
        require_output_folder(tmp_path / "gone" / "ds", "--output")

    class ReadOnly:
        f_flag = os.ST_RDONLY

    monkeypatch.setattr(os, "access", lambda path, mode: False)
    monkeypatch.setattr(os, "statvfs", lambda path: ReadOnly())
    with pytest.raises(InputError, match=rf"new \[--output\]: expected a place this user can write, got "
                                         rf"{tmp_path} is on a read-only file system"):
        require_output_folder(tmp_path / "new", "--output")
    with pytest.raises(InputError, match=r"c\.yaml \[-o\]: expected a place this user can write"):
        require_output_file(tmp_path / "c.yaml", "-o")
    monkeypatch.undo()

    def full_disk(**kwargs):  # (the name an atomic write's temporary file has: the user's file is named)
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "out" / ".a.k2j_8x.tmp.png"))

    monkeypatch.setattr(commands, "app", full_disk)
    monkeypatch.setattr(cli.sys, "argv", ["gtforge", "evaluate"])
    monkeypatch.setattr(cli.signal, "signal", lambda *a: None)  # (main's Ctrl-C handler and exit hook: not pytest's)
    monkeypatch.setattr(cli.atexit, "register", lambda *a: None)
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    assert exit_info.value.code == 2
    said = capsys.readouterr()
    lines = [line for line in (said.out + said.err).splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: {tmp_path / 'out' / 'a.png'}: could not be written or "
                                                   "read (No space left on device) (hint: check the path"), lines

    monkeypatch.setenv("GTFORGE_DEBUG", "1")  # asked for: the traceback
    with pytest.raises(OSError, match="No space left"):
        cli.main()
    monkeypatch.delenv("GTFORGE_DEBUG")
    for code, text in ((errno.EBADF, "Bad file descriptor"), (errno.EEXIST, "File exists")):
        def bug(code=code, text=text, **kwargs):
            raise OSError(code, text, "/x/y")

        monkeypatch.setattr(commands, "app", bug)
        with pytest.raises(OSError, match=text):  # not explained by a user's input (checked before): its traceback
            cli.main()


def test_a_folder_that_is_no_session_is_named_as_such(dataset, tmp_path):
    """A folder without session.yaml, camera files, board/ or scenes/ (a typo's sibling, a dataset, a run's outputs)
    was reported as a missing mech_intrinsics.yaml (newcomer run-through): now what a session holds and what the
    folder holds, exit 2, nothing written."""
    dataset = dataset[0]
    other = tmp_path / "notes"
    (other / "photos").mkdir(parents=True)
    (other / "readme.txt").write_text("x")
    run_out = tmp_path / "run_out"
    run_out.mkdir()
    (run_out / "run_state.json").write_text("{}")
    cases = [(other, "a folder with none of them (it holds photos/, readme.txt)"),
             (tmp_path / "empty", "a folder with none of them (it is empty)"),
             (dataset, "got a dataset gtforge built (no session.yaml)"),
             (run_out, "got gtforge run's output folder (no session.yaml)")]
    (tmp_path / "empty").mkdir()
    for folder, got in cases:
        for args in (["calibrate", folder, "-o", tmp_path / "c.yaml"], ["run", folder, "-o", tmp_path / "r"]):
            r = gtforge(*args)
            assert r.returncode == 2 and one_line_error(r), r.stderr
            assert f"{folder}: expected a capture session folder (session.yaml" in r.stderr and got in r.stderr, \
                r.stderr
            assert "gtforge import writes a session from recordings" in r.stderr
    assert not (tmp_path / "c.yaml").exists() and not (tmp_path / "r").exists()


def test_no_stage_writes_into_the_session_or_over_a_file_not_its_own(session_dir, true_calibration, dataset, tmp_path):
    """A newcomer's run-through: validate and evaluate wrote into the session's folder, validate into a dataset's,
    and the calibration-writing stages over any existing file (a report's HTML, a user's notes) or, given a folder,
    over calibrate's calibration.yaml there. Each is refused now, exit 2, nothing written; a stage's own earlier
    calibration is still replaced, and a folder gets the stage's own file name."""
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    before = tree_digest(sess), tree_digest(dataset[0])
    man = json.loads((dataset[0] / "manifest.json").read_text())
    cases = [(("validate", sess, "-c", true_calibration, "-o", sess / "val"), f"a path inside {sess}"),
             (("calibrate", sess, "-o", sess / "c.yaml", "--no-loo"), f"a path inside {sess}"),
             (("refine", sess, "-c", true_calibration, "-o", notes), "not a gtforge calibration (it would be lost)"),
             (("validate", sess, "-c", true_calibration, "-o", dataset[0]), "got a dataset gtforge built")]
    for args, needle in cases:
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r) and needle in r.stderr, (args[0], r.stderr)
    # evaluate: the dataset's own session (manifest.json's session_dir)
    (tmp_path / "ds").mkdir()
    shutil.copytree(dataset[0], tmp_path / "ds" / "d")
    m = json.loads((tmp_path / "ds" / "d" / "manifest.json").read_text())
    m["session_dir"] = str(sess)
    (tmp_path / "ds" / "d" / "manifest.json").write_text(json.dumps(m))
    r = gtforge("evaluate", tmp_path / "ds" / "d", "--sgbm", "-o", sess / "eval")
    assert r.returncode == 2 and one_line_error(r) and "the session the dataset was built from" in r.stderr, r.stderr
    assert (tree_digest(sess), tree_digest(dataset[0])) == before and notes.read_text() == "mine"
    assert man["session_dir"]  # (the fixture's dataset names its session too)
    # a folder holding calibrate's calibration.yaml: calibrate-scale writes its own scaled.yaml beside it
    folder = tmp_path / "calib"
    folder.mkdir()
    shutil.copy(true_calibration, folder / "calibration.yaml")
    mine = (folder / "calibration.yaml").read_bytes()
    r = gtforge("calibrate-scale", sess, "-c", folder / "calibration.yaml", "-o", folder)
    assert r.returncode == 0, r.stderr
    assert (folder / "calibration.yaml").read_bytes() == mine and (folder / "scaled.yaml").is_file()
    assert f"wrote {folder / 'scaled.yaml'}" in r.stdout


def test_an_evaluation_that_scored_nothing_says_so_and_exits_1(dataset, tmp_path):
    """--max-gt-sigma below every label's sigma left no pixel to score: exit 0 with tables of dashes before (a
    newcomer's run-through); a warning naming what left them out, and exit code 1."""
    r = gtforge("evaluate", dataset[0], "--sgbm", "--max-gt-sigma", "1e-9", "-o", tmp_path / "ev")
    assert r.returncode == 1, r.stderr
    assert "warning: no pixel was scored" in r.stderr and "left out by --max-gt-sigma" in r.stderr, r.stderr
    assert json.loads((tmp_path / "ev" / "results.json").read_text())["pooled"]["all"]["n_valid"] == 0
    r = gtforge("evaluate", dataset[0], "--sgbm", "-o", tmp_path / "ev2")
    assert r.returncode == 0 and "no pixel was scored" not in r.stderr, r.stderr


def test_a_file_given_for_a_folder_is_named_a_file(dataset, tmp_path):
    """A file where a folder is expected (the dataset's manifest.json, a prediction file) said "no such folder" or
    "no manifest.json" (a newcomer's run-through): it says a file now, and which folder to give."""
    man = dataset[0] / "manifest.json"
    for args in (("evaluate", dataset[0], "--predictions", man, "-o", tmp_path / "e"),
                 ("evaluate", man, "--sgbm", "-o", tmp_path / "e"), ("verify", man)):
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r), (args, r.stderr)
        assert "got a file" in r.stderr and f"give the folder that holds it ({dataset[0]})" in r.stderr, r.stderr
    assert not (tmp_path / "e").exists()
    # a folder that does not exist: both stages say so alike (evaluate said "no manifest.json")
    for args in (("evaluate", tmp_path / "nowhere", "--sgbm", "-o", tmp_path / "e"), ("verify", tmp_path / "nowhere")):
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r), (args, r.stderr)
        assert f"{tmp_path / 'nowhere'}: expected a dataset folder built by gtforge build-dataset, got no such " \
               "folder (hint: check the path (the -o of build-dataset))" in r.stderr, r.stderr
    assert not (tmp_path / "e").exists()


def test_predictions_all_refused_end_in_one_short_line_naming_their_folder(dataset, tmp_path):
    """Every prediction of the wrong size: the last line named the dataset and repeated the scenes' errors in a
    566-character hint (a run-through); now it names the predictions folder, once, after each scene's own line."""
    import numpy as np

    p = tmp_path / "p"
    p.mkdir()
    ids = sorted(d.name for d in (dataset[0] / "scenes").iterdir() if d.is_dir())
    for sid in ids:
        np.save(p / f"{sid}.npy", np.zeros((10, 12), np.float32))
    r = gtforge("evaluate", dataset[0], "--predictions", p, "-o", tmp_path / "e")
    assert r.returncode == 2, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(f"error: {p} [--predictions]: expected at least one scene scored, got none of {len(ids)}")
    assert len(last) < 300 and "Traceback" not in r.stderr, last
    assert sum(f"scene {sid}:" in r.stderr for sid in ids) == len(ids)  # each scene's reason, said as it came


def test_option_mistakes_say_what_to_give(dataset, tmp_path):
    """Errors a run-through found without a hint: each now says what to give."""
    cases = [(("verify", dataset[0], "--scenes", "000,,001"), "got '' (hint: its scenes: 000, 001"),
             (("verify", dataset[0], "--scenes", "009"), "got '009' (hint: its scenes:"),
             (("evaluate", dataset[0], "-o", tmp_path / "e"), "(hint: name the model to score"),
             (("evaluate", dataset[0], "--sgbm", "--predictions", tmp_path, "-o", tmp_path / "e"),
              "(hint: evaluate scores one model a run"),
             (("evaluate", dataset[0], "--sgbm", "--fit", "resize", "--resize", "544", "-o", tmp_path / "e"),
              "(hint: write both sides, e.g. --resize 1088x376)")]
    if __import__("importlib").util.find_spec("onnxruntime"):
        cases.append((("evaluate", dataset[0], "--onnx", tmp_path, "-o", tmp_path / "e"),
                       "got a folder (hint: a folder of predicted disparities goes to --predictions)"))
    for args, needle in cases:
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r) and needle in r.stderr, (args, r.stderr)
    assert not (tmp_path / "e").exists()


def test_outputs_inside_a_datasets_own_folders_are_refused_and_beside_the_session_accepted(session_dir,
                                                                                          true_calibration, dataset,
                                                                                          tmp_path):
    """A second run-through: validate and calibrate wrote into a dataset's views/ and scenes/ (evaluate refused
    them); -o at the session itself named one of its capture folders; a folder that holds the session (the demo's
    layout) is a place for a calibration file."""
    before = tree_digest(dataset[0])
    cases = [(("validate", session_dir, "-c", true_calibration, "-o", dataset[0] / "views" / "val"),
              "got a path inside the dataset's views/"),
             (("calibrate", session_dir, "--no-loo", "-o", dataset[0] / "scenes" / "000" / "c.yaml"),
              "got a path inside the dataset's scenes/"),
             (("validate", session_dir, "-c", true_calibration, "-o", session_dir), "got the session folder itself")]
    for args, needle in cases:
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r) and needle in r.stderr, (args[0], r.stderr)
    assert tree_digest(dataset[0]) == before
    holder = tmp_path / "lab"
    shutil.copytree(session_dir, holder / "session")
    r = gtforge("calibrate-scale", holder / "session", "-c", true_calibration, "-o", holder)
    assert r.returncode == 0 and (holder / "scaled.yaml").is_file(), r.stderr
