"""``gtforge import``: recordings -> a capture session (docs/capture-layout.md, "From recordings").

Plan, then write. The plan pairs every depth frame with the nearest texture frame of its own recording and with the
nearest stereo frame of the other recording (after the clock offset), keeps a pair only where every frame in it is
*still* (no change beyond ``still_threshold`` to its neighbours in its own stream), and keeps one pair (the smallest
skew) per still stretch: one capture per pose or scene. Kept pairs showing the session's board go to ``board/``,
the rest to ``scenes/`` (``--add``: the session's ``board_dir`` and ``scenes_dir``, its file names). The session is
written in a hidden folder beside ``SESSION`` and renamed into place when complete (``--add``: each capture folder
renamed in); an interrupted import leaves that folder, and rerunning the same command reuses the capture folders
already finished in it."""
from __future__ import annotations

import json
import os
import shutil
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gtforge.core.camera import CameraFile, StereoCalibrationFile
from gtforge.core.targets.detection import detect_target
from gtforge.core.targets.models import BoardModel, board_model_of, check_board_model
from gtforge.errors import InputError
from gtforge.infra.atomic import atomic_write_bytes
from gtforge.infra.digest import blake3_file
from gtforge.infra.signals import interrupt_deferred
from gtforge.io.cameras import load_camera, load_zed_rectified, read_zed_conf
from gtforge.io.captures import IMPORT_LANDING, FileNames, SessionFile, import_partial_folder
from gtforge.io.formats import write_image, write_png16, write_tiff_float
from gtforge.io.outputs import folders_above, free_path, refuse_inside_dataset_folders, require_output_folder
from gtforge.io.recordings import NO_FRAMES_HINT, RgbdRecording, StereoRecording, Stream, iter_frames
from gtforge.io.ros_recordings import Topics, open_recordings
from gtforge.io.vendors import load_structured_light_cameras
from gtforge.records.imports import ImportParams, ImportRecord, ImportRun, PairRecord, SourceFile

THUMB_W = 160
FETCH_BATCH = 16  # captures whose images are read in one pass over the recordings
REASONS = ("skew", "motion", "no image", "every/max")


@dataclass
class Pair:
    depth: int  # frame indices
    texture: int
    left: int | None
    right: int | None
    skew_ns: int
    segment: tuple[int, int]


@dataclass
class ImportSummary:
    session: Path
    captures: list[str]
    boards: int
    scenes: int
    dropped: dict[str, int]
    clock_offset_ms: float
    clock_offset_source: str
    warnings: list[str]


# ---- stillness ----------------------------------------------------------------------------------
def _thumb(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
    if img.dtype != np.uint8:
        hi = float(np.percentile(img, 99)) or 1.0
        img = np.clip(img.astype(np.float32) * (255.0 / hi), 0, 255)
    f = max(1, img.shape[1] // THUMB_W)
    return cv2.resize(img.astype(np.float32), (img.shape[1] // f, img.shape[0] // f), interpolation=cv2.INTER_AREA)


def motion_scores(streams: list[Stream], progress=None) -> list[np.ndarray]:
    """Per stream, per frame: the largest mean |grey difference| to its neighbours (0 for a lone frame). Every frame
    is read once (one pass per recording), only its reduced copy kept."""
    thumbs = [[None] * len(s.frames) for s in streams]
    where = {id(s): i for i, s in enumerate(streams)}
    total, n = sum(len(s.frames) for s in streams), 0
    for st, k, img in iter_frames((x, k) for x in streams for k in range(len(x.frames))):
        thumbs[where[id(st)]][k] = _thumb(img)
        n += 1
        if progress and (n % 25 == 0 or n == total):
            progress(f"stillness: frame {n}/{total}")
    out = []
    for th in thumbs:
        d = np.array([float(np.mean(np.abs(a - b))) if a.shape == b.shape else np.inf for a, b in zip(th[:-1], th[1:])])
        m = np.zeros(len(th))
        if d.size:
            m[:-1] = d
            m[1:] = np.maximum(m[1:], d)
        out.append(m)
    return out


def _segments(still: np.ndarray) -> np.ndarray:
    """Still stretch id per frame: frames separated by a moving frame get different ids."""
    return np.cumsum(~still)


def estimate_clock_offset(t_a: np.ndarray, moving_a: np.ndarray, t_b: np.ndarray, moving_b: np.ndarray,
                          tol_ns: float) -> tuple[float | None, int]:
    """Offset (ns, clock b minus clock a) that best lines up the starts of motion in the two streams."""
    def onsets(t, m):
        m = np.asarray(m, bool)
        return t[1:][m[1:] & ~m[:-1]] if m.size > 1 else t[:0]

    ea, eb = onsets(t_a, moving_a)[:60], onsets(t_b, moving_b)[:60]
    if ea.size < 2 or eb.size < 2:
        return None, 0
    best = (0, None)
    for c in (eb[None, :] - ea[:, None]).ravel():
        diff = np.abs((ea + c)[:, None] - eb[None, :]).min(axis=1)
        n = int((diff <= tol_ns).sum())
        if n > best[0]:
            best = (n, c)
    n, c = best
    if n < 2:
        return None, n
    j = np.abs((ea + c)[:, None] - eb[None, :]).argmin(axis=1)
    d = eb[j] - ea
    return float(np.median(d[np.abs(d - c) <= tol_ns])), n


# ---- planning -----------------------------------------------------------------------------------
def _nearest(t: np.ndarray, x: int) -> int:
    i = int(np.searchsorted(t, x))
    if i == 0:
        return 0
    if i == t.size:
        return t.size - 1
    return i if t[i] - x < x - t[i - 1] else i - 1


def _times(s: Stream) -> np.ndarray:
    return np.array([f.t_ns for f in s.frames], np.int64)


def plan_pairs(rgbd: RgbdRecording, stereo: StereoRecording | None, params: ImportParams, progress=None):
    """The kept pairs (one per still stretch), the drop counts, and the clock offset used (ns) with its source."""
    if stereo is None and (params.clock_offset_ms is not None or params.estimate_clock_offset):
        # one recording, one clock: an offset would be recorded in import.json's params and never applied
        given = "auto" if params.clock_offset_ms is None else f"{params.clock_offset_ms:g}"
        raise InputError(None, "--clock-offset-ms", "a stereo recording beside the depth recording (the offset is the "
                         "stereo clock minus the depth clock)", f"{given} with the depth recording "
                         f"{rgbd.path.name} alone", "leave --clock-offset-ms out, or name the stereo camera's "
                         "recording too: gtforge import DEPTH STEREO -o SESSION")
    td, tt = _times(rgbd.depth), _times(rgbd.texture)
    if not td.size or not tt.size:
        raise InputError(rgbd.path, rgbd.depth.name if not td.size else rgbd.texture.name, "frames", "none",
                         NO_FRAMES_HINT)
    scores = motion_scores([rgbd.texture] + ([stereo.left] if stereo is not None else []), progress)
    tex_still = scores[0] <= params.still_threshold
    tex_seg = _segments(tex_still)
    tol = params.max_skew_ms * 1e6
    offset, source = 0.0, "one clock"
    if stereo is not None:
        tl, tr = _times(stereo.left), _times(stereo.right)
        if not tl.size:
            raise InputError(stereo.path, stereo.left.name, "frames", "none", NO_FRAMES_HINT)
        left_still = scores[1] <= params.still_threshold
        left_seg = _segments(left_still)
        if params.clock_offset_ms is not None:
            offset, source = params.clock_offset_ms * 1e6, "given"
        elif stereo.path == rgbd.path and not params.estimate_clock_offset:
            source = "one clock"  # one bag: one recorder's clock, unless the user says otherwise
        else:
            overlap = min(tt[-1], tl[-1]) - max(tt[0], tl[0])
            if overlap > 0 and not params.estimate_clock_offset:
                source = "overlap"
            else:
                period = float(np.median(np.diff(tl))) if tl.size > 1 else tol
                est, n = estimate_clock_offset(tt, ~tex_still, tl, ~left_still, 1.5 * period)
                if est is None:
                    raise InputError(stereo.path, "clock", "two recordings whose clocks overlap (or >= 2 motion "
                                     "events both saw)", f"depth recording's colour frames {tt[0] / 1e9:.3f}-"
                                     f"{tt[-1] / 1e9:.3f} s, stereo left frames {tl[0] / 1e9:.3f}-{tl[-1] / 1e9:.3f} s "
                                     f"(each on its own clock), {n} common events",
                                     "give --clock-offset-ms (stereo clock minus depth clock)")
                offset, source = est, "motion events"
        lo, hi = max(tt[0] + offset, tl[0]), min(tt[-1] + offset, tl[-1])
        if hi < lo - tol:
            raise InputError(stereo.path, "clock", "recordings that overlap in time (after the clock offset)",
                             f"depth recording's colour frames {(tt[0] + offset) / 1e9:.3f}-"
                             f"{(tt[-1] + offset) / 1e9:.3f} s, stereo left frames {tl[0] / 1e9:.3f}-"
                             f"{tl[-1] / 1e9:.3f} s (offset {offset / 1e6:.1f} ms)",
                             "give --clock-offset-ms (stereo clock minus depth clock), or check the recordings")
    drops: Counter = Counter()
    pairs: list[Pair] = []
    nearest_skew_ns = np.inf  # the least skew of a pair dropped for skew (what --max-skew-ms would have to allow)
    for i, t in enumerate(td):
        k = _nearest(tt, int(t))
        skew = abs(int(tt[k]) - int(t))
        if skew > tol:
            drops["skew"] += 1
            nearest_skew_ns = min(nearest_skew_ns, skew)
            continue
        left = right = None
        seg = (int(tex_seg[k]), 0)
        still = bool(tex_still[k])
        if stereo is not None:
            ts = int(t + offset)
            left = _nearest(tl, ts)
            s2 = abs(int(tl[left]) - ts)
            if s2 > tol:
                drops["skew"] += 1
                nearest_skew_ns = min(nearest_skew_ns, max(skew, s2))
                continue
            if not tr.size or abs(int(tr[right := _nearest(tr, int(tl[left]))]) - int(tl[left])) > tol:
                drops["no image"] += 1
                continue
            skew = max(skew, s2, abs(int(tr[right]) - int(tl[left])))
            seg = (seg[0], int(left_seg[left]))
            still = still and bool(left_still[left])
        if not still:
            drops["motion"] += 1
            continue
        pairs.append(Pair(i, k, left, right, skew, seg))
    best: dict[tuple[int, int], Pair] = {}
    for p in pairs:
        if p.segment not in best or p.skew_ns < best[p.segment].skew_ns:
            best[p.segment] = p
    kept = sorted(best.values(), key=lambda p: p.depth)
    kept_every = kept[::params.every]
    if params.max_captures is not None:
        kept_every = kept_every[:params.max_captures]
    drops["every/max"] += len(kept) - len(kept_every)
    # the same still stretch: not dropped, one capture taken from it; counted apart for the stretches --every /
    # --max-captures left out (their one capture is in every/max), so that every depth frame is counted once
    taken = {p.segment for p in kept_every}
    n_same = (sum(p.segment in taken for p in pairs) - len(kept_every),
              sum(p.segment not in taken for p in pairs) - (len(kept) - len(kept_every)))
    return kept_every, {r: drops.get(r, 0) for r in REASONS}, offset, source, n_same, nearest_skew_ns / 1e6


# ---- writing ------------------------------------------------------------------------------------
def _sources(paths: list[Path]) -> list[SourceFile]:
    out = []
    for p in paths:
        files = sorted(q for q in Path(p).rglob("*") if q.is_file()) if Path(p).is_dir() else [Path(p)]
        out += [SourceFile(path=str(q.resolve()), size_bytes=q.stat().st_size, blake3=blake3_file(q)) for q in files]
    return out


def _dropped_text(dropped: dict[str, int], params: ImportParams, nearest_skew_ms: float = np.inf) -> str:
    """Why pairs were dropped, in words: ``2 dropped for skew (frames over 20 ms apart; the nearest 101.6 ms)``."""
    nearest = f"; the nearest {nearest_skew_ms:.1f} ms" if np.isfinite(nearest_skew_ms) else ""
    why = {"skew": f"skew (frames over {params.max_skew_ms:g} ms apart{nearest})",
           "motion": f"motion (over --still-threshold {params.still_threshold:g})",
           "no image": "a missing right image", "every/max": "--every / --max-captures"}
    return "; ".join(f"{n} dropped for {why.get(k, k)}" for k, n in dropped.items() if n) or "no frames"


def _write_rig_files(folder: Path, rgbd: RgbdRecording, stereo: StereoRecording | None, board: BoardModel | None):
    extra = {}
    if rgbd.kinect_calibration is not None and rgbd.depth_camera is not None:
        atomic_write_bytes(folder / "mech_intrinsics.json", rgbd.kinect_calibration)
        extra = dict(mech_intrinsics="mech_intrinsics.json", kinect_depth_mode=rgbd.kinect_modes[0],
                     kinect_color_mode=rgbd.kinect_modes[1])
    else:
        CameraFile(camera=rgbd.texture_camera).write(folder / "mech_intrinsics.yaml")
        if rgbd.depth_camera is not None:
            CameraFile(camera=rgbd.depth_camera).write(folder / "depth_intrinsics.yaml")
            extra = dict(depth_intrinsics="depth_intrinsics.yaml", T_mech_from_depth=rgbd.T_texture_from_depth.tolist())
    if stereo is not None and stereo.calibration_file is not None:
        atomic_write_bytes(folder / stereo.calibration_file.name, stereo.calibration_file.read_bytes())
        extra["zed_calibration"] = stereo.calibration_file.name
        if not stereo.rectified:
            extra["zed_rectified"] = False
    elif stereo is not None:
        StereoCalibrationFile(zed=stereo.stereo).write(folder / "zed_calibration.yaml")
    SessionFile(board=board, **extra).write(folder / "session.yaml")


def _requests(rgbd: RgbdRecording, stereo: StereoRecording | None, p: Pair) -> dict[str, tuple[Stream, int]]:
    req = {"tex": (rgbd.texture, p.texture), "depth": (rgbd.depth, p.depth)}
    if rgbd.ir is not None and rgbd.ir is not rgbd.texture:
        req["ir"] = (rgbd.ir, _nearest(_times(rgbd.ir), rgbd.depth.frames[p.depth].t_ns))
    if stereo is not None:
        req.update(left=(stereo.left, p.left), right=(stereo.right, p.right))
    return req


def _fetch(rgbd: RgbdRecording, stereo: StereoRecording | None, pairs: list[Pair]) -> list[dict[str, np.ndarray]]:
    """The images of these pairs (one pass per recording), each of its camera's size: only the first frame of each
    stream was checked when the recordings were opened, and a resolution changed mid-recording would write captures
    whose images do not fit the session's cameras. A one-line error before any of them is written."""
    reqs = [_requests(rgbd, stereo, p) for p in pairs]
    got = {(id(s), k): a for s, k, a in iter_frames({(id(s), k): (s, k) for r in reqs for s, k in r.values()}.values())}
    depth_cam = rgbd.depth_camera or rgbd.texture_camera  # (an IR image is the depth camera's)
    cams = {"tex": (rgbd, rgbd.texture_camera), "depth": (rgbd, depth_cam), "ir": (rgbd, depth_cam)}
    if stereo is not None:
        cams.update(left=(stereo, stereo.stereo.left), right=(stereo, stereo.stereo.right))
    for r in reqs:
        for name, (s, k) in r.items():
            rec, cam = cams[name]
            a = got[(id(s), k)]
            if a.shape[:2] != (cam.height_px, cam.width_px):
                raise InputError(rec.path, s.name, f"{cam.width_px}x{cam.height_px} frames (its camera_info and first "
                                 f"frame)", f"a {a.shape[1]}x{a.shape[0]} frame at {s.frames[k].t_ns / 1e9:.3f} s",
                                 "the resolution changed during the recording: import the part recorded at one "
                                 "resolution (a cut of the recording)")
    return [{name: got[(id(s), k)] for name, (s, k) in r.items()} for r in reqs]


def _write_capture(folder: Path, images: dict[str, np.ndarray], files: FileNames) -> None:
    """One capture folder, its files named as the session names them (``session.yaml``'s ``files``)."""
    tmp = folder.parent / f".{folder.name}.partial"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)

    def at(name: str) -> Path:
        (tmp / name).parent.mkdir(parents=True, exist_ok=True)  # (a name may hold a subfolder)
        return tmp / name
    tex = images["tex"]
    write_image(at(files.mech_texture), tex) if tex.dtype == np.uint8 else write_png16(at(files.mech_texture), tex)
    write_tiff_float(at(files.mech_depth), images["depth"])
    if "ir" in images:
        write_png16(at(files.depth_texture), images["ir"])
    if "left" in images:
        write_image(at(files.zed_left), images["left"])
        write_image(at(files.zed_right), images["right"])
    os.replace(tmp, folder)


def capture_folders(session: Path, sf: SessionFile) -> dict[str, str]:
    """kind ('board', 'scenes') -> the session's folder of those captures, relative to it (``board_dir``,
    ``scenes_dir``): where ``--add`` puts them. A folder outside the session is refused (its captures would not be the
    session's to record in ``import.json``)."""
    out = {}
    for kind, field in (("board", "board_dir"), ("scenes", "scenes_dir")):
        d = Path(getattr(sf, field))
        if d.is_absolute() or ".." in d.parts or not d.parts:
            raise InputError(session / "session.yaml", field, "a folder inside the session", repr(getattr(sf, field)),
                             "import into a new session")
        out[kind] = d.as_posix()
    return out


def _board_text(board: BoardModel) -> str:
    return board_model_of(board.spec()).describe()  # (defaults filled in: a ChArUco's marker size, dictionary)


def check_same_board(session: Path, sf: SessionFile, board: BoardModel | None) -> None:
    """``--add``: a board declared (``--board``, ``--cols`` ...) must be the session's (``session.yaml``'s ``board``,
    absent: the default 12x9 checkerboard); another one finds no board in the captures and sorts every one of them into
    the scenes. A one-line error before anything is written."""
    theirs = sf.board or BoardModel()
    if board is not None and board.spec() != theirs.spec():
        raise InputError(session / "session.yaml", "board", f"the session's board ({_board_text(theirs)})",
                         f"{_board_text(board)} (the board options)", "drop the board options to use the session's "
                         "board, or import into a new session")


def check_capture_files(session: Path, sf: SessionFile) -> None:
    """``--add``: the session's capture file names (``files``) and depth encoding must be ones import writes as
    they will be read: images as lossless PNG (16-bit ones too), depth as float32 mm TIFF. Anything else is a
    one-line error before anything is written, not captures that read back wrong."""
    for field in ("mech_texture", "depth_texture", "zed_left", "zed_right"):
        name = getattr(sf.files, field)
        if Path(name).suffix.lower() != ".png":
            raise InputError(session / "session.yaml", f"files.{field}", "a .png name (import writes its images as "
                             "lossless PNG)", repr(name), "import into a new session")
    name = sf.files.mech_depth
    if Path(name).suffix.lower() not in (".tif", ".tiff") or sf.depth_unit != "mm" or sf.depth_scale_mm is not None:
        raise InputError(session / "session.yaml", "files.mech_depth", "float32 mm TIFF depth (a .tif/.tiff name, "
                         "depth_unit mm, no depth_scale_mm: what import writes)", f"{name!r}, depth_unit "
                         f"{sf.depth_unit}, depth_scale_mm {sf.depth_scale_mm}", "import into a new session")


def _is_board(img: np.ndarray, spec) -> bool:
    try:
        return detect_target(img, spec) is not None
    except InputError:
        return False


def _same_camera(a, b) -> bool:
    """Two cameras (``PinholeCamera``) the same up to a file's float rounding."""
    if a is None or b is None:
        return a is b
    ka, kb = (np.array([c.fx_px, c.fy_px, c.cx_px, c.cy_px]) for c in (a, b))
    da, db = (np.pad(np.asarray(c.dist_coeffs, float), (0, 14 - len(c.dist_coeffs))) for c in (a, b))
    return (a.width_px, a.height_px) == (b.width_px, b.height_px) and np.allclose(ka, kb, rtol=1e-6, atol=1e-9) \
        and np.allclose(da, db, rtol=1e-6, atol=1e-9)


def _describe(cam) -> str:
    return "none" if cam is None else (f"{cam.width_px}x{cam.height_px} fx {cam.fx_px:.3f} fy {cam.fy_px:.3f} "
                                       f"cx {cam.cx_px:.3f} cy {cam.cy_px:.3f}")


def recording_serials(rgbd: RgbdRecording, stereo: StereoRecording | None) -> dict[str, str]:
    """role ('depth', 'stereo') -> the device's serial number, where the recording names it."""
    out = {"depth": rgbd.serial} if rgbd.serial else {}
    if stereo is not None and stereo.serial:
        out["stereo"] = stereo.serial
    return out


def check_same_rig(session: Path, rgbd: RgbdRecording, stereo: StereoRecording | None,
                   earlier: list[ImportRun]) -> None:
    """``--add``: the recordings must come from the rig the session was made with: the same device serials as every
    earlier import (``earlier``: ``import.json``'s runs), the same texture camera, depth camera and
    ``T_mech_from_depth``, and the same stereo pair (its rectified model; an SN.conf the same file) as the session's
    files. A mismatch is a one-line error before anything is written."""
    hint = "these recordings come from another rig, unit or resolution: import them into a new session"
    serials = recording_serials(rgbd, stereo)
    for run in earlier:
        for role, serial in run.serials.items():
            if serials.get(role, serial) != serial:
                raise InputError(session / "import.json", f"serials.{role}", f"the {role} device {serial}",
                                 f"{serials[role]} ({rgbd.path if role == 'depth' else stereo.path})", hint)
    if not (session / "session.yaml").is_file():
        return
    sf = SessionFile.read(session / "session.yaml")
    mech = session / sf.mech_intrinsics
    if mech.is_file():
        cams = load_structured_light_cameras(mech, depth_mode=sf.kinect_depth_mode, color_mode=sf.kinect_color_mode)
        depth_cam, T_mech_from_depth = cams.depth, cams.T_mech_from_depth
        if sf.depth_intrinsics:
            depth_cam, T_mech_from_depth = load_camera(session / sf.depth_intrinsics), np.array(sf.T_mech_from_depth)
        depth_file = session / (sf.depth_intrinsics or sf.mech_intrinsics)
        for what, mine, theirs, file in (("texture camera", rgbd.texture_camera, cams.texture, mech),
                                         ("depth camera", rgbd.depth_camera, depth_cam, depth_file)):
            if not _same_camera(mine, theirs):
                raise InputError(file, what, f"the session's {_describe(theirs)}", f"{_describe(mine)} in "
                                 f"{rgbd.path.name}", hint)
        T_mech_from_depth_new = rgbd.T_texture_from_depth
        if (T_mech_from_depth is None) != (T_mech_from_depth_new is None) or T_mech_from_depth is not None \
                and not np.allclose(T_mech_from_depth, T_mech_from_depth_new, rtol=0, atol=1e-6):
            raise InputError(session / "session.yaml", "T_mech_from_depth", "the session's depth-to-texture transform",
                             f"another one in {rgbd.path.name}", hint)
    zpath = session / sf.zed_calibration
    if stereo is None or not zpath.is_file():
        if (stereo is None) != (not zpath.is_file()):
            raise InputError(session, "stereo camera", "a stereo recording" if zpath.is_file() else "none",
                             "none" if stereo is None else stereo.path.name, hint)
        return
    if zpath.suffix.lower() == ".conf":
        if stereo.calibration_file is None or stereo.calibration_file.read_bytes() != zpath.read_bytes():
            raise InputError(zpath, "zed_calibration", f"the session's {zpath.name}",
                             str(stereo.calibration_file or "a recording without an SN.conf"), hint)
        theirs = read_zed_conf(zpath, stereo.stereo.left.width_px).rectification().stereo
    else:
        theirs = load_zed_rectified(zpath, session / sf.zed_right_info if sf.zed_right_info else None)
    mine = stereo.stereo
    if sf.zed_rectified != stereo.rectified or not _same_camera(mine.left, theirs.left) or not np.isclose(
            mine.baseline_mm, theirs.baseline_mm, rtol=1e-6) or not np.isclose(mine.doffs_px, theirs.doffs_px,
                                                                                atol=1e-6):
        raise InputError(zpath, "stereo camera", f"the session's {_describe(theirs.left)}, baseline "
                         f"{theirs.baseline_mm:.3f} mm", f"{_describe(mine.left)}, baseline {mine.baseline_mm:.3f} mm "
                         f"in {stereo.path.name}", hint)


def check_not_imported(sources: list[SourceFile], earlier: list[ImportRun]) -> None:
    """``--add``: a recording file already imported into the session (the same BLAKE3 in ``earlier``, ``import.json``'s
    runs, under any name) would add its captures a second time; a one-line error before anything is written."""
    # a rosbag2 folder's metadata.yaml is told by its data files: the same bytes in two recordings' metadata.yaml
    # would not make them one, and naming it would not say which recording was imported
    def data(files):
        return [f for f in files if Path(f.path).name != "metadata.yaml"]
    seen = {f.blake3: f.path for run in earlier for f in data(run.sources)}
    for f in data(sources):
        if f.blake3 in seen:
            raise InputError(f.path, "recording", "a recording not yet imported into this session",
                             f"the same bytes as {seen[f.blake3]} (import.json)",
                             "each recording is imported once; to import it again with other options, import it "
                             "into a new session")


def check_frames_not_imported(rgbd: RgbdRecording, kept: list[Pair], earlier: list[ImportRun]) -> None:
    """``--add``: a recording whose bytes differ from an imported one's but which holds its frames (a copy converted
    from ``.mcap`` to ``.db3``, a cut or a re-muxed file) would add those captures a second time; told by the kept
    pairs' depth and texture times, which ``import.json`` records (to the nanosecond, both: another recording of the
    device matches them only where its clock restarted in phase with this one's, a chance of about one in the frame
    period's microseconds). A one-line error before anything is written."""
    if not kept:
        return
    mine = {(rgbd.depth.frames[p.depth].t_ns, rgbd.texture.frames[p.texture].t_ns) for p in kept}
    best, hits = None, 0
    for run in earlier:
        n = len(mine & {(q.t_depth_ns, q.t_texture_ns) for q in run.pairs})
        if n > hits:
            best, hits = run, n
    if best is not None:
        raise InputError(rgbd.path, "recording", "a recording not yet imported into this session",
                         f"{hits} of the {len(kept)} captures it would add at the depth and texture times of "
                         f"captures imported from {best.depth_recording} (import.json)",
                         "each recording is imported once, and a copy, conversion or cut of one holds the same "
                         "frames; to import it again with other options, import it into a new session")


def import_recordings(paths: list[str | Path], session: str | Path, params: ImportParams | None = None,
                      topics: Topics | None = None, add: bool = False,
                      progress: Callable[[str], None] | None = None) -> ImportSummary:
    """Write ``session`` (docs/capture-layout.md) from one depth recording and optionally one stereo recording."""
    paths = [Path(p) for p in paths]
    session = Path(session)
    params, topics = params or ImportParams(), topics or Topics()
    refuse_output_inside(session)
    if params.board is not None:
        check_board_model(params.board)  # as calibrate will: refused now, not written into session.yaml
    for p in paths:
        owned = _recording_folder(p)
        if session.resolve().is_relative_to(owned):
            itself = session.resolve() == owned and owned.is_file()
            raise InputError(session, "output", "a session folder outside the recordings",
                             "the recording itself" if itself else "inside a recording",
                             f"give a new folder for the session, e.g. {free_path(owned.parent, owned.stem)}"
                             if itself else "gtforge never writes into a recording's folder")
    if session.exists() and not session.is_dir():
        raise InputError(session, "output", "a folder", "a file", "-o names the session folder to write; give a new "
                         f"one, e.g. {free_path(Path(os.path.abspath(session)).parent, session.stem or 'session')}")
    # the folder itself for the filesystem work (``-o .``, a symbolic link, one to another file system): the partial
    # folder goes beside it, on its file system, and the session is renamed into its place
    real = Path(os.path.realpath(session))
    exists = session.is_dir() and any(session.iterdir())
    if os.path.ismount(real):  # a rename cannot replace it, nor move captures into it from beside it
        raise InputError(session, "output", "a session folder that is not a mount point (the session is written "
                         "beside it, then renamed into place)", f"the mount point {real}",
                         f"give a new folder inside it, e.g. {free_path(real, 'session')}")
    if exists and not add:
        raise InputError(session, "output", "a new or empty session folder", "a non-empty folder",
                         "pass --add to add these recordings' captures to it")
    if exists and not (session / "session.yaml").is_file():
        raise InputError(session / "session.yaml", "--add", "a gtforge session to add the captures to",
                         "a folder without session.yaml", "import into a new folder (without --add)")
    # before any recording is read: the captures are written beside the session's folder, then moved into it
    # (a session and the sessions around it: its own checks, which name what they found)
    require_output_folder(session, "--output", session_ok=True)
    require_output_folder(real.parent, "--output", session_ok=True)
    add = add and exists  # --add into a new or empty folder: a new session, its rig files included
    # --add: the captures go where the session keeps them, named as it names them
    sf = SessionFile.read(session / "session.yaml") if add else SessionFile()
    dirs = capture_folders(session, sf)
    if add:
        check_capture_files(session, sf)
        check_same_board(session, sf, params.board)
    opened = open_recordings(paths, topics)
    try:
        rgbd, stereo = opened.rgbd, opened.stereo
        sources = _sources(paths)
        finished: list[str] = []  # an earlier import's landing finished first, as a warning says
        if add and exists:
            record = session / "import.json"
            landing = import_partial_folder(real) / IMPORT_LANDING
            if landing.is_file():  # an --add whose captures were landing when it was cut off (a crash): finish it
                with interrupt_deferred():
                    done = _finish_landing(landing.parent, real)
                if [f.blake3 for f in done.sources] == [f.blake3 for f in sources]:  # this very import: it is done
                    return _summary(session, done, dirs, ["an earlier run of this import was cut off while its "
                                                          "captures landed: finished now"])
                finished.append(f"an earlier import --add ({', '.join(Path(f.path).name for f in done.sources)}) "
                                "was cut off while its captures landed: finished first "
                                f"({', '.join(p.capture for p in done.pairs)})")
            earlier = ImportRecord.read(record).runs if record.is_file() else []
            check_same_rig(session, rgbd, stereo, earlier)
            check_not_imported(sources, earlier)
        kept, dropped, offset, source, n_same, nearest_skew_ms = plan_pairs(rgbd, stereo, params, progress)
        if add and exists:
            check_frames_not_imported(rgbd, kept, earlier)
        if not kept:
            raise InputError(paths[0], "captures", "at least one still, paired capture",
                             f"none ({_dropped_text(dropped, params, nearest_skew_ms)})",
                             "raise --max-skew-ms or --still-threshold, or check the clock offset")
        board = params.board
        if board is None and add:
            board = sf.board  # the session's own target (check_same_board: the one declared, if any)
        board = board or BoardModel()
        spec = board.spec()
        partial = import_partial_folder(real)
        # the recordings' bytes, not only their names: a partial folder left by an import of other bytes at the same
        # paths is started again, never resumed
        stamp = json.dumps({"sources": [(f.path, f.blake3) for f in sources], "params": params.model_dump(mode="json"),
                            "topics": {k: str(v) for k, v in topics.__dict__.items()}, "add": add})
        # resumed only when its plan is this one: a partial folder without .plan (a landing cut off) is started again
        if partial.is_dir() and (not (partial / ".plan").is_file() or (partial / ".plan").read_text() != stamp):
            shutil.rmtree(partial)
        partial.mkdir(parents=True, exist_ok=True)
        (partial / ".plan").write_text(stamp)
        if not add:
            _write_rig_files(partial, rgbd, stereo, params.board)
        # numbered per folder (a session may keep both kinds in one)
        start = {d: _next_index(session / d) if add else 0 for d in dirs.values()}
        names, records, kinds = [], [], {}
        batch: list[dict[str, np.ndarray]] = []
        for n, p in enumerate(kept):
            if n % FETCH_BATCH == 0:
                batch = _fetch(rgbd, stereo, kept[n:n + FETCH_BATCH])
            if progress:
                progress(f"capture {n + 1}/{len(kept)}")
            images = batch[n % FETCH_BATCH]
            kind = "board" if params.classify and _is_board(images["tex"], spec) else "scenes"
            name = f"{dirs[kind]}/{start[dirs[kind]]:03d}"
            start[dirs[kind]] += 1
            if not (partial / name).is_dir():
                _write_capture(partial / name, images, sf.files)
            names.append(name)
            kinds[name] = kind
            records.append(PairRecord(capture=name, t_depth_ns=rgbd.depth.frames[p.depth].t_ns,
                                      t_texture_ns=rgbd.texture.frames[p.texture].t_ns,
                                      t_left_ns=None if p.left is None else stereo.left.frames[p.left].t_ns,
                                      t_right_ns=None if p.right is None else stereo.right.frames[p.right].t_ns,
                                      skew_ms=p.skew_ns / 1e6))
        streams = {"depth": rgbd.depth.name, "texture": rgbd.texture.name}
        if stereo is not None:
            streams.update(left=stereo.left.name, right=stereo.right.name)
        # a lone frame has no neighbour to differ from: kept as still, which nothing checked
        lone = [f"{rec.path.name} ({st.name})" for rec, st in [(rgbd, rgbd.texture)]
                + ([(stereo, stereo.left)] if stereo is not None else []) if len(st.frames) == 1]
        unchecked = ([f"{lone[0]} holds one frame: its stillness cannot be checked (a lone frame is kept as "
                      "still); make sure nothing moved while it was taken"] if len(lone) == 1 else
                     [f"{' and '.join(lone)} each hold one frame: their stillness cannot be checked (lone frames are "
                      "kept as still); make sure nothing moved while they were taken"] if lone else [])
        boards = sum(k == "board" for k in kinds.values())
        # every capture a scene: the board declared is likely not the one the recording shows (classified silently)
        no_board = [f"no capture showed the board ({_board_text(board)}): all {len(names)} went to {dirs['scenes']}/; "
                    "if the recording has board captures, check --cols/--rows/--square-mm (and --board)"
                    ] if params.classify and not boards and names else []
        # build-dataset draws each fruit's split from its id, a scene without one its own fruit: one fruit captured in
        # several poses (a still stretch each) would be spread over train and test
        new_scenes = [n.rsplit("/", 1)[1] for n, k in kinds.items() if k == "scenes"]
        ungrouped = [n for n in new_scenes if n not in sf.fruit_ids]
        grouping = [f"the {len(ungrouped)} new scenes count as {len(ungrouped)} fruit in build-dataset's splits: where "
                    "several show one fruit (turned or moved between captures), name its fruit for each in "
                    "session.yaml's fruit_ids, or that fruit can land in both train and test"] \
            if len(ungrouped) > 1 else []
        warnings = finished + no_board + grouping + unchecked + rgbd.warnings + (
            stereo.warnings if stereo is not None else [
                "no stereo recording: the captures have no left.png/right.png, which calibrate, build-dataset and run "
                "need; import the depth and the stereo recordings together for a complete session"])
        run = ImportRun(sources=sources, depth_recording=str(rgbd.path.resolve()),
                        stereo_recording=None if stereo is None else str(stereo.path.resolve()), streams=streams,
                        notes=rgbd.notes + (stereo.notes if stereo else []) + [f"{n_same[0]} more still pairs in the "
                                                                               "kept captures' stretches"]
                        + ([f"{n_same[1]} more still pairs in the stretches --every/--max-captures left out"]
                           if n_same[1] else []),
                        serials=recording_serials(rgbd, stereo), params=params, clock_offset_ms=offset / 1e6,
                        clock_offset_source=source, pairs=records,
                        dropped=dropped)
        with interrupt_deferred():  # the captures and the record that lists them land together
            _land(partial, real, run, add)
    finally:
        opened.close()
    return ImportSummary(session, names, boards, len(names) - boards, dropped, offset / 1e6, source, warnings)


def refuse_output_inside(session: Path) -> None:
    """A session is never written inside another session (its captures would sit among that one's files, or be taken
    for its captures), inside a rosbag2 recording's folder (beside its metadata.yaml: a recording is never written
    into), inside a ``gtforge run``'s output folder (its stages' files), nor inside the folders build-dataset writes
    in a dataset; under any spelling of the path (relative, ``..``,
    symbolic links). A one-line error before any work, naming a free place beside."""
    refuse_inside_dataset_folders(session, "--output")
    for p, a in folders_above(session):
        what = "another capture session" if (a / "session.yaml").is_file() else \
            "a rosbag2 recording's folder" if (a / "metadata.yaml").is_file() else \
            "gtforge run's output folder" if (a / "run_state.json").is_file() else None
        if what is not None:
            name = "session" if p.is_file() else p.name  # (-o SESSION/session.yaml: a file, no session's name)
            raise InputError(session, "--output", "a session folder outside other sessions and recordings",
                             f"{'a file' if p.is_file() else 'a folder'} inside {what} ({a})",
                             f"write it beside, e.g. {free_path(a.parent, name)}")


def _summary(session: Path, run: ImportRun, dirs: dict[str, str], warnings: list[str]) -> ImportSummary:
    """The summary of a run already landed; ``dirs``: ``capture_folders``'s, which tell its boards from its scenes."""
    boards = sum(Path(p.capture).parent.as_posix() == dirs["board"] for p in run.pairs)
    return ImportSummary(session, [p.capture for p in run.pairs], boards, len(run.pairs) - boards, run.dropped,
                         run.clock_offset_ms, run.clock_offset_source, warnings)


def _recording_folder(p: Path) -> Path:
    """The folder a recording owns: a folder recording itself, a rosbag2 folder for one of its files (beside its
    metadata.yaml); a single-file recording owns only its file (a session may be written beside it)."""
    p = p.resolve()
    if p.is_dir():
        return p
    if (p.parent / "metadata.yaml").is_file():
        return p.parent
    return p


def _next_index(folder: Path) -> int:
    ids = [int(p.name) for p in folder.glob("[0-9][0-9][0-9]*") if p.name.isdigit()] if folder.is_dir() else []
    return max(ids, default=-1) + 1


def _land(partial: Path, session: Path, run: ImportRun, add: bool) -> None:
    """Move the finished import into place: the whole folder (new session, one rename) or each capture folder
    (``add``; journalled, so that a landing cut off by a crash is finished by the next import: ``_finish_landing``)."""
    if not add:
        (partial / ".plan").unlink()
        ImportRecord(runs=[run]).write(partial / "import.json")
        if session.is_dir():
            session.rmdir()  # empty (checked before)
        os.replace(partial, session)  # (cut off before this: the next import starts again, from the recordings)
        return
    atomic_write_bytes(partial / IMPORT_LANDING, run.model_dump_json().encode())
    (partial / ".plan").unlink()
    _finish_landing(partial, session)


def _finish_landing(partial: Path, session: Path) -> ImportRun:
    """Move the captures of the journalled run (``partial/.landing``) still in ``partial`` into ``session``, add the
    run to ``import.json`` unless it is there already, and remove ``partial``: what ``_land`` does, and what the next
    import does for a landing a crash (kill -9, power) cut off: never a capture that import.json does not list, nor
    one numbered again."""
    run = ImportRun.model_validate_json((partial / IMPORT_LANDING).read_bytes())
    # by the run's own capture names (relative to the session: its board_dir/scenes_dir), those not yet moved
    for name in sorted(p.capture for p in run.pairs):
        if not (partial / name).is_dir():
            continue
        if (session / name).exists():
            raise InputError(session / name, "capture", "no capture of this name (an import cut off while its "
                             f"captures landed holds one in {partial})", "one already there",
                             f"the session changed since; move {partial} away and import again")
        (session / name).parent.mkdir(parents=True, exist_ok=True)
        os.replace(partial / name, session / name)
    record = session / "import.json"
    previous = ImportRecord.read(record).runs if record.is_file() else []
    if run not in previous:
        ImportRecord(runs=previous + [run]).write(record)
    shutil.rmtree(partial)
    return run
