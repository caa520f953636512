"""Sensor recordings as streams of timestamped frames: ROS 1 / ROS 2 bags (``rosbags``, no ROS needed), RealSense
``.bag`` (librealsense's ROS 1 layout, lenient about the 4 bytes librealsense >= 2.49 appends to each Image) and
Azure Kinect ``.mkv`` (PyAV). What a recording holds, not what a session makes of it: ``gtforge.importer`` pairs the
frames and writes the session (docs/capture-layout.md, "From recordings").

Frames decode lazily: a bag (or a Kinect .mkv) is indexed once (timestamps only, nothing kept in memory), then read
again for the frames a step needs (``iter_frames``: one pass per recording for every stream asked for;
``Frame.decode()``: one frame). In memory, as everywhere in gtforge: depth float32 mm with NaN invalid, colour RGB
uint8."""
from __future__ import annotations

import re
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from gtforge.core.camera import DIST_LENGTHS, PinholeCamera, RectifiedStereo
from gtforge.core.geometry import make_T
from gtforge.errors import InputError
from gtforge.io.vendors import kinect_calibration_from_dict

EXTRA = "gtforge[recordings]"
BAG_SUFFIXES = (".bag", ".db3", ".mcap")

# Topic defaults, most specific first (zed-ros2-wrapper 4.x and 5.x, realsense-ros 4.x with and without the doubled
# namespace, ROS 1 wrappers); a user's --*-topic replaces the list. ``*`` matches one or more name components.
LEFT_TOPICS = ("*/left/image_rect_color", "*/left/color/rect/image", "*/left/image_rect_gray", "*/left/image_rect",
               "*/left/image_raw")
RIGHT_TOPICS = ("*/right/image_rect_color", "*/right/color/rect/image", "*/right/image_rect_gray",
                "*/right/image_rect", "*/right/image_raw")
DEPTH_TOPICS = ("*/aligned_depth_to_color/image_raw", "*/depth/image_rect_raw", "*/depth/image_raw",
                "*/depth_registered/image_raw", "*/depth/depth_registered", "*/depth/image", "*/Depth_0/image/data")
COLOR_TOPICS = ("*/color/image_raw", "*/color/image_rect_color", "*/rgb/image_raw", "*/rgb/image_rect_color",
                "*/Color_0/image/data")
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


@dataclass
class Frame:
    t_ns: int  # the device's stamp (header.stamp, Kinect device time): the recording's own clock
    decode: Callable[[], np.ndarray]
    ordinal: int = -1  # a bag's frame: its place among the topic's messages in the bag


@dataclass
class Stream:
    name: str  # topic or track
    frames: list[Frame]  # in time order
    camera: PinholeCamera | None = None
    source: Bag | KinectMkv | None = None  # frames read again from here (``fetch``); None: each Frame decodes itself
    lenient: bool = False
    post: list[Callable[[np.ndarray], np.ndarray]] = field(default_factory=list)  # after decoding (bag frames)

    def convert(self, a: np.ndarray) -> np.ndarray:
        for f in self.post:
            a = f(a)
        return a


def iter_frames(requests):
    """``(stream, index)`` pairs -> ``(stream, index, array)`` in any order: one pass per bag for all its streams."""
    by_bag: dict[int, tuple] = {}
    for s, k in requests:
        if s.source is None:
            yield s, k, s.frames[k].decode()
        else:
            by_bag.setdefault(id(s.source), (s.source, {}))[1].setdefault(id(s), (s, set()))[1].add(k)
    for bag, wants in by_bag.values():
        yield from bag.fetch(list(wants.values()))


@dataclass
class RgbdRecording:
    """A depth camera's recording: depth (on ``depth_camera``'s grid) and the texture (colour or IR) camera."""
    path: Path
    kind: str  # realsense, kinect, ros
    depth: Stream
    texture: Stream
    depth_camera: PinholeCamera | None
    texture_camera: PinholeCamera
    T_texture_from_depth: np.ndarray | None  # None: depth registered to the texture camera
    ir: Stream | None = None
    kinect_calibration: bytes | None = None  # the mkv's calibration.json attachment
    kinect_modes: tuple[str, str] | None = None  # (depth mode, colour mode)
    notes: list[str] = field(default_factory=list)
    serial: str | None = None  # the device's serial number where the recording names it
    warnings: list[str] = field(default_factory=list)  # for the user (the import's summary)


@dataclass
class StereoRecording:
    """A rectified stereo camera's recording (ZED or any left/right CameraInfo pair)."""
    path: Path
    left: Stream
    right: Stream
    stereo: RectifiedStereo
    notes: list[str] = field(default_factory=list)
    calibration_file: Path | None = None  # an SN<serial>.conf copied into the session as its zed_calibration
    rectified: bool = True  # False: raw images (an .svo2), rectified later with the SN.conf (zed_rectified: false)
    serial: str | None = None  # the camera's serial number where the recording names it
    warnings: list[str] = field(default_factory=list)  # for the user (the import's summary)


def require_extra(module: str):
    try:
        return __import__(module)
    except ImportError:
        raise InputError(None, "import", f"the Python package '{module}'", "not installed",
                         f"pip install '{EXTRA}'") from None


# ---- image decoding -------------------------------------------------------------------------------
# the hint where a recording holds no frame of a stream
NO_FRAMES_HINT = "is the recording empty, or cut short (a truncated file)?"


def _bad(path, topic, expected, actual, hint=None):
    return InputError(path, topic, expected, actual, hint)


DAMAGED_HINT = ("the recording is damaged at this frame (on disk, or as it was recorded): copy it again from the "
                "recorder, or record again")


def decode_jpeg(buf: bytes | np.ndarray, path, field: str) -> np.ndarray:
    """A JPEG's pixels: RGB uint8 (H, W, 3), grey (H, W) for a one-channel JPEG. Strict: libjpeg's recoverable errors
    ("Corrupt JPEG data: ...", a frame damaged on disk or by the recorder) are refused. OpenCV's decoder only prints
    them on stderr and returns the damaged picture, which would become a capture's texture. The same libjpeg-turbo
    decoding as OpenCV's otherwise (accurate IDCT, smooth upsampling: the real Kinect frame decodes identically)."""
    simplejpeg = require_extra("simplejpeg")
    data = buf.tobytes() if isinstance(buf, np.ndarray) else bytes(buf)
    try:
        grey = simplejpeg.decode_jpeg_header(data, strict=True)[2] == "Gray"
        img = simplejpeg.decode_jpeg(data, colorspace="GRAY" if grey else "RGB", strict=True)
    except ValueError as exc:
        raise InputError(path, field, "an intact JPEG frame", f"libjpeg: {str(exc).splitlines()[0][:80]}",
                         DAMAGED_HINT) from None
    return np.ascontiguousarray(img[..., 0]) if grey else img


def as_rgb(img: np.ndarray) -> np.ndarray:
    """A grey image as three equal channels (a colour stream's frame stays as it is)."""
    return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB) if img.ndim == 2 else img


def is_jpeg(buf: bytes | np.ndarray) -> bool:
    return bytes(buf[:3]) == b"\xff\xd8\xff"


def decode_image(msg, path, topic: str) -> np.ndarray:
    """sensor_msgs/Image -> RGB uint8 (H, W, 3), grey uint8 (H, W), uint16 (H, W) or float32 (H, W)."""
    enc = msg.encoding.lower()
    table = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4),
             "mono8": (np.uint8, 1), "8uc1": (np.uint8, 1), "mono16": (np.uint16, 1), "16uc1": (np.uint16, 1),
             "32fc1": (np.float32, 1)}
    if enc not in table:
        raise _bad(path, topic, f"an image encoding of {sorted(table)}", f"'{msg.encoding}'")
    dt, ch = table[enc]
    dt = np.dtype(dt).newbyteorder(">" if msg.is_bigendian else "<")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, np.uint8)
    if step < w * ch * dt.itemsize or data.size < h * step:
        raise _bad(path, topic, f"{h} rows of {step} bytes ({w}x{h} {enc})", f"{data.size} bytes",
                   "the message is truncated")
    a = data[:h * step].reshape(h, step)[:, :w * ch * dt.itemsize].copy().view(dt).reshape(h, w, ch)
    a = a.astype(dt.newbyteorder("="), copy=False)
    if enc.startswith("bgr"):
        a = a[..., 2::-1]
    elif ch == 4:
        a = a[..., :3]
    return np.ascontiguousarray(a[..., 0] if ch == 1 else a)


def decode_compressed(msg, path, topic: str) -> np.ndarray:
    """sensor_msgs/CompressedImage: JPEG/PNG colour, or image_transport's ``compressedDepth`` (12-byte header, PNG;
    32FC1 quantised as inverse depth)."""
    fmt = msg.format.lower()
    data = np.asarray(msg.data, np.uint8)
    if "compresseddepth" in fmt:
        body = data[12:]
        img = cv2.imdecode(body, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise _bad(path, topic, "a compressedDepth PNG", "undecodable bytes")
        if fmt.startswith("32fc1"):
            _, a, b = struct.unpack("<iff", data[:12].tobytes())
            v = img.astype(np.float32)
            with np.errstate(divide="ignore"):
                return np.where(img > 0, a / (v - b), np.nan).astype(np.float32)
        return img
    if is_jpeg(data):
        return decode_jpeg(data, path, topic)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise _bad(path, topic, "a JPEG/PNG CompressedImage", f"undecodable '{msg.format}' bytes")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    return img


def depth_mm(a: np.ndarray, unit: str, scale_mm: float, path, topic: str) -> np.ndarray:
    """Raw depth -> float32 mm, NaN invalid; metres refused where 'mm' was declared (and the values say metres). An
    image that is no depth map (not one channel of 16-bit unsigned or float: a mono8 or colour topic named as depth)
    is refused: its grey levels would be taken for millimetres."""
    if a.ndim != 2 or not (a.dtype == np.uint16 or np.issubdtype(a.dtype, np.floating)):
        channels = 1 if a.ndim == 2 else a.shape[-1]
        raise _bad(path, topic, "a depth image (one channel, 16-bit unsigned or float)",
                   f"{a.dtype}, {channels} channel{'s' if channels != 1 else ''}",
                   "is this the depth topic? name it with --depth-topic")
    d = a.astype(np.float32) * np.float32(scale_mm if unit == "mm" else 1000.0)
    d[~(d > 0) | ~np.isfinite(d)] = np.nan
    valid = d[np.isfinite(d)]
    if valid.size == 0:
        raise _bad(path, topic, "some valid depth", "no valid pixel", "is the scene out of range?")
    if unit == "mm" and np.median(valid) < 10.0:
        raise _bad(path, topic, "depth in mm (median >= 10)", f"median {float(np.median(valid)):.4g}",
                   f"{a.dtype} depth looks like metres: pass --depth-unit m")
    return d


# ---- CameraInfo ------------------------------------------------------------------------------------
def camera_from_info(info, path, topic: str) -> PinholeCamera:
    """CameraInfo -> camera (K, D: plumb_bob, rational_polynomial, 'Brown Conrady'; equidistant refused)."""
    model = (info.distortion_model or "").lower()
    D = np.asarray(info.D if hasattr(info, "D") else info.d, np.float64).ravel()
    K = np.asarray(info.K if hasattr(info, "K") else info.k, np.float64).reshape(3, 3)
    if model in ("equidistant", "fisheye", "kannala_brandt"):
        raise _bad(path, f"{topic} distortion_model", "plumb_bob or rational_polynomial", f"'{info.distortion_model}'",
                   "rectify the fisheye images first (image_proc) and import the rectified topic")
    if D.size and not np.any(D):
        D = np.zeros(0)
    if D.size not in DIST_LENGTHS:
        raise _bad(path, f"{topic} D", f"{'/'.join(map(str, DIST_LENGTHS[1:]))} distortion coefficients", f"{D.size}")
    try:
        return PinholeCamera.from_K(K, int(info.width), int(info.height), D)
    except Exception:
        raise _bad(path, f"{topic} K", "positive finite fx, fy", str(K.ravel().tolist())) from None


def rectified_from_projection(info, path, topic: str) -> PinholeCamera:
    P = np.asarray(info.P if hasattr(info, "P") else info.p, np.float64).reshape(3, 4)
    if P[0, 0] <= 0:
        return camera_from_info(info, path, topic)
    return PinholeCamera.from_K(P[:, :3], int(info.width), int(info.height), np.zeros(0))


def stereo_from_infos(left, right, path, topics: tuple[str, str]) -> RectifiedStereo:
    """A rectified pair from the two CameraInfo: ``P_right[0, 3] = -fx * B`` (ROS; metres) -> baseline mm."""
    lc, rc = rectified_from_projection(left, path, topics[0]), rectified_from_projection(right, path, topics[1])
    Pr = np.asarray(right.P if hasattr(right, "P") else right.p, np.float64).reshape(3, 4)
    if Pr[0, 0] <= 0 or Pr[0, 3] >= 0:
        raise _bad(path, f"{topics[1]} P", "a rectified right camera (P[0,3] = -fx * baseline < 0)",
                   f"P[0,3] = {Pr[0, 3]:g}", "record the rectified topics (image_rect_color), or pass both camera_info")
    if abs(lc.fx_px - rc.fx_px) > 1e-6 * lc.fx_px or abs(lc.cy_px - rc.cy_px) > 1e-3:
        raise _bad(path, f"{topics[1]} P", "the left camera's fx, cy (a rectified pair)",
                   f"fx {rc.fx_px:g} vs {lc.fx_px:g}, cy {rc.cy_px:g} vs {lc.cy_px:g}")
    return RectifiedStereo(left=lc, baseline_mm=float(-Pr[0, 3] / Pr[0, 0] * 1000.0), doffs_px=rc.cx_px - lc.cx_px)


def quat_T_mm(translation, rotation) -> np.ndarray:
    x, y, z, w = rotation.x, rotation.y, rotation.z, rotation.w
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    return make_T(R, np.array([translation.x, translation.y, translation.z]) * 1000.0)


# ---- a recording cut short --------------------------------------------------------------------------
TRUNCATED_HINT = ("the file was cut short (a copy or download stopped early, or a disk filled up): copy the whole "
                  "recording again from where it was recorded")


def _ebml_vint(b: bytes, i: int, keep_marker: bool = False) -> tuple[int, int, bool]:
    """An EBML variable-length integer at ``b[i]``: its value, its length in bytes, and whether it is all ones
    (a size that is "unknown")."""
    first = b[i]
    if first == 0:
        raise ValueError("an EBML number longer than 8 bytes")
    n = 9 - first.bit_length()
    value = first if keep_marker else first & ((1 << (8 - n)) - 1)
    for k in range(1, n):
        value = (value << 8) | b[i + k]
    unknown = not keep_marker and value == (1 << (7 * n)) - 1
    return value, n, unknown


def expected_size_bytes(path: str | Path) -> tuple[int, str] | None:
    """How many bytes a Matroska (``.mkv``) or ROS 1 (``.bag``) recording says it holds (at least), and where it says
    so, as ``(bytes, "N bytes (where)")``: the
    Segment's size (Matroska; written when the recorder closes the file), or the end of the index a ROS 1 bag's
    header points to (its ``index_pos``, then ``conn_count`` + ``chunk_count`` records). None where the file does
    not say (another format, a size left "unknown", an index never written) or cannot be parsed that far."""
    path = Path(path)
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(4096 + 64)
            if head.startswith(b"\x1a\x45\xdf\xa3"):  # EBML header, then the Segment
                i = 4
                hsize, n, _ = _ebml_vint(head, i)
                i += n + hsize
                seg_id, n, _ = _ebml_vint(head, i, keep_marker=True)
                if seg_id != 0x18538067:
                    return None
                i += n
                seg_size, n, unknown = _ebml_vint(head, i)
                if unknown:
                    return None
                return i + n + seg_size, f"{i + n + seg_size} bytes (its Matroska Segment's size)"
            if head.startswith(b"#ROSBAG V2.0\n"):
                header_len = struct.unpack_from("<I", head, 13)[0]
                header, j, fields = head[17:17 + header_len], 0, {}
                while j + 4 <= len(header):
                    field_len = struct.unpack_from("<I", header, j)[0]
                    name, _, value = header[j + 4:j + 4 + field_len].partition(b"=")
                    fields[name] = value
                    j += 4 + field_len
                index_pos = struct.unpack("<Q", fields[b"index_pos"])[0]
                if index_pos == 0:  # never indexed (a recorder killed): rosbag reindex's matter, not a size
                    return None
                if index_pos > size:  # the index itself is not there to count
                    return index_pos, f"at least {index_pos} bytes (its header's index_pos: the index starts there)"
                n_records = sum(struct.unpack("<I", fields[k])[0] for k in (b"conn_count", b"chunk_count"))
                end = index_pos
                for _ in range(n_records):  # each record: header length, header, data length, data
                    for _part in range(2):
                        f.seek(end)
                        raw = f.read(4)
                        if len(raw) < 4:
                            return end + 4, f"at least {end + 4} bytes (the index records its header counts)"
                        end += 4 + struct.unpack("<I", raw)[0]
                return end, f"{end} bytes (the end of the index records its header counts)"
    except (OSError, ValueError, KeyError, IndexError, struct.error):
        return None
    return None


MCAP_MAGIC = b"\x89MCAP0\r\n"


def check_not_truncated(path: str | Path) -> None:
    """A one-line error when a recording file is shorter than it says it is (``expected_size_bytes``), or is an MCAP
    file (ROS 2 ``.mcap``, ZED ``.svo2``) that does not end in the magic bytes its writer closes it with. A rosbag2
    folder: each of its ``.mcap`` files."""
    path = Path(path)
    if path.is_dir():
        for f in sorted(path.glob("*.mcap")):
            check_not_truncated(f)
        return
    if not path.is_file():
        return
    try:
        with open(path, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
            f.seek(max(0, path.stat().st_size - len(MCAP_MAGIC)))
            tail = f.read()
    except OSError:
        return
    if head == MCAP_MAGIC and (tail != MCAP_MAGIC or path.stat().st_size < 2 * len(MCAP_MAGIC)):
        raise InputError(path, "size", "an MCAP file that ends in its closing magic bytes (89 4d 43 41 50 30 0d 0a, "
                         "written when the recorder closes the file)", f"{path.stat().st_size} bytes that end "
                         "without them (truncated, or never closed)", TRUNCATED_HINT + "; one whose recorder was "
                         "killed may be recovered with the mcap CLI: mcap recover")
    expected = expected_size_bytes(path)
    if expected is None:
        return
    expected_bytes, what = expected
    actual = path.stat().st_size
    if actual < expected_bytes:
        raise InputError(path, "size", what, f"{actual} bytes (truncated)", TRUNCATED_HINT)


# ---- bags -------------------------------------------------------------------------------------------
def _bag_source(path: Path) -> Path:
    """A rosbag2 folder for a ``.db3``/``.mcap`` inside one (its metadata.yaml); otherwise the path itself."""
    if path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


class Bag:
    """A bag opened with rosbags' AnyReader; the index (topics, types, stamps) read once."""

    def __init__(self, path: str | Path):
        require_extra("rosbags")
        from rosbags.highlevel import AnyReader

        self.path = Path(path)
        if not self.path.exists():
            raise InputError(self.path, None, "a recording", "no such file or folder", "check the path")
        check_not_truncated(self.path)
        try:
            self.reader = AnyReader([_bag_source(self.path)])
            self.reader.open()
        except Exception as exc:
            hint = ("a ROS 2 bag is a folder with metadata.yaml beside its .db3 / .mcap files; a ROS 1 bag is one "
                    ".bag file" if self.path.is_dir() and not (self.path / "metadata.yaml").is_file() else
                    "the file may be truncated (was the recording stopped cleanly?)")
            raise InputError(self.path, None, "a readable ROS 1 / ROS 2 bag", f"{type(exc).__name__}: "
                             f"{str(exc)[:100]}", hint) from None
        self.topics = {c.topic: c.msgtype for c in self.reader.connections}
        if getattr(self.reader, "message_count", None) == 0:  # (before any topic is looked for: none would be found)
            self.reader.close()
            raise InputError(self.path, None, "a recording with messages",
                             f"an empty one ({len(self.topics)} topic(s) declared, 0 messages)",
                             "the recorder stopped before any message arrived; record again")

    def close(self):
        self.reader.close()

    def messages(self, topics: list[str]):
        conns = [c for c in self.reader.connections if c.topic in topics]
        try:
            yield from self.reader.messages(connections=conns)
        except InputError:
            raise
        except Exception as exc:
            raise InputError(self.path, ",".join(topics), "readable messages", f"{type(exc).__name__}: "
                             f"{str(exc)[:100]}", "the file may be truncated") from None

    def deserialize(self, raw: bytes, conn, lenient: bool = False):
        try:
            return self.reader.deserialize(raw, conn.msgtype)
        except Exception as exc:
            if lenient and conn.msgtype == "sensor_msgs/msg/Image" and len(raw) > 4:
                return self.deserialize(raw[:-4], conn)  # librealsense >= 2.49: a float32 depth unit appended
            raise InputError(self.path, conn.topic, f"a {conn.msgtype} message", f"{type(exc).__name__}: "
                             f"{str(exc)[:80]}", "the file may be truncated") from None

    def match(self, patterns: tuple[str, ...] | list[str], types=IMAGE_TYPES, role: str = "image") -> str | None:
        """The topic of the first pattern with a match; several topics for it: an error listing them."""
        images = [t for t, ty in self.topics.items() if ty in types]
        for p in patterns:
            rx = re.compile("^" + re.escape(p).replace(r"\*", ".+") + "(/compressed|/compressedDepth)?$")
            hits = sorted({t for t in images if rx.match(t)})
            raw = [t for t in hits if not t.endswith(("/compressed", "/compressedDepth"))]
            hits = raw or hits
            if len(hits) > 1:
                raise InputError(self.path, f"{role} topic", f"one {role} topic matching '{p}'",
                                 f"{len(hits)}: {', '.join(hits)}", f"choose one with --{role}-topic")
            if hits:
                return hits[0]
        return None

    def info_for(self, topic: str):
        """The CameraInfo beside an image topic: the nearest camera_info up the topic's namespace."""
        infos = [t for t, ty in self.topics.items() if ty == "sensor_msgs/msg/CameraInfo"]
        base = re.sub(r"/(compressed|compressedDepth)$", "", topic)
        parts = base.split("/")
        for k in range(len(parts) - 1, 0, -1):
            ns = "/".join(parts[:k])
            for cand in (f"{ns}/camera_info", f"{ns}/info/camera_info"):
                if cand in infos:
                    return self.first(cand)
        return None

    def first(self, topic: str):
        for conn, _, raw in self.messages([topic]):
            return self.deserialize(raw, conn)
        return None

    def stream(self, topic: str, lenient: bool = False, transform=None) -> Stream:
        return self.streams([topic], lenient, {topic: transform})[topic]

    def streams(self, topics: list[str], lenient: bool = False, transforms: dict | None = None) -> dict[str, Stream]:
        """The topics' frames stamped with header.stamp (one pass over the bag, the pixels not kept)."""
        transforms = transforms or {}
        stamps: dict[str, list[int]] = {t: [] for t in topics}
        for conn, t_bag, raw in self.messages(list(topics)):
            stamps[conn.topic].append(_stamp_ns(raw, conn, self, lenient) or t_bag)
        out = {}
        for t, ts in stamps.items():
            out[t] = _indexed_stream(t, ts, self, lenient=lenient, post=[transforms[t]] if transforms.get(t) else [])
        return out

    def fetch(self, wants: list[tuple[Stream, set[int]]]):
        """One pass over the bag: ``(stream, index, array)`` for the frames asked for."""
        by_topic = {s.name: (s, {s.frames[k].ordinal: k for k in ks}) for s, ks in wants}
        seen = dict.fromkeys(by_topic, -1)
        left = sum(len(w) for _, w in by_topic.values())
        for conn, _, raw in self.messages(list(by_topic)):
            seen[conn.topic] += 1
            s, want = by_topic[conn.topic]
            k = want.get(seen[conn.topic])
            if k is None:
                continue
            msg = self.deserialize(raw, conn, s.lenient)
            dec = decode_compressed if conn.msgtype.endswith("CompressedImage") else decode_image
            yield s, k, s.convert(dec(msg, self.path, conn.topic))
            left -= 1
            if not left:
                return


def _indexed_stream(name: str, stamps: list[int], source, **kw) -> Stream:
    """A stream of ``source``'s frames in time order, each knowing its place in the source (``ordinal``)."""
    s = Stream(name, [], source=source, **kw)
    s.frames = [Frame(stamps[o], (lambda k: lambda: next(iter_frames([(s, k)]))[2])(k), o)
                for k, o in enumerate(sorted(range(len(stamps)), key=stamps.__getitem__))]
    return s


def _stamp_ns(raw, conn, bag: Bag, lenient: bool) -> int:
    """header.stamp read from the serialised bytes (every sensor_msgs image starts with its Header): ROS 1
    ``seq, sec, nsec`` (uint32), ROS 2 CDR ``sec`` (int32), ``nanosec`` (uint32) after the 4-byte encapsulation."""
    if conn.msgtype in IMAGE_TYPES and len(raw) >= 12:
        if bag.reader.is2:
            little = raw[1] == 1  # CDR_LE
            sec, nsec = struct.unpack_from("<iI" if little else ">iI", raw, 4)
        else:
            sec, nsec = struct.unpack_from("<II", raw, 4)
        return sec * 1_000_000_000 + nsec
    m = bag.deserialize(raw, conn, lenient)
    return m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec


def check_size(cam: PinholeCamera, img: np.ndarray, path, topic: str) -> None:
    if img.shape[:2] != (cam.height_px, cam.width_px):
        raise InputError(path, f"{topic} camera_info", f"intrinsics for {img.shape[1]}x{img.shape[0]} images",
                         f"{cam.width_px}x{cam.height_px}", "the camera_info belongs to another resolution or camera")


# ---- RealSense .bag (librealsense's ROS 1 layout) ---------------------------------------------------
def is_realsense_bag(bag: Bag) -> bool:
    return any(t.startswith("/device_0/sensor_") for t in bag.topics)


def read_realsense(bag: Bag) -> RgbdRecording:
    """Depth (``Depth_<i>``) and colour (``Color_<i>``, else ``Infrared_1``) streams, each stream's camera_info, the
    depth units option (``Depth_Units``; older files ``Depth Units``), the colour stream's ``tf/0``: librealsense
    writes each stream's extrinsic to the depth stream, read here as ``T_color_from_depth`` (metres -> mm; the
    direction checked on a real D435 file, tests/io/test_recordings.py), and the device's serial number."""
    path = bag.path
    depth_t = next((t for t in bag.topics if re.search(r"/Depth_\d+/image/data$", t)), None)
    tex_t = next((t for t in bag.topics if re.search(r"/Color_\d+/image/data$", t)), None) \
        or next((t for t in bag.topics if re.search(r"/Infrared_1/image/data$", t)), None)
    if depth_t is None:
        raise InputError(path, "depth topic", "a RealSense depth stream (/device_0/sensor_*/Depth_*/image/data)",
                         "none", "was the depth stream enabled when recording?")
    if tex_t is None:
        raise InputError(path, "colour topic", "a RealSense colour or infrared stream", "none",
                         "record with the colour (or infrared) stream enabled as well as depth")
    units = [t for t in bag.topics if re.search(r"/option/Depth[ _]Units/value$", t)]
    scale_mm = float(bag.first(units[0]).data) * 1000.0 if units else 1.0  # librealsense's default: 1 mm a count
    cams = {}
    for t in (depth_t, tex_t):
        info_t = t.replace("/image/data", "/info/camera_info")
        info = bag.first(info_t) if info_t in bag.topics else None
        if info is None:
            raise InputError(path, info_t, "the stream's camera_info", "missing",
                             "give the bag librealsense wrote, whole (RealSense Viewer / rs-record): it holds each "
                             "stream's camera_info")
        cams[t] = camera_from_info(info, path, info_t)
    tf_t = tex_t.replace("/image/data", "/tf/0")
    T_texture_from_depth = (quat_T_mm(*(lambda m: (m.translation, m.rotation))(bag.first(tf_t)))
                            if tf_t in bag.topics else None)
    got = bag.streams([depth_t, tex_t], lenient=True)
    depth, tex = got[depth_t], got[tex_t]
    depth.camera, tex.camera = cams[depth_t], cams[tex_t]
    depth.post.append(lambda a: depth_mm(a, "mm", scale_mm, path, depth_t))
    serial = None
    if "/device_0/info" in bag.topics:
        for conn, _, raw in bag.messages(["/device_0/info"]):
            kv = bag.deserialize(raw, conn)
            serial = kv.value if kv.key == "Serial Number" else serial
    return RgbdRecording(path, "realsense", depth, tex, cams[depth_t], cams[tex_t], T_texture_from_depth,
                         notes=[f"depth units {scale_mm:g} mm per count" + ("" if units else " (assumed: the bag has "
                                "no Depth Units option; librealsense's default)")], serial=serial)


# ---- Azure Kinect .mkv -----------------------------------------------------------------------------
KINECT_COLOR_MODES = {720: "720P", 1080: "1080P", 1440: "1440P", 1536: "1536P", 2160: "2160P", 3072: "3072P"}


def read_kinect_mkv(path: str | Path) -> RgbdRecording:
    """COLOR (MJPG / NV12 / YUY2 / BGRA), DEPTH and IR (``b16g``: 16-bit big-endian) tracks, the ``calibration.json``
    attachment (read by ``gtforge.io.vendors``) and the device timestamps: the tracks' pts (microseconds), which the
    recorder shifted to start at 0, plus the ``K4A_START_OFFSET_NS`` tag that undoes the shift (Azure Kinect
    Sensor SDK, ``k4a_record_configuration_t::start_timestamp_offset_usec``)."""
    av = require_extra("av")
    path = Path(path)
    check_not_truncated(path)
    try:
        container = av.open(str(path))
    except Exception as exc:
        raise InputError(path, None, "an Azure Kinect recording (Matroska)", f"{type(exc).__name__}",
                         "the file may be truncated") from None
    tracks, calib = {}, None
    for s in container.streams:
        title = (s.metadata or {}).get("title", "")
        if s.type == "attachment" or title == "" and (s.metadata or {}).get("filename") == "calibration.json":
            if (s.metadata or {}).get("filename") == "calibration.json":
                calib = bytes(s.data)
        elif title in ("COLOR", "DEPTH", "IR"):
            tracks[title] = s
    if calib is None:
        raise InputError(path, "calibration.json", "the recording's calibration attachment", "missing",
                         "record with k4arecorder (it embeds the device calibration)")
    if "DEPTH" not in tracks:
        raise InputError(path, "DEPTH track", "a depth track", f"tracks {sorted(tracks)}", "record with depth on")
    stamps: dict[str, list[int]] = {k: [] for k in tracks}
    index = {s.index: k for k, s in tracks.items()}
    tag = (container.metadata or {}).get("K4A_START_OFFSET_NS", "0")
    try:
        start_offset_ns = int(tag)
    except ValueError:
        raise InputError(path, "K4A_START_OFFSET_NS", "an integer (ns)", repr(tag)[:40],
                         "record with k4arecorder") from None
    try:
        for pkt in container.demux(list(tracks.values())):
            if pkt.size and pkt.pts is not None:
                stamps[index[pkt.stream.index]].append(int(round(pkt.pts * pkt.time_base * 1e9)) + start_offset_ns)
    except Exception as exc:
        raise InputError(path, "packets", "a complete recording", f"{type(exc).__name__}",
                         "the file may be truncated") from None
    dmode = tracks["DEPTH"].metadata.get("K4A_DEPTH_MODE", "")
    ctrack = tracks.get("COLOR")
    import json

    data = json.loads(calib.decode(errors="replace"))
    w, h = tracks["DEPTH"].codec_context.width, tracks["DEPTH"].codec_context.height

    def b16g(buf: bytes, w=w, h=h):
        return np.frombuffer(buf, ">u2", count=w * h).reshape(h, w).astype(np.uint16)

    decoders = {"DEPTH": b16g, "IR": b16g}
    cmode = "720P"
    if ctrack is not None:
        cw, ch = ctrack.codec_context.width, ctrack.codec_context.height
        tag = ctrack.codec_context.codec_tag if ctrack.codec_context.codec_tag else ""
        cmode = KINECT_COLOR_MODES.get(ch)
        decoders["COLOR"] = lambda b: _kinect_color(b, tag, cw, ch, path)
    source = KinectMkv(path, {k: s.index for k, s in tracks.items()}, decoders)
    depth = _indexed_stream("DEPTH", stamps["DEPTH"], source, post=[lambda a: depth_mm(a, "mm", 1.0, path, "DEPTH")])
    # (a recording cut short can hold an IR track without one frame in it: as good as none)
    ir = _indexed_stream("IR", stamps["IR"], source) if stamps.get("IR") else None
    if ctrack is None and ir is None:  # a depth-only recording: the IR image is its texture
        raise InputError(path, "IR track", "IR frames (a depth-only recording's texture)",
                         "none" if "IR" in tracks else "no IR track", NO_FRAMES_HINT)
    # depth-only recording: the IR image is the texture (pixel-aligned with the depth)
    texture = _indexed_stream("COLOR", stamps["COLOR"], source) if ctrack is not None else ir
    k = kinect_calibration_from_dict(data, path, dmode, cmode)
    depth.camera = k.depth
    if ctrack is None:
        texture.camera = k.depth
        rec = RgbdRecording(path, "kinect", depth, texture, None, k.depth, None, ir=ir, kinect_calibration=calib,
                            kinect_modes=(dmode, cmode))
    else:
        texture.camera = k.color
        rec = RgbdRecording(path, "kinect", depth, texture, k.depth, k.color, k.T_color_from_depth, ir=ir,
                            kinect_calibration=calib, kinect_modes=(dmode, cmode))
    rec.notes.append(f"depth mode {dmode}, colour mode {cmode}")
    rec.notes.append(f"frame times: device time (track time + K4A_START_OFFSET_NS {start_offset_ns} ns)")
    if "IR" in tracks and ir is None:
        rec.warnings.append(f"{path.name}: its IR track holds no frame (a recording cut short?): the captures have "
                            "no IR.png")
    rec.serial = (container.metadata or {}).get("K4A_DEVICE_SERIAL_NUMBER") or None
    container.close()
    return rec


class KinectMkv:
    """A Kinect recording's tracks, demuxed again for the frames asked for (the packets are not kept)."""

    def __init__(self, path: Path, tracks: dict[str, int], decoders: dict[str, Callable[[bytes], np.ndarray]]):
        self.path, self.tracks, self.decoders = path, tracks, decoders

    def fetch(self, wants: list[tuple[Stream, set[int]]]):
        av = require_extra("av")
        by_track = {s.name: (s, {s.frames[k].ordinal: k for k in ks}) for s, ks in wants}
        name_of = {self.tracks[n]: n for n in by_track}
        seen = dict.fromkeys(by_track, -1)
        left = sum(len(w) for _, w in by_track.values())
        with av.open(str(self.path)) as c:
            for pkt in c.demux([c.streams[self.tracks[n]] for n in by_track]):
                if not pkt.size or pkt.pts is None:
                    continue
                name = name_of[pkt.stream.index]
                seen[name] += 1
                s, want = by_track[name]
                k = want.get(seen[name])
                if k is None:
                    continue
                yield s, k, s.convert(self.decoders[name](bytes(pkt)))
                left -= 1
                if not left:
                    return


def _kinect_color(buf: bytes, tag: str, w: int, h: int, path) -> np.ndarray:
    """A COLOR frame as RGB. The Azure Kinect SDK's player knows four FourCCs for it (matroska_read.cpp's
    read_bitmap_info_header): MJPG, NV12, YUY2 and BGRA; anything else is refused, not guessed from its size."""
    if tag.upper() == "MJPG" or (tag == "" and is_jpeg(buf)):
        return as_rgb(decode_jpeg(buf, path, "COLOR"))
    need = {"NV12": w * h * 3 // 2, "YUY2": w * h * 2, "BGRA": w * h * 4}.get(tag)
    if need is not None and len(buf) < need:
        raise InputError(path, f"COLOR frame ({tag}, {w}x{h})", f"{need} bytes", f"{len(buf)} bytes", DAMAGED_HINT)
    a = np.frombuffer(buf, np.uint8)
    if tag == "NV12":
        return cv2.cvtColor(a[:need].reshape(h * 3 // 2, w), cv2.COLOR_YUV2RGB_NV12)
    if tag == "YUY2":
        return cv2.cvtColor(a[:need].reshape(h, w, 2), cv2.COLOR_YUV2RGB_YUY2)
    if tag == "BGRA":
        return np.ascontiguousarray(a[:need].reshape(h, w, 4)[..., 2::-1])
    raise InputError(path, "COLOR codec", "MJPG, NV12, YUY2 or BGRA", f"'{tag}'",
                     "record with k4arecorder: MJPG by default, NV12/YUY2 with --color-mode 720p_NV12/720p_YUY2")
