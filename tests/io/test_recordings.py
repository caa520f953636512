"""Recordings read as gtforge reads captures (gtforge.io.recordings): the real Azure Kinect .mkv against the frames
extracted from it (../shared/data/azure-kinect-frame), the real RealSense .bag against its own camera_info, a
librealsense >= 2.49 bag (4 bytes after each Image), and the ROS encodings one by one."""
from __future__ import annotations

import re
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import shared_data

pytest.importorskip("rosbags")
pytest.importorskip("av")

from gtforge.errors import InputError
from gtforge.io.formats import read_image
from gtforge.io.recordings import (
    Bag,
    camera_from_info,
    decode_compressed,
    decode_image,
    depth_mm,
    read_kinect_mkv,
    read_realsense,
    stereo_from_infos,
)
from gtforge.io.vendors import read_kinect_calibration

RS_BAG = "realsense_d435_single_depth_color_640x480.bag"


def test_azure_kinect_mkv_matches_the_extracted_frame():
    rec_dir, frame_dir = shared_data("recordings"), shared_data("azure-kinect-frame")
    r = read_kinect_mkv(rec_dir / "azure_kinect_recording.mkv")
    assert [len(s.frames) for s in (r.depth, r.texture, r.ir)] == [1, 1, 1]
    # device time: the track's 463,945 us (pyk4a's test of this file: the playback's length) plus the recording's
    # start offset, 336,277 us (its start_timestamp_offset_usec)
    assert r.depth.frames[0].t_ns == r.texture.frames[0].t_ns == 463_945_000 + 336_277_000
    assert "frame times: device time (track time + K4A_START_OFFSET_NS 336277000 ns)" in r.notes
    depth = r.depth.frames[0].decode()
    png = read_image(frame_dir / "depth_nfov_unbinned_mm.png")
    assert depth.dtype == np.float32 and np.array_equal(np.isnan(depth), png == 0)
    assert np.array_equal(np.nan_to_num(depth).astype(np.uint16), png)  # b16g big-endian, lossless
    assert np.array_equal(r.ir.frames[0].decode(), read_image(frame_dir / "ir_nfov_unbinned.png"))
    color = r.texture.frames[0].decode()
    jpg = read_image(frame_dir / "color_720p.jpg")
    assert color.shape == jpg.shape and np.abs(color.astype(int) - jpg).mean() < 1.0  # the same JPEG
    k = read_kinect_calibration(frame_dir / "calibration.json", "NFOV_UNBINNED", "720P")
    assert r.depth_camera == k.depth and r.texture_camera == k.color
    assert np.allclose(r.T_texture_from_depth, k.T_color_from_depth, atol=0, rtol=0)
    assert r.kinect_modes == ("NFOV_UNBINNED", "720P")


@pytest.mark.parametrize("name", ["azure_kinect_recording.mkv", RS_BAG])
def test_a_truncated_recording_is_one_line_naming_the_size_it_declares(tmp_path, name):
    """A copy of a real recording cut anywhere: one line naming the file, the size the file itself declares (the
    Matroska Segment's size; a ROS 1 bag's index position and index records) and the size there is. Was: an .mkv cut
    where only its IR frame was missing imported with a warning (exit 0), one cut at its start said 'got OSError',
    and a .bag 'AnyReaderError: Bag index looks damaged'."""
    data = (shared_data("recordings") / name).read_bytes()
    from gtforge.io.recordings import check_not_truncated, expected_size_bytes

    assert expected_size_bytes(shared_data("recordings") / name)[0] == len(data)  # the whole file: all it declares
    check_not_truncated(shared_data("recordings") / name)
    index_pos = 997_561  # the bag's header: its index starts there, 36,521 bytes of index records after it
    for size in (1_000, len(data) // 2, len(data) * 9 // 10, len(data) - 100, len(data) - 1):
        cut = tmp_path / f"cut{Path(name).suffix}"
        cut.write_bytes(data[:size])
        with pytest.raises(InputError) as e:
            read_kinect_mkv(cut) if name.endswith(".mkv") else Bag(cut)
        if name.endswith(".mkv"):
            declared = f"{len(data)} bytes (its Matroska Segment's size)"
        elif size < index_pos:
            declared = f"at least {index_pos} bytes (its header's index_pos: the index starts there)"
        else:  # cut inside the index: its size, or as far as the records left can be followed
            m = re.search(r"expected (at least )?(\d+) bytes \((the end of )?the index records its header counts\)",
                          str(e.value))
            assert m and (int(m[2]) == len(data) if m[3] else size < int(m[2]) <= len(data)), str(e.value)
            declared = m[0].removeprefix("expected ")
        assert str(e.value).startswith(f"{cut} [size]: expected {declared}, got {size} bytes (truncated) (hint: the "
                                       "file was cut short"), str(e.value)
        assert "\n" not in str(e.value)


def test_a_damaged_jpeg_frame_is_refused_and_an_intact_one_decodes_as_opencv_does(tmp_path):
    """The real Kinect recording's MJPEG colour frame decodes exactly as OpenCV decodes it (the same libjpeg-turbo
    decoding); a copy of the recording with 4 KiB of that frame zeroed (a damaged disk block) is one line naming the
    file, the track and libjpeg's complaint. Before, OpenCV printed 'Corrupt JPEG data' on stderr and the damaged
    picture was imported as the capture's texture."""
    import av

    src = shared_data("recordings") / "azure_kinect_recording.mkv"
    with av.open(str(src)) as c:
        jpg = next(bytes(p) for p in c.demux([s for s in c.streams if s.metadata.get("title") == "COLOR"]) if p.size)
    ref = cv2.cvtColor(cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    assert np.array_equal(read_kinect_mkv(src).texture.frames[0].decode(), ref)
    data = bytearray(src.read_bytes())
    at = data.find(jpg[:4096])
    assert at > 0 and data.count(jpg[:4096]) == 1
    mid = at + len(jpg) // 2
    data[mid:mid + 4096] = bytes(4096)
    damaged = tmp_path / "damaged.mkv"
    damaged.write_bytes(bytes(data))
    rec = read_kinect_mkv(damaged)  # (the index and the depth frame are intact)
    assert rec.depth.frames[0].decode().shape == (576, 640)
    with pytest.raises(InputError) as e:
        rec.texture.frames[0].decode()
    assert str(e.value).startswith(f"{damaged} [COLOR]: expected an intact JPEG frame, got libjpeg: Corrupt JPEG "
                                   "data"), str(e.value)
    assert "copy it again from the recorder" in str(e.value) and "\n" not in str(e.value)


def test_compressed_jpeg_colour_and_grey_and_a_damaged_one():
    """A ROS CompressedImage JPEG: colour as RGB, grey as one channel, both as OpenCV decodes them; bytes lost from
    the middle of one refused (libjpeg's 'premature end of data segment'), where OpenCV returned the picture."""
    yy, xx = np.mgrid[0:240, 0:320]
    smooth = np.dstack([xx, yy, (xx + yy) // 2]).astype(np.uint8)
    for img in (smooth, smooth[..., 1].copy()):
        enc = cv2.imencode(".jpg", img[..., ::-1] if img.ndim == 3 else img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1]
        ocv = cv2.imdecode(enc, cv2.IMREAD_UNCHANGED)
        got = decode_compressed(_Msg(format="jpeg", data=enc), "f.bag", "/cam/image/compressed")
        assert np.array_equal(got, ocv[..., ::-1] if ocv.ndim == 3 else ocv) and got.shape == img.shape
        cut = np.concatenate([enc[:len(enc) // 2], enc[len(enc) // 2 + 100:]])
        assert cv2.imdecode(cut, cv2.IMREAD_UNCHANGED) is not None  # OpenCV: a picture (and a warning on stderr)
        with pytest.raises(InputError, match=r"^f\.bag \[/cam/image/compressed\]: expected an intact JPEG frame, got "
                                             r"libjpeg: Corrupt JPEG data"):
            decode_compressed(_Msg(format="jpeg", data=cut), "f.bag", "/cam/image/compressed")


def test_a_truncated_mcap_is_one_line_naming_its_missing_closing_magic(tmp_path):
    """A ROS 2 .mcap (alone or in its rosbag2 folder) cut short: one line naming the closing magic bytes it lacks
    and its size (was 'got AnyReaderError: File end magic is invalid.')."""
    pytest.importorskip("mcap")
    from mcap.writer import Writer

    from gtforge.io.recordings import check_not_truncated

    whole = tmp_path / "whole.mcap"
    with open(whole, "wb") as f:
        w = Writer(f)
        w.start()
        ch = w.register_channel(topic="/camera/depth/image_raw", message_encoding="cdr", schema_id=0)
        for k in range(20):
            w.add_message(ch, log_time=k, publish_time=k, data=bytes(500))
        w.finish()
    check_not_truncated(whole)
    data = whole.read_bytes()
    folder = tmp_path / "bag"
    folder.mkdir()
    for size in (20, len(data) // 2, len(data) - 1):
        (folder / "cut.mcap").write_bytes(data[:size])
        for given, named in ((folder / "cut.mcap", folder / "cut.mcap"), (folder, folder / "cut.mcap")):
            with pytest.raises(InputError) as e:
                Bag(given)
            assert str(e.value).startswith(f"{named} [size]: expected an MCAP file that ends in its closing magic "
                                           "bytes (89 4d 43 41 50 30 0d 0a, written when the recorder closes the "
                                           f"file), got {size} bytes that end without them (truncated, or never "
                                           "closed) (hint: "), str(e.value)


def test_ctrl_c_while_a_bag_is_read_stays_ctrl_c(monkeypatch):
    """The command's Ctrl-C (``Interrupted``, raised by its SIGINT handler wherever the code is) inside a bag's reader:
    the reader's ``except Exception`` made it one line of bad input, 'expected a sensor_msgs/msg/Image message, got
    Interrupted: ...', exit 2 (a run-through: Ctrl-C mid-import). Now it passes through, as KeyboardInterrupt does."""
    from gtforge.errors import INTERRUPTED, Interrupted

    assert not issubclass(Interrupted, Exception)

    def interrupted(*args, **kwargs):
        raise Interrupted(INTERRUPTED)

    bag = Bag(shared_data("recordings") / RS_BAG)
    try:
        conn = next(c for c in bag.reader.connections if c.msgtype == "sensor_msgs/msg/Image")
        raw = next(r for c, _, r in bag.reader.messages(connections=[conn]))
        monkeypatch.setattr(bag.reader, "deserialize", interrupted)
        with pytest.raises(Interrupted):
            bag.deserialize(raw, conn, lenient=True)
        monkeypatch.setattr(bag.reader, "messages", interrupted)
        with pytest.raises(Interrupted):
            list(bag.messages([conn.topic]))
    finally:
        bag.close()


def test_realsense_bag_depth_in_mm_and_intrinsics_match_its_camera_info():
    path = shared_data("recordings") / RS_BAG
    bag = Bag(path)
    try:
        r = read_realsense(bag)
        infos = {t: bag.first(t) for t in bag.topics if t.endswith("/info/camera_info")}
        raw = None
        for conn, _, data in bag.messages(["/device_0/sensor_0/Depth_0/image/data"]):
            raw = decode_image(bag.deserialize(data, conn), path, conn.topic)
            break
        depth = r.depth.frames[0].decode()  # frames decode while the bag is open
        color = r.texture.frames[0].decode()
    finally:
        bag.close()
    d_info = infos["/device_0/sensor_0/Depth_0/info/camera_info"]
    c_info = infos["/device_0/sensor_1/Color_0/info/camera_info"]
    for cam, info in ((r.depth_camera, d_info), (r.texture_camera, c_info)):
        assert (cam.width_px, cam.height_px) == (info.width, info.height)
        assert np.array_equal(cam.K, np.asarray(info.K, np.float64).reshape(3, 3))
    assert [len(r.depth.frames), len(r.texture.frames)] == [2, 1]
    assert raw.dtype == np.uint16 and depth.shape == (480, 640)
    # depth units 0.001 m per count: the counts are mm, 0 invalid
    assert np.array_equal(np.nan_to_num(depth).astype(np.uint16), raw)
    assert 300 < np.nanmedian(depth) < 5000
    assert color.shape == (480, 640, 3)
    # the colour camera sits ~15 mm along the depth camera's x axis (D435)
    T_texture_from_depth = r.T_texture_from_depth
    assert 10 < T_texture_from_depth[0, 3] < 20 and np.allclose(
        T_texture_from_depth[:3, :3] @ T_texture_from_depth[:3, :3].T, np.eye(3), atol=1e-9)


def _ros1_bag(path, extra_bytes: bool):
    """A librealsense-layout ROS 1 bag, 4 bytes after each Image when ``extra_bytes`` (librealsense >= 2.49)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    types = ts.types
    depth = (np.arange(48, dtype=np.uint16).reshape(6, 8) * 10 + 500)
    color = np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3)

    def header(t):
        return types["std_msgs/msg/Header"](seq=0, stamp=types["builtin_interfaces/msg/Time"](sec=t, nanosec=5),
                                            frame_id="")

    def image(t, a, enc):
        data = a.view(np.uint8).reshape(-1)
        return types["sensor_msgs/msg/Image"](header=header(t), height=6, width=8, encoding=enc, is_bigendian=0,
                                              step=data.size // 6, data=data)

    def info(fx):
        roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return types["sensor_msgs/msg/CameraInfo"](header=header(0), height=6, width=8,
                                                   distortion_model="Brown Conrady",
                                                   D=np.zeros(5), K=np.array([fx, 0, 4, 0, fx, 3, 0, 0, 1.0]),
                                                   R=np.zeros(9), P=np.zeros(12), binning_x=0, binning_y=0, roi=roi)
    with Writer(path) as w:
        def put(topic, msgtype, msg, t=1):
            c = w.add_connection(topic, msgtype, typestore=ts)
            data = bytes(ts.serialize_ros1(msg, msgtype))
            w.write(c, t * 1_000_000_000, data + (struct.pack("<f", 0.001) if extra_bytes and "Image" in msgtype
                                                  else b""))
        put("/device_0/sensor_0/Depth_0/image/data", "sensor_msgs/msg/Image", image(1, depth, "mono16"))
        put("/device_0/sensor_1/Color_0/image/data", "sensor_msgs/msg/Image", image(1, color, "rgb8"))
        put("/device_0/sensor_0/Depth_0/info/camera_info", "sensor_msgs/msg/CameraInfo", info(10.0))
        put("/device_0/sensor_1/Color_0/info/camera_info", "sensor_msgs/msg/CameraInfo", info(12.0))
        put("/device_0/sensor_0/option/Depth_Units/value", "std_msgs/msg/Float32",
            types["std_msgs/msg/Float32"](data=1e-4))
    return depth, color


@pytest.mark.parametrize("extra_bytes", [False, True])
def test_realsense_bag_from_librealsense_2_49_reads_too(tmp_path, extra_bytes):
    depth, color = _ros1_bag(tmp_path / "rs.bag", extra_bytes)
    bag = Bag(tmp_path / "rs.bag")
    try:
        r = read_realsense(bag)
        d = r.depth.frames[0].decode()
        c = r.texture.frames[0].decode()
    finally:
        bag.close()
    assert r.depth.frames[0].t_ns == 1_000_000_005
    assert np.allclose(d, depth * np.float32(0.1))  # Depth_Units 1e-4 m per count: 0.1 mm
    assert np.array_equal(c, color) and r.T_texture_from_depth is None
    assert r.depth_camera.fx_px == 10.0 and r.texture_camera.fx_px == 12.0


class _Msg:
    def __init__(self, **kw):
        self.__dict__.update(kw)


def test_image_encodings():
    rgb = np.random.default_rng(0).integers(0, 255, (5, 7, 3), dtype=np.uint8)

    def msg(a, enc, big=False, pad=0):
        rows = a.reshape(a.shape[0], -1).view(np.uint8)
        rows = np.hstack([rows, np.zeros((a.shape[0], pad), np.uint8)])
        return _Msg(encoding=enc, is_bigendian=int(big), height=a.shape[0], width=a.shape[1], step=rows.shape[1],
                    data=rows.ravel())
    assert np.array_equal(decode_image(msg(rgb, "rgb8", pad=3), "f", "t"), rgb)
    assert np.array_equal(decode_image(msg(np.ascontiguousarray(rgb[..., ::-1]), "bgr8"), "f", "t"), rgb)
    bgra = np.dstack([rgb[..., ::-1], np.full(rgb.shape[:2], 255, np.uint8)])
    assert np.array_equal(decode_image(msg(bgra, "bgra8"), "f", "t"), rgb)
    d16 = np.arange(35, dtype=np.uint16).reshape(5, 7) * 300
    assert np.array_equal(decode_image(msg(d16.astype(">u2"), "16UC1", big=True), "f", "t"), d16)
    f32 = (d16 / 1000).astype(np.float32)
    assert np.array_equal(decode_image(msg(f32, "32FC1", pad=4), "f", "t"), f32)
    with pytest.raises(InputError, match="truncated"):
        m = msg(rgb, "rgb8")
        m.data = m.data[:-10]
        decode_image(m, "f", "t")
    with pytest.raises(InputError, match="yuv422"):
        decode_image(msg(rgb, "yuv422"), "f", "t")


def test_an_image_that_is_no_depth_map_is_refused_as_depth():
    """A mono8 or colour image named as depth had its grey levels taken for millimetres (a run-through); now refused,
    naming the topic and what came. 16-bit unsigned and float depth are read as ever."""
    grey = np.full((4, 5), 200, np.uint8)
    for a, what in ((grey, "uint8, 1 channel"), (np.dstack([grey] * 3), "uint8, 3 channels"),
                    (grey.astype(np.int16), "int16, 1 channel")):
        with pytest.raises(InputError) as err:
            depth_mm(a, "mm", 1.0, "rec.bag", "/cam/depth")
        assert str(err.value) == ("rec.bag [/cam/depth]: expected a depth image (one channel, 16-bit unsigned or "
                                  f"float), got {what} (hint: is this the depth topic? name it with --depth-topic)")
    assert np.array_equal(depth_mm(grey.astype(np.uint16), "mm", 1.0, "f", "t"), np.full((4, 5), 200, np.float32))
    assert np.allclose(depth_mm(np.full((4, 5), 0.5, np.float32), "m", 1.0, "f", "t"), 500.0)


def test_compressed_and_compressed_depth():
    rgb = np.random.default_rng(1).integers(0, 255, (6, 9, 3), dtype=np.uint8)
    png = cv2.imencode(".png", rgb[..., ::-1])[1]
    assert np.array_equal(decode_compressed(_Msg(format="png", data=png), "f", "t"), rgb)
    d16 = (np.arange(54, dtype=np.uint16).reshape(6, 9) + 400)
    body = struct.pack("<iff", 0, 0.0, 0.0) + cv2.imencode(".png", d16)[1].tobytes()
    out = decode_compressed(_Msg(format="16UC1; compressedDepth png", data=np.frombuffer(body, np.uint8)), "f", "t")
    assert np.array_equal(out, d16)


def test_camera_info_models_and_stereo_baseline():
    def info(model, D, P=None, w=640, h=480):
        K = [500.0, 0, 320, 0, 500, 240, 0, 0, 1]
        return _Msg(distortion_model=model, D=np.asarray(D, float), K=np.asarray(K), width=w, height=h,
                    P=np.asarray(P if P is not None else [500.0, 0, 320, 0, 0, 500, 240, 0, 0, 0, 1, 0]))
    assert camera_from_info(info("plumb_bob", [0.1, 0, 0, 0, 0]), "f", "t").dist_coeffs[0] == 0.1
    assert len(camera_from_info(info("rational_polynomial", [0.1] * 8), "f", "t").dist_coeffs) == 8
    with pytest.raises(InputError, match="equidistant"):
        camera_from_info(info("equidistant", [0.1] * 4), "f", "t")
    right = info("plumb_bob", [0] * 5, [500.0, 0, 322, -500 * 0.063, 0, 500, 240, 0, 0, 0, 1, 0])
    s = stereo_from_infos(info("plumb_bob", [0] * 5), right, "f", ("l", "r"))
    assert s.baseline_mm == pytest.approx(63.0) and s.doffs_px == pytest.approx(2.0)
    with pytest.raises(InputError, match="rectified right camera"):
        stereo_from_infos(info("plumb_bob", [0] * 5), info("plumb_bob", [0] * 5), "f", ("l", "r"))


def test_raw_stereo_topics_are_rectified_with_their_camera_info():
    from gtforge.io.ros_recordings import _rectify_map

    K = np.array([[300.0, 0, 80], [0, 300, 60], [0, 0, 1]])
    D = np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
    img = np.random.default_rng(2).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    img = cv2.GaussianBlur(img, (7, 7), 2)
    info = _Msg(K=K.ravel(), D=D, R=np.eye(3).ravel(), P=np.c_[K, np.zeros(3)].ravel(), width=160, height=120)
    out = _rectify_map(info)(img)
    ref = cv2.undistort(img, K, D)
    assert np.abs(out.astype(int) - ref)[10:-10, 10:-10].mean() < 1.0
    info.D = np.zeros(5)
    assert _rectify_map(info) is None  # nothing to undo


def test_topic_choice_lists_the_candidates_and_svo_version_1_is_refused_with_a_hint(tmp_path):
    from gtforge.io.recordings import DEPTH_TOPICS, LEFT_TOPICS
    from gtforge.io.ros_recordings import open_recordings

    bag = object.__new__(Bag)
    bag.path = tmp_path / "x.mcap"
    img = "sensor_msgs/msg/Image"
    bag.topics = {"/zed/zed_node/left/image_rect_color": img, "/zed2/zed_node/left/image_rect_color": img,
                  "/camera/camera/depth/image_rect_raw": img, "/camera/camera/depth/image_rect_raw/compressedDepth":
                  "sensor_msgs/msg/CompressedImage", "/camera/camera/depth/camera_info": "sensor_msgs/msg/CameraInfo"}
    with pytest.raises(InputError, match="/zed/zed_node/left/image_rect_color, /zed2/zed_node") as e:
        bag.match(LEFT_TOPICS, role="left")
    assert "--left-topic" in str(e.value)
    assert bag.match(DEPTH_TOPICS, role="depth") == "/camera/camera/depth/image_rect_raw"  # raw before compressed
    (tmp_path / "a.svo").write_bytes(b"x")  # version 1: another container
    with pytest.raises(InputError, match="ZED_SVO_Export"):
        open_recordings([tmp_path / "a.svo"])


@pytest.mark.parametrize("name", ["rec.mkv", "rec.svo2", "rec.SVO"])
def test_a_folder_under_a_one_file_recordings_name_is_one_line_saying_so(tmp_path, name):
    """A folder named like an Azure Kinect .mkv or a ZED .svo2 / .svo: one line saying a folder came where the
    recording file was expected (before: 'got IsADirectoryError (hint: the file may be truncated)' for a .mkv, the
    same after the calibration check for an .svo2, 'an .svo that is no .svo2' for an .svo)."""
    from gtforge.io.ros_recordings import Topics, open_recordings

    (tmp_path / name).mkdir()
    conf = tmp_path / "SN1.conf"
    conf.write_text("[STEREO]\n")
    with pytest.raises(InputError) as e:
        open_recordings([tmp_path / name], Topics(zed_calibration=conf))
    assert e.value.file == str(tmp_path / name) and e.value.actual == "a folder"
    assert "one file" in e.value.expected and "ZED SDK export folder" in e.value.hint
    assert list((tmp_path / name).iterdir()) == []


def test_one_recording_named_twice_is_one_line_naming_it(tmp_path):
    """The same recording given twice (as written, or through a link): one line naming it, before either is read
    (it said 'recordings: expected one depth recording and at most one stereo recording, got 2 depth, 0 stereo (hint:
    import them one pair at a time)', naming no file, after reading both)."""
    from gtforge.io.ros_recordings import open_recordings

    rec = tmp_path / "rec.mkv"
    rec.write_bytes(b"\x1a\x45\xdf\xa3 not read")  # never opened: the refusal comes first
    (tmp_path / "link.mkv").symlink_to(rec)
    for second, also in ((rec, ""), (tmp_path / "link.mkv", f" (also as {rec})")):
        with pytest.raises(InputError) as e:
            open_recordings([rec, second])
        assert e.value.file == str(second) and e.value.actual == "the same recording twice" + also
        assert "each once" in e.value.hint


def test_depth_not_aligned_to_colour_gets_its_pose_from_tf_static(tmp_path):
    """realsense-ros without align_depth: depth/image_rect_raw on the depth camera, the pose from /tf_static's tree."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from gtforge.core.camera import PinholeCamera
    from gtforge.core.geometry import invert_T
    from gtforge.io.ros_recordings import open_recordings
    from gtforge.synthetic_recordings import _header, _image, _info

    ts = get_typestore(Stores.ROS2_HUMBLE)
    types = ts.types
    cam = PinholeCamera.from_K(np.array([[50.0, 0, 16], [0, 50, 12], [0, 0, 1]]), 32, 24, np.zeros(0))
    dcam = cam.model_copy(update={"fx_px": 45.0, "fy_px": 45.0})
    depth = np.full((24, 32), 800, np.uint16)
    color = np.zeros((24, 32, 3), np.uint8)

    def tf(parent, child, xyz, q):
        return types["geometry_msgs/msg/TransformStamped"](
            header=_header(ts, 0, parent), child_frame_id=child,
            transform=types["geometry_msgs/msg/Transform"](
                translation=types["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
                rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))
    opt = (-0.5, 0.5, -0.5, 0.5)  # camera_*_frame -> optical frame (x forward -> z forward)
    tfs = [tf("camera_link", "camera_depth_frame", (0, 0, 0), (0, 0, 0, 1)),
           tf("camera_depth_frame", "camera_depth_optical_frame", (0, 0, 0), opt),
           tf("camera_link", "camera_color_frame", (0.0005, 0.015, 0.0001), (0, 0, 0.0087265, 0.9999619)),
           tf("camera_color_frame", "camera_color_optical_frame", (0, 0, 0), opt)]
    with Writer(tmp_path / "rs", version=9) as w:
        def put(topic, msgtype, msg):
            c = w.add_connection(topic, msgtype, typestore=ts)
            w.write(c, 1, ts.serialize_cdr(msg, msgtype))
        put("/tf_static", "tf2_msgs/msg/TFMessage", types["tf2_msgs/msg/TFMessage"](transforms=tfs))
        for ns, frame, img, enc, c in (("depth", "camera_depth_optical_frame", depth, "16UC1", dcam),
                                       ("color", "camera_color_optical_frame", color, "rgb8", cam)):
            put(f"/camera/camera/{ns}/image_rect_raw" if ns == "depth" else "/camera/camera/color/image_raw",
                "sensor_msgs/msg/Image", _image(ts, 5, frame, img, enc))
            put(f"/camera/camera/{ns}/camera_info", "sensor_msgs/msg/CameraInfo", _info(ts, 5, frame, c))
    o = open_recordings([tmp_path / "rs"])
    try:
        from gtforge.io.recordings import quat_T_mm

        def Tq(xyz, q):
            return quat_T_mm(types["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
                             types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        T_link_from_depth = Tq((0, 0, 0), (0, 0, 0, 1)) @ Tq((0, 0, 0), opt)
        T_link_from_color = Tq((0.0005, 0.015, 0.0001), (0, 0, 0.0087265, 0.9999619)) @ Tq((0, 0, 0), opt)
        expected = invert_T(T_link_from_color) @ T_link_from_depth
        assert np.allclose(o.rgbd.T_texture_from_depth, expected, atol=1e-9)
        assert abs(o.rgbd.T_texture_from_depth[0, 3] - 15.0) < 0.2  # the colour camera 15 mm to the depth's left
        assert o.rgbd.depth_camera == dcam and np.nanmedian(o.rgbd.depth.frames[0].decode()) == 800
    finally:
        o.close()


def test_kinect_colour_formats():
    from gtforge.io.recordings import _kinect_color

    rgb = np.random.default_rng(3).integers(0, 255, (8, 12, 3), dtype=np.uint8)
    bgra = np.dstack([rgb[..., ::-1], np.full((8, 12), 255, np.uint8)])
    assert np.array_equal(_kinect_color(bgra.tobytes(), "BGRA", 12, 8, "f"), rgb)
    nv12 = cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_I420)  # same planes as NV12 for a flat check of the shape
    assert _kinect_color(nv12.tobytes(), "NV12", 12, 8, "f").shape == (8, 12, 3)
    yuy2 = np.zeros((8, 12, 2), np.uint8) + 128
    assert _kinect_color(yuy2.tobytes(), "YUY2", 12, 8, "f").shape == (8, 12, 3)
    smooth = np.dstack([*np.meshgrid(np.arange(16) * 10, np.arange(16) * 12), np.full((16, 16), 90)]).astype(np.uint8)
    jpg = cv2.imencode(".jpg", smooth[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes()
    assert np.abs(_kinect_color(jpg, "MJPG", 16, 16, "f").astype(int) - smooth).mean() < 3
    assert np.array_equal(_kinect_color(jpg, "", 16, 16, "f"), _kinect_color(jpg, "MJPG", 16, 16, "f"))
    with pytest.raises(InputError, match="MJPG, NV12"):
        _kinect_color(b"\x00" * 10, "H264", 12, 8, "f")
    # the SDK's player knows BGRA only: an RGBA tag (its channels the other way round) or a frame of BGRA's size under
    # another tag is refused, not decoded with BGRA's channel order
    for tag in ("RGBA", ""):
        with pytest.raises(InputError, match=f"COLOR codec.*'{tag}'"):
            _kinect_color(bgra.tobytes(), tag, 12, 8, "f")
    # a frame cut short: one line naming the format and both sizes, not numpy's reshape error
    with pytest.raises(InputError, match=r"COLOR frame \(NV12, 12x8\).*144 bytes.*100 bytes"):
        _kinect_color(nv12.tobytes()[:100], "NV12", 12, 8, "f")


# ---- ZED .svo2 (gtforge.io.zed_svo) ---------------------------------------------------------------------------
def _svo2_frames(n: int, w: int = 96, h: int = 64):
    """``n`` (t_ns, left, right) frames of a smooth grey texture moving 1 px per frame; right = left shifted 5 px."""
    rng = np.random.default_rng(1)
    grey = cv2.resize(rng.integers(0, 255, (h // 8, (w + 64) // 8), dtype=np.uint8), (w + 64, h),
                      interpolation=cv2.INTER_LINEAR)
    tex = np.dstack([grey] * 3)
    return [(5_000_000_000 + k * 66_666_667, tex[:, 8 + k:8 + k + w].copy(), tex[:, 13 + k:13 + k + w].copy())
            for k in range(n)]


@pytest.mark.parametrize("codec", ["h264", "hevc"])
def test_svo2_frames_decode_from_their_keyframe_at_their_log_time(tmp_path, codec):
    pytest.importorskip("mcap")
    from gtforge.io.recordings import iter_frames
    from gtforge.io.zed_svo import read_zed_svo2
    from gtforge.synthetic import default_raw_zed, write_raw_zed_conf
    from gtforge.synthetic_recordings import write_svo2

    frames = _svo2_frames(20, 672, 376)  # a VGA eye: the SN.conf's resolution
    path = write_svo2(tmp_path / "r.svo2", frames, codec=codec, serial=777, gop=8)
    conf = write_raw_zed_conf(tmp_path / "SN777.conf", default_raw_zed(), "neg-x")
    rec = read_zed_svo2(path, conf)
    assert rec.serial == "777" and not rec.rectified and rec.calibration_file == conf and rec.warnings
    assert [f.t_ns for f in rec.left.frames] == [t for t, _, _ in frames] == [f.t_ns for f in rec.right.frames]
    svo = rec.left.source
    assert svo.codec == codec and [k for k, key in enumerate(svo.keyframe) if key] == [0, 8, 16]
    wanted = [(rec.left, 19), (rec.right, 11), (rec.left, 3), (rec.left, 11)]
    batch = {(s.name, k): a for s, k, a in iter_frames(wanted)}
    for s, k in wanted:
        alone = next(iter_frames([(s, k)]))[2]  # decoded from its own keyframe: the same image
        assert np.array_equal(alone, batch[(s.name, k)])
        truth = frames[k][1 if s is rec.left else 2]
        assert alone.shape == truth.shape
        err = np.abs(alone.astype(int) - truth).mean()
        assert 0 < err < 3.0, (s.name, k, err)  # lossy, close; the other eye would be 5 px off
        assert np.abs(alone.astype(int) - frames[k][2 if s is rec.left else 1]).mean() > 2 * err


def test_svo2_bad_files_are_one_line_errors(tmp_path):
    pytest.importorskip("mcap")
    from mcap.writer import Writer

    from gtforge.io.zed_svo import read_zed_svo2
    from gtforge.synthetic import default_raw_zed, write_raw_zed_conf
    from gtforge.synthetic_recordings import write_svo2

    conf = write_raw_zed_conf(tmp_path / "SN12345.conf", default_raw_zed(), "neg-x")
    good = write_svo2(tmp_path / "good.svo2", _svo2_frames(3, 672, 376), serial=12345)
    cases = {}
    cut = tmp_path / "cut.svo2"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    cases[cut] = "truncated"
    for name, topic, payload in (("other.svo2", "Camera_SN12345/sensors", b"{}"),
                                 ("lossless.svo2", "Camera_SN12345/side_by_side", bytes(range(200)))):
        with open(tmp_path / name, "wb") as f:
            w = Writer(f)
            w.start()
            ch = w.register_channel(topic=topic, message_encoding="zed_sdk_encoded", schema_id=0)
            w.add_message(ch, log_time=1, publish_time=1, data=payload)
            w.finish()
    cases[tmp_path / "other.svo2"] = "side_by_side"
    cases[tmp_path / "lossless.svo2"] = "LOSSLESS"
    for path, words in cases.items():
        with pytest.raises(InputError, match=words) as e:
            read_zed_svo2(path, conf)
        assert "\n" not in str(e.value)
    with pytest.raises(InputError, match="SN12345.conf") as e:  # another unit's conf
        read_zed_svo2(good, write_raw_zed_conf(tmp_path / "SN999.conf", default_raw_zed(), "neg-x"))
    assert "serial" in str(e.value)
    with pytest.raises(InputError, match="--zed-calibration"):
        read_zed_svo2(good, None)
    # an SVO2 named .svo is read as one; a version-1 .svo is refused (test_topic_choice_...)
    from gtforge.io.ros_recordings import Topics, open_recordings

    renamed = tmp_path / "renamed.svo"
    renamed.write_bytes(good.read_bytes())
    with pytest.raises(InputError, match="depth recording"):  # read as a stereo recording: no depth camera named
        open_recordings([renamed], Topics(zed_calibration=conf))


def test_realsense_extrinsic_direction_puts_depth_edges_on_colour_edges():
    """The real D435 bag's ``Color_0/tf/0`` is read as ``T_color_from_depth``: its depth silhouettes, rendered into
    the colour camera with it, land on the colour image's edges; with its inverse (or the rotation transposed) they
    do not (docs/capture-layout.md states the figures)."""
    from gtforge.core.alignment.edge_features import depth_edges, edge_offset_px, edge_strength, undistort_image
    from gtforge.core.geometry import invert_T, make_T
    from gtforge.io.recordings import iter_frames

    bag = Bag(shared_data("recordings") / RS_BAG)
    try:
        r = read_realsense(bag)
        depths = [a for _, _, a in iter_frames([(r.depth, k) for k in range(len(r.depth.frames))])]
        color = next(iter_frames([(r.texture, 0)]))[2]
    finally:
        bag.close()
    assert r.serial == "728612070259"
    T_texture_from_depth = r.T_texture_from_depth
    image, pinhole = undistort_image(color, r.texture_camera)
    strength = edge_strength(image, 1.5)
    offsets = {}
    candidates = {"as read": T_texture_from_depth, "inverse": invert_T(T_texture_from_depth),
                  "rotation transposed": make_T(T_texture_from_depth[:3, :3].T, T_texture_from_depth[:3, 3])}
    for name, cand in candidates.items():
        offsets[name] = [edge_offset_px(depth_edges(d, r.depth_camera, cand, pinhole), cand, pinhole, strength)
                         for d in depths]
    print({k: [round(o.magnitude_px, 2) for o in v] for k, v in offsets.items()})
    assert all(o.interior and o.magnitude_px < 2.0 for o in offsets["as read"])
    for name in ("inverse", "rotation transposed"):
        assert all(o.magnitude_px > 5.0 for o in offsets[name]), name


def test_zed_sdk_export_folder_bgra_pngs_with_an_sn_conf(tmp_path):
    """A ZED SDK export folder (``left%06d.png`` / ``right%06d.png`` as ZED_SVO_Export writes them, BGRA): RGB frames at
    ``i / fps``, a left image without its right left out, the SN.conf's rectified pair (the images are the SDK's
    rectified ones: ``rectified`` stays True)."""
    from gtforge.io.cameras import read_zed_conf
    from gtforge.io.ros_recordings import is_zed_export, read_zed_export
    from gtforge.synthetic import default_raw_zed, write_raw_zed_conf

    rng = np.random.default_rng(4)
    folder = tmp_path / "export"
    folder.mkdir()
    images = {}
    for i in (0, 1, 2, 3):
        for side in ("left", "right") if i < 3 else ("left",):
            rgb = rng.integers(0, 255, (376, 672, 3), dtype=np.uint8)
            cv2.imwrite(str(folder / f"{side}{i:06d}.png"), np.dstack([rgb[..., ::-1], np.full((376, 672), 255,
                                                                                                np.uint8)]))
            images[side, i] = rgb
    conf = write_raw_zed_conf(tmp_path / "SN10027514.conf", default_raw_zed(), "neg-x")
    assert is_zed_export(folder) and not is_zed_export(tmp_path)
    rec = read_zed_export(folder, 15.0, conf)
    assert [f.t_ns for f in rec.left.frames] == [0, 66_666_667, 133_333_333] == [f.t_ns for f in rec.right.frames]
    for i in range(3):
        assert np.array_equal(rec.left.frames[i].decode(), images["left", i])
        assert np.array_equal(rec.right.frames[i].decode(), images["right", i])
    assert rec.stereo == read_zed_conf(conf, 672).rectification().stereo
    assert rec.calibration_file == conf and rec.rectified
