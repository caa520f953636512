"""No stage writes over a file the session reads (issue 36, item 1): ``-o`` naming session.yaml, an intrinsics file or
the ZED calibration, under every spelling of the path, is refused with exit 2 and the file stays as it was."""
import os
import shutil
from pathlib import Path

import pytest
from conftest import gtforge, one_line_error, tree_digest

from gtforge.errors import InputError
from gtforge.io.captures import open_session

EXAMPLE = Path(__file__).resolve().parents[2] / "calib_data_examples" / "session"
SESSION_FILES = ("session.yaml", "mech_intrinsics.yaml", "zed_calibration.yaml")


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    """A copy of the shipped example session."""
    sess = tmp_path_factory.mktemp("example") / "session"
    shutil.copytree(EXAMPLE, sess)
    return sess


def spellings(sess: Path, name: str, tmp: Path) -> list[str]:
    """Ways to name ``sess/name``: absolute, with ``..``, relative to the working folder, through a symbolic link to
    the session and to the file, and a hard link."""
    (tmp / "sess_link").symlink_to(sess)
    (tmp / "file_link.yaml").symlink_to(sess / name)
    os.link(sess / name, tmp / "hard_link.yaml")
    return [str(sess / name), str(sess / "board" / ".." / name), os.path.relpath(sess / name),
            str(tmp / "sess_link" / name), str(tmp / "file_link.yaml"), str(tmp / "hard_link.yaml")]


@pytest.mark.parametrize("name", SESSION_FILES)
def test_every_spelling_of_a_session_file_is_refused(example, name, tmp_path):
    sess = example
    session = open_session(sess)
    for out in spellings(sess, name, tmp_path):
        with pytest.raises(InputError, match="the session's files are never written") as e:
            session.refuse_output_over_inputs(out)
        assert name in str(e.value), out
    # a new file beside the session, and one with a session file's name elsewhere, are fine
    session.refuse_output_over_inputs(tmp_path / name)
    session.refuse_output_over_inputs(sess.parent / "calib_new.yaml")


@pytest.mark.slow
def test_the_stages_refuse_to_write_over_session_files(example, tmp_path):
    """calibrate, calibrate-scale and refine, run as a user runs them: exit 2, one line, nothing changed."""
    from gtforge.calibrate import calibrate
    from gtforge.records.calibration import CalibrateParams

    sess = example
    calib = tmp_path / "calib.yaml"
    calibrate(sess, calib, CalibrateParams(leave_one_out=False, self_rectify=False))
    before = tree_digest(sess)
    (tmp_path / "link").symlink_to(sess)
    runs = [("calibrate", sess, "-o", sess / "zed_calibration.yaml", "--no-loo"),
            ("calibrate", sess, "-o", sess / "board" / ".." / "session.yaml", "--no-loo"),
            ("calibrate-scale", sess, "-c", calib, "-o", tmp_path / "link" / "mech_intrinsics.yaml"),
            ("refine", sess, "-c", calib, "-o", sess / "zed_calibration.yaml")]
    for args in runs:
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r), (args, r.stderr)
        assert "never written" in r.stderr, r.stderr
    assert tree_digest(sess) == before


@pytest.mark.parametrize("line,says", [
    ("fruit_ids: {000: melon1, 001: melon1}", "[fruit_ids]: expected a valid session.yaml (Value error, scene ids as "
     "text: quote them in YAML ('000': melon07); 0 reads as a number), got {0: 'melon1', 1: 'melon1'} (hint: "
     "correct fruit_ids in the file, then rerun)"),
    ("video_frame: -3", "[video_frame]: expected a valid session.yaml (Input should be greater than or equal to 0), "
     "got -3 (hint: correct video_frame in the file, then rerun)"),
    ("zed_rectifed: true", "[zed_rectifed]: expected a valid session.yaml (Extra inputs are not permitted), got True "
     "(hint: did you mean zed_rectified?)"),
    ("lighting: led", "[lighting]: expected a valid session.yaml (Extra inputs are not permitted), got 'led' "
     "(hint: remove lighting: not a field of session.yaml)")])
def test_session_yaml_slips_are_named_with_what_to_write(line, says, tmp_path):
    """Unquoted scene ids (YAML reads 000 as 0: said without a hint), a negative video frame (accepted) and a
    misspelt key (no hint) in session.yaml: one line each that says what to write (a run-through)."""
    from gtforge.io.captures import SessionFile

    (tmp_path / "session.yaml").write_text(line + "\n")
    with pytest.raises(InputError) as err:
        SessionFile.read(tmp_path / "session.yaml")
    assert str(err.value) == f"{tmp_path / 'session.yaml'} {says}"


def test_a_file_gtforge_writes_that_does_not_validate_is_written_again_by_its_command(tmp_path):
    """A calibration file of another schema (edited by hand, or another version's): the hint names the command that
    writes it (it had none)."""
    from gtforge.records.calibration import CalibrationFile

    (tmp_path / "calibration.yaml").write_text("schema_version: 99\n")
    with pytest.raises(InputError) as err:
        CalibrationFile.read(tmp_path / "calibration.yaml")
    assert err.value.field == "schema_version" and err.value.actual == "99"
    assert err.value.hint == ("write it again with gtforge calibrate (was it edited by hand, or written by another "
                              "gtforge version?)")
