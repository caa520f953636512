"""Folders made once per test run and shared by every pytest-xdist worker (the synthetic sessions, the shared
calibration), and the prefetch that makes them in the background while the first tests run (tests/conftest.py).

Run as a script, it makes the folders a pickled list on its standard input names: ``[(root, name, kwargs), ...]``."""
from __future__ import annotations

import fcntl
import hashlib
import pickle
import shutil
import sys
from pathlib import Path
from typing import Callable

import gtforge.synthetic

# the generator's version: its source (a change to it renders every session again)
GENERATOR_VERSION = hashlib.sha256(Path(gtforge.synthetic.__file__).read_bytes()).hexdigest()[:12]

# the sessions the tests use, by the name of the fixture that returns them (``session_spec``): the prefetch makes
# those the collected tests need
SPECS: dict[str, tuple[str, dict]] = {}


def session_spec(fixture: str, name: str, **kwargs) -> tuple[str, dict]:
    """Declare the synthetic session fixture ``fixture`` returns: ``generate_session(folder, **kwargs)``, or with
    ``raw_zed=True`` ``generate_raw_zed_session(folder, **kwargs)`` (raw ZED images and their SN.conf)."""
    SPECS[fixture] = (name, kwargs)
    return name, kwargs


def folder_of(root: Path, name: str, key: dict) -> Path:
    digest = hashlib.sha256(repr((GENERATOR_VERSION, sorted(key.items()))).encode()).hexdigest()[:12]
    return root / f"{name}-{digest}"


def made_once(root: Path, name: str, make: Callable[[Path], object], **key) -> Path:
    """The folder ``make(folder)`` fills under ``root``, made once: whoever comes first makes it, the others wait for
    it (a lock file beside it), a finished one is never made again (a ``.done`` file). The name carries the generator's
    version and ``key`` (the arguments it is made with). Tests must not write into it: they copy it first."""
    root.mkdir(parents=True, exist_ok=True)
    out = folder_of(root, name, key)
    done = out.with_name(out.name + ".done")
    with open(out.with_name(out.name + ".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(out, ignore_errors=True)
            make(out)
            done.touch()
    return out


def make_session(root: Path, name: str, kwargs: dict) -> Path:
    from gtforge.synthetic import generate_raw_zed_session, generate_session

    args = {k: v for k, v in kwargs.items() if k != "raw_zed"}
    generate = generate_raw_zed_session if kwargs.get("raw_zed") else generate_session
    return made_once(root, name, lambda d: generate(d, **args), **kwargs)


def make_calibration(root: Path, session_dir: Path) -> Path:
    """The shared calibration of the shared session: the file, and the result as ``calibrate`` returned it."""
    from gtforge.calibrate import calibrate
    from gtforge.records.calibration import CalibrateParams

    def make(d):
        res = calibrate(session_dir, d / "calibration.yaml", CalibrateParams(use_depth=False))
        (d / "result.pickle").write_bytes(pickle.dumps(res))

    return made_once(root, "calib", make, session=str(session_dir))


def main() -> None:
    for root, name, kwargs in pickle.loads(sys.stdin.buffer.read()):
        root = Path(root)
        if name == "calib":
            make_calibration(root, make_session(root, *kwargs))
        else:
            make_session(root, name, kwargs)


if __name__ == "__main__":
    main()
