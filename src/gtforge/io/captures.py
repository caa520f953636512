"""Capture readers: structured-light depth + texture, ZED images (side-by-side, separate, video),
and capture folders (docs/capture-layout.md).

Over 500 lines on purpose: ``Session`` is the one reader every stage uses for every capture layout (separate,
side-by-side and raw ZED images with an SN.conf), and its checks name the file and field they refuse."""
from __future__ import annotations

import io
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal

import numba
import numpy as np
import tifffile
from pydantic import Field, field_validator

from gtforge.core.camera import PinholeCamera, RectifiedStereo
from gtforge.core.schema import GTModel, VersionedFile, matrix4_field
from gtforge.core.zed.selfcal import corrected_right
from gtforge.core.targets.models import BoardModel
from gtforge.errors import InputError, MissingFileError, first_of
from gtforge.infra.digest import blake3_hex
from gtforge.infra.unbuffered import AlignedBuffer, aligned_buffer
from gtforge.io.cameras import DEFAULT_ZED_CONF_READING, ZedConfReading, load_camera, load_zed_rectified, read_zed_conf
from gtforge.io.formats import PNG_SIGNATURE, read_image
from gtforge.io.outputs import free_path, gtforge_folder_kind
from gtforge.io.vendors import load_structured_light_cameras

DEPTH_SUFFIXES = (".tif", ".tiff", ".png", ".npy")


# ---- depth ----------------------------------------------------------------------------------
def read_depth(path: str | Path, depth_unit: Literal["mm", "m"] = "mm", depth_scale_mm: float | None = None,
               camera: PinholeCamera | None = None, field: str = "depth",
               data: bytes | memoryview | None = None) -> np.ndarray:
    """Depth map -> ``(H, W)`` float32 mm with NaN invalid.

    float32 TIFF (Mech-Eye ``DepthMap.tiff``; NaN or 0 invalid), 16-bit PNG (``depth_scale_mm`` mm per
    count, 0 invalid), ``.npy`` (NaN, 0 or negative invalid). A median valid value below 10 (over every 16th
    pixel) is refused as metres unless ``depth_unit="m"``. ``data``: the file's bytes, already read.
    """
    path = Path(path)
    if data is None and not path.is_file():
        raise MissingFileError(path, field, "a depth map file", hint="check the capture folder / session.yaml")
    suf = path.suffix.lower()
    if suf not in DEPTH_SUFFIXES:
        raise InputError(path, field, f"a depth map ({', '.join(DEPTH_SUFFIXES)})", f"'{suf}'",
                         "export float32 TIFF (mm), 16-bit PNG (with depth_scale_mm) or .npy; session.yaml's "
                         "files.mech_depth names it (docs/capture-layout.md)")
    try:
        source = path if data is None else io.BytesIO(data)
        if suf in (".tif", ".tiff"):
            a = tifffile.imread(source) if data is None else _tiff_image(data)
        elif suf == ".npy":
            a = np.load(source, allow_pickle=False)
        else:
            a = read_image(path, expect="uint16", field=field, data=data)
    except InputError:
        raise
    except Exception as exc:
        raise InputError(path, field, "a readable depth map", f"{type(exc).__name__}: {str(exc)[:80]}",
                         "the file may be truncated") from None
    a = np.asarray(a)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim != 2:
        raise InputError(path, field, "a single-channel (H, W) depth map", f"shape {a.shape}",
                         "Mech-Eye exports depth as DepthMap.tiff; a point-cloud TIFF has 3 channels")
    if suf == ".png":
        if depth_scale_mm is None:
            raise InputError(path, "depth_scale_mm", "a depth scale for 16-bit PNG depth", "none given",
                             "set 'depth_scale_mm' in session.yaml (e.g. 0.1 for 0.1 mm per count)")
        scale = np.float32(depth_scale_mm)
    else:
        if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
            raise InputError(path, field, "numeric depth", str(a.dtype),
                             "write the depth as float32 mm (TIFF, .npy) or uint16 counts (PNG with depth_scale_mm)")
        scale = np.float32(1.0)
    if a.dtype not in (np.float32, np.uint16):  # the two types depth files come in: no other kernel compiled
        a = a.astype(np.float32)
    d, n_valid = _depth_mm(np.ascontiguousarray(a), scale)
    if not n_valid:
        raise InputError(path, field, "some valid depth", "no valid pixel", "is the scene out of range?")
    if depth_unit == "m":
        d *= 1000.0
    else:
        # every 16th pixel tells metres from mm as well as all do. Fewer than half of them below 10 mm: their median
        # is not below 10 (counted in one pass); the median itself (a sort) only where it may be
        n_sample, n_below = _grid_count_below(d, 4, np.float32(10.0))
        if not n_sample or 2 * n_below >= n_sample:
            sample = d[::4, ::4]
            sample = sample[np.isfinite(sample)]
            med = float(np.median(sample if sample.size else d[np.isfinite(d)]))
            if med < 10.0:
                raise InputError(path, field, "depth in mm (median valid value >= 10)", f"median {med:.4g}",
                                 "this looks like metres: set 'depth_unit: m' in the session's session.yaml")
    if camera is not None:
        camera.check_image_size(d.shape, path, "depth map")
    return d


@numba.njit(cache=True)
def _grid_count_below(d, step, limit):
    """Over every ``step``-th row and column of ``d``: how many values are not NaN, and how many of them are below
    ``limit``."""
    n = below = 0
    for v in range(0, d.shape[0], step):
        for u in range(0, d.shape[1], step):
            x = d[v, u]
            if x == x:
                n += 1
                below += x < limit
    return n, below


def _tiff_image(data: bytes | memoryview) -> np.ndarray:
    """What ``tifffile.imread`` returns for a TIFF file's bytes ``data``. Where the image is the file's one page, stored
    uncompressed as one run of its bytes in this machine's byte order (Mech-Eye's ``DepthMap.tiff``), a read-only view
    of ``data`` (tifffile would copy it into a new array, for a depth map that is copied once more into mm)."""
    with tifffile.TiffFile(io.BytesIO(data)) as tif:
        page = tif.pages[0]
        if len(tif.pages) == 1 and len(tif.series) == 1 and tif.series[0].shape == page.shape and page.ndim == 2 \
                and not page.is_tiled and page.compression == 1 and page.predictor == 1 and page.fillorder == 1 \
                and page.dtype is not None and tif.byteorder == ("<" if sys.byteorder == "little" else ">"):
            offsets, counts = page.dataoffsets, page.databytecounts
            n = page.shape[0] * page.shape[1]
            if sum(counts) == n * page.dtype.itemsize and offsets[0] + sum(counts) <= len(data) \
                    and all(o == offsets[0] + sum(counts[:i]) for i, o in enumerate(offsets)):
                return np.frombuffer(data, page.dtype, n, offsets[0]).reshape(page.shape)
        return tif.asarray()


@numba.njit(cache=True)
def _depth_mm(a, scale):
    """float32 ``a * scale`` with 0, negative, inf and NaN -> NaN, and the number of valid pixels; one pass."""
    H, W = a.shape
    d = np.empty((H, W), np.float32)
    n = 0
    for v in range(H):
        for u in range(W):
            x = np.float32(a[v, u]) * scale
            if x > 0 and x < np.inf:
                d[v, u] = x
                n += 1
            else:
                d[v, u] = np.nan
    return d, n


def read_texture(path: str | Path, camera: PinholeCamera | None = None, field: str = "texture",
                 data: bytes | memoryview | None = None) -> np.ndarray:
    img = read_image(path, field=field, data=data)
    if img.dtype == np.uint16:  # some Mech-Eye exports are 16-bit grey
        img = (img / 257.0).round().astype(np.uint8)
    if img.dtype != np.uint8:
        raise InputError(path, field, "an 8/16-bit image", str(img.dtype),
                         "export the texture as an 8- or 16-bit PNG (Mech-Eye's 2DImage.png)")
    if camera is not None:
        camera.check_image_size(img.shape, path, "texture image")
    return img


# ---- ZED images -----------------------------------------------------------------------------
def split_side_by_side(img: np.ndarray, eye_width_px: int | None = None, path=None) -> tuple[np.ndarray, np.ndarray]:
    w = img.shape[1]
    if w % 2:
        raise InputError(path, "width", "an even side-by-side width (2 x eye width)", f"{w} px",
                         "is the image cropped? a side-by-side frame is the left eye then the right, uncropped")
    half = w // 2
    if eye_width_px is not None and half != eye_width_px:
        raise InputError(path, "width", f"{2 * eye_width_px} px (2 x {eye_width_px} eye width)", f"{w} px",
                         "is this a side-by-side image at the calibrated resolution?")
    return np.ascontiguousarray(img[:, :half]), np.ascontiguousarray(img[:, half:])


def read_video_frame(path: str | Path, frame_index: int = 0) -> np.ndarray:
    """One RGB frame of a side-by-side UVC recording (MP4/AVI) through imageio's ffmpeg plugin."""
    import imageio.v2 as iio2

    path = Path(path)
    if not path.is_file():
        raise MissingFileError(path, "video", "a video file",
                               hint="check the capture folder / session.yaml's files.zed_video "
                                    "(docs/capture-layout.md)")
    try:
        reader = iio2.get_reader(path, format="FFMPEG")
    except Exception as exc:
        raise InputError(path, "video", "an MP4/AVI readable by ffmpeg", f"{type(exc).__name__}",
                         "is the recording complete?") from None
    try:
        n = reader.count_frames()
        if not 0 <= frame_index < n:
            raise InputError(path, "frame", f"a frame index in [0, {n})", str(frame_index),
                             f"set session.yaml's video_frame to a frame of the recording (0 to {n - 1})")
        return np.asarray(reader.get_data(frame_index))[..., :3].copy()
    finally:
        reader.close()


# ---- capture folders ------------------------------------------------------------------------
class FileNames(GTModel):
    """File names inside each capture folder (defaults: vendor names). Override in session.yaml."""

    mech_texture: str = "2DImage.png"
    mech_depth: str = "DepthMap.tiff"
    zed_left: str = "left.png"
    zed_right: str = "right.png"
    zed_side_by_side: str = "zed_sbs.png"
    zed_video: str = "zed.mp4"
    fruit_mask: str = "fruit_mask.png"
    # a separate depth camera's own image, pixel-aligned with its depth (an Azure Kinect's infrared image, which
    # gtforge import writes); optional: align-depth adds its edges where it is there
    depth_texture: str = "IR.png"


class SessionFile(VersionedFile):
    """``session.yaml`` at the root of a capture session (every field optional)."""

    KIND: ClassVar[str] = "session.yaml"

    mech_intrinsics: str = "mech_intrinsics.yaml"
    # a depth camera apart from the texture camera (docs/capture-layout.md); absent: one camera
    depth_intrinsics: str | None = None
    T_mech_from_depth: list[list[float]] | None = None
    # with mech_intrinsics an Azure Kinect calibration.json: the modes the captures were recorded in (docs/cameras.md)
    kinect_depth_mode: Literal["NFOV_2X2BINNED", "NFOV_UNBINNED", "WFOV_2X2BINNED", "WFOV_UNBINNED"] | None = None
    kinect_color_mode: Literal["720P", "1080P", "1440P", "1536P", "2160P", "3072P"] | None = None
    zed_calibration: str = "zed_calibration.yaml"
    zed_right_info: str | None = None
    zed_rectified: bool = True
    # raw ZED images + SN.conf: how the conf's STEREO numbers are read (docs/conventions.md, "ZED SN.conf");
    # absent: gtforge calibrate chooses it from the board images and records it in the calibration file
    zed_conf_reading: ZedConfReading | None = None
    depth_unit: Literal["mm", "m"] = "mm"
    depth_scale_mm: float | None = None
    video_frame: int = Field(0, ge=0)
    board_dir: str = "board"
    scenes_dir: str = "scenes"
    files: FileNames = Field(default_factory=FileNames)
    fruit_ids: dict[str, str] = Field(default_factory=dict)
    # the calibration target (gtforge.core.targets.models.BoardModel: kind, cols, rows, square_size_mm, ...); absent:
    # the command line's (default: the 12x9 checkerboard)
    board: BoardModel | None = None

    @field_validator("T_mech_from_depth", mode="before")
    @classmethod
    def _T4(cls, v):
        return None if v is None else matrix4_field(v)

    @field_validator("fruit_ids", mode="before")
    @classmethod
    def _quoted_ids(cls, v):
        # YAML reads an unquoted 000 as the number 0: its scene's name is gone, so it is refused, not guessed
        if isinstance(v, dict):
            numbers = [k for k in v if not isinstance(k, str)]
            if numbers:
                raise ValueError(f"scene ids as text: quote them in YAML ('000': melon07); {numbers[0]!r} reads as a "
                                 "number")
        return v


def evenly_spread(items: Sequence, k: int | None) -> list:
    """At most ``k`` of ``items``, evenly spread over their order (the first and, for ``k`` > 1, the last among them);
    all of them when ``k`` is None or not fewer. The stages that fit a few terms to a session's scenes use this many
    (``SelfRectifyParams``, ``ScaleParams``, ``RefineParams``: ``max_scenes``), the same ones every time."""
    n = len(items)
    if k is None or k >= n:
        return list(items)
    return [items[i] for i in np.unique(np.round(np.linspace(0, n - 1, k)).astype(int))]


@dataclass
class Capture:
    """One capture: structured-light texture + depth, rectified ZED left/right (RGB uint8).

    ``mech_texture``, ``zed_left`` and ``zed_right`` are None when the capture was loaded with
    ``decode_images=False`` and the files passed the header checks (see ``Session.load_capture``)."""

    name: str
    folder: Path
    mech_texture: np.ndarray | None
    depth_mm: np.ndarray  # on the depth camera's pixel grid (the texture camera's when the unit has one camera)
    zed_left: np.ndarray | None
    zed_right: np.ndarray | None
    fruit_mask: np.ndarray | None = None
    fruit_id: str | None = None
    input_files: list[Path] = field(default_factory=list)
    # set when zed_left / zed_right are exactly an RGB PNG file's pixels (no split, rectification, conversion)
    zed_left_file: Path | None = None
    zed_right_file: Path | None = None
    # the input files read whole to build the arrays above, by name: the BLAKE3 of exactly the bytes decoded
    read_records: dict[str, "ReadRecord"] = field(default_factory=dict)
    # the bytes of the ZED PNGs ``Session.decoded_images`` read, by name: a build writes them out as im0/im1 from here
    # instead of reading the files a second time
    read_buffers: dict[str, AlignedBuffer] = field(default_factory=dict)


@dataclass(frozen=True)
class ReadRecord:
    """A file as it was read: the BLAKE3 of the bytes (``io.digest``), and its size and modification time from just
    before."""

    blake3: str
    size_bytes: int
    mtime_ns: int
    read_at_ns: int


def read_recorded(path: Path, records: dict[str, ReadRecord],
                  buffers: dict[str, AlignedBuffer] | None = None) -> bytes | memoryview | None:
    """The bytes of ``path``, recorded in ``records`` under its name (hashing what is read saves reading the file
    again to hash it, and the hash is of the very bytes the scene was built from). None when it cannot be read,
    for the reader to report as usual; not recorded when the file changed size while being read. ``buffers``: the
    bytes are read into an ``AlignedBuffer``, kept there under the file's name (ready to be written out again past
    the page cache, ``atomic.atomic_write_buffer``), and a memoryview of it is returned; without it, ``bytes`` (which
    ``io.BytesIO`` shares instead of copying, as the TIFF reader's does)."""
    try:
        st = path.stat()
        read_at_ns = time.time_ns()
        if buffers is None:
            data = path.read_bytes()
        else:
            with open(path, "rb", buffering=0) as f:
                buf = aligned_buffer(st.st_size)
                n = f.readinto(buf.padded)  # (one byte more than the size fits, if the file grew)
                while n < len(buf.padded) and (k := f.readinto(buf.padded[n:])):
                    n += k
                same_size = n == st.st_size and not f.read(1)
            data = memoryview(buf.data) if same_size else path.read_bytes()  # (changed while read: as it is now)
    except OSError:
        return None
    if len(data) == st.st_size:
        records[path.name] = ReadRecord(blake3_hex(data), st.st_size, st.st_mtime_ns, read_at_ns)
        if buffers is not None and same_size:
            buffers[path.name] = buf
    return data


def missing_capture_file(exc: InputError) -> bool:
    """Whether ``load_capture`` failed because a file of the capture is not there (a capture that did not complete):
    the stages that read many captures skip that one with a warning, as one whose board is not found; a file that is
    there but wrong stops them (one line, exit 2)."""
    return isinstance(exc, MissingFileError)


def leave_out_hint(exc: InputError, capture: str, option: str = "--captures") -> InputError:
    """``exc`` with a hint that names the option that leaves the capture out."""
    hint = (f"or leave capture {capture} out with {option} (the other captures' names; gtforge run has no such option: "
            "move the folder out of the session)")
    return InputError(exc.file, exc.field, exc.expected, exc.actual, f"{exc.hint}; {hint}" if exc.hint else hint)


@dataclass
class Session:
    root: Path
    config: SessionFile
    mech: PinholeCamera  # the texture camera (2D image)
    zed: RectifiedStereo
    # ZedRectification when raw images + SN.conf; for images rectified before gtforge with a correction of the right
    # camera, gtforge.core.zed.selfcal.RightImageCorrection (the self-rectification) or CorrectedRightImage (with
    # calibrate-scale's yaw); None: the images are used as they are
    rectification: object | None
    depth_cam: PinholeCamera | None = None  # the depth map's camera when it is not the texture camera
    T_mech_from_depth: np.ndarray | None = None

    @property
    def depth_camera(self) -> PinholeCamera:
        return self.depth_cam if self.depth_cam is not None else self.mech

    def capture_roots(self) -> list[Path]:
        """The folders that hold captures (``board/``, ``scenes/``, ``gauges/``), as named in the session."""
        return [self.root / self.config.board_dir, self.root / self.config.scenes_dir, self.root / "gauges"]

    def session_files(self) -> list[Path]:
        """The files the session reads besides its captures: ``session.yaml`` and every file it names (the texture
        and depth cameras' intrinsics, the ZED calibration or SN.conf, the right camera's info)."""
        c = self.config
        names = [c.mech_intrinsics, c.depth_intrinsics, c.zed_calibration, c.zed_right_info]
        return [self.root / "session.yaml"] + [self.root / n for n in names if n]

    def refuse_output_over_inputs(self, out: str | Path, option: str = "--output") -> None:
        """Refuse an output path inside the session folder, one that contains a capture folder, or a file the session
        reads (``session_files``, wherever they are): a session's inputs are never written, nor anything put into its
        folder, under any spelling of the path (relative, ``..``, symbolic or hard links).

        Symlinked captures count with both their name and their target."""
        out_abs = Path(os.path.abspath(out))
        out_real = Path(os.path.realpath(out))
        for f in self.session_files():
            if not (f.exists() or f.is_symlink()):
                continue
            same = out_real == Path(os.path.realpath(f)) or out_abs == Path(os.path.abspath(f))
            if not same and out_real.exists():
                try:
                    same = os.path.samefile(out_real, f)
                except OSError:
                    same = False
            if same:
                raise InputError(out, option, "a path that is not one of the session's own files",
                                 f"the session's {f.name} ({os.path.realpath(f)})",
                                 "the session's files are never written; write the output beside the session, "
                                 "e.g. -o calib.yaml")
        for root in {Path(os.path.abspath(self.root)), Path(os.path.realpath(self.root))}:
            for o in {out_abs, out_real}:
                if o == root or root in o.parents:
                    raise InputError(out, option, "a path outside the session folder (its captures and files are never "
                                     "written, nor anything put beside them)",
                                     "the session folder itself" if o == root else f"a path inside {root}",
                                     f"write the output beside the session, e.g. {option} "
                                     f"{free_path(root.parent, o.name if o != root else 'out')}")
        protected: list[Path] = []
        for croot in self.capture_roots():
            if croot.is_dir():
                protected += [Path(os.path.abspath(croot)), Path(os.path.realpath(croot))]
                for c in croot.iterdir():
                    if c.is_dir():
                        protected += [Path(os.path.abspath(c)), Path(os.path.realpath(c))]
        for o in {out_abs, out_real}:
            for p in protected:
                if o == p or p in o.parents or o in p.parents:
                    raise InputError(out, option, "a folder outside the session's capture folders",
                                     f"a path {'inside' if o == p or p in o.parents else 'containing'} {p}",
                                     "captures are never written; choose a separate output folder")

    def capture_dirs(self, kind: Literal["board", "scenes"]) -> list[Path]:
        d = self.root / (self.config.board_dir if kind == "board" else self.config.scenes_dir)
        if not d.is_dir():
            raise InputError(d, None, f"a folder of {kind} captures", "no such folder",
                             "see docs/capture-layout.md" + ("; gtforge import puts a capture in board/ only where it "
                                                             "finds the board its --board/--cols/--rows declare"
                                                             if (self.root / "import.json").is_file() else ""))
        dirs = sorted(p for p in d.iterdir() if p.is_dir() and not p.name.startswith("."))
        if not dirs:
            raise InputError(d, None, "at least one capture folder", "none",
                             f"put each {kind} capture in a folder of its own in it (docs/capture-layout.md)")
        # ids are the names in the session (a symlinked capture keeps its link's name); one capture
        # reached under two names would be built twice and could land in two splits
        seen: dict[Path, Path] = {}
        for p in dirs:
            real = p.resolve()
            if real in seen:
                raise InputError(p, None, "each capture folder once", f"the same capture as {seen[real].name} ({real})",
                                 "remove the duplicate link")
            seen[real] = p
            if kind == "scenes" and any(c.isspace() for c in p.name):
                raise InputError(p, "scene id", "a folder name without spaces (the scene's id in the dataset's "
                                 "space-separated split lists)", repr(p.name), "rename the folder")
        return dirs

    def select(self, kind: Literal["board", "scenes"], include: list[str] | None = None,
               exclude: list[str] | None = None, option: str | None = None) -> list[Path]:
        """Capture folders of ``kind``, optionally only ``include`` and never ``exclude`` (by folder name).
        ``option``: the command-line option ``include`` came from, named in the error for an unknown name (default
        ``--captures`` for boards, ``--scenes`` for scenes)."""
        dirs = self.capture_dirs(kind)
        names = {d.name for d in dirs}
        include_option = option or ("--captures" if kind == "board" else "--scenes")
        for given, given_by in ((include, include_option), (exclude, "exclude")):
            unknown = [n for n in (given or []) if n not in names]
            if unknown:
                raise InputError(dirs[0].parent, given_by, f"capture names of {kind}/ ({first_of(sorted(names))})",
                                 ", ".join(unknown), "names are the capture folders' names")
        if include:
            dirs = [d for d in dirs if d.name in set(include)]
        if exclude:
            dirs = [d for d in dirs if d.name not in set(exclude)]
        return dirs

    def select_scenes(self, include: list[str] | None, most: int | None) -> tuple[list[Path], int]:
        """The scene folders ``include`` names (``select``), or, without names, at most ``most`` of the session's scenes
        (``evenly_spread``; None: every one); and how many scenes that leaves out (0 when they are named)."""
        dirs = self.select("scenes", include)
        if include is not None:
            return dirs, 0
        chosen = evenly_spread(dirs, most)
        return chosen, len(dirs) - len(chosen)

    def capture_files(self, folder: Path) -> list[Path]:
        """The input files a capture uses (for hashing), without reading them."""
        f = self.config.files
        out = [folder / f.mech_depth, folder / f.mech_texture]
        if (folder / f.zed_left).exists():
            out += [folder / f.zed_left, folder / f.zed_right]
        elif (folder / f.zed_side_by_side).exists():
            out.append(folder / f.zed_side_by_side)
        elif (folder / f.zed_video).exists():
            out.append(folder / f.zed_video)
        if (folder / f.fruit_mask).exists():
            out.append(folder / f.fruit_mask)
        return out

    def load_capture(self, folder: str | Path, need_right: bool = True, decode_images: bool = True) -> Capture:
        """Read one capture folder. ``decode_images=False`` (a build: it copies the ZED PNGs, and decodes the images
        only if its verification reads them, with ``decoded_images``): the texture and separate ZED left/right files
        that are complete PNGs (IEND present) of the right size and type, without rectification, are checked from
        their headers and not decoded; their arrays are then None. Anything else is decoded as usual, so every error
        stays the same."""
        folder = Path(folder)
        f = self.config.files
        records: dict[str, ReadRecord] = {}
        tex_path = folder / f.mech_texture
        tex_size = self.mech.width_px, self.mech.height_px
        tex = None if not decode_images and _png_checks_out(tex_path, tex_size, (0, 2)) else read_texture(
            tex_path, self.mech, "mech_texture", read_recorded(tex_path, records))
        depth_path = folder / f.mech_depth
        depth = read_depth(depth_path, self.config.depth_unit, self.config.depth_scale_mm, self.depth_camera,
                           "mech_depth", read_recorded(depth_path, records))
        eye_w = self.zed.left.width_px
        verbatim: list[Path | None] = [None, None]
        zed_files = folder / f.zed_left, folder / f.zed_right
        eye_size = self.zed.left.width_px, self.zed.left.height_px
        if not decode_images and self.rectification is None and all(
                _png_checks_out(p, eye_size, (2,)) for p in zed_files):
            left = right = None
            verbatim = list(zed_files)
        elif (folder / f.zed_left).exists():
            left = read_image(folder / f.zed_left, expect="uint8", field="zed_left",
                              data=read_recorded(folder / f.zed_left, records))
            right = read_image(folder / f.zed_right, expect="uint8", field="zed_right",
                               data=read_recorded(folder / f.zed_right, records)) if need_right or (
                folder / f.zed_right).exists() else None
            src = src_right = folder / f.zed_left
            if right is not None:
                src_right = folder / f.zed_right
            verbatim = [p if _is_rgb8_png(p) else None for p in (folder / f.zed_left, folder / f.zed_right)]
        elif (folder / f.zed_side_by_side).exists():
            src = src_right = folder / f.zed_side_by_side
            left, right = split_side_by_side(read_image(src, expect="uint8", field="zed_side_by_side",
                                                        data=read_recorded(src, records)), eye_w, src)
        elif (folder / f.zed_video).exists():
            src = src_right = folder / f.zed_video
            left, right = split_side_by_side(read_video_frame(src, self.config.video_frame), eye_w, src)
        else:
            raise MissingFileError(folder, "zed images",
                                   f"{f.zed_left}+{f.zed_right}, {f.zed_side_by_side} or {f.zed_video}",
                                   "none of them", "see docs/capture-layout.md")
        if left is not None:
            if left.ndim == 2:
                left = np.repeat(left[..., None], 3, axis=2)
            if right is not None and right.ndim == 2:
                right = np.repeat(right[..., None], 3, axis=2)
            self.zed.left.check_image_size(left.shape, src, "ZED left image")
            if right is not None:
                self.zed.left.check_image_size(right.shape, src_right, "ZED right image")
            if self.rectification is not None and right is not None:
                left, right = self.rectification.rectify(left, right)
                # (a correction of the right camera alone may leave the left image the file's pixels)
                verbatim = [verbatim[0] if getattr(self.rectification, "left_unchanged", False) else None, None]
        mask = None
        if (folder / f.fruit_mask).exists():
            mask = read_image(folder / f.fruit_mask, field="fruit_mask",
                              data=read_recorded(folder / f.fruit_mask, records))
            if mask.ndim == 3:
                mask = mask[..., 0]
            self.zed.left.check_image_size(mask.shape, folder / f.fruit_mask, "fruit mask")
            mask = mask > 0
        return Capture(folder.name, folder, tex, depth, left, right, mask,
                       self.config.fruit_ids.get(folder.name), self.capture_files(folder), *verbatim, records)

    def decoded_images(self, cap: Capture, zed_rows: int | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``(texture, ZED left, ZED right)`` of a capture, decoding what ``load_capture(decode_images=False)`` left
        undecoded (read now and recorded in ``cap.read_records``, as load_capture records what it reads; the header
        checks were done then). ``zed_rows``: only the ZED images' first rows are needed (``verify.zed_rows_used``):
        an undecoded one is decoded that far only, and its array has that many rows."""
        f = self.config.files
        tex = cap.mech_texture
        if tex is None:
            path = cap.folder / f.mech_texture
            tex = read_texture(path, self.mech, "mech_texture", read_recorded(path, cap.read_records))
        eyes = []
        for img, path, name in ((cap.zed_left, cap.zed_left_file, "zed_left"),
                                (cap.zed_right, cap.zed_right_file, "zed_right")):
            if img is None and path is not None:
                img = read_image(path, expect="uint8", field=name,
                                 data=read_recorded(path, cap.read_records, cap.read_buffers), rows=zed_rows)
            eyes.append(img)
        return tex, eyes[0], eyes[1]


_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def _png_header(path: Path) -> tuple[int, int, int, int, bool] | None:
    """``(width, height, bit depth, colour type, ends with IEND)`` of a PNG from its first 26 and last 12 bytes;
    None when the file cannot be read or is no PNG."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(26)
            fh.seek(-12, os.SEEK_END)
            tail = fh.read(12)
    except OSError:
        return None
    if len(head) < 26 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    return (int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big"), head[24], head[25],
            tail == _PNG_IEND)


def _is_rgb8_png(path: Path) -> bool:
    """True for an 8-bit RGB (colour type 2) PNG, read from its IHDR header."""
    h = _png_header(path)
    return h is not None and h[2] == 8 and h[3] == 2


def _png_checks_out(path: Path, size_wh: tuple[int, int], colour_types: tuple[int, ...]) -> bool:
    """True when ``path`` is an 8-bit PNG of ``size_wh`` with one of ``colour_types`` (0 grey, 2 RGB) that ends
    with its IEND chunk (not truncated). False for anything else, including unreadable files: the caller then
    decodes the file and reports what is wrong."""
    h = _png_header(path)
    return h is not None and (h[0], h[1]) == tuple(size_wh) and h[2] == 8 and h[3] in colour_types and h[4]


def _what_folder_holds(root: Path) -> str:
    """A folder's first few entries, named for an error message."""
    names = sorted(e.name + ("/" if e.is_dir() else "") for e in root.iterdir())
    if not names:
        return "it is empty"
    return "it holds " + ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")


# an import --add's journal in the folder beside the session where the import writes before its captures land: the
# run being landed, written whole before its first capture moves (open_session refuses the session while it is there)
IMPORT_LANDING = ".landing"


def import_partial_folder(session: str | Path) -> Path:
    """Where ``gtforge import`` writes a session's captures before they land: beside the session's real folder."""
    real = Path(os.path.realpath(session))
    return real.parent / f".{real.name}.import-partial"


def open_session(root: str | Path, zed_conf_reading: str | None = None, zed_right_correction=None,
                 zed_right_yaw_deg: float = 0.0) -> Session:
    """Read ``session.yaml`` (optional) and the camera files of a capture session.

    ``zed_conf_reading``: the SN.conf reading a calibration file recorded (``CalibrationFile.zed_conf``);
    it must agree with session.yaml's ``zed_conf_reading`` when both are set. Neither: the default reading
    (``gtforge.io.cameras.DEFAULT_ZED_CONF_READING``); calibrate then chooses from the board images.
    ``zed_right_correction``: the right camera's correction a calibration file recorded
    (``gtforge.core.zed.selfcal.ZedRightCorrection``): folded into the SN.conf rectification of raw images, or applied
    to the right image of images rectified before gtforge. ``zed_right_yaw_deg``: calibrate-scale's yaw of the right
    camera (``Rig.scale_corrections``), composed with it into the same single resampling of the right image
    (``gtforge.core.zed.selfcal.corrected_right``)."""

    root = Path(root)
    if not root.is_dir():
        raise InputError(root, None, "a capture session folder", "no such folder", "see docs/capture-layout.md")
    landing = import_partial_folder(root) / IMPORT_LANDING
    if landing.is_file():  # some of an import's captures are in the session, the rest beside it, import.json not yet
        raise InputError(root, "captures", "a session whose last import --add landed whole",
                         f"one cut off while its captures landed ({landing.parent} holds the rest)",
                         "run the same gtforge import --add again: it finishes the landing first")
    cfg_path = root / "session.yaml"
    cfg = SessionFile.read(cfg_path) if cfg_path.exists() else SessionFile()
    if not cfg_path.exists() and (gtforge_folder_kind(root) or not any(
            (root / n).exists() for n in (cfg.mech_intrinsics, cfg.zed_calibration, "board", "scenes"))):
        raise InputError(root, None, "a capture session folder (session.yaml, mech_intrinsics.yaml, "
                         "zed_calibration.yaml, board/, scenes/: docs/capture-layout.md)",
                         f"{kind} (no session.yaml)" if (kind := gtforge_folder_kind(root)) else
                         f"a folder with none of them ({_what_folder_holds(root)})",
                         "check the path; gtforge import writes a session from recordings, gtforge synth a "
                         "synthetic one")
    # a vendor file may hold both cameras (Kinect calibration.json, Mech-Eye API YAML): docs/cameras.md
    cams = load_structured_light_cameras(root / cfg.mech_intrinsics, depth_mode=cfg.kinect_depth_mode,
                                         color_mode=cfg.kinect_color_mode)
    mech, depth_cam, T_mech_from_depth = cams
    if depth_cam is not None and (cfg.depth_intrinsics or cfg.T_mech_from_depth is not None):
        raise InputError(cfg_path, "depth_intrinsics/T_mech_from_depth", "no separate depth camera when "
                         f"mech_intrinsics ({cfg.mech_intrinsics}) already holds one", "both",
                         "remove depth_intrinsics and T_mech_from_depth from session.yaml")
    if depth_cam is None:
        depth_cam = load_camera(root / cfg.depth_intrinsics) if cfg.depth_intrinsics else None
        T_mech_from_depth = np.array(cfg.T_mech_from_depth) if cfg.T_mech_from_depth is not None else None
    zpath = root / cfg.zed_calibration
    if not zpath.is_file():
        raise InputError(zpath, "zed_calibration", "the stereo camera's calibration (session.yaml's zed_calibration)",
                         "no such file", _no_stereo_hint(root))
    rectification = None
    if zpath.suffix.lower() == ".conf":
        # raw images: the eye width comes from the first image found
        eye_w = _guess_eye_width(root, cfg)
        if zed_conf_reading and cfg.zed_conf_reading and zed_conf_reading != cfg.zed_conf_reading:
            raise InputError(cfg_path, "zed_conf_reading", f"'{zed_conf_reading}', as the calibration recorded",
                             f"'{cfg.zed_conf_reading}'", "calibrate again, or set session.yaml back to the reading "
                             "the calibration was made with")
        reading = zed_conf_reading or cfg.zed_conf_reading or DEFAULT_ZED_CONF_READING
        rectification = read_zed_conf(zpath, eye_w).rectification(reading)
        zed = rectification.stereo
        if cfg.zed_rectified:
            rectification = None  # SDK-rectified images with the factory conf: only the model is used
    else:
        zed = load_zed_rectified(zpath, root / cfg.zed_right_info if cfg.zed_right_info else None)
    if not MIN_BASELINE_MM <= zed.baseline_mm <= MAX_BASELINE_MM:  # (a length in metres: 0.063 for a ZED Mini)
        raise InputError(zpath, "baseline", f"a stereo baseline in mm, {MIN_BASELINE_MM:g} to {MAX_BASELINE_MM:g} "
                         "(a ZED Mini's is 63 mm, a ZED 2's 120 mm)", f"{zed.baseline_mm:g} mm",
                         "is it in metres or micrometres? gtforge's lengths are in mm (docs/conventions.md)")
    rectification = corrected_right(rectification, zed, zed_right_correction, zed_right_yaw_deg)
    return Session(root, cfg, mech, zed, rectification, depth_cam, T_mech_from_depth)


# the stereo baselines a session may have: a length outside is in another unit (metres, micrometres)
MIN_BASELINE_MM = 1.0
MAX_BASELINE_MM = 10_000.0


def _no_stereo_hint(root: Path) -> str:
    """What to do about a session without its stereo camera's calibration: a session ``gtforge import`` wrote from
    a depth recording alone has no stereo images either. (``import.json`` read as plain JSON: its model,
    ``records.imports.ImportRecord``, is a layer above this module.)"""
    import json

    try:
        runs = json.loads((root / "import.json").read_text(encoding="utf-8"))["runs"]
        depth_only = bool(runs) and all(r.get("stereo_recording") is None for r in runs)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        depth_only = False
    if depth_only:
        return ("this session was imported from a depth recording alone (import.json): its captures have no stereo "
                "images; import the depth and the stereo recordings together: gtforge import DEPTH STEREO -o SESSION")
    return "check the path in session.yaml (docs/capture-layout.md)"


def _guess_eye_width(root: Path, cfg: SessionFile) -> int:
    f = cfg.files
    for kind in (cfg.board_dir, cfg.scenes_dir):
        d = root / kind
        if not d.is_dir():
            continue
        for cap in sorted(d.iterdir()):
            if (cap / f.zed_left).exists():
                return read_image(cap / f.zed_left).shape[1]
            if (cap / f.zed_side_by_side).exists():
                return read_image(cap / f.zed_side_by_side).shape[1] // 2
    raise InputError(root, "zed images", "at least one ZED image to choose the SN.conf resolution", "none found",
                     f"put the ZED images in the captures under {cfg.board_dir}/ or {cfg.scenes_dir}/ with the names "
                     f"of session.yaml's files ({f.zed_left}, {f.zed_side_by_side}; docs/capture-layout.md)")
