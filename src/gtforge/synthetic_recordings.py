"""A synthetic session recorded as ROS 2 bags (``.mcap`` or ``.db3``): the exact captures of a hand-laid session
(``gtforge.synthetic.generate_session``) played as two cameras' streams, each on its own clock, for
``gtforge import`` to turn back into that session (tests/stages/test_import.py).

The depth camera's bag holds what realsense-ros records (``/camera/camera/color/image_raw`` rgb8,
``/camera/camera/aligned_depth_to_color/image_raw`` 32FC1 metres or 16UC1 mm, their camera_info); the stereo
camera's what zed-ros2-wrapper records (``/zed/zed_node/{left,right}/image_rect_color`` bgra8 and camera_info, P of
the rectified pair), or a ZED SDK export folder, or a ZED ``.svo2`` (``write_svo2``: the layout of
gtforge.io.zed_svo, the session's left|right images as H.264/H.265 video; a raw-ZED session,
``gtforge.synthetic.generate_raw_zed_session``, gives raw images as a real ``.svo2`` holds). The timeline: every
capture held still for ``still_frames`` frames, then ``motion_frames`` frames of the rig moving (the images
shifted), except after the captures in ``jumps``: there the next capture follows at once (a scene moved between two
frames, no motion frames). Both cameras run at ``fps`` with their own clock origin, a phase offset and timing
jitter."""
from __future__ import annotations

import base64
import json
import struct
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from gtforge.core.camera import CameraFile, PinholeCamera, StereoCalibrationFile
from gtforge.io.captures import read_depth, read_texture
from gtforge.io.formats import read_image

RGBD_TOPICS = {"color": "/camera/camera/color", "depth": "/camera/camera/aligned_depth_to_color"}
ZED_TOPICS = {"left": "/zed/zed_node/left", "right": "/zed/zed_node/right"}


@dataclass
class RecordingsTruth:
    rgbd_bag: Path
    stereo_bag: Path
    clock_offset_ms: float  # stereo clock minus depth clock (the true one)
    captures: list[str]  # the hand-laid capture (board/000 ...) of every still stretch, in time order
    frame_capture: list[str | None] = field(default_factory=list)  # per frame: the capture shown, None in motion
    stereo_times_ns: list[int] = field(default_factory=list)  # per frame: its time on the stereo camera's clock


def _ros_types():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def _header(ts, t_ns: int, frame_id: str):
    types = ts.types
    return types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=int(t_ns // 1_000_000_000),
                                                                                  nanosec=int(t_ns % 1_000_000_000)),
                                        frame_id=frame_id)


def _image(ts, t_ns: int, frame_id: str, a: np.ndarray, encoding: str):
    a = np.ascontiguousarray(a)
    h, w = a.shape[:2]
    data = a.view(np.uint8).reshape(-1)
    return ts.types["sensor_msgs/msg/Image"](header=_header(ts, t_ns, frame_id), height=h, width=w,
                                             encoding=encoding, is_bigendian=0, step=data.size // h, data=data)


def _info(ts, t_ns: int, frame_id: str, cam: PinholeCamera, P: np.ndarray | None = None):
    types = ts.types
    D = np.asarray(cam.dist_coeffs, np.float64)
    model = "rational_polynomial" if D.size == 8 else "plumb_bob"
    D = D if D.size in (5, 8) else np.zeros(5)
    K = np.array([[cam.fx_px, 0, cam.cx_px], [0, cam.fy_px, cam.cy_px], [0, 0, 1.0]])
    P = np.c_[K, np.zeros(3)] if P is None else P
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return types["sensor_msgs/msg/CameraInfo"](header=_header(ts, t_ns, frame_id), height=cam.height_px,
                                               width=cam.width_px, distortion_model=model, d=D, k=K.ravel(),
                                               r=np.eye(3).ravel(), p=P.ravel(), binning_x=0, binning_y=0, roi=roi)


def _shifted(a: np.ndarray, px: int) -> np.ndarray:
    return np.roll(a, px, axis=1)


def write_ros2_recordings(session_dir: str | Path, out_dir: str | Path, *, storage: str = "mcap", fps: float = 15.0,
                          still_frames: int = 4, motion_frames: int = 2, jumps: tuple[int, ...] = (),
                          depth_clock_s: float = 1000.0, stereo_clock_s: float = 4321.0, phase_ms: float = 7.0,
                          jitter_ms: float = 2.0, depth_encoding: str = "32FC1", seed: int = 0,
                          captures: list[str] | None = None, info_camera: PinholeCamera | None = None,
                          zed_export: bool = False, svo2_codec: str | None = None,
                          svo2_serial: int = 12345) -> RecordingsTruth:
    """Write ``out_dir/rgbd`` and ``out_dir/zed`` (rosbag2 folders) from the hand-laid session ``session_dir``.

    ``captures``: these capture folders only (``board/000``...; default all, boards first); ``info_camera``: the
    depth camera's camera_info says this camera instead of the session's (a wrong file, for the error tests);
    ``zed_export``: the stereo camera as a ZED SDK export folder instead (``out_dir/zed/left%06d.png`` ... BGRA, its
    clock: frame index / fps) beside the session's ``zed_calibration.yaml``; ``svo2_codec`` ('h264' or 'hevc'): the
    stereo camera as a ZED ``out_dir/zed.svo2`` instead (``write_svo2``: the session's left|right images, raw for a
    raw-ZED session, as lossy video)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    session_dir, out_dir = Path(session_dir), Path(out_dir)
    ts = _ros_types()
    rng = np.random.default_rng(seed)
    mech = CameraFile.read(session_dir / "mech_intrinsics.yaml").camera
    caps = captures or [f"{k}/{p.name}" for k in ("board", "scenes") for p in sorted((session_dir / k).glob("[0-9]*"))]
    # the timeline: per frame, the capture shown and the image shift (0 = still)
    timeline: list[tuple[str, int]] = []
    for i, c in enumerate(caps):
        timeline += [(c, 0)] * still_frames
        if i not in jumps and i < len(caps) - 1:
            timeline += [(c, 9 * (j + 1)) for j in range(motion_frames)]
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    period = 1e9 / fps
    t_true = np.arange(len(timeline)) * period
    t_depth = (depth_clock_s * 1e9 + t_true + rng.uniform(-jitter_ms, jitter_ms, t_true.size) * 1e6).astype(np.int64)
    t_zed = (stereo_clock_s * 1e9 + t_true + phase_ms * 1e6
             + rng.uniform(-jitter_ms, jitter_ms, t_true.size) * 1e6).astype(np.int64)
    ros_stereo = not zed_export and svo2_codec is None
    if ros_stereo:
        zed = StereoCalibrationFile.read(session_dir / "zed_calibration.yaml").zed
        P_left = np.array([[zed.left.fx_px, 0, zed.left.cx_px, 0], [0, zed.left.fy_px, zed.left.cy_px, 0],
                           [0, 0, 1, 0]])
        P_right = P_left.copy()
        P_right[0, 2] += zed.doffs_px
        P_right[0, 3] = -zed.left.fx_px * zed.baseline_mm / 1000.0
        right_cam = zed.left.model_copy(update={"cx_px": zed.left.cx_px + zed.doffs_px})
    cache: dict[str, dict[str, np.ndarray]] = {}

    def load(c):
        if c not in cache:
            d = session_dir / c
            cache.clear()
            cache[c] = dict(tex=read_texture(d / "2DImage.png"), depth=read_depth(d / "DepthMap.tiff"),
                            left=read_image(d / "left.png"), right=read_image(d / "right.png"))
        return cache[c]

    if zed_export:
        import cv2

        (out_dir / "zed").mkdir(parents=True)
        for k, (c, shift) in enumerate(timeline):
            a = load(c)
            for side in ("left", "right"):
                img = _shifted(a[side], shift)
                cv2.imwrite(str(out_dir / "zed" / f"{side}{k:06d}.png"),
                            np.dstack([img[..., ::-1], np.full(img.shape[:2], 255, np.uint8)]))
        stereo_clock_s, phase_ms = 0.0, 0.0
    stereo_path = out_dir / "zed"
    if svo2_codec is not None:
        stereo_path = out_dir / "zed.svo2"
        out_dir.mkdir(parents=True, exist_ok=True)
        write_svo2(stereo_path, ((int(t_zed[k]), _shifted(load(c)["left"], s), _shifted(load(c)["right"], s))
                                 for k, (c, s) in enumerate(timeline)), codec=svo2_codec, serial=svo2_serial, fps=fps)
    for name, topics in (("rgbd", RGBD_TOPICS),) + ((("zed", ZED_TOPICS),) if ros_stereo else ()):
        with Writer(out_dir / name, version=9, storage_plugin=plugin) as w:
            conns = {}
            for role, ns in topics.items():
                conns[role] = w.add_connection(f"{ns}/image_raw" if name == "rgbd" else f"{ns}/image_rect_color",
                                               "sensor_msgs/msg/Image", typestore=ts)
                conns[role + "_info"] = w.add_connection(f"{ns}/camera_info", "sensor_msgs/msg/CameraInfo",
                                                         typestore=ts)
            for k, (c, shift) in enumerate(timeline):
                a = load(c)
                if name == "rgbd":
                    t = int(t_depth[k])
                    depth = _shifted(a["depth"], shift)
                    if depth_encoding == "32FC1":
                        depth, enc = (depth / np.float32(1000.0)).astype(np.float32), "32FC1"
                    else:
                        depth, enc = np.nan_to_num(np.round(depth), nan=0).astype(np.uint16), depth_encoding
                    tex = _shifted(a["tex"], shift)
                    msgs = {"color": _image(ts, t, "camera_color_optical_frame", tex,
                                            "rgb8" if tex.ndim == 3 else "mono8"),
                            "depth": _image(ts, t, "camera_color_optical_frame", depth, enc),
                            "color_info": _info(ts, t, "camera_color_optical_frame", info_camera or mech),
                            "depth_info": _info(ts, t, "camera_color_optical_frame", info_camera or mech)}
                else:
                    t = int(t_zed[k])

                    def bgra(img):
                        return np.dstack([img[..., 2::-1], np.full(img.shape[:2], 255, np.uint8)])

                    msgs = {"left": _image(ts, t, "zed_left_camera_optical_frame", bgra(_shifted(a["left"], shift)),
                                           "bgra8"),
                            "right": _image(ts, t, "zed_left_camera_optical_frame",
                                            bgra(_shifted(a["right"], shift)), "bgra8"),
                            "left_info": _info(ts, t, "zed_left_camera_optical_frame", zed.left, P_left),
                            "right_info": _info(ts, t, "zed_right_camera_optical_frame", right_cam, P_right)}
                for role, m in msgs.items():
                    w.write(conns[role], t + 1000, ts.serialize_cdr(m, m.__msgtype__))
    return RecordingsTruth(out_dir / "rgbd", stereo_path, (stereo_clock_s - depth_clock_s) * 1e3 + phase_ms,
                           caps, [c if s == 0 else None for c, s in timeline],
                           [int(round(k * 1e9 / fps)) for k in range(len(timeline))] if zed_export else t_zed.tolist())


# ---- ZED .svo2 (gtforge.io.zed_svo: the layout and what it rests on) ---------------------------------------------
SVO2_TRAILER = struct.Struct("<IIIiiiQIiiIi4x")  # 56 bytes: width, height, 0x5c002c00, 1, 2, -1, t_ns, video bytes,
#                                                 frame type (3 keyframe, 0 other), last keyframe, frame index, 0


def write_svo2(path: str | Path, frames, *, codec: str = "h264", serial: int = 12345, fps: float = 15.0,
               crf: int = 23, gop: int = 15) -> Path:
    """An SVO2-layout MCAP from ``(t_ns, left, right)`` RGB frames: ``svo_header`` (JSON: the SDK version and a
    base64 128-byte header with width, height, serial, fps), ``Camera_SN<serial>/side_by_side`` (each left|right
    image one H.264/H.265 access unit, Annex B, low-latency encoding without B-frames: an 8-byte size prefix, the
    video bytes, a 56-byte trailer; log time = the frame's time) and ``svo_footer`` (JSON: the frames' times).
    ``crf``: the encoder's quality (libx264/libx265's default 23; lower is better). The IMU channels are left out."""
    import av  # optional dependencies (gtforge[recordings]): imported where used
    from mcap.writer import Writer

    path = Path(path)
    topic = f"Camera_SN{serial}/side_by_side"
    times: list[int] = []
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="gtforge synthetic (SVO2 layout)")
        js = w.register_schema(name="sl_type", encoding="jsonschema", data=b"{}")
        vs = w.register_schema(name=topic, encoding="zed_sdk_encoded", data=b"")
        hdr = w.register_channel(topic="svo_header", message_encoding="json", schema_id=js)
        sbs = w.register_channel(topic=topic, message_encoding="zed_sdk_encoded", schema_id=vs)
        ftr = w.register_channel(topic="svo_footer", message_encoding="json", schema_id=js)
        ctx = None
        last_key = 0
        for k, (t, left, right) in enumerate(frames):
            img = np.ascontiguousarray(np.concatenate([left, right], axis=1))
            if ctx is None:
                if img.shape[0] % 2 or img.shape[1] % 2:  # 4:2:0 video, as the ZED SDK records, needs even sizes
                    raise ValueError(f"write_svo2 needs an even image size (ZED resolutions are), got "
                                     f"{img.shape[1]}x{img.shape[0]} side by side")
                ctx = av.CodecContext.create("libx264" if codec == "h264" else "libx265", "w")
                ctx.width, ctx.height, ctx.pix_fmt = img.shape[1], img.shape[0], "yuv420p"
                ctx.time_base, ctx.framerate = Fraction(1, 1000), Fraction(fps).limit_denominator(1000)
                ctx.gop_size = gop
                ctx.thread_count = 1  # one core: the tests share the machine (and one thread is deterministic)
                ctx.options = ({"preset": "veryfast", "tune": "zerolatency", "crf": str(crf)} if codec == "h264" else
                               {"preset": "veryfast", "tune": "zerolatency", "crf": str(crf),
                                "x265-params": "log-level=error:bframes=0:pools=1:frame-threads=1"})
                head = struct.pack("<9I", img.shape[1], img.shape[0], serial, int(round(fps)), 0, 8, 0, 1000, 2001)
                head += bytes(128 - len(head))
                w.add_message(hdr, log_time=t, publish_time=t, data=json.dumps(
                    {"ZED_SDK_version": "4.2.0", "header": base64.b64encode(head).decode()}).encode())
            frame = av.VideoFrame.from_ndarray(img, format="rgb24")
            frame.pts = k
            packets = ctx.encode(frame)
            if len(packets) != 1:
                raise RuntimeError(f"the encoder returned {len(packets)} packets for frame {k} (expected one)")
            video = bytes(packets[0])
            key = bool(packets[0].is_keyframe)
            last_key = k if key else last_key
            trailer = SVO2_TRAILER.pack(img.shape[1], img.shape[0], 0x5C002C00, 1, 2, -1, t, len(video),
                                        3 if key else 0, last_key, k, 0)
            w.add_message(sbs, log_time=t, publish_time=t,
                          data=struct.pack("<II", len(video) + len(trailer), len(video)) + video + trailer)
            times.append(t)
        w.add_message(ftr, log_time=times[-1], publish_time=times[-1], data=json.dumps({topic: times}).encode())
        w.finish()
    return path
