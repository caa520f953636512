"""The ``gtforge`` command line (issue 11 item 13): help, usage and errors read as plain words."""
import re

import numpy as np
import pytest
import typer
from conftest import synthetic_session
from made_once import session_spec
from typer.testing import CliRunner

import gtforge
from gtforge.cli.commands import app

LEAKS = re.compile(r"<bool>|<path>|<int>|<float>|<str>|<list\[|\{[a-z_]+\}|--no-no-")


def _commands():
    group = typer.main.get_command(app)
    return group, sorted(group.commands)


def test_every_help_page_is_free_of_type_leaks_and_every_option_has_help():
    group, names = _commands()
    assert {"calibrate", "build-dataset", "validate", "evaluate", "compare", "synth", "demo"} <= set(names)
    runner = CliRunner()
    for args in [["--help"]] + [[n, "--help"] for n in names]:
        r = runner.invoke(app, args, env={"COLUMNS": "200"})
        assert r.exit_code == 0, (args, r.output)
        assert not LEAKS.search(r.output), (args, LEAKS.search(r.output).group(0))
    for n in names:
        for p in group.commands[n].params:
            assert p.help, f"gtforge {n}: {p.name} has no help text"
            assert "--no-no-" not in " ".join(getattr(p, "secondary_opts", []))


def test_every_bracketed_word_of_a_help_text_is_shown():
    """typer's boxed help reads help texts as rich markup: "calibrate -> [align-depth] ->" showed as "calibrate ->  ->"
    in the top-level help, and a text escaped for rich ("gtforge\\[dask]") kept its backslash in click's plain help
    (a narrow terminal). Every bracketed word is shown as written, boxed or plain."""
    group, names = _commands()
    runner = CliRunner()
    pages = [([], group)] + [([n], group.commands[n]) for n in names]
    seen = 0
    for width in (80, 200):
        for args, cmd in pages:
            out = runner.invoke(app, args + ["--help"], env={"COLUMNS": str(width)}).output
            flat = re.sub(r"\s+", " ", out.replace("│", " "))
            assert "\\[" not in flat, (args, width)
            texts = [getattr(o, "_plain_help", o.help) for o in (cmd, *cmd.params) if getattr(o, "help", None)]
            for text in texts:
                for word in re.findall(r"\[[^\]\n]+\]", text):
                    seen += 1
                    assert re.sub(r"\s+", " ", word) in flat, (args, width, word)
    assert seen >= 6  # the group's "[align-depth]" and the two "gtforge[dask]", at both widths


def test_help_never_cuts_an_option_name_short_on_a_narrow_terminal():
    """At 80 columns typer's boxed table cut long names to "--legacy-patte…" (newcomer run-through): a command whose
    table does not fit gets click's plain help, which wraps; every width shows every option's names whole."""
    group, names = _commands()
    runner = CliRunner()
    plain = set()
    for width in (80, 100, 120, 160):
        for n in names:
            out = runner.invoke(app, [n, "--help"], env={"COLUMNS": str(width)}).output
            assert "…" not in out, (n, width, [line for line in out.splitlines() if "…" in line])
            words = set(re.findall(r"--[a-z][a-z0-9-]*", out))
            for p in group.commands[n].params:
                assert set(o for o in p.opts + p.secondary_opts if o.startswith("--")) <= words, (n, width, p.name)
            if "╭" not in out:
                plain.add((n, width))
    assert ("import", 80) in plain and ("build-dataset", 100) in plain  # the two the run-through saw cut
    assert not {n for n, w in plain if w == 160}  # a wide terminal keeps the boxed help


def test_usage_errors_name_arguments_plainly():
    r = CliRunner().invoke(app, ["calibrate"], env={"COLUMNS": "200"})
    assert r.exit_code == 2
    assert "Usage: root calibrate [OPTIONS] SESSION" in r.output and "Missing argument 'SESSION'" in r.output
    assert not LEAKS.search(r.output)
    r = CliRunner().invoke(app, ["compare"], env={"COLUMNS": "200"})
    assert "RESULTS..." in r.output and not LEAKS.search(r.output)


def test_version():
    r = CliRunner().invoke(app, ["--version"])
    assert r.exit_code == 0 and r.output.strip() == f"gtforge {gtforge.__version__}"


def test_evaluate_help_says_a_model_option_is_required(tmp_path):
    r = CliRunner().invoke(app, ["evaluate", "--help"], env={"COLUMNS": "200"})
    assert "Exactly one model option is required: --onnx, --torchscript, --predictions or --sgbm." in r.output
    assert "Model (exactly one is required)" in r.output
    from gtforge.errors import InputError

    with pytest.raises(InputError, match="exactly one of --onnx, --torchscript, --predictions, --sgbm, got 0 given"):
        CliRunner().invoke(app, ["evaluate", str(tmp_path)], catch_exceptions=False)


def test_flags_are_named_positively():
    group, _ = _commands()
    opts = {n: {o for p in c.params for o in [*getattr(p, "opts", []), *getattr(p, "secondary_opts", [])]}
            for n, c in group.commands.items()}
    assert {"--loo", "--no-loo"} <= opts["calibrate"] and "--no-no-loo" not in opts["calibrate"]
    assert {"--clouds", "--no-clouds"} <= opts["evaluate"] and "--no-no-clouds" not in opts["evaluate"]
    assert "--max-gt-sigma" in opts["evaluate"]


def test_synth_prints_progress_off_terminal(tmp_path):
    r = CliRunner().invoke(app, ["synth", str(tmp_path / "s"), "--boards", "1", "--scenes", "1", "--scale", "0.1"])
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    assert lines[:2] == ["board 000", "scene 000"] and lines[-1] == f"wrote {tmp_path / 's'}"


def test_synth_renders_other_targets_and_a_raw_zed(tmp_path):
    """synth's board options (as calibrate takes them) and --raw-zed: the sessions calibrate is meant for, which only
    the Python API could render (a run-through). session.yaml declares the target; the raw ZED session holds its
    SN.conf and says its images are raw; options the raw-ZED generator does not take are refused by name; a ChArUco
    without its dictionary is refused as calibrate would refuse it. (No capture rendered: the generator's targets and
    raw ZED are tests/core/test_targets.py's and test_selfcal.py's; a 6-pose ChArUco session from this command at 0.6x
    calibrates at 0.039 px RMS, PASS.)"""
    from gtforge.io.captures import SessionFile

    r = CliRunner().invoke(app, ["synth", str(tmp_path / "c"), "--boards", "0", "--scenes", "0", "--scale", "0.2",
                                 "--board", "charuco", "--cols", "9", "--rows", "7", "--square-mm", "30",
                                 "--marker-mm", "22", "--dictionary", "DICT_5X5_100"])
    assert r.exit_code == 0, r.output
    b = SessionFile.read(tmp_path / "c" / "session.yaml").board
    assert (b.kind, b.cols, b.rows, b.square_size_mm, b.marker_size_mm, b.dictionary) == (
        "charuco", 9, 7, 30.0, 22.0, "DICT_5X5_100")
    r = CliRunner().invoke(app, ["synth", str(tmp_path / "k"), "--boards", "0", "--scenes", "0", "--scale", "0.2",
                                 "--cols", "8", "--rows", "5"])  # a checkerboard of another size: declared too
    assert r.exit_code == 0, r.output
    b = SessionFile.read(tmp_path / "k" / "session.yaml").board
    assert (b.kind, b.cols, b.rows, b.square_size_mm) == ("checkerboard", 8, 5, 20.0)
    r = CliRunner().invoke(app, ["synth", str(tmp_path / "r"), "--raw-zed", "--boards", "0", "--scenes", "0",
                                 "--board", "circles_asymmetric", "--cols", "4", "--rows", "11", "--square-mm", "20"])
    assert r.exit_code == 0, r.output
    sf = SessionFile.read(tmp_path / "r" / "session.yaml")
    assert sf.zed_rectified is False and (tmp_path / "r" / sf.zed_calibration).is_file()
    assert sf.zed_calibration == "SN12345.conf" and sf.board.kind == "circles_asymmetric"
    for args, says in ((["--raw-zed", "--scale", "0.3", "--gauges"], "got --scale, --gauges"),
                       (["--board", "charuco"], "board.dictionary")):
        r = CliRunner().invoke(app, ["synth", str(tmp_path / "no"), *args])  # (the command prints it in one line)
        assert type(r.exception).__name__ == "InputError" and says in str(r.exception), r.output
        assert not (tmp_path / "no").exists()


# what `gtforge synth S --boards 5 --scenes 3 --scale 0.3 --seed 5 --separate-depth-camera --depth-pose-error-deg
# 0.1,-0.15,0.1` renders (its options as the command passes them on), made once in the background
DEPTH_POSE_SPEC = session_spec("depth_pose_session", "depth_pose", n_board=5, n_scenes=3, scale=0.3, seed=5,
                               depth_noise_mm=0.03, two_camera=True, depth_pose_error_deg=(0.1, -0.15, 0.1))


@pytest.fixture(scope="module")
def depth_pose_session(request):
    return synthetic_session(request, DEPTH_POSE_SPEC)


def test_synth_writes_a_turned_depth_camera_pose(tmp_path):
    """synth's --separate-depth-camera and --depth-pose-error-deg: session.yaml's pose of the depth camera is the true
    one turned by the error (left perturbation, degrees), the truth file keeps the true one."""
    from gtforge.core.geometry import perturb_left
    from gtforge.io.captures import SessionFile
    from gtforge.synthetic import SyntheticTruth

    sess = tmp_path / "s"
    r = CliRunner().invoke(app, ["synth", str(sess), "--boards", "0", "--scenes", "1", "--scale", "0.1",
                                 "--separate-depth-camera", "--depth-pose-error-deg", "0.1,-0.15,0.1"])
    assert r.exit_code == 0, r.output
    written = np.array(SessionFile.read(sess / "session.yaml").T_mech_from_depth)
    true = np.array(SyntheticTruth.read(sess / "truth" / "rig_truth.yaml").T_mech_from_depth)
    expected = perturb_left(true, np.r_[np.radians([0.1, -0.15, 0.1]), 0.0, 0.0, 0.0])
    assert np.allclose(written, expected, atol=1e-12) and not np.allclose(written, true, atol=1e-6)


@pytest.mark.slow
def test_a_separate_depth_cameras_pose_through_the_commands(depth_pose_session, tmp_path):
    """A unit whose depth camera is turned against session.yaml (as synth renders it: DEPTH_POSE_SPEC); calibrate then
    calibrate-scale (the README's order) print and write its rotation, the correction being the inverse turn."""
    from gtforge.records.calibration import CalibrationFile

    sess = depth_pose_session
    r = CliRunner().invoke(app, ["calibrate", str(sess), "-o", str(tmp_path / "calib.yaml"), "--no-loo",
                                 "--self-rectify-scenes", "2"])
    assert r.exit_code == 0, r.output
    sr = CalibrationFile.read(tmp_path / "calib.yaml").zed_self_rectification  # of its 3 scenes 000 and 002
    assert [c.capture for c in sr.captures][-2:] == ["scenes/000", "scenes/002"] and sr.scenes_not_matched == 1
    r = CliRunner().invoke(app, ["calibrate-scale", str(sess), "-c", str(tmp_path / "calib.yaml"),
                                 "-o", str(tmp_path / "scaled.yaml")])
    assert r.exit_code == 0, r.output
    lines = {ln.split(":")[0].strip(): ln for ln in r.output.splitlines() if ln.startswith("  depth_pose_r")}
    assert set(lines) == {"depth_pose_rx_deg", "depth_pose_ry_deg", "depth_pose_rz_deg"}, r.output
    info = CalibrationFile.read(tmp_path / "scaled.yaml").scale_calibration
    for axis, truth in zip("xyz", (-0.1, 0.15, -0.1)):
        t = info.terms[f"depth_pose_r{axis}_deg"]
        assert abs(t.estimate - truth) < 3 * t.sigma and t.sigma < 0.08, (axis, t)
    assert info.terms["depth_pose_rx_deg"].status == "applied" and "[applied]" in lines["depth_pose_rx_deg"]


def test_options_default_to_the_models_values():
    """An option named as a parameter model's field shows and passes the model's default (both read
    gtforge.infra.defaults; the booleans are the flags' own): one number in one place."""
    from gtforge.core.alignment.edge_alignment import EdgeAlignmentParams
    from gtforge.records.calibration import CalibrateParams, ScaleParams
    from gtforge.records.dataset import BuildParams
    from gtforge.records.validation import ValidateParams
    from gtforge.refine import RefineParams

    models = {"build-dataset": BuildParams, "validate": ValidateParams, "align-depth": EdgeAlignmentParams,
              "calibrate": CalibrateParams, "calibrate-scale": ScaleParams, "refine": RefineParams}
    group, _ = _commands()
    checked = 0
    for name, model in models.items():
        for p in group.commands[name].params:
            if p.name in model.model_fields and p.default is not None:
                assert p.default == model.model_fields[p.name].default, (name, p.name)
                checked += 1
    bp = BuildParams()
    split = next(p for p in group.commands["build-dataset"].params if p.name == "split")
    assert split.default == f"{bp.split_train:g},{bp.split_val:g}"
    assert checked >= 12


@pytest.mark.parametrize("argv,pool", [
    (["gtforge", "build-dataset", "S", "-c", "c.yaml", "-o", "out"], ("gtforge.build_dataset", None)),
    (["gtforge", "-v", "verify", "ds"], ("gtforge.verify", None)),
    (["gtforge", "build-dataset", "S", "-c", "c.yaml", "--workers", "1"], ("gtforge.build_dataset", 1)),
    (["gtforge", "build-dataset", "--workers", "3", "S"], ("gtforge.build_dataset", 3)),
    (["gtforge", "build-dataset", "S", "--workers=3"], ("gtforge.build_dataset", 3)),
    (["gtforge", "build-dataset", "S", "--workers", "two"], None),  # Typer reports it, once parsed
    (["gtforge", "build-dataset", "S", "--workers=0"], None),
    (["gtforge", "build-dataset", "S", "--workers"], None),
    (["gtforge", "verify", "ds", "--scheduler", "tcp://h:8786"], None),
    (["gtforge", "build-dataset", "--help"], None),
    (["gtforge", "calibrate", "build-dataset"], None),  # a folder named like a command is not one
    (["gtforge", "--workers", "2", "calibrate"], None),
    (["gtforge"], None),
])
def test_which_command_lines_start_the_pool_before_parsing(argv, pool):
    from gtforge.cli import pool_of

    assert pool_of(argv) == pool


SPY = '''
import json, sys
from gtforge.infra import scheduling
calls, start = [], scheduling.prestart_pool
def spy(module, *args, **kw):
    calls.append([module, "typer" in sys.modules, kw.get("warm_up_later", False), kw.get("warm_up") is not None,
                  scheduling._FORK_SERVER.get("n_threads") is not None])
    return start(module, *args, **kw)
scheduling.prestart_pool = spy
if __name__ == "__main__":  # (a pool worker runs this script again, as __mp_main__)
    from gtforge.cli import main
    sys.argv = ["gtforge", "build-dataset", *sys.argv[1:]]
    try:
        main()
    except SystemExit as e:
        print(json.dumps({"calls": calls, "code": e.code,
                          "handed": scheduling._FORK_SERVER.get("warm_up_handed", False)}))
'''


@pytest.mark.parametrize("workers", [[], ["--workers", "2"]])
def test_build_dataset_starts_its_fork_server_before_the_commands_are_imported(session_dir, true_calibration,
                                                                                tmp_path, workers):
    """``gtforge build-dataset`` with the default workers, or a count of them given, starts the pool's fork server
    before Typer and the commands are imported (the server's imports start 0.1 s earlier), and hands it the warm-up
    once the options are parsed."""
    import subprocess
    import sys

    from gtforge.infra.scheduling import cpu_count

    script = tmp_path / "spy.py"
    script.write_text(SPY)
    r = subprocess.run([sys.executable, str(script), str(session_dir), "-c", str(true_calibration), "-o",
                        str(tmp_path / "out"), *workers], capture_output=True, text=True, timeout=300)
    out = __import__("json").loads(r.stdout.strip().splitlines()[-1])
    assert out["code"] in (0, None), r.stderr[-3000:]
    assert (tmp_path / "out" / "manifest.json").exists()
    calls = out["calls"]
    if not workers and cpu_count() < 2:  # no pool: the command line is still judged, nothing starts
        assert calls[0][:3] == ["gtforge.build_dataset", False, True] and not calls[0][4]
        return
    # main (before typer), then the command with the warm-up (the server is running), then the library's own call
    assert calls[0] == ["gtforge.build_dataset", False, True, False, False]
    assert calls[1] == ["gtforge.build_dataset", True, False, True, True]
    assert all(c[4] for c in calls[1:])
    assert out["handed"]


SPIN = '''
import os, sys
seen = []
class Spy:  # the value OpenBLAS reads when numpy, and with it OpenBLAS, loads
    def find_spec(self, name, path=None, target=None):
        if name == "numpy":
            seen.append(os.environ.get("OPENBLAS_THREAD_TIMEOUT"))
sys.meta_path.insert(0, Spy())
from gtforge.cli import main
sys.argv = ["gtforge", "validate", "/nonexistent"]  # (exits with 2 once the stage, numpy with it, is imported)
try:
    main()
except SystemExit:
    pass
print(seen[0])
'''


@pytest.mark.parametrize("preset, expected", [(None, "20"), ("12", "12")])
def test_the_command_stops_openblas_threads_spinning_unless_the_user_set_it(preset, expected):
    """numpy and OpenCV each load OpenBLAS, whose idle threads spin 2**28 cycles before they sleep (0.2 CPU s of every
    command's imports, beside the pool's fork server): the command sets 2**20 before numpy loads, and a user's own
    value stands."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_THREAD_TIMEOUT"}
    if preset is not None:
        env["OPENBLAS_THREAD_TIMEOUT"] = preset
    r = subprocess.run([sys.executable, "-c", SPIN], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split()[-1] == expected


def test_a_binary_file_given_as_a_gtforge_file_is_a_one_line_error_and_a_bom_is_read(tmp_path):
    from gtforge.errors import InputError
    from gtforge.io.captures import SessionFile
    from gtforge.records.calibration import CalibrationFile

    blob = tmp_path / "calibration.yaml"
    blob.write_bytes(b"\x1a\x45\xdf\xa3\x9f\x42\x86")  # how a Matroska (.mkv) file starts
    with pytest.raises(InputError, match=r"calibration.yaml: expected a gtforge calibration file .*a YAML/JSON text "
                                         r"file, got binary data \(byte 0x9f at offset 4 is not UTF-8 text\)"):
        CalibrationFile.read(blob)
    saved = SessionFile(video_frame=3).write(tmp_path / "session.yaml")
    saved.write_bytes(b"\xef\xbb\xbf" + saved.read_bytes())  # a byte-order mark, as some editors write one
    assert SessionFile.read(saved) == SessionFile(video_frame=3)


def test_a_refused_board_option_is_named_as_the_user_typed_it(tmp_path):
    from gtforge.errors import InputError

    with pytest.raises(InputError, match=r"^--board: expected a value 'checkerboard', .* got 'hexagon' "
                       r"\(hint: docs/capture-layout\.md 'Declaring the board' lists the kinds .*\)$"):
        CliRunner().invoke(app, ["calibrate", str(tmp_path), "--board", "hexagon"], catch_exceptions=False)


@pytest.mark.parametrize("args", [["-v", "verify", "MISSING"], ["verify", "MISSING", "-v"],
                                  ["verify", "--verbose", "MISSING"]])
def test_verbose_is_taken_before_or_after_the_command(args, tmp_path, monkeypatch):
    import logging

    monkeypatch.chdir(tmp_path)
    r = CliRunner().invoke(app, args)
    assert r.exit_code != 0 and "No such option" not in r.output  # (the missing dataset's error)
    assert logging.getLogger().level == logging.INFO
    logging.getLogger().setLevel(logging.WARNING)


def test_no_command_has_a_v_of_its_own_and_a_v_after_dashdash_is_an_argument(tmp_path, monkeypatch):
    import logging

    group, names = _commands()
    for n in names:
        for p in group.commands[n].params:
            assert not {"-v", "--verbose"} & set(getattr(p, "opts", []) + getattr(p, "secondary_opts", [])), n
    monkeypatch.chdir(tmp_path)
    logging.getLogger().setLevel(logging.WARNING)
    r = CliRunner().invoke(app, ["verify", "MISSING", "--", "-v"], env={"COLUMNS": "200"})
    assert r.exit_code == 2 and "unexpected extra argument(s) (-v)" in r.output
    assert logging.getLogger().level == logging.WARNING


IMPORTS_GC = '''
import gc, json, sys
from gtforge.cli import main
sys.argv = ["gtforge", "verify", "/nonexistent"]  # a pool command: exits with 2 once its imports are done
try:
    main()
except SystemExit as exc:
    code = exc.code
print(json.dumps([code, gc.isenabled(), gc.get_stats()[2]["collections"], gc.get_freeze_count(),
                  "gtforge.verify" in sys.modules]))
'''


def test_the_commands_imports_run_without_the_garbage_collector_and_are_frozen():
    """A build's imports make some 100,000 objects and next to no garbage: the collector's passes over them while they
    loaded cost 0.035 of the command's 0.39 CPU s (its pool's server: 0.08 of 0.49). They run with it off, are frozen
    (no later collection walks them) and it is on again for the stage."""
    import json
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", IMPORTS_GC], capture_output=True, text=True, timeout=120)
    code, enabled, full_collections, frozen, imported = json.loads(r.stdout.strip().splitlines()[-1])
    assert (code, enabled, full_collections, imported) == (2, True, 0, True), r.stderr[-2000:]
    assert frozen > 50_000
