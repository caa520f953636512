"""Checks on the folders a stage is asked to write into, made before anything is written; and the folders a stage
made, removed again when it stopped on bad input before writing into them."""
from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from gtforge.errors import InputError


# the folders gtforge writes whole, by the file that marks each
GTFORGE_FOLDERS = (("run_state.json", "gtforge run's output folder"), ("manifest.json", "a dataset gtforge built"),
                   ("session.yaml", "a capture session"))


def gtforge_folder_kind(path: str | Path) -> str | None:
    """What ``path`` is where gtforge writes it whole (a run's outputs, a dataset, a session); else None."""
    for marker, kind in GTFORGE_FOLDERS:
        if (Path(path) / marker).is_file():
            return kind
    return None


def refuse_gtforge_folder(path: str | Path, option: str = "--output") -> None:
    """A stage's outputs never go into a run's, a dataset's or a session's own folder (their files would sit among
    another stage's, which neither knows of)."""
    kind = gtforge_folder_kind(path)
    if kind is not None:
        raise InputError(path, option, "a folder for this stage's outputs (new, empty, or its own earlier one)",
                         kind, "give a new folder, e.g. beside it")


# the folders build-dataset writes inside a dataset (its scenes and the layouts training code reads)
DATASET_FOLDERS = ("scenes", "views", "kitti", "eth3d", "filenames", "verification", "report")
# and the files at its top
DATASET_FILES = ("manifest.json", "build_report.html", "verification.html", "verification.json")


def folders_above(path: str | Path) -> Iterator[tuple[Path, Path]]:
    """``(p, a)`` for each folder ``a`` above ``path``, under both its spellings ``p``: absolute as given, and with
    symbolic links and ``..`` resolved (a marker file above either makes ``path`` part of what it marks)."""
    for p in dict.fromkeys((Path(os.path.abspath(path)), Path(os.path.realpath(path)))):
        for a in p.parents:
            yield p, a


def refuse_inside_dataset_folders(path: str | Path, option: str = "--output") -> None:
    """No stage's output inside the folders build-dataset writes in a dataset (any dataset above ``path``, a run's
    ``dataset/`` too): its files would sit among the scenes and layouts that training code reads. A new folder
    beside them (``DATASET/evaluation``) is fine. Under any spelling of the path (relative, ``..``, symbolic links)."""
    for p, a in folders_above(path):
        if (a / "manifest.json").is_file():
            first = p.relative_to(a).parts[0]
            if first in DATASET_FOLDERS:
                raise InputError(path, option, "a path outside the folders build-dataset writes",
                                 f"a path inside the dataset's {first}/ ({a})",
                                 "a dataset's scenes and layouts are its own; write beside them, e.g. "
                                 f"{a / 'evaluation'}")


# what marks a capture session without a session.yaml (docs/capture-layout.md: every field has a default): one of its
# camera files under the default name beside its captures
SESSION_CAMERA_FILES = ("mech_intrinsics.yaml", "zed_calibration.yaml")
SESSION_CAPTURE_FOLDERS = ("board", "scenes")


def is_capture_session(folder: str | Path) -> bool:
    """``folder`` is a capture session: its ``session.yaml``, or a camera file under its default name beside
    ``board/`` or ``scenes/`` (a hand-laid session without a session.yaml)."""
    f = Path(folder)
    if (f / "session.yaml").is_file():
        return True
    return any((f / n).is_file() for n in SESSION_CAMERA_FILES) and any(
        (f / d).is_dir() for d in SESSION_CAPTURE_FOLDERS)


def refuse_inside_capture_sessions(path: str | Path, option: str = "--output") -> None:
    """No stage writes into a capture session, the one it reads or any other (``build-dataset -o SESSION`` replaced
    the session's scene folders with the dataset's), nor anything beside its captures: ``path`` is neither a session
    folder nor inside one, under any spelling (relative, ``..``, symbolic links). ``gtforge import`` and ``synth``,
    which write sessions, make their own checks."""
    for p in dict.fromkeys((Path(os.path.abspath(path)), Path(os.path.realpath(path)))):
        for a in (p, *p.parents):
            if is_capture_session(a):
                raise InputError(path, option, "a path outside every capture session folder (a session's captures "
                                 "and files are never written, nor anything put beside them)",
                                 f"the capture session {a} itself" if a == p else
                                 f"a path inside the capture session {a}",
                                 f"write beside the session, e.g. {option} "
                                 f"{free_path(a.parent, p.name if a != p else 'out')}")


def free_path(folder: str | Path, name: str) -> Path:
    """``folder/name``, or where that is taken ``folder/<stem>-2<suffix>``, ``-3`` ...: a name a hint may suggest."""
    p = Path(folder) / name
    k = 2
    while p.exists() or p.is_symlink():
        p = p.with_name(f"{Path(name).stem}-{k}{Path(name).suffix}")
        k += 1
    return p


def require_output_folder(path: str | Path, option: str = "--output", session_ok: bool = False) -> Path:
    """``path`` is an existing folder or does not exist yet (it is then created by the stage), and this user can
    write there; a file is refused, and so is a path in a capture session (``session_ok``: a stage that writes
    sessions, which checks its own). Checked before a stage's work, not found when it writes."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(p, option, "a folder (new or existing)", "a file", "give a folder path for the outputs")
    if not session_ok:
        refuse_inside_capture_sessions(p, option)
    refuse_inside_dataset_folders(p, option)
    _require_writable_parents(p, option)
    return p


def require_output_file(path: str | Path, option: str = "--output") -> Path:
    """``path`` is a file that may be written (new, or replaced whole): not a folder, its parents folders (or not
    there yet), writable by this user."""
    p = Path(path)
    if p.is_dir():
        raise InputError(p, option, "a file path", "a folder", "give the output file's name, e.g. FOLDER/out.yaml")
    refuse_inside_capture_sessions(p, option)
    refuse_inside_dataset_folders(p, option)
    _require_writable_parents(p, option)
    return p


def _require_writable_parents(p: Path, option: str) -> None:
    """The nearest existing folder at or above ``p`` is a folder this user can write into (what ``mkdir -p`` and a
    file's creation there need); a file further up is refused (mkdir would fail on it with a traceback)."""
    for q in [p, *p.parents]:
        if not (q.exists() or q.is_symlink()):
            continue
        if not q.exists():  # (a symbolic link to nothing: mkdir and open both fail on it)
            raise InputError(p, option, "a path whose folders exist or can be made",
                             f"{q} is a symbolic link to nothing ({os.readlink(q)})", "remove the link or fix it")
        if q != p and not q.is_dir():
            raise InputError(p, option, "a path whose parents are folders", f"{q} is a file",
                             f"give {option} a path under a folder, or move the file {q} away")
        folder = q if q.is_dir() else q.parent
        if not os.access(folder, os.W_OK | os.X_OK):
            try:
                read_only = bool(os.statvfs(folder).f_flag & os.ST_RDONLY)
            except OSError:
                read_only = False
            raise InputError(p, option, "a place this user can write",
                             f"{folder} is on a read-only file system" if read_only
                             else f"{folder} is not writable by this user", "choose another output path")
        return


def require_new_or_empty_folder(path: str | Path, option: str, hint: str,
                                reusable_if: str | tuple[str, ...] | None = None) -> Path:
    """``path`` does not exist, is an empty folder, or (``reusable_if``) holds that file, or one of those files
    (relative to ``path``): the mark of a folder this command wrote before and may write again. Anything else is
    refused."""
    p = require_output_folder(path, option, session_ok=True)
    marks = (reusable_if,) if isinstance(reusable_if, str) else (reusable_if or ())
    if p.is_dir():
        entries = [e for e in p.iterdir()]
        if entries and not any((p / m).is_file() for m in marks):
            raise InputError(p, option, "a new or empty folder" + (f" (or one with {marks[0]})" if marks else ""),
                             f"a folder with {len(entries)} entr{'y' if len(entries) == 1 else 'ies'}", hint)
    refuse_inside_capture_sessions(p, option)  # (after: a session itself is a folder that is not empty, said first)
    return p


def new_folders(*folders: str | Path) -> list[Path]:
    """Those of ``folders`` that do not exist yet: asked before a stage makes them (give the deepest first)."""
    return [Path(f) for f in folders if not Path(f).exists()]


def remove_if_empty(folders: list[Path]) -> None:
    """Remove each of ``folders`` (``new_folders``: the ones this stage made) that is still empty, in order; a folder
    with anything in it stays (``rmdir``). A stage stopped by bad input leaves no empty folder behind."""
    for f in folders:
        with contextlib.suppress(OSError):
            f.rmdir()
