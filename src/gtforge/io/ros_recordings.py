"""Which recording is what: a file (or rosbag2 folder) opened and its streams chosen by topic.

``open_recordings`` reads every recording the user names and returns the depth camera's (``RgbdRecording``) and
the stereo camera's (``StereoRecording``): a RealSense ``.bag`` and a Kinect ``.mkv`` are depth recordings; a ROS bag
is whatever its topics hold (a stereo pair: left/right images with their CameraInfo, as zed-ros2-wrapper records
them; an RGB-D camera: depth + colour, as realsense-ros records them), one bag may hold both."""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gtforge.errors import InputError
from gtforge.io.cameras import load_zed_rectified, read_zed_conf
from gtforge.io.formats import read_image
from gtforge.io.recordings import (
    BAG_SUFFIXES,
    COLOR_TOPICS,
    DEPTH_TOPICS,
    LEFT_TOPICS,
    NO_FRAMES_HINT,
    RIGHT_TOPICS,
    Bag,
    Frame,
    RgbdRecording,
    StereoRecording,
    Stream,
    as_rgb,
    camera_from_info,
    check_size,
    depth_mm,
    is_realsense_bag,
    read_kinect_mkv,
    read_realsense,
    stereo_from_infos,
)
from gtforge.io.zed_svo import is_mcap, read_zed_svo2

ZED_EXPORT = re.compile(r"^(left|right)(\d+)\.(png|jpg|jpeg)$", re.IGNORECASE)


def is_zed_export(path: Path) -> bool:
    return path.is_dir() and not (path / "metadata.yaml").is_file() and any(ZED_EXPORT.match(f.name)
                                                                               for f in path.iterdir())


def read_zed_export(folder: Path, fps: float | None, calibration: Path | None) -> StereoRecording:
    """A ZED SDK export folder (``left%06d.png`` / ``right%06d.png``, BGRA or BGR, rectified by the SDK): frame ``i``
    at ``i / fps`` on the folder's own clock; the calibration the user names (``SN<serial>.conf``: OpenCV's rectified
    model of it, the conf copied into the session; or a rectified YAML gtforge reads)."""
    files: dict[str, dict[int, Path]] = {"left": {}, "right": {}}
    for f in folder.iterdir():
        m = ZED_EXPORT.match(f.name)
        if m:
            files[m.group(1).lower()][int(m.group(2))] = f
    both = sorted(set(files["left"]) & set(files["right"]))
    if not both:
        raise InputError(folder, "left/right", "left%06d.png and right%06d.png with the same numbers", "no pair",
                         "export the SVO as left/right image sequences with the ZED SDK (ZED_SVO_Export) into this "
                         "folder")
    if fps is None or not fps > 0 or not np.isfinite(fps):
        raise InputError(folder, "--fps", "the frame rate of the ZED export (its images carry no time), a positive "
                         "number", "none" if fps is None else f"{fps:g}", "pass --fps (e.g. 15)")
    if calibration is None:
        raise InputError(folder, "--zed-calibration", "the ZED's calibration (SN<serial>.conf or rectified YAML)",
                         "none", "pass --zed-calibration SN12345.conf")

    def rgb(path):  # (read_image: a truncated PNG refused, where cv2.imread returns the rows it could read)
        return as_rgb(read_image(path))

    def stream(side):
        return Stream(side, [Frame(int(round(i * 1e9 / fps)), (lambda p: lambda: rgb(p))(files[side][i]))
                             for i in both])
    left, right = stream("left"), stream("right")
    first = left.frames[0].decode()
    calibration = Path(calibration)
    if calibration.suffix.lower() == ".conf":
        stereo, copy = read_zed_conf(calibration, first.shape[1]).rectification().stereo, calibration
    else:
        stereo, copy = load_zed_rectified(calibration), None
    left.camera = right.camera = stereo.left
    return StereoRecording(folder, left, right, stereo, notes=[f"ZED export, {fps:g} fps, {calibration.name}"],
                           calibration_file=copy)


@dataclass
class Topics:
    """The user's topic choices (None: the defaults of gtforge.io.recordings) and the depth unit override."""
    depth: str | None = None
    color: str | None = None
    left: str | None = None
    right: str | None = None
    depth_unit: str | None = None  # None: by encoding (16-bit mm, 32FC1 m)
    fps: float | None = None  # a ZED export folder's frame rate
    zed_calibration: Path | None = None  # a ZED export folder's or an .svo2's calibration


def _pats(given: str | None, defaults):
    return (given,) if given else defaults


def _ros_rgbd(bag: Bag, topics: Topics) -> RgbdRecording | None:
    depth_t = bag.match(_pats(topics.depth, DEPTH_TOPICS), role="depth")
    if depth_t is None:
        if topics.depth:
            raise InputError(bag.path, "depth topic", f"an image topic '{topics.depth}'", "none",
                             f"image topics: {', '.join(_images(bag)) or 'none'}")
        return None
    color_t = bag.match(_pats(topics.color, COLOR_TOPICS), role="color")
    if color_t is None:
        raise InputError(bag.path, "color topic", "a colour image topic beside the depth", "none",
                         f"choose one with --color-topic (image topics: {', '.join(_images(bag))})")
    if color_t == depth_t:  # one image taken as both: its colour read as depth
        raise InputError(bag.path, "depth topic", "a depth image topic other than the colour image's",
                         f"'{depth_t}', the colour topic too", "name the depth topic with --depth-topic, the colour "
                         f"one with --color-topic (image topics: {', '.join(_images(bag))})")
    cams = {}
    for t in (depth_t, color_t):
        info = bag.info_for(t)
        if info is None:
            raise InputError(bag.path, f"{t} camera_info", "a CameraInfo topic beside the image", "none",
                             "record the camera_info topics too")
        cams[t] = camera_from_info(info, bag.path, t)
    got = bag.streams([depth_t, color_t])
    depth, tex = got[depth_t], got[color_t]
    depth.camera, tex.camera = cams[depth_t], cams[color_t]
    unit = topics.depth_unit

    def to_mm(a, unit=unit):
        u = unit or ("m" if a.dtype == np.float32 else "mm")
        return depth_mm(a, u, 1.0, bag.path, depth_t)

    depth.post.append(to_mm)
    registered = "aligned" in depth_t or "registered" in depth_t or cams[depth_t] == cams[color_t]
    T_color_from_depth = None
    if not registered:
        T_color_from_depth = _tf_static(bag, color_t, depth_t)
        if T_color_from_depth is None:
            raise InputError(bag.path, "/tf_static", f"the transform between {color_t} and {depth_t}", "none",
                             "record aligned_depth_to_color, or /tf_static")
    return RgbdRecording(bag.path, "ros", depth, tex, None if registered else cams[depth_t], cams[color_t],
                         T_color_from_depth, notes=[f"topics {depth_t}, {color_t}"])


def _tf_static(bag: Bag, color_t: str, depth_t: str):
    """A first guess of T_color_from_depth from /tf_static: the frames of the two CameraInfo headers joined through
    the static transform tree (realsense-ros: camera_link -> camera_*_frame -> camera_*_optical_frame)."""
    if "/tf_static" not in bag.topics:
        return None
    from gtforge.core.geometry import invert_T
    from gtforge.io.recordings import quat_T_mm

    cf, df = bag.info_for(color_t).header.frame_id, bag.info_for(depth_t).header.frame_id
    edges: dict[str, dict[str, np.ndarray]] = {}
    for conn, _, raw in bag.messages(["/tf_static"]):
        for tr in bag.deserialize(raw, conn).transforms:
            T_parent_from_child = quat_T_mm(tr.transform.translation, tr.transform.rotation)
            edges.setdefault(tr.header.frame_id, {})[tr.child_frame_id] = T_parent_from_child
            edges.setdefault(tr.child_frame_id, {})[tr.header.frame_id] = invert_T(T_parent_from_child)
    T_color_from_frame = {cf: np.eye(4)}  # breadth first from the colour frame
    todo = [cf]
    while todo:
        f = todo.pop(0)
        for g, T_f_from_g in edges.get(f, {}).items():
            if g not in T_color_from_frame:
                T_color_from_frame[g] = T_color_from_frame[f] @ T_f_from_g
                todo.append(g)
    return T_color_from_frame.get(df)


def _images(bag: Bag) -> list[str]:
    return sorted(t for t, ty in bag.topics.items() if ty.startswith("sensor_msgs/msg/") and "Image" in ty)


def _half_pair(bag: Bag, topics: Topics, left_t: str | None, right_t: str | None) -> InputError:
    """What is wrong with a bag holding one camera of a stereo pair (a topic of one side, none of the other)."""
    found, role = (left_t, "right") if right_t is None else (right_t, "left")
    pats = _pats(getattr(topics, role), RIGHT_TOPICS if role == "right" else LEFT_TOPICS)
    return InputError(bag.path, f"{role} topic", f"the {role} image beside {found} (a topic matching "
                      f"{', '.join(pats[:2])}, ...)", f"none among {', '.join(_images(bag))}",
                      f"name it with --{role}-topic, or record both cameras of the pair")


def _ros_stereo(bag: Bag, topics: Topics, halves: list[InputError]) -> StereoRecording | None:
    """The bag's stereo pair, or None. One camera of a pair without the other is refused when its topics were named
    (--left-topic / --right-topic); otherwise it is added to ``halves`` (a depth bag may carry a stray camera topic:
    said only if no stereo recording is found at all)."""
    left_t = bag.match(_pats(topics.left, LEFT_TOPICS), role="left")
    right_t = bag.match(_pats(topics.right, RIGHT_TOPICS), role="right")
    if left_t is None and right_t is None:
        return None
    if left_t is None or right_t is None:
        if topics.left or topics.right:
            raise _half_pair(bag, topics, left_t, right_t)
        halves.append(_half_pair(bag, topics, left_t, right_t))
        return None
    infos = [bag.info_for(t) for t in (left_t, right_t)]
    if any(i is None for i in infos):
        raise InputError(bag.path, "camera_info", f"CameraInfo beside {left_t} and {right_t}", "missing",
                         "record the left and right camera_info topics")
    stereo = stereo_from_infos(infos[0], infos[1], bag.path, (left_t, right_t))
    maps = [None, None] if "rect" in left_t and "rect" in right_t else [_rectify_map(i) for i in infos]
    got = bag.streams([left_t, right_t], transforms={left_t: maps[0], right_t: maps[1]})
    left, right = got[left_t], got[right_t]
    left.camera = right.camera = stereo.left
    notes = [f"topics {left_t}, {right_t}"]
    if maps[0] is not None or maps[1] is not None:
        notes.append("raw stereo images rectified with each camera_info's K, D, R, P (cv2.initUndistortRectifyMap)")
    return StereoRecording(bag.path, left, right, stereo, notes=notes)


def _rectify_map(info):
    """Raw images (a topic without 'rect') with a lens model or a rectifying rotation: remapped onto P's camera,
    as image_proc's rectify does; None when there is nothing to undo."""
    K = np.asarray(info.K if hasattr(info, "K") else info.k, np.float64).reshape(3, 3)
    D = np.asarray(info.D if hasattr(info, "D") else info.d, np.float64).ravel()
    R = np.asarray(info.R if hasattr(info, "R") else info.r, np.float64).reshape(3, 3)
    P = np.asarray(info.P if hasattr(info, "P") else info.p, np.float64).reshape(3, 4)
    if not np.any(R):
        R = np.eye(3)
    if not np.any(D) and np.allclose(R, np.eye(3)) and np.allclose(K, P[:, :3]):
        return None
    mx, my = cv2.initUndistortRectifyMap(K, D, R, P[:, :3], (int(info.width), int(info.height)), cv2.CV_32FC1)

    def rectify(img):
        return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    return rectify


# what a recording's first bytes say it is
_MAGIC = ((b"\x1a\x45\xdf\xa3", "a Matroska file (.mkv)", (".mkv",)),
          (b"#ROSBAG V2.0", "a ROS 1 bag (.bag)", (".bag",)),
          (b"\x89MCAP", "an MCAP file (.mcap, .svo2)", (".mcap", ".svo2", ".svo")),
          (b"SQLite format 3\x00", "a rosbag2 SQLite file (.db3)", (".db3",)),
          # files often given in a recording's place: an image renamed, an archive not unpacked
          (b"\xff\xd8\xff", "a JPEG image", ()), (b"\x89PNG", "a PNG image", ()), (b"II*\x00", "a TIFF image", ()),
          (b"MM\x00*", "a TIFF image", ()), (b"PK\x03\x04", "a ZIP archive", ()), (b"\x1f\x8b", "a gzip archive", ()))

_RECORDING_KINDS = {what for _, what, suffixes in _MAGIC if suffixes}
# recordings that are one file, never a folder (a folder under such a name was opened as the file: "got
# IsADirectoryError (hint: the file may be truncated)")
_ONE_FILE_SUFFIXES = {".mkv": "an Azure Kinect recording", ".svo2": "a ZED SVO2 recording",
                      ".svo": "a ZED SVO recording"}


def _looks_like(p: Path) -> str | None:
    """What ``p``'s first bytes show it to be when its suffix says otherwise (a file renamed by mistake, an image or
    archive given instead, a download cut short), else None (a folder, a suffix gtforge does not know, a match)."""
    suffix = p.suffix.lower()
    if p.is_dir() or suffix not in {s for _, _, suffixes in _MAGIC for s in suffixes}:
        return None
    with open(p, "rb") as f:
        head = f.read(16)
    for magic, what, suffixes in _MAGIC:
        if head.startswith(magic):
            return None if suffix in suffixes else what
    if suffix == ".svo":  # a ZED SVO version 1 file: its own message (open_recordings)
        return None
    if not head:
        return "an empty file"
    if all(32 <= b < 127 or b in b"\r\n\t" for b in head):
        return "text (an error page saved in its place?)"
    return f"data of no recording format (first bytes {head[:8].hex(' ')})"


@dataclass
class Opened:
    rgbd: RgbdRecording | None
    stereo: StereoRecording | None
    bags: list[Bag]

    def close(self):
        for b in self.bags:
            b.close()


def _refuse_one_recording_twice(paths: list[Path]) -> None:
    """One recording named twice (the same path, or another path to it: a link, ``./``): one line naming it, before
    either is read (it said "expected one depth recording ..., got 2 depth", naming no file)."""
    for i, p in enumerate(paths):
        twice = next((q for q in paths[:i] if p.exists() and q.exists() and p.samefile(q)), None)
        if twice is not None:
            raise InputError(p, None, "each recording once (the depth camera's, and the stereo camera's)",
                             "the same recording twice" + ("" if str(twice) == str(p) else f" (also as {twice})"),
                             "name the depth camera's recording and the stereo camera's, each once")


def open_recordings(paths: list[Path], topics: Topics | None = None) -> Opened:
    """The depth camera's and the stereo camera's recordings among ``paths`` (one or two files/folders)."""
    topics = topics or Topics()
    rgbd_c, stereo_c, bags = [], [], []
    halves: list[InputError] = []  # bags with one camera of a stereo pair (``_ros_stereo``)
    calibration_used = False  # --zed-calibration applies to a ZED export folder or an .svo2 only
    used: set[str] = set()  # the options some recording here reads (the others are refused, not ignored)
    _refuse_one_recording_twice([Path(p) for p in paths])
    for p in paths:
        p = Path(p)
        if not p.exists():
            raise InputError(p, None, "a recording (file or folder)", "no such file or folder",
                             "check the path (docs/capture-layout.md 'From recordings' lists what import reads)")
        if p.is_dir() and p.suffix.lower() in _ONE_FILE_SUFFIXES and not is_zed_export(p):
            raise InputError(p, None, f"the recording file its suffix {p.suffix} names "
                             f"({_ONE_FILE_SUFFIXES[p.suffix.lower()]}, one file)", "a folder",
                             "give the recording file itself; a folder is read as a rosbag2 folder (metadata.yaml "
                             "beside its .db3 / .mcap) or a ZED SDK export folder (left%06d.png / right%06d.png)")
        looks_like = _looks_like(p)
        if looks_like is not None:
            raise InputError(p, None, f"the recording its suffix {p.suffix} names",
                             f"{looks_like} (by its first bytes)",
                             "name the file by what it holds (.bag for a ROS 1 / RealSense bag, .mcap, .db3, .mkv)"
                             if looks_like in _RECORDING_KINDS else
                             "is this the recording? give the file the recorder wrote (copied whole)")
        if p.suffix.lower() == ".mkv":
            rgbd_c.append(read_kinect_mkv(p))
            continue
        if is_zed_export(p):
            stereo_c.append(read_zed_export(p, topics.fps, topics.zed_calibration))
            calibration_used = True
            used.add("fps")
            continue
        if p.suffix.lower() == ".svo2" or p.suffix.lower() == ".svo" and is_mcap(p):  # an SVO2 renamed .svo too
            stereo_c.append(read_zed_svo2(p, topics.zed_calibration))
            calibration_used = True
            continue
        if p.suffix.lower() == ".svo":
            raise InputError(p, None, "a recording gtforge reads (.svo2 of ZED SDK 4.x and later)",
                             "an .svo that is no .svo2 (MCAP): a ZED SVO version 1 file (an undocumented container) "
                             "or another file",
                             "export left/right PNGs with the ZED SDK (ZED_SVO_Export), or record .svo2 with ZED SDK "
                             ">= 4")
        if not (p.suffix.lower() in BAG_SUFFIXES or p.is_dir()):
            raise InputError(p, None, "a .bag, .db3, .mcap, rosbag2 folder or Azure Kinect .mkv",
                             f"'{p.suffix or p.name}'", "give the file the recorder wrote, with its own suffix; "
                             "docs/capture-layout.md 'From recordings' lists what import reads")
        bag = Bag(p)
        bags.append(bag)
        if is_realsense_bag(bag):
            rgbd_c.append(read_realsense(bag))
            continue
        s = _ros_stereo(bag, topics, halves)
        if s is not None:  # the stereo topics chose this pair
            used |= {"left", "right"}
        # a stereo bag beside another recording holds depth only where --depth-topic names one of its topics
        named = topics.depth is not None and bag.match((topics.depth,), role="depth") is not None
        r = _ros_rgbd(bag, topics) if (s is None or len(paths) == 1 or named) else None
        if r is not None:  # the depth topics chose these streams
            used |= {"depth", "color", "depth_unit"}
        if s is None and r is None:
            raise InputError(p, "depth topic", "a depth image topic (or a left/right stereo pair)", "none",
                             f"image topics: {', '.join(_images(bag)) or 'none'}; choose with --depth-topic")
        if r is not None:
            rgbd_c.append(r)
        if s is not None:
            stereo_c.append(s)
    if len(rgbd_c) > 1 or len(stereo_c) > 1:
        raise InputError(None, "recordings", "one depth recording and at most one stereo recording",
                         f"{len(rgbd_c)} depth, {len(stereo_c)} stereo", "import them one pair at a time")
    if not rgbd_c:
        raise InputError(paths[0], "depth topic", "a depth recording (depth image topic)", "none",
                         "name the depth camera's recording too, or its topic with --depth-topic")
    if not stereo_c and halves:  # imported depth-only, as asked; the warning says what looked like half a pair
        rgbd_c[0].warnings.append(f"half a stereo pair, not imported: {halves[0]}")
    for name, option, applies in (("depth", "--depth-topic", "a ROS bag's depth topic"),
                                  ("color", "--color-topic", "a ROS bag's colour topic beside its depth"),
                                  ("depth_unit", "--depth-unit", "a ROS bag's depth images"),
                                  ("left", "--left-topic", "a ROS bag's stereo pair"),
                                  ("right", "--right-topic", "a ROS bag's stereo pair"),
                                  ("fps", "--fps", "a ZED SDK export folder (left%06d.png, no timestamps)")):
        if getattr(topics, name) is not None and name not in used:
            kinds = ", ".join(sorted({c.kind for c in rgbd_c} | {"stereo" for _ in stereo_c}))
            raise InputError(None, option, f"a recording it applies to ({applies})",
                             f"{getattr(topics, name)!r}, which none of these recordings ({kinds or 'none'}) took its "
                             "streams from", f"leave {option} out, or check the topic's name in the bag (a RealSense "
                             ".bag, an Azure Kinect .mkv and a ZED .svo2 name their own streams, units and timing)")
    if topics.zed_calibration is not None and not calibration_used:
        raise InputError(topics.zed_calibration, "--zed-calibration", "a ZED .svo2 or ZED SDK export folder to apply "
                         "it to", "none among the recordings" if not stereo_c else
                         f"{stereo_c[0].path.name}, whose stereo pair has its own camera_info",
                         "leave --zed-calibration out: a ROS stereo pair's camera_info is its calibration")
    rgbd = rgbd_c[0]
    first = rgbd.depth.frames[0].decode() if rgbd.depth.frames else None
    if first is None:
        raise InputError(rgbd.path, rgbd.depth.name, "depth frames", "none", NO_FRAMES_HINT)
    check_size(rgbd.depth_camera or rgbd.texture_camera, first, rgbd.path, rgbd.depth.name)
    if rgbd.texture.frames:
        check_size(rgbd.texture_camera, rgbd.texture.frames[0].decode(), rgbd.path, rgbd.texture.name)
    stereo = stereo_c[0] if stereo_c else None
    if stereo is not None and stereo.left.frames:
        check_size(stereo.stereo.left, stereo.left.frames[0].decode(), stereo.path, stereo.left.name)
    if stereo is not None and stereo.right.frames:
        check_size(stereo.stereo.right, stereo.right.frames[0].decode(), stereo.path, stereo.right.name)
    return Opened(rgbd, stereo, bags)
