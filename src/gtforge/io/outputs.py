"""Checks on the folders a stage is asked to write into, made before anything is written; and the folders a stage
made, removed again when it stopped on bad input before writing into them."""
from __future__ import annotations

import contextlib
from pathlib import Path

from gtforge.errors import InputError


def require_output_folder(path: str | Path, option: str = "--output") -> Path:
    """``path`` is an existing folder or does not exist yet (it is then created by the stage); a file is refused."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(p, option, "a folder (new or existing)", "a file", "give a folder path for the outputs")
    for parent in p.parents:  # mkdir would fail on a file further up with a traceback
        if parent.exists():
            if not parent.is_dir():
                raise InputError(p, option, "a path whose parents are folders", f"{parent} is a file")
            break
    return p


def require_new_or_empty_folder(path: str | Path, option: str, hint: str, reusable_if: str | None = None) -> Path:
    """``path`` does not exist, is an empty folder, or (``reusable_if``) holds that file (relative to ``path``):
    the mark of a folder this command wrote before and may write again. Anything else is refused."""
    p = require_output_folder(path, option)
    if p.is_dir():
        entries = [e for e in p.iterdir()]
        if entries and not (reusable_if and (p / reusable_if).is_file()):
            raise InputError(p, option, "a new or empty folder" + (f" (or one with {reusable_if})" if reusable_if
                                                                     else ""),
                             f"a folder with {len(entries)} entries", hint)
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
