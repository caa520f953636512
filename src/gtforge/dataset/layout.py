"""A dataset folder's files and how a build knows a scene is up to date: the files a scene holds, its inputs' hashes
(BLAKE3, with a size+mtime fast path) and the checks that a landed scene is the one this build asked for."""
from __future__ import annotations

import os
import time
from collections.abc import Callable, Collection
from pathlib import Path
from typing import TYPE_CHECKING

from gtforge.errors import InputError, first_of
from gtforge.infra.digest import blake3_file
from gtforge.io.outputs import DATASET_FILES, DATASET_FOLDERS, free_path
from gtforge.records.dataset import BuildParams, InputStamp, SceneMeta

if TYPE_CHECKING:
    from gtforge.io.captures import ReadRecord


# the KITTI view's disparity folders (its image_2/image_3 are links to the scene's im0/im1)
KITTI_DISPARITY_DIRS = ("disp_occ_0", "disp_noc_0", "disp_occ_1", "disp_noc_1")



def require_dataset(path: str | Path, manifest_hint: str) -> Path:
    """``path`` is a dataset build-dataset wrote (a folder with its manifest.json), for the stages that read one
    (verify, evaluate); ``manifest_hint``: what to do about a folder without a manifest, in the stage's words."""
    ds = Path(path)
    if not ds.is_dir():
        raise InputError(ds, None, "a dataset folder built by gtforge build-dataset",
                         "a file" if ds.is_file() else "no such folder",
                         f"give the folder that holds it ({ds.parent})" if ds.is_file()
                         else "check the path (the -o of build-dataset)")
    if not (ds / "manifest.json").is_file():
        raise InputError(ds, "manifest.json", "a dataset built by gtforge build-dataset", "no manifest.json",
                         manifest_hint)
    return ds


def require_dataset_folder(out: Path, session, overwrite: bool, option: str = "--output") -> None:
    """build-dataset's output folder: new or empty, a dataset it built from this session before (or what a first
    build cut off left: only the entries a dataset holds), a dataset built from a copy of this session elsewhere
    (``_built_from_these_captures``: a session moved or copied with its dataset), or, with ``overwrite``, any dataset.
    Refused: a ``gtforge run``'s output folder (its dataset is ``dataset/`` inside it), a dataset built from another
    session (this session's scenes would replace those with the same ids and leave the others in scenes/, kitti/ and
    eth3d/, one dataset of two sessions), a folder holding anything else. ``session``: the ``CaptureSession``."""
    if not out.is_dir():
        return
    if (out / "run_state.json").is_file():
        raise InputError(out, option, "a folder for a dataset (new, empty, or a dataset build-dataset wrote)",
                         "gtforge run's output folder",
                         f"the run's dataset is {out / 'dataset'}: rerun gtforge run, or build into a new folder, "
                         f"e.g. {free_path(out.parent, 'dataset')}")
    manifest = out / "manifest.json"
    if manifest.is_file():
        recorded = _read_manifest(manifest)
        where = recorded.get("session_dir")
        if isinstance(where, str) and where and not overwrite and not _same_folder(Path(where), session.root) \
                and not _built_from_these_captures(recorded.get("scenes"), session):
            raise InputError(manifest, "session_dir", f"a dataset built from this session ({session.root.resolve()})",
                             f"one built from {where}, whose scenes' inputs are not this session's",
                             "build into a new folder (this session's scenes would replace that dataset's with the "
                             "same ids and leave its others beside them); if the session was moved from there and "
                             "its captures edited since, --overwrite rebuilds every scene from it here")
        return
    foreign = sorted(e.name for e in out.iterdir()
                     if not e.name.startswith(".") and e.name not in DATASET_FOLDERS + DATASET_FILES)
    if foreign:
        raise InputError(out, option, "a folder for a dataset (new, empty, or a dataset build-dataset wrote)",
                         f"a folder holding {first_of(foreign)}, which no dataset holds",
                         f"give a new folder, e.g. {free_path(out, 'dataset')}")


def _read_manifest(manifest: Path) -> dict:
    """An earlier build's manifest as plain JSON, or {} where it cannot be read (the build reads it again, and
    reports what is wrong with it)."""
    import json

    try:
        value = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return value if isinstance(value, dict) else {}


def _built_from_these_captures(scenes, session) -> bool:
    """Whether a dataset whose manifest holds ``scenes`` (scene id -> its meta, as JSON) was built from copies of
    this session's captures: at least half of its scenes are scene folders here that still have the input files it
    recorded, with the recorded sizes (a stat each, no reading). Captures deleted or edited since are left out or
    rebuilt by the build as in its own folder; two sessions' PNG and TIFF captures do not agree in size file for
    file."""
    if not isinstance(scenes, dict) or not scenes:
        return False
    here = {d.name: d for d in session.capture_dirs("scenes")}
    same = 0
    for sid, meta in scenes.items():
        stamps = meta.get("input_stamps") if isinstance(meta, dict) else None
        if sid not in here or not isinstance(stamps, dict) or not stamps:
            continue
        files = {p.name: p for p in session.capture_files(here[sid]) if p.exists()}
        if set(files) == set(stamps) and all(isinstance(s, dict) and files[n].stat().st_size == s.get("size_bytes")
                                             for n, s in stamps.items()):
            same += 1
    return 2 * same >= len(scenes)


def _same_folder(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


# A recorded size + mtime is trusted only when the file was last modified this long before it was hashed:
# a file rewritten within the filesystem's timestamp granularity of the hash could keep both (as git's
# "racily clean" entries).
STAMP_MARGIN_NS = 2_000_000_000



def hash_inputs(paths: list[Path], read: dict[str, "ReadRecord"] | None = None
                ) -> tuple[dict[str, str], dict[str, "InputStamp"]]:
    """BLAKE3 of each input (``io.digest``), and its size + mtime taken just before hashing (for
    ``inputs_unchanged``).
    ``read``: files the capture reader already hashed as it read them (``Capture.read_records``), by name."""
    hashes, stamps = {}, {}
    for p in paths:
        r = (read or {}).get(p.name)
        if r is not None:
            hashes[p.name] = r.blake3
            stamps[p.name] = InputStamp(size_bytes=r.size_bytes, mtime_ns=r.mtime_ns, hashed_at_ns=r.read_at_ns)
            continue
        st = p.stat()
        now_ns = time.time_ns()
        hashes[p.name] = blake3_file(p)
        stamps[p.name] = InputStamp(size_bytes=st.st_size, mtime_ns=st.st_mtime_ns, hashed_at_ns=now_ns)
    return hashes, stamps



def inputs_unchanged(meta: "SceneMeta", paths: list[Path]) -> bool:
    """Resume check: the same input files with the same contents as when ``meta``'s scene was built.
    A file whose size and mtime equal the recorded ones (and was not modified within ``STAMP_MARGIN_NS``
    of being hashed) counts as unchanged without reading it; any other file is hashed and compared."""
    if {p.name for p in paths} != set(meta.input_blake3):
        return False
    for p in paths:
        st = p.stat()
        s = meta.input_stamps.get(p.name)
        if s is not None and s.size_bytes == st.st_size and s.mtime_ns == st.st_mtime_ns \
                and s.mtime_ns < s.hashed_at_ns - STAMP_MARGIN_NS:
            continue
        if blake3_file(p) != meta.input_blake3[p.name]:
            return False
    return True



def scene_files(params: BuildParams) -> list[str]:
    """The files build_one_scene writes into a scene folder with these parameters."""
    return (["im0.png", "im1.png", "disp0GT.pfm", "mask0nocc.png", "region.png", "weight.tiff", "depth0.tiff",
             "calib.txt", "meta.json"] + (["disp1GT.pfm", "mask1nocc.png"] if params.right_gt else [])
            + (["disp0GT_sigma.pfm"] if params.sigma else []) + (["cloud.ply"] if params.ply else []))



def file_stamp(path: Path) -> tuple[int, int] | None:
    """``path``'s (inode, mtime in ns), None if it does not exist: tells a file written since from the one seen."""
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mtime_ns



def landed_meta(out: Path, sid: str, stamp_before: tuple[int, int] | None, phash: Callable[[SceneMeta], str],
                calib_sha: str, expected: list[str]) -> "SceneMeta | None":
    """The meta of scene ``sid`` if a worker of this run landed it whole (a new meta.json, for these parameters and
    this calibration, with every scene file) and then died before it reported it; else None."""
    meta_path = out / "scenes" / sid / "meta.json"
    if file_stamp(meta_path) in (None, stamp_before):
        return None
    try:
        m = SceneMeta.read(meta_path)
    except InputError:
        return None
    return m if built_as_asked(m, meta_path.parent, phash, calib_sha, expected) else None



def built_as_asked(m: SceneMeta, scene_dir: Path, phash: Callable[[SceneMeta], str], calib_sha: str,
                   expected: list[str]) -> bool:
    """Whether the scene in ``scene_dir`` (its meta ``m``) was built with these parameters (``phash(m)``: the hash
    such a scene records) and this calibration and still has every scene file (none deleted since)."""
    return m.params_hash == phash(m) and m.calibration_sha256 == calib_sha and \
        all((scene_dir / name).is_file() for name in expected)


def plan_scenes(session, dirs: list[Path], out: Path, phash: Callable[[SceneMeta], str], calib_sha: str,
                expected: list[str], overwrite: bool = False,
                rebuild: Collection[str] = ()) -> tuple[list[Path], list[str], dict[str, SceneMeta]]:
    """Which capture folders a build must (re)build: ``(todo, unchanged scene ids, their metas)``. A scene is
    unchanged when its folder was built with these parameters and this calibration, holds every expected file, and
    its inputs are unchanged (``inputs_unchanged``); ``overwrite`` rebuilds every scene, ``rebuild`` those named."""
    todo, unchanged, metas = [], [], {}
    for d in dirs:
        meta_path = out / "scenes" / d.name / "meta.json"
        if not overwrite and d.name not in rebuild and meta_path.exists():
            try:
                m = SceneMeta.read(meta_path)
                files = [p for p in session.capture_files(d) if p.exists()]
                if built_as_asked(m, meta_path.parent, phash, calib_sha, expected) and inputs_unchanged(m, files):
                    unchanged.append(d.name)
                    metas[d.name] = m
                    continue
            except InputError:
                pass
        todo.append(d)
    return todo, unchanged, metas

