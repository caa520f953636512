"""ZED ``.svo2`` recordings read without the ZED SDK: an MCAP container (``mcap``) whose
``Camera_SN<serial>/side_by_side`` channel carries the raw (unrectified) left|right images as one H.264 or H.265
video stream, decoded with PyAV. The lens calibration is not in the file: the user names the unit's
``SN<serial>.conf``, and the session keeps the raw images with ``zed_rectified: false`` (calibrate rectifies them).

What the layout rests on (no Stereolabs specification is public; docs/capture-layout.md, "From recordings", cites
them): two independent reverse-engineering write-ups of ZED SDK 4.x/5.x files, RadarML/open-svo2 (docs/format.md)
and "Reverse-engineering SVO2" (nes.is-a.dev, 2025). Both list the channels ``svo_header`` (JSON),
``Camera_SN<serial>/side_by_side`` (schema encoding ``zed_sdk_encoded``), ``Camera_SN<serial>/sensors``,
``.../integrated_sensors`` and ``svo_footer``; open-svo2 gives one side-by-side message as an 8-byte prefix (u32 size
of the rest, u32 size of the video bytes), an Annex-B H.264/H.265 access unit, and a 56-byte trailer (width, height,
a u64 timestamp, frame type, frame index...). gtforge relies only on the channel name, the prefix and the Annex-B
bytes; a frame's time is the MCAP message's ``log_time`` (ns, by the MCAP specification), not the trailer's
timestamp (whose unit the two write-ups disagree on). ``.svo`` (version 1) is another, undocumented container."""
from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np

from gtforge.errors import InputError
from gtforge.io.cameras import read_zed_conf
from gtforge.io.recordings import StereoRecording, Stream, _indexed_stream, check_not_truncated, require_extra

SIDE_BY_SIDE = re.compile(r"^Camera_SN(\d+)/side_by_side$")
MCAP_MAGIC = b"\x89MCAP0\r\n"
LOSSY_WARNING = ("the ZED images come from lossy H.264/H.265 video: their texture is worse for verification than the "
                 "PNGs of an SDK export or a ROS recording (docs/capture-layout.md, 'From recordings')")


def is_mcap(path: Path) -> bool:
    """The file starts with MCAP's magic bytes (an SVO2, whatever its name says)."""
    try:
        with open(path, "rb") as f:
            return f.read(8) == MCAP_MAGIC
    except OSError:
        return False


def annexb_payload(data: bytes) -> bytes | None:
    """The Annex-B video bytes of one side-by-side message: after the 8-byte prefix (u32 size of the rest, u32 size
    of the video) when the sizes agree with the message, else the whole message if it starts with a start code."""
    if len(data) >= 8:
        rest, video = struct.unpack_from("<II", data, 0)
        if rest == len(data) - 8 and 0 < video <= rest:
            return data[8:8 + video]
    if data[:4] == b"\x00\x00\x00\x01" or data[:3] == b"\x00\x00\x01":
        return data
    return None


def _nal_types(payload: bytes, codec: str, limit: int = 8) -> list[int]:
    out, i = [], 0
    while len(out) < limit:
        i = payload.find(b"\x00\x00\x01", i)
        if i < 0 or i + 3 >= len(payload):
            break
        b = payload[i + 3]
        out.append((b >> 1) & 0x3F if codec == "hevc" else b & 0x1F)
        i += 3
    return out


def video_codec(payload: bytes) -> str | None:
    """'hevc' or 'h264' from a keyframe's parameter sets (HEVC VPS/SPS/PPS/AUD with their 2-byte header, H.264
    SPS/AUD) among its first NAL units, else None."""
    i = 0
    for _ in range(8):
        i = payload.find(b"\x00\x00\x01", i)
        if i < 0 or i + 4 >= len(payload):
            return None
        b, b2 = payload[i + 3], payload[i + 4]
        if not b & 0x80 and (b >> 1) & 0x3F in (32, 33, 34, 35) and b2 == 0x01:
            return "hevc"
        if not b & 0x80 and b & 0x1F in (7, 9):
            return "h264"
        i += 3
    return None


def _is_keyframe(payload: bytes, codec: str) -> bool:
    types = _nal_types(payload, codec)
    return any(16 <= t <= 21 or t == 32 for t in types) if codec == "hevc" else any(t in (5, 7) for t in types)


class ZedSvo:
    """An ``.svo2``'s side-by-side channel: indexed once (log times, keyframes), decoded again for the frames asked
    for (from the keyframe before each, every frame after it in order: inter frames need their references)."""

    def __init__(self, path: Path):
        require_extra("mcap")
        from mcap.reader import make_reader  # an optional dependency (gtforge[recordings])

        self.path = path
        check_not_truncated(path)
        try:
            with open(path, "rb") as f:
                summary = make_reader(f).get_summary()
            if summary is not None:
                topics = sorted({c.topic for c in summary.channels.values()})
            else:  # a file written without a summary section: the channels of its messages
                with open(path, "rb") as f:
                    topics = sorted({ch.topic for _, ch, _ in make_reader(f).iter_messages()})
        except InputError:
            raise
        except Exception as exc:
            raise InputError(path, None, "a ZED SVO2 recording (MCAP)", f"{type(exc).__name__}: {str(exc)[:80]}",
                             "the file may be truncated (was the recording stopped cleanly?)") from None
        sbs = [t for t in topics if SIDE_BY_SIDE.match(t)]
        if len(sbs) != 1:
            raise InputError(path, "channel", "one Camera_SN<serial>/side_by_side channel",
                             f"{len(sbs)} among {', '.join(topics) or 'no channel'}",
                             "is this a ZED SDK 4.x/5.x .svo2 file?")
        self.topic = sbs[0]
        self.serial = int(SIDE_BY_SIDE.match(self.topic).group(1))
        self.t_ns: list[int] = []
        self.keyframe: list[bool] = []
        self.codec: str | None = None
        for k, (log_time, data) in enumerate(self._messages()):
            payload = annexb_payload(data)
            if payload is None:
                raise InputError(path, f"{self.topic} message {k}", "an H.264/H.265 frame (Annex B)",
                                 f"{len(data)} bytes of another encoding", "a LOSSLESS-mode SVO2 is not read: export "
                                 "left/right PNGs with the ZED SDK (ZED_SVO_Export), or record with H264/H265")
            if self.codec is None:
                self.codec = video_codec(payload)
                if self.codec is None:
                    raise InputError(path, self.topic, "H.264 or H.265 video", "an unknown NAL stream",
                                     "export left/right PNGs with the ZED SDK (ZED_SVO_Export)")
            self.t_ns.append(log_time)
            self.keyframe.append(_is_keyframe(payload, self.codec))
        if not self.t_ns:
            raise InputError(path, self.topic, "video frames", "none",
                             "is the recording complete? record again, or export left/right PNGs with the ZED SDK "
                             "(ZED_SVO_Export)")
        if not self.keyframe[0]:
            raise InputError(path, f"{self.topic} message 0", "a keyframe first", "an inter frame",
                             "the file may be cut at its start")

    def _messages(self):
        from mcap.reader import make_reader  # an optional dependency (gtforge[recordings])

        try:
            with open(self.path, "rb") as f:
                for _, _, m in make_reader(f).iter_messages(topics=[self.topic], log_time_order=False):
                    yield m.log_time, m.data
        except InputError:
            raise
        except Exception as exc:
            raise InputError(self.path, self.topic, "readable messages", f"{type(exc).__name__}: {str(exc)[:80]}",
                             "the file may be truncated (was the recording stopped cleanly?)") from None

    def fetch(self, wants: list[tuple[Stream, set[int]]]):
        """One pass: ``(stream, index, array)`` for the frames asked for; ``left``/``right`` are the halves."""
        av = require_extra("av")
        by_ordinal: dict[int, list[tuple[Stream, int]]] = {}
        for s, ks in wants:
            for k in ks:
                by_ordinal.setdefault(s.frames[k].ordinal, []).append((s, k))
        if not by_ordinal:
            return
        n = len(self.t_ns)
        key_before = np.maximum.accumulate(np.where(self.keyframe, np.arange(n), 0))
        decode = np.zeros(n, bool)
        for o in by_ordinal:
            decode[key_before[o]:o + 1] = True
        last = max(by_ordinal)
        ctx = av.CodecContext.create(self.codec, "r")

        def emit(frames):
            for fr in frames:
                want = by_ordinal.pop(int(fr.pts), [])
                img = fr.to_ndarray(format="rgb24") if want else None  # once for both halves
                for s, k in want:
                    w = img.shape[1] // 2
                    yield s, k, s.convert(np.ascontiguousarray(img[:, :w] if s.name.endswith("left") else img[:, w:]))

        messages = self._messages()
        try:
            for o, (_, data) in enumerate(messages):
                if o > last:
                    break
                if not decode[o]:
                    continue
                pkt = av.Packet(annexb_payload(data))
                pkt.pts = o
                try:
                    frames = ctx.decode(pkt)
                except av.FFmpegError as exc:
                    raise InputError(self.path, f"{self.topic} message {o}", f"a decodable {self.codec} frame",
                                     f"{type(exc).__name__}", "the file may be damaged") from None
                yield from emit(frames)
        finally:
            messages.close()
        yield from emit(ctx.decode(None))
        if by_ordinal:
            raise InputError(self.path, self.topic, "every frame asked for decoded",
                             f"{len(by_ordinal)} not (first: message {min(by_ordinal)})", "the file may be damaged")


def read_zed_svo2(path: str | Path, calibration: Path | None) -> StereoRecording:
    """An ``.svo2``: the raw left/right halves of the side-by-side video at each message's log time, with the
    ``SN<serial>.conf`` the user names (refused when its serial is not the recording's camera)."""
    path = Path(path)
    if calibration is None:
        raise InputError(path, "--zed-calibration", "the ZED's factory calibration (an .svo2 holds none)", "none",
                         "pass --zed-calibration SN<serial>.conf (ZED Explorer or the SDK downloads it)")
    calibration = Path(calibration)
    svo = ZedSvo(path)
    if calibration.suffix.lower() != ".conf":
        raise InputError(calibration, "--zed-calibration", "the unit's SN<serial>.conf (an .svo2 holds raw images)",
                         f"'{calibration.name}'", f"pass SN{svo.serial}.conf")
    m = re.match(r"^SN(\d+)\.conf$", calibration.name, re.IGNORECASE)
    if m and int(m.group(1)) != svo.serial:
        raise InputError(calibration, "serial", f"SN{svo.serial}.conf (the camera that recorded {path.name})",
                         calibration.name, "name the conf of the unit that made the recording")
    left = _indexed_stream(f"{svo.topic}:left", svo.t_ns, svo)
    right = _indexed_stream(f"{svo.topic}:right", svo.t_ns, svo)
    first = next(svo.fetch([(left, {0})]))[2]
    stereo = read_zed_conf(calibration, first.shape[1]).rectification().stereo
    left.camera = right.camera = stereo.left
    return StereoRecording(path, left, right, stereo, calibration_file=calibration, rectified=False,
                           serial=str(svo.serial),
                           notes=[f"ZED SVO2, camera SN{svo.serial}, {svo.codec} video, {len(svo.t_ns)} frames, "
                                  f"{calibration.name}; raw images (zed_rectified: false)"], warnings=[LOSSY_WARNING])
