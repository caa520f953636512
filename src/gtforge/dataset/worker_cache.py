"""What a build worker keeps between scenes: the opened session and the calibration (keyed by their stamps, so that
a changed file is read again), and the heap a scene needs (``scene_heap_bytes``)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from gtforge.io.calibrated_session import open_with_calibration
from gtforge.records.calibration import CalibrationFile

if TYPE_CHECKING:
    from gtforge.core.camera import PinholeCamera

# Per worker process. A Dask worker (or this process with workers=1) lives across builds: an entry is
# reloaded when its files changed (session: their size and mtime; calibration: its sha256).
WORKER_CACHE: dict = {}

# What a worker's heap grows by over its first scenes, a ZED pixel: build-dataset's first full-resolution scene (2208 x
# 1242, default options) 174 MB, 63.5 bytes a pixel, rounded down (smaller scenes need more a pixel: 27 MB at a
# quarter of the size, and a reservation short of the need leaves the rest to page faults, as without one); verify's
# 121 MB in its first scene, 173 MB by the third (benchmarks/RESULTS.md, "Round 9 (issue 39)")
SCENE_HEAP_BYTES_PER_ZED_PX = 60


def scene_heap_bytes(zed_left: PinholeCamera) -> int:
    """The heap a pool worker reserves before its first scene (``run_tasks(heap_bytes=)``, ``scheduling.reserve_heap``)
    for scenes of the ZED's left image ``zed_left``."""
    return SCENE_HEAP_BYTES_PER_ZED_PX * zed_left.width_px * zed_left.height_px



def cached_session(session_dir: str, calib: CalibrationFile):
    """The session as ``calib`` sees it (``CalibrationFile.open_session``: the SN.conf reading, the ZED
    self-rectification and calibrate-scale's yaw of the right camera it recorded)."""
    corr = calib.zed_right_correction
    key = (session_dir, calib.zed_conf_reading, corr.model_dump_json() if corr is not None else None,
           calib.rig.zed_right_yaw_deg)
    hit = WORKER_CACHE.get(key)
    if hit is None or hit[1] != session_stamp(hit[0]):
        session = open_with_calibration(session_dir, calib)
        hit = WORKER_CACHE[key] = (session, session_stamp(session))
    return hit[0]



def session_stamp(session) -> tuple:
    c = session.config
    stamp = []
    for name in ("session.yaml", c.mech_intrinsics, c.depth_intrinsics, c.zed_calibration, c.zed_right_info):
        if name:
            try:
                st = (session.root / name).stat()
                stamp.append((name, st.st_size, st.st_mtime_ns))
            except OSError:
                stamp.append((name, None, None))
    return tuple(stamp)



def cached_calibration(path: str, sha256: str) -> CalibrationFile:
    key = ("calib", path)
    hit = WORKER_CACHE.get(key)
    if hit is None or hit[1] != sha256:
        hit = WORKER_CACHE[key] = (CalibrationFile.read(path), sha256)
    return hit[0]
