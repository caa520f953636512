"""``gtforge import`` with exact truth: a synthetic session (gtforge.synthetic) played as two ROS 2 recordings
(gtforge.synthetic_recordings: a zed-ros2-wrapper-like stereo bag and a realsense-ros-like RGB-D bag, own clocks,
jitter, frames in motion, a scene that changes between two frames) and imported back: the session written is the
hand-laid one file for file, in-motion frames are dropped and no capture mixes the frames of two scenes. Bad input
through the real command: one-line errors, exit 2, nothing written."""
from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import synthetic_session
from made_once import session_spec

from tests.conftest import gtforge, one_line_error, shared_data

pytest.importorskip("rosbags")
pytest.importorskip("av")

from gtforge.errors import InputError
from gtforge.importer import import_recordings
from gtforge.io.captures import read_depth
from gtforge.records.imports import ImportParams, ImportRecord
from gtforge.synthetic import generate_session
from gtforge.synthetic_recordings import write_ros2_recordings

CAPTURE_FILES = ("2DImage.png", "left.png", "right.png")  # byte for byte; the depth went through metres (32FC1)
# a raw-ZED session (VGA, SN12345.conf; the one tests/core/test_rectification.py declares: made once for both)
RAW_ZED = session_spec("raw_zed_session", "raw_zed", raw_zed=True, reading="neg-all", n_board=4, n_scenes=1, seed=5,
                       supersample=2)


@pytest.fixture(scope="module")
def hand(tmp_path_factory):
    """2 board poses + 2 scenes at 0.25x, noise-free depth (the hand-laid session)."""
    d = tmp_path_factory.mktemp("hand")
    generate_session(d, n_board=2, n_scenes=2, scale=0.25, seed=3, depth_noise_mm=0.0, image_noise=1.0,
                     supersample=1)
    return d


@pytest.fixture(scope="module")
def recs(hand, tmp_path_factory):
    """The session as .mcap recordings; scenes/000 -> scenes/001 at once (no motion frames between: index 2)."""
    return write_ros2_recordings(hand, tmp_path_factory.mktemp("rec"), storage="mcap", jumps=(2,))


def _same_session(hand: Path, imported: Path, captures: list[str]):
    assert sorted(captures) == sorted(f"{k}/{p.name}" for k in ("board", "scenes") for p in (hand / k).glob("0*"))
    for c in captures:
        for f in CAPTURE_FILES:
            assert (imported / c / f).read_bytes() == (hand / c / f).read_bytes(), f"{c}/{f}"
        a, b = read_depth(imported / c / "DepthMap.tiff"), read_depth(hand / c / "DepthMap.tiff")
        assert np.array_equal(np.isnan(a), np.isnan(b))
        assert np.nanmax(np.abs(a - b) / b) <= 1.2e-7  # mm -> m -> mm in float32: at most one rounding
    for f in ("mech_intrinsics.yaml", "zed_calibration.yaml"):
        assert (imported / f).read_bytes() == (hand / f).read_bytes(), f


def test_mcap_recordings_import_to_the_hand_laid_session(hand, recs, tmp_path):
    out = tmp_path / "session"
    s = import_recordings([recs.rgbd_bag, recs.stereo_bag], out, ImportParams(clock_offset_ms=recs.clock_offset_ms))
    assert (s.boards, s.scenes) == (2, 2) and s.clock_offset_source == "given"
    _same_session(hand, out, s.captures)
    rec = ImportRecord.read(out / "import.json")
    run = rec.runs[0]
    assert run.streams == {"depth": "/camera/camera/aligned_depth_to_color/image_raw",
                           "texture": "/camera/camera/color/image_raw",
                           "left": "/zed/zed_node/left/image_rect_color",
                           "right": "/zed/zed_node/right/image_rect_color"}
    assert {Path(f.path).name for f in run.sources} >= {"rgbd.mcap", "zed.mcap", "metadata.yaml"}
    # 20 frames: 4 captures x 4 still frames + 2 x 2 moving frames (none at the jump, none after the last); dropped:
    # the 4 moving ones and the 6 still frames beside a moving frame or the jump (the recording's first and last
    # have one neighbour, which is still)
    assert run.dropped["motion"] == 4 + 6 and run.dropped["skew"] == 0
    assert all(p.skew_ms <= run.params.max_skew_ms for p in run.pairs)
    # the moved scene: no capture takes its depth frame and its ZED frame from the two sides of the jump
    t0 = (np.array([p.t_depth_ns for p in run.pairs]), np.array([p.t_left_ns for p in run.pairs]))
    assert len(set(t0[0])) == len(set(t0[1])) == 4
    assert not list(tmp_path.glob(".*import-partial"))


def test_db3_recordings_through_the_command_with_an_estimated_clock_offset(hand, tmp_path):
    recs = write_ros2_recordings(hand, tmp_path / "rec", storage="db3", motion_frames=3, seed=5)
    out = tmp_path / "session"
    r = gtforge("import", recs.rgbd_bag / "rgbd.db3", recs.stereo_bag, "-o", out)
    assert r.returncode == 0, r.stderr
    assert "motion events" in r.stdout and "captures" in r.stdout
    run = ImportRecord.read(out / "import.json").runs[0]
    assert abs(run.clock_offset_ms - recs.clock_offset_ms) < 1000 / 15 / 2  # within half a frame
    _same_session(hand, out, [p.capture for p in run.pairs])


def test_add_to_an_existing_session_and_refuse_without_add(hand, recs, tmp_path):
    out = tmp_path / "session"
    p = ImportParams(clock_offset_ms=recs.clock_offset_ms, max_captures=2)
    import_recordings([recs.rgbd_bag, recs.stereo_bag], out, p)
    # every depth frame counted once: the captures, the drops, the other still pairs of the captures' stretches and
    # of the stretches --max-captures left out (those were all called "in the kept captures' stretches")
    run = ImportRecord.read(out / "import.json").runs[0]
    same = [int(n.split()[0]) for n in run.notes if " more still pairs in the " in n]
    assert run.notes[-2:] == [f"{same[0]} more still pairs in the kept captures' stretches",
                              f"{same[1]} more still pairs in the stretches --every/--max-captures left out"]
    assert len(run.pairs) + sum(run.dropped.values()) + sum(same) == len(recs.frame_capture)
    assert run.dropped["every/max"] == 2 and same == [3, 3]  # 2 captures kept, 2 stretches left out
    before = sorted(x.relative_to(out) for x in out.rglob("*"))
    with pytest.raises(InputError, match="--add"):
        import_recordings([recs.rgbd_bag, recs.stereo_bag], out, p)
    assert sorted(x.relative_to(out) for x in out.rglob("*")) == before
    # the same recordings again (under another name too) would duplicate their captures: refused, nothing written
    again = tmp_path / "again"
    shutil.copytree(recs.rgbd_bag, again)
    with pytest.raises(InputError, match="import.json") as dup:
        import_recordings([again, recs.stereo_bag], out, p, add=True)
    assert "not yet imported" in str(dup.value) and str(recs.rgbd_bag.resolve()) in str(dup.value)
    assert "metadata.yaml" not in str(dup.value)  # (the bag's data file is named: it said "the same bytes as
    # .../metadata.yaml")
    assert sorted(x.relative_to(out) for x in out.rglob("*")) == before
    # the same frames in other bytes: the .mcap rewritten as a .db3 bag without its first messages (a conversion and
    # a cut, as a lab's tools make them): refused by the captures' times, nothing written (helper-29)
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    cut = {}
    for name, bag in (("rgbd", recs.rgbd_bag), ("zed", recs.stereo_bag)):
        cut[name] = tmp_path / f"{name}_cut_db3"
        with AnyReader([Path(bag)]) as reader, \
                Writer(cut[name], version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
            conns = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=ts) for c in reader.connections}
            for k, (conn, t_ns, raw) in enumerate(reader.messages()):
                if k >= 6:
                    w.write(conns[conn.topic], t_ns, raw)
        assert list(cut[name].glob("*.db3"))
    with pytest.raises(InputError, match="import.json") as dup:
        import_recordings([cut["rgbd"], cut["zed"]], out, p, add=True)
    cut = cut["rgbd"]
    assert str(dup.value).startswith(f"{cut}") and "captures imported from" in str(dup.value), dup.value
    assert re.search(r"[12] of the 2 captures it would add", str(dup.value)), dup.value
    assert sorted(x.relative_to(out) for x in out.rglob("*")) == before
    # other recordings of the same rig: added, numbered after the session's captures
    more = write_ros2_recordings(hand, tmp_path / "more", captures=["board/001", "scenes/000"], seed=1)
    s = import_recordings([more.rgbd_bag, more.stereo_bag], out,
                          ImportParams(clock_offset_ms=more.clock_offset_ms), add=True)
    assert s.captures == ["board/002", "scenes/000"]
    rec = ImportRecord.read(out / "import.json")
    assert len(rec.runs) == 2 and rec.runs[0].dropped["every/max"] == 2


def test_a_charuco_board_is_declared_at_import_as_at_calibrate(tmp_path):
    """--board charuco needs its dictionary and marker size, as calibrate takes them (import had no --dictionary, so
    a ChArUco board could not be declared)."""
    rec = shared_data("recordings") / "azure_kinect_recording.mkv"
    base = ["import", rec, "--board", "charuco", "--cols", "7", "--rows", "5", "--square-mm", "40"]
    r = gtforge(*base, "-o", tmp_path / "no")
    assert r.returncode == 2 and one_line_error(r) and "board.dictionary" in r.stderr and "--dictionary" in r.stderr
    r = gtforge(*base, "--marker-mm", "30", "--dictionary", "DICT_4X4_50", "--legacy-pattern", "-o", tmp_path / "k")
    assert r.returncode == 0, r.stderr
    from gtforge.io.captures import SessionFile

    board = SessionFile.read(tmp_path / "k" / "session.yaml").board
    assert (board.kind, board.cols, board.rows, board.square_size_mm, board.marker_size_mm, board.dictionary,
            board.legacy_pattern) == ("charuco", 7, 5, 40.0, 30.0, "DICT_4X4_50", True)


def test_real_recordings_import_through_the_command(tmp_path):
    rec_dir, frame_dir = shared_data("recordings"), shared_data("azure-kinect-frame")
    from gtforge.io.captures import read_depth
    from gtforge.io.formats import read_image

    before = sorted(os.listdir(rec_dir))
    r = gtforge("import", rec_dir / "azure_kinect_recording.mkv", "-o", tmp_path / "k")
    assert r.returncode == 0, r.stderr
    cap = tmp_path / "k" / "scenes" / "000"
    png = read_image(frame_dir / "depth_nfov_unbinned_mm.png")
    assert np.array_equal(np.nan_to_num(read_depth(cap / "DepthMap.tiff")).astype(np.uint16), png)
    assert np.array_equal(read_image(cap / "IR.png"), read_image(frame_dir / "ir_nfov_unbinned.png"))
    assert json.loads((tmp_path / "k" / "mech_intrinsics.json").read_text()) == \
        json.loads((frame_dir / "calibration.json").read_text())  # the attachment, as the frame's folder has it
    from gtforge.io.captures import SessionFile
    from gtforge.io.vendors import load_structured_light_cameras, read_kinect_calibration

    sf = SessionFile.read(tmp_path / "k" / "session.yaml")
    cams = load_structured_light_cameras(tmp_path / "k" / sf.mech_intrinsics, depth_mode=sf.kinect_depth_mode,
                                         color_mode=sf.kinect_color_mode)
    k = read_kinect_calibration(frame_dir / "calibration.json", "NFOV_UNBINNED", "720P")
    assert (cams.texture, cams.depth) == (k.color, k.depth)
    color = read_image(cap / "2DImage.png")
    assert np.abs(color.astype(int) - read_image(frame_dir / "color_720p.jpg")).mean() < 1.0
    # a depth recording alone: no stereo images, and the chain says so in one line instead of naming a missing file
    assert "no stereo recording" in r.stderr
    # its one colour frame: kept, but nothing could check that it was still, which a warning says
    assert "warning: azure_kinect_recording.mkv (COLOR) holds one frame: its stillness cannot be checked" in r.stderr
    r = gtforge("run", tmp_path / "k", "-o", tmp_path / "k_run")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "[zed_calibration]" in r.stderr and "imported from a depth recording alone" in r.stderr
    assert not (tmp_path / "k_run").exists()
    # the recording cut short, wherever: one line with the size its Matroska Segment declares and the size there is
    # (cut where only its IR frame was missing, it imported with a warning and exit 0, the truncation unnoticed)
    data = (rec_dir / "azure_kinect_recording.mkv").read_bytes()
    # (other sizes, and the RealSense .bag: tests/io/test_recordings.py)
    size = 1_600_000
    (tmp_path / "cut.mkv").write_bytes(data[:size])
    r = gtforge("import", tmp_path / "cut.mkv", "-o", tmp_path / "cut")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert r.stderr.startswith(f"error: {tmp_path / 'cut.mkv'} [size]: expected {len(data)} bytes (its Matroska "
                               f"Segment's size), got {size} bytes (truncated) (hint: "), r.stderr
    assert not (tmp_path / "cut").exists()
    # a copy with other bytes (padded at the end) added to the session imported from the recording: its one
    # capture's frame is already there
    (tmp_path / "padded.mkv").write_bytes(data + bytes(64))
    listed = sorted(p.relative_to(tmp_path / "k") for p in (tmp_path / "k").rglob("*"))
    with pytest.raises(InputError) as dup:  # (in-process: the command's one line is its str)
        import_recordings([tmp_path / "padded.mkv"], tmp_path / "k", add=True)
    assert "1 of the 1 captures it would add at the depth and texture times of captures imported from" in \
        str(dup.value)
    assert sorted(p.relative_to(tmp_path / "k") for p in (tmp_path / "k").rglob("*")) == listed
    # a clock offset with one recording (one clock) is refused, not recorded in import.json's params and ignored
    r = gtforge("import", rec_dir / "azure_kinect_recording.mkv", "-o", tmp_path / "k_offset", "--clock-offset-ms",
                "50")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert r.stderr.startswith("error: --clock-offset-ms: expected a stereo recording beside the depth recording (the "
                               "offset is the stereo clock minus the depth clock), got 50 with the depth recording "
                               "azure_kinect_recording.mkv alone (hint: "), r.stderr
    assert not (tmp_path / "k_offset").exists()
    with pytest.raises(InputError, match="got auto with the depth recording realsense_d435"):
        import_recordings([rec_dir / "realsense_d435_single_depth_color_640x480.bag"], tmp_path / "rs_offset",
                          ImportParams(estimate_clock_offset=True, max_skew_ms=150))
    assert not (tmp_path / "rs_offset").exists()
    r = gtforge("import", rec_dir / "realsense_d435_single_depth_color_640x480.bag", "-o", tmp_path / "rs0")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "got none (2 dropped for skew (frames over 20 ms apart; the nearest 101.6 ms))" in r.stderr
    assert not (tmp_path / "rs0").exists()
    r = gtforge("import", rec_dir / "realsense_d435_single_depth_color_640x480.bag", "-o", tmp_path / "rs",
                "--max-skew-ms", "150")
    assert r.returncode == 0, r.stderr
    # options the recording does not read are refused by name, not ignored
    for rec, opt in (("realsense_d435_single_depth_color_640x480.bag", ["--depth-topic", "/nope"]),
                     ("realsense_d435_single_depth_color_640x480.bag", ["--depth-unit", "m"]),
                     ("azure_kinect_recording.mkv", ["--color-topic", "/x"]),
                     ("azure_kinect_recording.mkv", ["--fps", "15"])):
        r = gtforge("import", rec_dir / rec, "-o", tmp_path / "refused", "--max-skew-ms", "150", *opt)
        assert r.returncode == 2 and one_line_error(r), r.stderr
        assert r.stderr.startswith(f"error: {opt[0]}: expected a recording it applies to"), r.stderr
        assert not (tmp_path / "refused").exists()
    run = json.loads((tmp_path / "rs" / "import.json").read_text())["runs"][0]
    assert run["dropped"]["skew"] == 1 and len(run["pairs"]) == 1  # 2 depth frames, 1 colour frame 101 ms away
    assert sorted(os.listdir(rec_dir)) == before  # nothing written beside the recordings


def _truncated(recs, tmp_path):
    d = tmp_path / "trunc"
    shutil.copytree(recs.rgbd_bag, d)
    f = d / "rgbd.mcap"
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])
    return [d, recs.stereo_bag], []


def _wrong_resolution(recs, tmp_path):
    from gtforge.core.camera import CameraFile

    hand = Path(recs.hand)
    cam = CameraFile.read(hand / "mech_intrinsics.yaml").camera
    wrong = cam.model_copy(update={"width_px": cam.width_px * 2, "height_px": cam.height_px * 2})
    bad = write_ros2_recordings(hand, tmp_path / "wrong", captures=["board/000"], info_camera=wrong)
    return [bad.rgbd_bag, bad.stereo_bag], []


def _metres_as_mm(recs, tmp_path):
    return [recs.rgbd_bag, recs.stereo_bag], ["--depth-unit", "mm", "--clock-offset-ms", str(recs.clock_offset_ms)]


def _empty(recs, tmp_path):
    """A rosbag2 recording whose topics are declared and hold no message (a recorder stopped at once)."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with Writer(tmp_path / "empty", version=8) as w:
        for topic in ("/camera/depth/image_raw", "/camera/color/image_raw"):
            w.add_connection(topic, "sensor_msgs/msg/Image", typestore=ts)
        w.add_connection("/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
    return [tmp_path / "empty"], []


def _renamed(recs, tmp_path):
    """The depth recording's .mcap copied under a .mkv name (a file renamed by mistake)."""
    shutil.copy(Path(recs.rgbd_bag) / "rgbd.mcap", tmp_path / "rgbd.mkv")
    return [tmp_path / "rgbd.mkv", recs.stereo_bag], []


def _written(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


BAD = {
    "renamed recording": (_renamed, "expected the recording its suffix .mkv names, got an MCAP file (.mcap, .svo2) "
                          "(by its first bytes)"),
    "an image named as a bag": (lambda recs, tmp: ([_written(tmp / "photo.bag", b"\xff\xd8\xff\xe0" + bytes(60))], []),
                                "photo.bag: expected the recording its suffix .bag names, got a JPEG image (by its "
                                "first bytes) (hint: is this the recording?"),
    "an error page saved as a recording": (lambda recs, tmp: ([_written(tmp / "rec.mkv", b"<html>404</html>")], []),
                                           "got text (an error page saved in its place?)"),
    "missing recording": (lambda recs, tmp: ([tmp / "nope.mkv"], []), "nope.mkv: expected a recording (file or "
                          "folder), got no such file or folder"),
    "board no detector can find": (lambda recs, tmp: ([recs.rgbd_bag, recs.stereo_bag], ["--cols", "2"]),
                                   "expected at least 3x3 inner corners, got 2x9"),
    "clock offset not a number": (lambda recs, tmp: ([recs.rgbd_bag, recs.stereo_bag], ["--clock-offset-ms", "nan"]),
                                  "--clock-offset-ms: expected a finite number, got nan"),
    "an option no recording reads": (lambda recs, tmp: ([recs.rgbd_bag, recs.stereo_bag], ["--fps", "15"]),
                                     "error: --fps: expected a recording it applies to (a ZED SDK export folder"),
    "truncated bag": (_truncated, "truncated"),
    "empty recording": (_empty, "got an empty one (3 topic(s) declared, 0 messages)"),
    "half a stereo pair": (lambda recs, tmp: ([recs.rgbd_bag, recs.stereo_bag], ["--right-topic", "/zed/none"]),
                           "[right topic]: expected the right image beside"),
    "no depth topic": (lambda recs, tmp: ([recs.stereo_bag], []), "depth"),
    "depth topic the colour topic": (lambda recs, tmp: ([recs.rgbd_bag, recs.stereo_bag], [
        "--depth-topic", "/camera/camera/color/image_raw"]), "[depth topic]: expected a depth image topic other than "
        "the colour image's, got '/camera/camera/color/image_raw', the colour topic too"),
    "32FC1 declared mm": (_metres_as_mm, "metres"),
    "intrinsics of another resolution": (_wrong_resolution, "another resolution"),
    "clocks never overlapping": (lambda recs, tmp: ([recs.rgbd_bag, recs.stereo_bag], ["--clock-offset-ms", "0"]),
                                 "overlap"),
}


def test_a_stray_camera_topic_warns_and_the_depth_imports(hand, recs, tmp_path):
    """A depth recording that also carries one camera of a stereo pair (no topic named): imported depth-only, as
    before, with a warning naming the missing side; naming the topic makes it an error (BAD's 'half a stereo pair')."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    mixed = tmp_path / "mixed"
    with AnyReader([Path(recs.rgbd_bag), Path(recs.stereo_bag)]) as reader, Writer(mixed, version=8) as w:
        keep = [c for c in reader.connections if "/right/" not in c.topic]
        out = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=ts) for c in keep}
        for conn, t_ns, raw in reader.messages(connections=keep):
            w.write(out[conn.topic], t_ns, raw)
    r = gtforge("import", mixed, "-o", tmp_path / "s", "--max-captures", "1")
    assert r.returncode == 0, r.stderr
    assert "warning: half a stereo pair, not imported: " in r.stderr and "[right topic]" in r.stderr
    assert "no stereo recording" in r.stderr and not list((tmp_path / "s").glob("*/*/left.png"))


def test_one_bag_holding_both_cameras_takes_the_clock_offset_given_or_estimated(hand, recs, tmp_path):
    """One bag with both cameras' topics, stamped by two clocks (a bag merged from two machines' recordings): the
    clock offset given was ignored for one bag ('one clock'), and the error said to give it (a run-through). Now the
    given offset and --clock-offset-ms auto apply; without either it stays one clock."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    both = tmp_path / "both"
    with AnyReader([Path(recs.rgbd_bag), Path(recs.stereo_bag)]) as reader, Writer(both, version=8) as w:
        out = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=ts) for c in reader.connections}
        for conn, t_ns, raw in reader.messages():
            w.write(out[conn.topic], t_ns, raw)
    s = import_recordings([both], tmp_path / "given", ImportParams(clock_offset_ms=recs.clock_offset_ms))
    assert (s.clock_offset_source, s.clock_offset_ms) == ("given", recs.clock_offset_ms)
    _same_session(hand, tmp_path / "given", s.captures)
    s = import_recordings([both], tmp_path / "auto", ImportParams(estimate_clock_offset=True))
    assert s.clock_offset_source == "motion events" and abs(s.clock_offset_ms - recs.clock_offset_ms) < 1000 / 15 / 2
    _same_session(hand, tmp_path / "auto", s.captures)
    with pytest.raises(InputError, match="offset 0.0 ms"):  # one clock: these two never overlap
        import_recordings([both], tmp_path / "one")
    assert not (tmp_path / "one").exists()


def test_a_session_inside_another_session_a_recording_or_a_dataset_is_refused_first(recs, tmp_path):
    """-o inside another session, inside a rosbag2 recording's folder (one not being imported) or inside a dataset's
    scenes was written there (a run-through). Now refused under any spelling (.., a symbolic link), before the
    recordings are even opened (a missing one is not what the error names), naming a free place beside."""
    from gtforge.io.captures import SessionFile

    (tmp_path / "sess").mkdir()
    SessionFile().write(tmp_path / "sess" / "session.yaml")
    (tmp_path / "link").symlink_to(tmp_path / "sess")
    (tmp_path / "sess" / "inner").mkdir()
    (tmp_path / "alias").symlink_to(tmp_path / "sess" / "inner")  # only its real path is inside the session
    (tmp_path / "ds" / "scenes").mkdir(parents=True)
    (tmp_path / "ds" / "manifest.json").write_text("{}")
    (tmp_path / "sub").mkdir()  # taken: the hint names the next free name
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "run_state.json").write_text("{}")  # a gtforge run's folder: its stages' files
    nope = [tmp_path / "nope.mkv"]
    for out, inside, hint in (
            (tmp_path / "run" / "new", f"gtforge run's output folder ({tmp_path / 'run'})",
             f"write it beside, e.g. {tmp_path / 'new'}"),
            (tmp_path / "x" / ".." / "sess" / "sub", f"another capture session ({tmp_path / 'sess'})",
             f"write it beside, e.g. {tmp_path / 'sub-2'}"),
            (tmp_path / "link" / "sub", f"another capture session ({tmp_path / 'link'})",
             f"write it beside, e.g. {tmp_path / 'sub-2'}"),
            (tmp_path / "alias" / "s", f"another capture session ({tmp_path / 'sess'})",
             f"write it beside, e.g. {tmp_path / 's'}"),
            (Path(recs.stereo_bag) / "s", f"a rosbag2 recording's folder ({Path(recs.stereo_bag)})",
             f"write it beside, e.g. {Path(recs.stereo_bag).parent / 's'}")):
        with pytest.raises(InputError) as err:
            import_recordings(nope, out)
        assert str(err.value) == (f"{out} [--output]: expected a session folder outside other sessions and recordings, "
                                  f"got a folder inside {inside} (hint: {hint})")
        assert not Path(os.path.abspath(out)).exists()
    r = gtforge("import", recs.rgbd_bag, recs.stereo_bag, "-o", tmp_path / "ds" / "scenes" / "s")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "expected a path outside the folders build-dataset writes, got a path inside the dataset's scenes/" \
        in r.stderr
    assert [x.name for x in (tmp_path / "ds" / "scenes").iterdir()] == []
    assert sorted(x.name for x in (tmp_path / "sess").iterdir()) == ["inner", "session.yaml"]
    assert not list((tmp_path / "sess" / "inner").iterdir())
    assert sorted(os.listdir(recs.stereo_bag)) == ["metadata.yaml", "zed.mcap"]
    assert sorted(x.name for x in (tmp_path / "run").iterdir()) == ["run_state.json"]
    rec = tmp_path / "rec.mkv"
    rec.write_bytes(b"")
    with pytest.raises(InputError) as err:  # -o the recording itself: said so (was "inside a recording")
        import_recordings([rec], rec)
    assert str(err.value) == (f"{rec} [output]: expected a session folder outside the recordings, got the recording "
                              f"itself (hint: give a new folder for the session, e.g. {tmp_path / 'rec'})")


def test_output_dot_a_link_a_mount_point_and_a_file(recs, tmp_path, monkeypatch):
    """-o . wrote its partial folder as ./..import-partial inside the target and stopped with an OSError traceback;
    -o a symbolic link to an empty folder stopped with NotADirectoryError; an empty mount point with EBUSY (a run-
    through). Now the partial folder goes beside the real folder and the session lands in it; a mount point is
    refused in one line before any work, a file with a hint."""
    import gtforge.importer as importer

    p = ImportParams(clock_offset_ms=recs.clock_offset_ms, max_captures=1)
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    s = import_recordings([recs.rgbd_bag, recs.stereo_bag], ".", p)
    assert s.captures == ["board/000"]
    assert sorted(x.name for x in here.iterdir()) == ["board", "import.json", "mech_intrinsics.yaml", "session.yaml",
                                                      "zed_calibration.yaml"]
    assert not list(tmp_path.glob(".*import-partial"))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "empty").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "empty")
    s = import_recordings([recs.rgbd_bag, recs.stereo_bag], tmp_path / "link", p)
    assert s.captures == ["board/000"] and (tmp_path / "link").is_symlink()
    assert (tmp_path / "empty" / "board" / "000" / "left.png").read_bytes() == \
        (here / "board" / "000" / "left.png").read_bytes()
    assert not list(tmp_path.glob(".*import-partial"))
    mount = tmp_path / "disk"
    mount.mkdir()
    real_ismount = os.path.ismount
    monkeypatch.setattr(importer.os.path, "ismount", lambda q: Path(q) == mount or real_ismount(q))
    with pytest.raises(InputError) as err:
        import_recordings([tmp_path / "nope.mkv"], mount, p)
    assert str(err.value) == (f"{mount} [output]: expected a session folder that is not a mount point (the session "
                              f"is written beside it, then renamed into place), got the mount point {mount} "
                              f"(hint: give a new folder inside it, e.g. {mount / 'session'})")
    assert not list(mount.iterdir()) and not list(tmp_path.glob(".*import-partial"))
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(InputError) as err:
        import_recordings([recs.rgbd_bag], tmp_path / "notes.txt", p)
    assert str(err.value) == (f"{tmp_path / 'notes.txt'} [output]: expected a folder, got a file (hint: -o names the "
                              f"session folder to write; give a new one, e.g. {tmp_path / 'notes'})")


def test_add_through_a_link_to_another_file_system(hand, recs, more, tmp_path):
    """--add through a symbolic link to a session on another file system wrote its partial folder beside the link and
    stopped at the first capture's rename (EXDEV, a traceback; a run-through). Now it works beside the real session."""
    shm = Path("/dev/shm")
    if not shm.is_dir() or os.stat(shm).st_dev == os.stat(tmp_path).st_dev:
        pytest.skip("needs /dev/shm on another file system than the tests' temporary folder")
    import tempfile

    with tempfile.TemporaryDirectory(dir=shm) as far:
        import_recordings([recs.rgbd_bag, recs.stereo_bag], Path(far) / "s",
                          ImportParams(clock_offset_ms=recs.clock_offset_ms, max_captures=1))
        (tmp_path / "s").symlink_to(Path(far) / "s")
        s = import_recordings([more.rgbd_bag, more.stereo_bag], tmp_path / "s",
                              ImportParams(clock_offset_ms=more.clock_offset_ms), add=True)
        assert s.captures == ["board/001", "scenes/000"]
        assert (Path(far) / "s" / "scenes" / "000" / "left.png").read_bytes() == \
            (hand / "scenes" / "000" / "left.png").read_bytes()
        assert len(ImportRecord.read(Path(far) / "s" / "import.json").runs) == 2
        assert not list(tmp_path.glob(".*import-partial")) and not list(Path(far).glob(".*import-partial"))


def test_a_resolution_change_mid_recording_is_refused_before_the_session_lands(hand, recs, tmp_path):
    """Only each stream's first frame was checked against its camera_info: depth frames that changed resolution
    mid-recording were written into captures the session's cameras do not fit (a run-through). Now each fetched frame
    is checked, a one-line error naming the recording, stream, frame time and sizes, and the session never lands."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    topic = "/camera/camera/aligned_depth_to_color/image_raw"
    changed = tmp_path / "changed"
    with AnyReader([Path(recs.rgbd_bag)]) as reader, Writer(changed, version=8) as w:
        out = {c.topic: w.add_connection(c.topic, c.msgtype, typestore=ts) for c in reader.connections}
        stamps = sorted(t for c, t, _ in reader.messages() if c.topic == topic)
        t_change = stamps[len(stamps) // 2]
        for conn, t_ns, raw in reader.messages():
            if conn.topic == topic and t_ns >= t_change:  # from here on at half the resolution (32FC1)
                msg = ts.deserialize_cdr(raw, conn.msgtype)
                d = msg.data.view(np.float32).reshape(msg.height, msg.width)[::2, ::2].copy()
                msg.height, msg.width, msg.step, msg.data = d.shape[0], d.shape[1], 4 * d.shape[1], d.view(np.uint8)
                msg.data = msg.data.ravel()
                raw = ts.serialize_cdr(msg, conn.msgtype)
            w.write(out[conn.topic], t_ns, raw)
    session = tmp_path / "s"
    with pytest.raises(InputError) as err:
        import_recordings([changed, recs.stereo_bag], session, ImportParams(clock_offset_ms=recs.clock_offset_ms))
    w, h = read_depth(hand / "board" / "000" / "DepthMap.tiff").shape[::-1]
    m = re.fullmatch(rf"{changed} \[{topic}\]: expected {w}x{h} frames \(its camera_info and first frame\), got a "
                     rf"{(w + 1) // 2}x{(h + 1) // 2} frame at (\d+\.\d{{3}}) s \(hint: the resolution changed during "
                     r"the recording: import the part recorded at one resolution \(a cut of the recording\)\)",
                     str(err.value))
    assert m, err.value
    assert float(m.group(1)) >= t_change / 1e9 - 5e-4
    assert not session.exists()


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_a_one_line_error_and_writes_nothing(hand, recs, tmp_path, case):
    recs.hand = hand
    make, words = BAD[case]
    paths, opts = make(recs, tmp_path)
    out = tmp_path / "out" / "session"
    r = gtforge("import", *paths, "-o", out, *opts)
    assert r.returncode == 2, r.stderr
    assert one_line_error(r), r.stderr
    assert words in r.stderr
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_without_the_extra_the_error_names_it(monkeypatch, tmp_path):
    import sys

    from gtforge.io.recordings import Bag

    monkeypatch.setitem(sys.modules, "rosbags", None)
    with pytest.raises(InputError, match=r"gtforge\[recordings\]"):
        Bag(tmp_path / "x.bag")
    from gtforge.io.zed_svo import ZedSvo

    monkeypatch.setitem(sys.modules, "mcap", None)
    with pytest.raises(InputError, match=r"gtforge\[recordings\]"):
        ZedSvo(tmp_path / "x.svo2")


@pytest.mark.slow
def test_import_calibrate_build_gives_the_hand_laid_ground_truth(session_dir, calibration, tmp_path):
    """The conftest session (7 boards, 3 scenes, 0.4x) recorded and imported, then calibrate -> build-dataset on both:
    the same extrinsic and the same ground truth (EPE to each other <= 0.001 px), as exact against the truth."""
    from gtforge.build_dataset import build_dataset
    from gtforge.calibrate import calibrate
    from gtforge.io.formats import read_pfm
    from gtforge.records.calibration import CalibrateParams

    recs = write_ros2_recordings(session_dir, tmp_path / "rec", storage="mcap", jumps=(8,))
    imported = tmp_path / "imported"
    s = import_recordings([recs.rgbd_bag, recs.stereo_bag], imported,
                          ImportParams(clock_offset_ms=recs.clock_offset_ms))
    assert (s.boards, s.scenes) == (7, 3)
    res = calibrate(imported, tmp_path / "calibration.yaml", CalibrateParams(use_depth=False, leave_one_out=False))
    assert np.abs(res.rig.T_zed_from_mech - calibration[1].rig.T_zed_from_mech).max() < 1e-6
    epe = {}
    for name, sess, calib in (("hand", session_dir, calibration[0]), ("imported", imported,
                                                                       tmp_path / "calibration.yaml")):
        out = tmp_path / f"ds_{name}"
        build_dataset(sess, calib, out, workers=1, scenes=["000"])
        epe[name] = read_pfm(out / "scenes" / "000" / "disp0GT.pfm")
    ok = np.isfinite(epe["hand"]) & np.isfinite(epe["imported"])
    assert np.array_equal(np.isfinite(epe["hand"]), np.isfinite(epe["imported"]))
    diff = np.abs(epe["hand"] - epe["imported"])[ok]
    truth = np.load(session_dir / "truth" / "scene_000.npz")["zed_disparity_px"]
    t_ok = ok & np.isfinite(truth)
    print(f"imported vs hand-laid GT: mean {diff.mean():.2e} px, max {diff.max():.2e} px; EPE to truth: imported "
          f"{np.abs(epe['imported'] - truth)[t_ok].mean():.4f} px, "
          f"hand-laid {np.abs(epe['hand'] - truth)[t_ok].mean():.4f}"
          f" px; extrinsic max |dT| {np.abs(res.rig.T_zed_from_mech - calibration[1].rig.T_zed_from_mech).max():.1e}")
    assert diff.mean() <= 0.001
    assert np.abs(epe["imported"] - truth)[t_ok].mean() < 0.05


class Stop(Exception):
    """An import stopped from its progress callback (as a Ctrl-C would stop it there)."""


def stop_at(message: str):
    def progress(msg: str) -> None:
        if msg == message:
            raise Stop
    return progress


def test_an_interrupted_import_resumes_with_the_captures_already_written(hand, recs, tmp_path):
    out = tmp_path / "session"
    p = ImportParams(clock_offset_ms=recs.clock_offset_ms)
    with pytest.raises(Stop):
        import_recordings([recs.rgbd_bag, recs.stereo_bag], out, p, progress=stop_at("capture 3/4"))
    assert not out.exists()
    partial = tmp_path / ".session.import-partial"
    done = sorted(str(x.relative_to(partial)) for x in partial.glob("*/0*"))
    assert done == ["board/000", "board/001"]
    stamp = (partial / "board" / "000" / "left.png").stat().st_mtime_ns
    s = import_recordings([recs.rgbd_bag, recs.stereo_bag], out, p)
    assert len(s.captures) == 4 and not partial.exists()
    assert (out / "board" / "000" / "left.png").stat().st_mtime_ns == stamp  # reused, not written again
    _same_session(hand, out, s.captures)


def test_add_needs_a_session_and_into_a_new_folder_writes_a_whole_one(hand, recs, tmp_path):
    """--add into a folder that is no session (its rig files would be missing) is refused, the folder untouched;
    --add into a new folder writes a whole session (session.yaml and the cameras), as without --add."""
    p = ImportParams(clock_offset_ms=recs.clock_offset_ms, max_captures=1)
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "notes.txt").write_text("mine")
    with pytest.raises(InputError) as err:
        import_recordings([recs.rgbd_bag, recs.stereo_bag], notes, p, add=True)
    assert str(err.value).startswith(f"{notes / 'session.yaml'} [--add]: expected a gtforge session to add the "
                                     "captures to, got a folder without session.yaml")
    assert [x.name for x in notes.iterdir()] == ["notes.txt"] and not (tmp_path / ".notes.import-partial").exists()
    s = import_recordings([recs.rgbd_bag, recs.stereo_bag], tmp_path / "new", p, add=True)
    assert s.captures == ["board/000"]
    assert {"session.yaml", "mech_intrinsics.yaml", "zed_calibration.yaml", "import.json"} <= \
        {x.name for x in (tmp_path / "new").iterdir()}
    for f in ("mech_intrinsics.yaml", "zed_calibration.yaml", "board/000/left.png"):
        assert (tmp_path / "new" / f).read_bytes() == (hand / f).read_bytes(), f


def test_a_partial_import_of_other_bytes_at_the_same_paths_is_not_resumed(hand, tmp_path):
    """An import stopped, then the recordings at its paths replaced by others (the same options): the rerun starts
    again; the partial folder's captures came from the other bytes."""
    rec = tmp_path / "rec"
    a = write_ros2_recordings(hand, tmp_path / "a", captures=["board/000", "board/001"])
    b = write_ros2_recordings(hand, tmp_path / "b", captures=["board/001", "board/000"])
    assert a.clock_offset_ms == b.clock_offset_ms
    shutil.copytree(tmp_path / "a", rec)
    paths, p = [rec / "rgbd", rec / "zed"], ImportParams(clock_offset_ms=a.clock_offset_ms)
    with pytest.raises(Stop):
        import_recordings(paths, tmp_path / "s", p, progress=stop_at("capture 2/2"))
    assert (tmp_path / ".s.import-partial" / "board" / "000").is_dir()
    shutil.rmtree(rec)
    shutil.copytree(tmp_path / "b", rec)
    s = import_recordings(paths, tmp_path / "s", p)
    assert s.captures == ["board/000", "board/001"]
    for name, theirs in (("board/000", "board/001"), ("board/001", "board/000")):  # b's order, not a's
        assert (tmp_path / "s" / name / "left.png").read_bytes() == (hand / theirs / "left.png").read_bytes()


def test_ctrl_c_while_added_captures_land_lands_them_all_first(hand, recs, tmp_path, monkeypatch):
    """A Ctrl-C while --add moves the captures into the session takes effect once they and import.json are in place:
    never a capture in the session that import.json does not list, nor a rerun numbering them again."""
    import os
    import signal

    import gtforge.importer as importer

    out = tmp_path / "s"
    p = ImportParams(clock_offset_ms=recs.clock_offset_ms, max_captures=1)
    import_recordings([recs.rgbd_bag, recs.stereo_bag], out, p)
    more = write_ros2_recordings(hand, tmp_path / "more", captures=["board/001", "scenes/000"], seed=1)
    real_replace, moved = os.replace, []

    def replace_then_ctrl_c(src, dst):
        real_replace(src, dst)
        if Path(dst).parent.parent == out:  # a capture landing in the session (not a capture's own write)
            moved.append(dst)
            if len(moved) == 1:
                os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(importer.os, "replace", replace_then_ctrl_c)
    # Python's own Ctrl-C (a test that ran gtforge.cli.main in this process may have left the command's handler)
    old_handler = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            import_recordings([more.rgbd_bag, more.stereo_bag], out,
                              ImportParams(clock_offset_ms=more.clock_offset_ms), add=True)
    finally:
        signal.signal(signal.SIGINT, old_handler)
    assert len(moved) >= 2  # the second capture landed after the Ctrl-C
    runs = ImportRecord.read(out / "import.json").runs
    assert [r.capture for run in runs for r in run.pairs] == ["board/000", "board/001", "scenes/000"]
    assert sorted(f"{k}/{x.name}" for k in ("board", "scenes") for x in (out / k).iterdir()) == \
        ["board/000", "board/001", "scenes/000"]
    assert not (tmp_path / ".s.import-partial").exists()


class _Crash(BaseException):
    """A process killed at this point (kill -9, power): nothing after it runs, no handler, no clean-up."""


@pytest.mark.parametrize("crash_at", ["second capture", "clean-up"])
def test_an_add_cut_off_while_its_captures_land_is_finished_by_the_next_import(hand, recs, tmp_path, monkeypatch,
                                                                              crash_at):
    """--add lands capture by capture (a journal first): a crash part-way left captures that import.json did not
    list, and the same import run again numbered them a second time. Now the next import finishes that landing, and
    the same import run again says it is done."""
    import gtforge.importer as importer

    out = tmp_path / "s"
    p = ImportParams(clock_offset_ms=recs.clock_offset_ms, max_captures=1)
    import_recordings([recs.rgbd_bag, recs.stereo_bag], out, p)
    more = write_ros2_recordings(hand, tmp_path / "more", captures=["board/001", "scenes/000"], seed=1)
    real_replace, real_rmtree, moved = os.replace, shutil.rmtree, []

    def replace_then_crash(src, dst):
        if Path(dst).parent.parent == out:  # a capture landing in the session
            if crash_at == "second capture" and moved:
                raise _Crash
            moved.append(dst)
        real_replace(src, dst)

    def rmtree_crash(path, *args, **kwargs):
        if crash_at == "clean-up" and Path(path).name == ".s.import-partial":
            raise _Crash
        real_rmtree(path, *args, **kwargs)

    monkeypatch.setattr(importer.os, "replace", replace_then_crash)
    monkeypatch.setattr(importer.shutil, "rmtree", rmtree_crash)
    args = ([more.rgbd_bag, more.stereo_bag], out, ImportParams(clock_offset_ms=more.clock_offset_ms))
    with pytest.raises(_Crash):
        import_recordings(*args, add=True)
    assert (tmp_path / ".s.import-partial" / ".landing").is_file()
    monkeypatch.setattr(importer.os, "replace", real_replace)
    monkeypatch.setattr(importer.shutil, "rmtree", real_rmtree)
    s = import_recordings(*args, add=True)  # the same command again
    assert s.captures == ["board/001", "scenes/000"] and "cut off" in " ".join(s.warnings)
    runs = ImportRecord.read(out / "import.json").runs
    assert [r.capture for run in runs for r in run.pairs] == ["board/000", "board/001", "scenes/000"]
    assert sorted(f"{k}/{x.name}" for k in ("board", "scenes") for x in (out / k).iterdir()) == \
        ["board/000", "board/001", "scenes/000"]
    assert not (tmp_path / ".s.import-partial").exists()
    for c in ("board/001", "scenes/000"):  # each landed whole: the recordings' frames (hand-laid board/001, scenes/000)
        for f in CAPTURE_FILES:
            assert (out / c / f).read_bytes() == (hand / c / f).read_bytes(), f"{c}/{f}"
    with pytest.raises(InputError, match="import.json"):  # and once done, a third time is refused as ever
        import_recordings(*args, add=True)


def test_a_cut_off_landing_is_finished_and_said_when_another_import_adds(hand, recs, tmp_path, monkeypatch):
    """The next import --add of other recordings finishes the cut-off landing first and says so in its warnings (it
    was silent, its table counting only its own captures; a run-through)."""
    import gtforge.importer as importer

    out = tmp_path / "s"
    import_recordings([recs.rgbd_bag, recs.stereo_bag], out, ImportParams(clock_offset_ms=recs.clock_offset_ms,
                                                                           max_captures=1))
    more = write_ros2_recordings(hand, tmp_path / "more", captures=["board/001", "scenes/000"], seed=1)
    other = write_ros2_recordings(hand, tmp_path / "other", captures=["scenes/001"], seed=2)
    real_replace, moved = os.replace, []

    def replace_then_crash(src, dst):
        if Path(dst).parent.parent == out:
            if moved:
                raise _Crash
            moved.append(dst)
        real_replace(src, dst)

    monkeypatch.setattr(importer.os, "replace", replace_then_crash)
    with pytest.raises(_Crash):
        import_recordings([more.rgbd_bag, more.stereo_bag], out, ImportParams(clock_offset_ms=more.clock_offset_ms),
                          add=True)
    monkeypatch.setattr(importer.os, "replace", real_replace)
    # meanwhile a stage reading the session (calibrate, run, build-dataset) is refused: board/001 is in it, scenes/000
    # beside it, and import.json lists neither (they were read as the session's before)
    from gtforge.io.captures import open_session
    with pytest.raises(InputError, match=r"session whose last import --add landed whole, got one cut off while "
                       r"its captures landed .*\.s\.import-partial holds the rest.*run the same gtforge import "
                       r"--add again"):
        open_session(out)
    s = import_recordings([other.rgbd_bag, other.stereo_bag], out,
                          ImportParams(clock_offset_ms=other.clock_offset_ms), add=True)
    assert s.captures == ["scenes/001"]
    open_session(out)
    note = [w for w in s.warnings if "cut off while its captures landed: finished first" in w]
    assert len(note) == 1 and "(board/001, scenes/000)" in note[0], s.warnings
    runs = ImportRecord.read(out / "import.json").runs
    assert [r.capture for run in runs for r in run.pairs] == ["board/000", "board/001", "scenes/000", "scenes/001"]
    assert not (tmp_path / ".s.import-partial").exists()


@pytest.fixture(scope="module")
def more(hand, tmp_path_factory):
    """Other recordings of the same rig: board/001 and scenes/000 again, on other clocks (for --add)."""
    return write_ros2_recordings(hand, tmp_path_factory.mktemp("more"), captures=["board/001", "scenes/000"], seed=1)


def test_add_writes_where_and_as_the_session_names_its_captures(hand, recs, more, tmp_path, monkeypatch):
    """--add into a session whose session.yaml names its own folders and files (board_dir, scenes_dir, files): the
    captures went into new board/ and scenes/ folders as 2DImage.png, DepthMap.tiff, left.png, right.png, which the
    session never reads (a run-through). Now they land in its folders under its names, import.json names them so, and
    a landing cut off and finished by the next import counts them by those folders."""
    import gtforge.importer as importer
    from gtforge.io.captures import FileNames, SessionFile, open_session

    out = tmp_path / "s"
    import_recordings([recs.rgbd_bag, recs.stereo_bag], out, ImportParams(clock_offset_ms=recs.clock_offset_ms))
    names = {"2DImage.png": "tex.png", "DepthMap.tiff": "depth/d.tiff", "left.png": "L.png", "right.png": "R.png"}
    for kind, folder in (("board", "boards"), ("scenes", "fruit")):
        os.rename(out / kind, out / folder)
        for cap in (out / folder).iterdir():
            (cap / "depth").mkdir()
            for a, b in names.items():
                os.rename(cap / a, cap / b)
    sf = SessionFile.read(out / "session.yaml")
    sf.model_copy(update={"board_dir": "boards", "scenes_dir": "fruit", "files": FileNames(
        mech_texture="tex.png", mech_depth="depth/d.tiff", zed_left="L.png", zed_right="R.png")}).write(
        out / "session.yaml")
    real_replace, moved = os.replace, []

    def replace_then_crash(src, dst):
        if Path(dst).parent.parent == out:  # a capture landing in the session
            if moved:
                raise _Crash
            moved.append(dst)
        real_replace(src, dst)

    monkeypatch.setattr(importer.os, "replace", replace_then_crash)
    args = ([more.rgbd_bag, more.stereo_bag], out, ImportParams(clock_offset_ms=more.clock_offset_ms))
    with pytest.raises(_Crash):
        import_recordings(*args, add=True)
    monkeypatch.setattr(importer.os, "replace", real_replace)
    s = import_recordings(*args, add=True)  # finishes the landing
    assert (s.captures, s.boards, s.scenes) == (["boards/002", "fruit/002"], 1, 1)
    assert sorted(x.name for x in out.iterdir() if x.is_dir()) == ["boards", "fruit"]
    runs = ImportRecord.read(out / "import.json").runs
    assert [r.capture for r in runs[1].pairs] == ["boards/002", "fruit/002"]
    for mine, theirs in (("boards/002", "board/001"), ("fruit/002", "scenes/000")):
        assert sorted(str(x.relative_to(out / mine)) for x in (out / mine).rglob("*") if x.is_file()) == \
            sorted(names.values())
        for a, b in names.items():
            if a != "DepthMap.tiff":
                assert (out / mine / b).read_bytes() == (hand / theirs / a).read_bytes(), f"{mine}/{b}"
    session = open_session(out)
    assert [d.name for d in session.capture_dirs("board")] == ["000", "001", "002"]
    a, b = session.load_capture(out / "fruit" / "002").depth_mm, read_depth(hand / "scenes" / "000" / "DepthMap.tiff")
    assert np.array_equal(np.isnan(a), np.isnan(b)) and np.nanmax(np.abs(a - b) / b) <= 1.2e-7
    # a depth encoding import does not write (16-bit PNG): refused before anything is written
    sf = SessionFile.read(out / "session.yaml")
    sf.model_copy(update={"files": sf.files.model_copy(update={"mech_depth": "d.png"}), "depth_scale_mm": 0.1}).write(
        out / "session.yaml")
    before = sorted(x.relative_to(out) for x in out.rglob("*"))
    other = write_ros2_recordings(hand, tmp_path / "other", captures=["scenes/001"], seed=2)
    with pytest.raises(InputError) as err:
        import_recordings([other.rgbd_bag, other.stereo_bag], out, ImportParams(clock_offset_ms=other.clock_offset_ms),
                          add=True)
    assert str(err.value).startswith(f"{out / 'session.yaml'} [files.mech_depth]: expected float32 mm TIFF depth")
    assert sorted(x.relative_to(out) for x in out.rglob("*")) == before


def test_add_refuses_another_board_and_a_board_found_nowhere_is_warned_of(hand, recs, more, tmp_path):
    """--add with board options other than the session's board sorted every board capture into the scenes, silently
    (a run-through); now refused, naming both boards. An import whose captures show no board at all warns, naming the
    board it looked for."""
    from gtforge.core.targets.models import BoardModel

    out = tmp_path / "s"
    import_recordings([recs.rgbd_bag, recs.stereo_bag], out, ImportParams(clock_offset_ms=recs.clock_offset_ms,
                                                                           max_captures=1))
    before = {x.relative_to(out): x.read_bytes() for x in out.rglob("*") if x.is_file()}
    r = gtforge("import", more.rgbd_bag, more.stereo_bag, "-o", out, "--add", "--cols", "10",
                "--clock-offset-ms", str(more.clock_offset_ms))
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert f"{out / 'session.yaml'} [board]: expected the session's board (checkerboard 12 x 9 inner corners, 20 mm " \
        "squares), got checkerboard 10 x 9 inner corners, 20 mm squares (the board options)" in r.stderr, r.stderr
    assert "drop the board options to use the session's board, or import into a new session" in r.stderr
    assert {x.relative_to(out): x.read_bytes() for x in out.rglob("*") if x.is_file()} == before
    assert not list(tmp_path.glob(".*import-partial"))
    # the session's own board, declared: taken as ever
    s = import_recordings([more.rgbd_bag, more.stereo_bag], out, ImportParams(
        clock_offset_ms=more.clock_offset_ms, board=BoardModel(cols=12, rows=9)), add=True)
    assert (s.captures, s.boards, s.scenes) == (["board/001", "scenes/000"], 1, 1)
    assert not [w for w in s.warnings if "no capture showed the board" in w]
    # a new session with a board the recording never shows: every capture a scene, and a warning says why
    s = import_recordings([recs.rgbd_bag, recs.stereo_bag], tmp_path / "t", ImportParams(
        clock_offset_ms=recs.clock_offset_ms, board=BoardModel(cols=14, rows=11)))
    assert (s.boards, s.scenes) == (0, 4)
    assert "no capture showed the board (checkerboard 14 x 11 inner corners, 20 mm squares): all 4 went to scenes/; " \
        "if the recording has board captures, check --cols/--rows/--square-mm (and --board)" in s.warnings


def test_zed_sdk_export_folder_with_the_depth_recording(hand, tmp_path):
    recs = write_ros2_recordings(hand, tmp_path / "rec", zed_export=True, motion_frames=3, seed=2)
    assert (recs.stereo_bag / "left000000.png").is_file()
    out = tmp_path / "session"
    r = gtforge("import", recs.rgbd_bag, recs.stereo_bag, "-o", out, "--fps", "15",
                "--zed-calibration", hand / "zed_calibration.yaml")
    assert r.returncode == 0, r.stderr
    run = ImportRecord.read(out / "import.json").runs[0]
    assert run.clock_offset_source == "motion events"
    assert abs(run.clock_offset_ms - recs.clock_offset_ms) < 1000 / 15 / 2
    _same_session(hand, out, [p.capture for p in run.pairs])
    from gtforge.io.ros_recordings import Topics

    with pytest.raises(InputError, match="--zed-calibration"):
        import_recordings([recs.rgbd_bag, recs.stereo_bag], tmp_path / "s2", topics=Topics(fps=15.0))
    assert not (tmp_path / "s2").exists()


def test_a_zed_calibration_with_a_ros_stereo_pair_is_refused_not_ignored(hand, recs, tmp_path):
    """A ROS stereo pair's camera_info is its calibration: a --zed-calibration beside it would be silently unused."""
    from gtforge.io.ros_recordings import Topics

    with pytest.raises(InputError) as err:
        import_recordings([recs.rgbd_bag, recs.stereo_bag], tmp_path / "s", ImportParams(max_captures=1),
                          topics=Topics(zed_calibration=hand / "zed_calibration.yaml"))
    assert str(err.value).startswith(f"{hand / 'zed_calibration.yaml'} [--zed-calibration]: expected a ZED .svo2")
    assert "has its own camera_info" in str(err.value) and "leave --zed-calibration out" in str(err.value)
    assert not (tmp_path / "s").exists()


def test_depth_topic_named_with_a_separate_stereo_bag(hand, recs, tmp_path):
    """--depth-topic with the depth and the stereo camera in two bags: the depth bag's topic is taken (the stereo bag,
    which lacks it, stopped the import: 'expected an image topic'); a topic neither bag has is refused by name."""
    from gtforge.io.ros_recordings import Topics

    p = ImportParams(clock_offset_ms=recs.clock_offset_ms, max_captures=1)
    s = import_recordings([recs.rgbd_bag, recs.stereo_bag], tmp_path / "s", p,
                          topics=Topics(depth="/camera/camera/aligned_depth_to_color/image_raw"))
    assert s.captures == ["board/000"]
    for f in ("2DImage.png", "left.png"):
        assert (tmp_path / "s" / "board" / "000" / f).read_bytes() == (hand / "board" / "000" / f).read_bytes()
    with pytest.raises(InputError, match="depth"):
        import_recordings([recs.rgbd_bag, recs.stereo_bag], tmp_path / "t", p, topics=Topics(depth="/nope"))
    assert not (tmp_path / "t").exists()


def test_every_and_no_classify(recs, tmp_path):
    s = import_recordings([recs.rgbd_bag, recs.stereo_bag], tmp_path / "s",
                          ImportParams(clock_offset_ms=recs.clock_offset_ms, every=2, classify=False))
    assert s.captures == ["scenes/000", "scenes/001"] and s.dropped["every/max"] == 2
    t_left = [p.t_left_ns for p in ImportRecord.read(tmp_path / "s" / "import.json").runs[0].pairs]
    assert t_left == sorted(t_left)


def test_add_refuses_recordings_of_another_rig(hand, recs, tmp_path):
    """--add with a depth camera whose camera_info differs from the session's texture camera: one line, exit 2, the
    session unchanged."""
    from gtforge.core.camera import CameraFile

    out = tmp_path / "session"
    import_recordings([recs.rgbd_bag, recs.stereo_bag], out, ImportParams(clock_offset_ms=recs.clock_offset_ms,
                                                                          max_captures=1))
    before = {x.relative_to(out): x.read_bytes() for x in out.rglob("*") if x.is_file()}
    cam = CameraFile.read(hand / "mech_intrinsics.yaml").camera
    other = write_ros2_recordings(hand, tmp_path / "other", captures=["board/000"],
                                  info_camera=cam.model_copy(update={"fx_px": cam.fx_px * 1.01}))
    r = gtforge("import", other.rgbd_bag, other.stereo_bag, "-o", out, "--add")
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "texture camera" in r.stderr and "mech_intrinsics.yaml" in r.stderr and "new session" in r.stderr
    assert {x.relative_to(out): x.read_bytes() for x in out.rglob("*") if x.is_file()} == before
    assert not list(tmp_path.glob(".*import-partial"))


@pytest.fixture(scope="module")
def raw_zed_session(request):
    return synthetic_session(request, RAW_ZED)


@pytest.fixture(scope="module")
def svo_import(raw_zed_session, tmp_path_factory):
    """The raw-ZED session recorded as an RGB-D bag and a ZED .svo2 (H.264), imported through the command with its
    SN12345.conf."""
    pytest.importorskip("mcap")
    d = tmp_path_factory.mktemp("svo")
    recs = write_ros2_recordings(raw_zed_session, d / "rec", svo2_codec="h264")
    r = gtforge("import", recs.rgbd_bag, recs.stereo_bag, "-o", d / "session", "--zed-calibration",
                raw_zed_session / "SN12345.conf", "--clock-offset-ms", recs.clock_offset_ms)
    return recs, d / "session", r


@pytest.mark.slow
def test_svo2_imports_the_raw_images_with_the_conf(raw_zed_session, svo_import, tmp_path):
    from gtforge.io.captures import SessionFile
    from gtforge.io.formats import read_image

    recs, out, r = svo_import
    assert r.returncode == 0, r.stderr
    assert "warning: the ZED images come from lossy H.264/H.265 video" in r.stderr + r.stdout
    sf = SessionFile.read(out / "session.yaml")
    assert (sf.zed_calibration, sf.zed_rectified) == ("SN12345.conf", False)
    assert (out / "SN12345.conf").read_bytes() == (raw_zed_session / "SN12345.conf").read_bytes()
    run = ImportRecord.read(out / "import.json").runs[0]
    assert run.serials == {"stereo": "12345"} and run.streams["left"] == "Camera_SN12345/side_by_side:left"
    captures = [p.capture for p in run.pairs]
    assert sorted(captures) == ["board/000", "board/001", "board/002", "board/003", "scenes/000"]
    psnr = []
    for c in captures:
        assert (out / c / "2DImage.png").read_bytes() == (raw_zed_session / c / "2DImage.png").read_bytes()
        a, b = read_depth(out / c / "DepthMap.tiff"), read_depth(raw_zed_session / c / "DepthMap.tiff")
        assert np.array_equal(np.isnan(a), np.isnan(b)) and np.nanmax(np.abs(a - b) / b) <= 1.2e-7
        for f in ("left.png", "right.png"):
            a, b = read_image(out / c / f).astype(float), read_image(raw_zed_session / c / f).astype(float)
            assert a.shape == b.shape == (376, 672, 3)
            psnr.append(10 * np.log10(255 ** 2 / np.mean((a - b) ** 2)))
    print(f"svo2 (H.264, crf 23) left/right PSNR against the PNGs: {min(psnr):.1f}-{max(psnr):.1f} dB")
    assert 33.0 < min(psnr) and max(psnr) < 60.0  # lossy, but the same images
    # the log times of the .svo2 are the stereo clock of import.json
    assert {p.t_left_ns for p in run.pairs} <= set(int(t) for t in recs.stereo_times_ns)
    # --add with another unit's recording: refused by its serial
    other = write_ros2_recordings(raw_zed_session, tmp_path / "other", captures=["scenes/000"], svo2_codec="h264",
                                  svo2_serial=999)
    conf = tmp_path / "SN999.conf"
    shutil.copy(raw_zed_session / "SN12345.conf", conf)
    r = gtforge("import", other.rgbd_bag, other.stereo_bag, "-o", out, "--add", "--zed-calibration", conf)
    assert r.returncode == 2 and one_line_error(r), r.stderr
    assert "serials.stereo" in r.stderr and "12345" in r.stderr and "999" in r.stderr


@pytest.mark.slow
def test_svo2_import_calibrate_build_measures_the_lossy_video(raw_zed_session, svo_import, tmp_path):
    """import -> calibrate -> build-dataset from the .svo2: the extrinsic and the ground truth against the exact
    truth, and what the lossy video costs verification: the hand-laid and the imported session built with one
    calibration have the same ground truth (it comes from the depth), and differ only in their ZED images."""
    from gtforge.build_dataset import build_dataset
    from gtforge.calibrate import calibrate
    from gtforge.io.formats import read_pfm
    from gtforge.records.calibration import CalibrateParams
    from gtforge.records.verification import VerificationResult
    from gtforge.synthetic import SyntheticTruth

    _, imported, r = svo_import
    assert r.returncode == 0, r.stderr
    res = calibrate(imported, tmp_path / "calibration.yaml", CalibrateParams(leave_one_out=False))
    assert res.zed_conf.reading == "neg-all" and res.rectification.overall.fit_mean_abs_px <= 0.05
    T_zed_from_mech_true = np.array(SyntheticTruth.read(raw_zed_session / "truth" / "rig_truth.yaml").T_zed_from_mech)
    dt_mm = float(np.abs(res.rig.T_zed_from_mech[:3, 3] - T_zed_from_mech_true[:3, 3]).max())
    gt, ver = {}, {}
    for name, sess in (("hand", raw_zed_session), ("svo2", imported)):
        out = tmp_path / f"ds_{name}"
        assert build_dataset(sess, tmp_path / "calibration.yaml", out, workers=1).built == ["000"]
        gt[name] = read_pfm(out / "scenes" / "000" / "disp0GT.pfm")
        ver[name] = VerificationResult.read(out / "verification.json").scenes["000"]
    assert np.array_equal(gt["hand"], gt["svo2"], equal_nan=True)  # the GT does not see the ZED images
    truth = np.load(raw_zed_session / "truth" / "scene_000.npz")["zed_disparity_px"]
    ok = np.isfinite(gt["svo2"]) & np.isfinite(truth)
    epe = float(np.abs(gt["svo2"] - truth)[ok].mean())
    h, s = ver["hand"], ver["svo2"]
    print(f"svo2 chain: extrinsic max |dt| {dt_mm:.3f} mm, EPE to truth {epe:.4f} px; verification hand-laid vs svo2: "
          f"texture ZNCC {h.texture_all.correlation:.3f} vs {s.texture_all.correlation:.3f}, shift "
          f"{h.texture_all.magnitude_px:.3f} vs {s.texture_all.magnitude_px:.3f} px (noise "
          f"{h.texture_all.dx_noise_px:.4f} vs {s.texture_all.dx_noise_px:.4f}), stereo bad-match "
          f"{h.stereo['all'].bad_match_pct:.3f} vs {s.stereo['all'].bad_match_pct:.3f} %, disparity bias noise "
          f"{h.stereo['all'].disparity_bias_noise_px:.4f} vs {s.stereo['all'].disparity_bias_noise_px:.4f} px")
    assert dt_mm < 1.0 and epe < 0.05
    assert s.status == h.status == "ok"
    # the lossy images: less alike after alignment, more bad stereo matches, noisier figures
    assert s.texture_all.correlation < h.texture_all.correlation
    assert s.stereo["all"].bad_match_pct > h.stereo["all"].bad_match_pct
    assert s.stereo["all"].disparity_bias_noise_px > h.stereo["all"].disparity_bias_noise_px


def test_scenes_imported_without_fruit_ids_are_said_to_count_as_fruit_each(hand, recs, tmp_path):
    """Two scenes imported are two fruit to build-dataset's splits unless session.yaml's fruit_ids groups them: one
    fruit turned between captures could land in train and test, and nothing said so (a run-through). Said once an
    import, of the new scenes fruit_ids does not name."""
    import yaml

    out = tmp_path / "s"
    s = import_recordings([recs.rgbd_bag, recs.stereo_bag], out, ImportParams(clock_offset_ms=recs.clock_offset_ms))
    assert s.scenes == 2
    said = [w for w in s.warnings if "fruit_ids" in w]
    assert said == ["the 2 new scenes count as 2 fruit in build-dataset's splits: where several show one fruit "
                    "(turned or moved between captures), name its fruit for each in session.yaml's fruit_ids, or "
                    "that fruit can land in both train and test"]
    two = write_ros2_recordings(hand, tmp_path / "two", captures=["scenes/000", "scenes/001"], seed=5)
    cfg = yaml.safe_load((out / "session.yaml").read_text())
    cfg["fruit_ids"] = {"002": "melon1"}  # the next import's first new scene, named beforehand: one left ungrouped
    (out / "session.yaml").write_text(yaml.safe_dump(cfg))
    s = import_recordings([two.rgbd_bag, two.stereo_bag], out, ImportParams(clock_offset_ms=two.clock_offset_ms),
                          add=True)
    assert s.captures == ["scenes/002", "scenes/003"] and not [w for w in s.warnings if "fruit_ids" in w]
