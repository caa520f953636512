"""A user's captures are sacred, outputs are normal files, Ctrl-C stops cleanly, wrong settings are caught.
Each test reproduces a fault a new user met (issue 11) through the command line."""
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import tifffile
from conftest import gtforge, one_line_error, tree_digest

from gtforge.records.calibration import CalibrationFile

pytestmark = pytest.mark.slow  # every test runs the real command on the shared session (conftest.py)


def test_build_refuses_outputs_in_or_around_the_captures(session_dir, true_calibration, tmp_path):
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    before = tree_digest(sess)
    for out in (sess, sess / "scenes", sess / "scenes" / "000", sess / "scenes" / "000" / "gt", sess / "board" / "x"):
        r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", out, "--workers", "1")
        assert r.returncode == 2 and one_line_error(r), (out, r.stderr)
        assert "--output" in r.stderr and "capture" in r.stderr
    assert tree_digest(sess) == before  # nothing written, nothing replaced
    # a symlinked capture's target counts too
    (tmp_path / "link_target").symlink_to(sess / "scenes" / "001")
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", tmp_path / "link_target" / "ds")
    assert r.returncode == 2 and one_line_error(r)
    # validate and calibrate refuse the same way
    r = gtforge("validate", sess, "-c", true_calibration, "-o", sess / "board")
    assert r.returncode == 2 and one_line_error(r)
    r = gtforge("calibrate", sess, "-o", sess / "board" / "000" / "calib.yaml")
    assert r.returncode == 2 and one_line_error(r)
    assert tree_digest(sess) == before


def test_no_stage_writes_into_another_session_or_a_foreign_folder(session_dir, true_calibration, tmp_path):
    """``build-dataset -o OTHER_SESSION`` replaced that session's scene folders with the dataset's (a newcomer's
    run-through, round 4): every stage refuses any capture session, not only the one it reads; build-dataset refuses
    a run's folder, a dataset of another session and a folder of someone else's files."""
    sess, other = tmp_path / "sess", tmp_path / "other"
    shutil.copytree(session_dir, sess)
    shutil.copytree(session_dir, other)
    hand_laid = tmp_path / "hand_laid"  # a session without session.yaml: its camera file beside scenes/
    shutil.copytree(session_dir / "scenes", hand_laid / "scenes")
    shutil.copy(session_dir / "mech_intrinsics.yaml", hand_laid)
    (hand_laid / "session.yaml").unlink(missing_ok=True)
    before = {p: tree_digest(p) for p in (other, hand_laid)}
    for args, out in [(("build-dataset", sess, "-c", true_calibration, "--workers", "1"), other),
                      (("build-dataset", sess, "-c", true_calibration, "--workers", "1"), other / "scenes" / "new"),
                      (("build-dataset", sess, "-c", true_calibration, "--workers", "1"), hand_laid),
                      (("calibrate", sess), other / "calibration.yaml"),
                      (("validate", sess, "-c", true_calibration), hand_laid / "validation")]:
        r = gtforge(*args, "-o", out)
        assert r.returncode == 2 and one_line_error(r), (args[0], out, r.stderr)
        assert "expected a path outside every capture session folder" in r.stderr, r.stderr
        assert f"capture session {other if other in [out, *out.parents] else hand_laid}" in r.stderr, r.stderr
    assert {p: tree_digest(p) for p in before} == before
    # a folder of the user's own files: refused, untouched
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", mine, "--workers", "1", "--no-verify")
    assert r.returncode == 2 and one_line_error(r) and "got a folder holding notes.txt, which no dataset holds" \
        in r.stderr, r.stderr
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    # a dataset of another session: refused (its scenes with this session's ids would be replaced, the others kept);
    # other's textures saved again uncompressed: the same scene ids, other captures
    import cv2

    for png in sorted(other.glob("scenes/*/2DImage.png")):
        cv2.imwrite(str(png), cv2.imread(str(png), cv2.IMREAD_UNCHANGED), [cv2.IMWRITE_PNG_COMPRESSION, 0])
    ds = tmp_path / "ds"
    r = gtforge("build-dataset", other, "-c", true_calibration, "-o", ds, "--workers", "1", "--no-verify")
    assert r.returncode == 0, r.stderr
    ds_before = tree_digest(ds)
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", ds, "--workers", "1", "--no-verify")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert f"manifest.json [session_dir]: expected a dataset built from this session ({sess.resolve()}), got one " \
           f"built from {other.resolve()}, whose scenes' inputs are not this session's" in r.stderr, r.stderr
    assert tree_digest(ds) == ds_before
    # the same session moved (or copied) with its dataset: the build resumes there, nothing rebuilt
    moved = tmp_path / "moved"
    other.rename(moved)
    scenes_before = tree_digest(ds / "scenes")
    r = gtforge("build-dataset", moved, "-c", true_calibration, "-o", ds, "--workers", "1", "--no-verify")
    assert r.returncode == 0, r.stderr
    manifest = json.loads((ds / "manifest.json").read_text())
    assert manifest["session_dir"] == str(moved.resolve())
    assert r.stdout.startswith("built 0, unchanged 3, failed 0") and tree_digest(ds / "scenes") == scenes_before
    # another session with --overwrite: every scene rebuilt from it
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", ds, "--workers", "1", "--no-verify",
                "--overwrite")
    assert r.returncode == 0, r.stderr
    assert json.loads((ds / "manifest.json").read_text())["session_dir"] == str(sess.resolve())
    # a run's folder: its dataset is dataset/ inside it
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "run_state.json").write_text("{}")
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", run_dir, "--workers", "1")
    assert r.returncode == 2 and one_line_error(r) and "got gtforge run's output folder" in r.stderr, r.stderr
    assert sorted(p.name for p in run_dir.iterdir()) == ["run_state.json"]


def test_symlinked_scenes_keep_their_names(session_dir, true_calibration, tmp_path):
    """Sessions assembled from several capture days by links: ids come from the link names, never the targets."""
    day0, day1 = tmp_path / "day0", tmp_path / "day1"
    for day in (day0, day1):
        shutil.copytree(session_dir / "scenes" / "000", day / "000")
    sess = tmp_path / "sess"
    sess.mkdir()
    for f in ("mech_intrinsics.yaml", "zed_calibration.yaml"):
        shutil.copy(session_dir / f, sess / f)
    (sess / "scenes").mkdir()
    (sess / "scenes" / "r0_000").symlink_to(day0 / "000")
    (sess / "scenes" / "r1_000").symlink_to(day1 / "000")
    out = tmp_path / "ds"
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", out, "--workers", "2", "--no-verify")
    assert r.returncode == 0, r.stderr
    assert "built 2" in r.stdout
    assert sorted(p.name for p in (out / "scenes").iterdir()) == ["r0_000", "r1_000"]
    assert not (out / "scenes" / "000").exists()
    # one capture reached under two names would be built twice: refused
    (sess / "scenes" / "again").symlink_to(day0 / "000")
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", tmp_path / "ds2")
    assert r.returncode == 2 and one_line_error(r) and "same capture" in r.stderr


def test_ctrl_c_stops_the_build_promptly(session_dir, true_calibration, tmp_path):
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    for i in range(3, 14):  # enough queued scenes that the run cannot finish by itself in the test's time
        shutil.copytree(session_dir / "scenes" / f"{i % 3:03d}", sess / "scenes" / f"{i:03d}")
    out = tmp_path / "ds"
    p = subprocess.Popen([sys.executable, "-m", "gtforge.cli", "build-dataset", str(sess), "-c", str(true_calibration),
                          "-o", str(out), "--workers", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline and not list((out / "scenes").glob("*/meta.json")):
        time.sleep(0.1)
    assert list((out / "scenes").glob("*/meta.json")), "no scene landed"
    t = time.time()
    os.killpg(p.pid, signal.SIGINT)  # a terminal's Ctrl-C reaches the whole process group
    stdout, stderr = p.communicate(timeout=60)
    stopped_s = time.time() - t
    assert p.returncode == 130, (p.returncode, stderr[-2000:])
    assert stopped_s < 10, stopped_s  # the issue: within a couple of seconds (10 allows a loaded CI machine)
    assert "interrupted:" in stderr and "rerun the same command to resume" in stderr and "Traceback" not in stderr
    assert "leaked semaphore" not in stderr  # (numba's lock in each terminated worker)
    names = [d.name for d in (out / "scenes").iterdir()]
    assert not [n for n in names if n.startswith(".")]  # no half-written scene left behind
    for n in names:
        assert (out / "scenes" / n / "meta.json").exists()
    assert len(names) < 14
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", out, "--workers", "2", "--no-verify")
    assert r.returncode == 0 and "failed 0" in r.stdout  # the rerun resumes


def test_a_build_started_with_ctrl_c_ignored_runs_to_its_end(session_dir, true_calibration, tmp_path):
    """A background job of a shell script (``gtforge build-dataset ... &``) inherits SIGINT ignored, so that the
    terminal's Ctrl-C stops the script, not the job. The command kept that until it set its own handler: such a build
    then stopped with 130 at the script's Ctrl-C. It now runs to its end, pool and all, as a Python program does."""
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    shutil.copytree(session_dir / "scenes" / "000", sess / "scenes" / "003")  # 4 scenes: 2 still to build at the Ctrl-C
    out = tmp_path / "ds"
    command = " ".join(shlex.quote(str(a)) for a in [sys.executable, "-m", "gtforge.cli", "build-dataset", sess, "-c",
                                                      true_calibration, "-o", out, "--workers", "2", "--no-verify"])
    p = subprocess.Popen(["sh", "-c", f"trap '' INT; exec {command}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline and not list((out / "scenes").glob("*/meta.json")) and p.poll() is None:
        time.sleep(0.05)
    assert p.poll() is None, "the build ended before the Ctrl-C"
    os.killpg(p.pid, signal.SIGINT)  # the whole group: the command, its fork server and its workers
    stdout, stderr = p.communicate(timeout=300)
    assert p.returncode == 0, (p.returncode, stderr[-2000:])
    assert "built 4" in stdout and "interrupted" not in stderr
    assert sorted(d.name for d in (out / "scenes").iterdir()) == [f"{i:03d}" for i in range(4)]
    assert (out / "manifest.json").is_file()


def test_a_closed_output_pipe_does_not_cut_the_build_short(session_dir, true_calibration, tmp_path):
    """``gtforge build-dataset ... | head -0``: the reader has gone before the command prints. The build still ends
    whole (manifest, reports) with its own exit code and no traceback; before, its progress bar's last print (on
    standard output, off a terminal too) raised BrokenPipeError and the command stopped with 1 before its manifest."""
    out = tmp_path / "ds"
    p = subprocess.Popen([sys.executable, "-m", "gtforge.cli", "build-dataset", str(session_dir), "-c",
                          str(true_calibration), "-o", str(out), "--workers", "1"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    p.stdout.close()  # as `| head -0` does
    stderr = p.stderr.read()
    assert p.wait(timeout=300) == 0, stderr[-2000:]
    assert "Traceback" not in stderr and "BrokenPipe" not in stderr and "Exception ignored" not in stderr
    for name in ("manifest.json", "build_report.html", "verification.json"):
        assert (out / name).is_file(), name
    r = gtforge("build-dataset", session_dir, "-c", true_calibration, "-o", out, "--workers", "1")
    assert r.returncode == 0 and "built 0, unchanged 3, failed 0" in r.stdout  # and complete: nothing to redo
    assert "build-dataset" not in r.stdout  # the progress bar is a terminal's only, on stderr


@pytest.mark.parametrize("umask,mode", [(0o022, 0o644), (0o027, 0o640)])
def test_outputs_follow_the_umask(session_dir, true_calibration, tmp_path, umask, mode):
    out = tmp_path / "ds"
    r = gtforge("build-dataset", session_dir, "-c", true_calibration, "-o", out, "--workers", "1", "--no-verify",
                umask=umask)
    assert r.returncode == 0, r.stderr
    files = [os.path.join(d, f) for d, _, fs in os.walk(out) for f in fs]
    assert len(files) > 20
    for f in files:
        assert os.stat(f).st_mode & 0o777 == mode, (f, oct(os.stat(f).st_mode))
    r = gtforge("validate", session_dir, "-c", true_calibration, "-o", tmp_path / "val", "--captures", "000",
                umask=umask)
    assert os.stat(tmp_path / "val" / "validation.html").st_mode & 0o777 == mode


def test_calibrate_into_a_folder_and_wrong_square_size(session_dir, tmp_path):
    (tmp_path / "calib").mkdir()
    # (the self-rectification is not what these runs test: left out, as in the runs below)
    r = gtforge("calibrate", session_dir, "-o", f"{tmp_path / 'calib'}/", "--no-loo", "--no-self-rectify", "--captures",
                "000,001,002,003")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "calib" / "calibration.yaml").is_file()
    assert "board squares measured in the depth: 20.00 mm (declared 20 mm)" in r.stdout
    # a folder that does not exist yet, given with a trailing slash
    r = gtforge("calibrate", session_dir, "-o", f"{tmp_path / 'new'}/", "--no-loo", "--no-self-rectify", "--captures",
                "000,001,002,003")
    assert r.returncode == 0 and (tmp_path / "new" / "calibration.yaml").is_file()
    # 25 mm declared for a 20 mm board: caught from the depth camera's view of the board
    r = gtforge("calibrate", session_dir, "-o", tmp_path / "wrong.yaml", "--no-loo", "--no-self-rectify",
                "--square-mm", "25")
    assert r.returncode == 2 and one_line_error(r)
    assert "25 mm declared, 20.00 mm measured" in r.stderr and "--square-mm 20.0" in r.stderr
    assert not (tmp_path / "wrong.yaml").exists()
    # a ratio of length units (the depth in m read as mm, here 0.02 mm declared for 20): the depth's unit, first
    r = gtforge("calibrate", session_dir, "-o", tmp_path / "wrong.yaml", "--no-loo", "--no-self-rectify",
                "--square-mm", "0.02")
    assert r.returncode == 2 and one_line_error(r)
    assert "(hint: the depth reads 1000x the board: set the depth maps' unit (depth_unit / depth_scale_mm" \
        in r.stderr and "--square-mm 20.0" not in r.stderr, r.stderr
    # 20.5 mm, within the 3 % the refusal allows: a PASS, with the extrinsic tens of sigma off (a run-through); a
    # WARN naming the measured size now
    from gtforge.calibrate import calibrate
    from gtforge.core.targets.models import BoardModel
    from gtforge.records.calibration import CalibrateParams

    c = calibrate(session_dir, None, CalibrateParams(board=BoardModel(square_size_mm=20.5), leave_one_out=False,
                                                     self_rectify=False), captures=["000", "001", "002", "003"])
    assert c.verdict == "WARN" and any(
        "the board's squares measure 20.00 mm in the depth, -2.4 % from the declared 20.5 mm" in x
        for x in c.verdict_reasons), c.verdict_reasons
    assert not [x for x in CalibrationFile.read(tmp_path / "calib" / "calibration.yaml").verdict_reasons
                if "squares measure" in x]


def test_use_depth_disagreement_fails_loudly(session_dir, tmp_path):
    """A depth camera 1.5 % off in scale: the squares still pass the 3 % check, but the depth solve disagrees with
    the reprojection solve by millimetres; the calibration is written and the command exits 1 with a FAIL verdict."""
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    for d in (sess / "board").iterdir():
        f = d / "DepthMap.tiff"
        tifffile.imwrite(f, (tifffile.imread(f) * 1.015).astype(np.float32))
    r = gtforge("calibrate", sess, "-o", tmp_path / "c.yaml", "--no-loo", "--no-self-rectify", "--use-depth")
    assert r.returncode == 1, r.stdout + r.stderr
    assert "verdict: FAIL" in r.stdout and "depth method differs" in r.stdout
    c = CalibrationFile.read(tmp_path / "c.yaml")
    assert c.verdict == "FAIL" and c.methods[1].trans_diff_to_primary_mm > 1.0  # allowed: max(1 mm, 5 sigma)


def test_validate_uses_the_calibrations_board(session_dir, true_calibration, tmp_path):
    c = CalibrationFile.read(true_calibration)
    c.board = c.board.model_copy(update={"square_size_mm": 25.0})  # as if calibrated with --square-mm 25
    c.write(tmp_path / "c25.yaml")
    r = gtforge("validate", session_dir, "-c", tmp_path / "c25.yaml", "-o", tmp_path / "v1", "--captures", "000,001")
    assert r.returncode == 1 and "Z geometric" in r.stdout  # the 25 mm board's diagonal is 25 % off
    r = gtforge("validate", session_dir, "-c", tmp_path / "c25.yaml", "-o", tmp_path / "v2", "--captures", "000,001",
                "--square-mm", "20")
    assert r.returncode == 0, r.stdout


def test_errors_name_real_options_and_files(session_dir, true_calibration, tmp_path):
    # metres: the hint names session.yaml's depth_unit (there is no --depth-unit option)
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    f = sess / "scenes" / "001" / "DepthMap.tiff"
    tifffile.imwrite(f, (tifffile.imread(f) / 1000).astype(np.float32))
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", tmp_path / "ds", "--workers", "1", "--no-verify")
    assert r.returncode == 1
    out = r.stdout + r.stderr
    assert "depth_unit: m" in out and "session.yaml" in out and "--depth-unit" not in out
    assert out.count("median 0.") == 1  # the failed scene is reported once
    # a file that is not a calibration: named by what it is for, no class names, no <input>
    (tmp_path / "x.yaml").write_text("hello: 1\n")
    r = gtforge("build-dataset", sess, "-c", tmp_path / "x.yaml", "-o", tmp_path / "ds2")
    assert r.returncode == 2 and one_line_error(r)
    assert "gtforge calibration file" in r.stderr and "CalibrationFile" not in r.stderr and "<input>" not in r.stderr
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", tmp_path / "ds3", "--split", "nonsense")
    assert r.returncode == 2 and "<input>" not in r.stderr and "--split" in r.stderr


def _fork_servers_with(marker: str) -> list[int]:
    """The live multiprocessing fork servers whose environment holds ``marker`` (Linux /proc). (Not the resource
    tracker, which the command also starts: it leaves once it reads the end of its pipe, maybe just after the
    command.)"""
    pids = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if marker.encode() in (d / "environ").read_bytes() and b"forkserver" in (d / "cmdline").read_bytes():
                pids.append(int(d.name))
        except OSError:
            continue
    return pids


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="reads /proc (Linux)")
def test_a_build_that_ends_before_its_pool_leaves_no_fork_server_behind(session_dir, tmp_path):
    """Bad input found once the pool's fork server has started (before option parsing): the command exits with 2
    and its server is gone with it. Before, the server went on with its imports (0.5 s of a core) holding the
    command's stdout and stderr, so a pipeline or a caller reading them waited for it."""
    marker = f"GTFORGE_TEST_MARK={os.getpid()}-{tmp_path.name}"
    (tmp_path / "x.yaml").write_text("hello: 1\n")
    env = {**os.environ, marker.split("=")[0]: marker.split("=")[1]}
    with open(tmp_path / "stderr.txt", "w") as err:  # a file, not a pipe: run() returns when the command exits
        r = subprocess.run([sys.executable, "-m", "gtforge.cli", "build-dataset", str(session_dir), "-c",
                            str(tmp_path / "x.yaml"), "-o", str(tmp_path / "ds"), "--workers", "2"],
                           stdout=subprocess.DEVNULL, stderr=err, env=env, timeout=300)
    assert r.returncode == 2 and "gtforge calibration file" in (tmp_path / "stderr.txt").read_text()
    assert _fork_servers_with(marker) == []
    assert not (tmp_path / "ds").exists()


def test_empty_splits_are_reported(session_dir, true_calibration, tmp_path):
    r = gtforge("build-dataset", session_dir, "-c", true_calibration, "-o", tmp_path / "ds", "--workers", "1",
                "--no-verify", "--split", "0.5,0.5")
    assert r.returncode == 0
    assert "came out empty" in r.stderr and "fruit_ids" in r.stderr  # 3 scenes, 2 fruit: test is empty
    assert (tmp_path / "ds" / "filenames" / "test.txt").read_text() == ""


def _pool_workers(pid: int) -> list[str]:
    """The local pool's worker processes of process ``pid``: the children of its fork server (or, where workers are
    spawned, its own children that run ``spawn_main``)."""
    def children(k):
        return subprocess.run(["pgrep", "-P", str(k)], capture_output=True, text=True).stdout.split()

    def cmdline(k):
        return open(f"/proc/{k}/cmdline").read().replace("\0", " ")

    out = []
    for k in children(pid):
        if "forkserver" in cmdline(k):
            out += children(k)
        elif "spawn_main" in cmdline(k) and "resource_tracker" not in cmdline(k):
            out.append(k)
    return out


def test_a_dying_local_worker_lists_its_scenes_as_failed(session_dir, true_calibration, tmp_path):
    """A pool process killed mid-build (out of memory, say): the scenes it took down are listed as failed, the
    others land, the command exits 1, and the rerun builds the rest."""
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    for i in range(3, 12):
        shutil.copytree(session_dir / "scenes" / f"{i % 3:03d}", sess / "scenes" / f"{i:03d}")
    out = tmp_path / "ds"
    p = subprocess.Popen([sys.executable, "-m", "gtforge.cli", "build-dataset", str(sess), "-c", str(true_calibration),
                          "-o", str(out), "--workers", "2", "--no-verify"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while time.time() < deadline and not list((out / "scenes").glob("*/meta.json")):
        time.sleep(0.01)
    # freeze the pool as soon as a scene has landed, so that scenes are still unbuilt when one worker is killed
    # (on a fast machine the other scenes could otherwise all land before the kill, and nothing would fail)
    workers = _pool_workers(p.pid)
    assert workers
    for k in workers:
        os.kill(int(k), signal.SIGSTOP)
    landed = len(list((out / "scenes").glob("*/meta.json")))
    assert 1 <= landed < 12
    os.kill(int(workers[0]), signal.SIGKILL)
    for k in workers[1:]:
        os.kill(int(k), signal.SIGCONT)
    stdout, stderr = p.communicate(timeout=300)
    assert p.returncode == 1, stderr[-2000:]
    assert "a worker process died" in stderr and "Traceback" not in stderr
    man = __import__("json").loads((out / "manifest.json").read_text())
    assert man["failures"] and all("worker process died" in v for v in man["failures"].values())
    # a scene that landed before its worker was killed is built, not failed (its result never came back), views too
    landed = sorted(m.parent.name for m in (out / "scenes").glob("*/meta.json"))
    assert len(man["failures"]) + len(landed) == 12 and not set(man["failures"]) & set(landed)
    assert sorted(man["scenes"]) == landed
    assert all((out / "kitti" / "training" / "disp_noc_0" / f"{s}_10.png").is_file() for s in landed)
    # no half-written scene left: the command waited for the workers the broken pool terminated (one could still
    # hold its scene's lock when the command tidied up)
    assert not [d for d in (out / "scenes").iterdir() if d.name.startswith(".")]
    r = gtforge("build-dataset", sess, "-c", true_calibration, "-o", out, "--workers", "2", "--no-verify")
    assert r.returncode == 0 and "failed 0" in r.stdout
    assert len(list((out / "scenes").glob("*/meta.json"))) == 12


def test_a_stage_never_writes_its_calibration_into_a_runs_folder(session_dir, true_calibration, tmp_path):
    """calibrate -o RUN/scaled.yaml (or -o RUN) replaced the run's own stage files, which its certificate cites and its
    later stages read (a run-through: the certificate said PASS of figures its files no longer held). Refused, one
    line, before any work, for calibrate, calibrate-scale, refine and align-depth."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "run_state.json").write_text("{}")
    (run / "scaled.yaml").write_text("the run's own\n")
    before = tree_digest(run)
    cases = [("calibrate", session_dir, "-o", run / "scaled.yaml", "--no-loo"), ("calibrate", session_dir, "-o", run),
             ("calibrate-scale", session_dir, "-c", true_calibration, "-o", run),
             ("refine", session_dir, "-c", true_calibration, "-o", run / "refined.yaml"),
             ("align-depth", session_dir, "-c", true_calibration, "-o", run / "x.yaml")]
    for args in cases:
        r = gtforge(*args)
        assert r.returncode == 2 and one_line_error(r), (args, r.stderr[-1500:])
        assert "expected a path outside gtforge run's output folder" in r.stderr and "write it beside the run, e.g. " \
            f"{tmp_path}" in r.stderr, r.stderr
    assert tree_digest(run) == before
