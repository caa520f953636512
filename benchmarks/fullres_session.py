"""Full-resolution synthetic capture sessions for the benchmarks.

Rendering is the slow part (about 10 s a scene), so a few distinct fruit scenes are rendered once
(ZED 2K 2208x1242 left/right PNG, Mech-Eye-like 1920x1200 ``DepthMap.tiff`` float32 mm + ``2DImage.png``)
and hard-linked into as many scene folders as asked. Renders are kept in ``WORKDIR/renders`` and reused
by later runs with the same settings. The calibration file holds the exact extrinsic.
"""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np

from gtforge.core.camera import CameraFile, Rig, StereoCalibrationFile
from gtforge.records.calibration import CalibrationFile
from gtforge.synthetic import default_rig, random_fruit_scene, render_capture, write_capture

RENDER_SETTINGS = dict(scale=1.0, supersample=1, depth_noise_mm=0.05, seed=0)


def render_distinct(workdir: Path, n_distinct: int, log=print) -> list[Path]:
    """``n_distinct`` rendered capture folders under ``workdir/renders`` (reused when already there)."""
    root = workdir / "renders"
    stamp = root / "settings.json"
    want = json.dumps(RENDER_SETTINGS, sort_keys=True)
    if stamp.exists() and stamp.read_text() != want:
        shutil.rmtree(root)
    root.mkdir(parents=True, exist_ok=True)
    stamp.write_text(want)
    rig = default_rig(RENDER_SETTINGS["scale"])
    out = []
    t0 = time.perf_counter()
    for i in range(n_distinct):
        d = root / f"{i:03d}"
        if not (d / "done").exists():
            rng = np.random.default_rng(RENDER_SETTINGS["seed"] + i)
            cap = render_capture(f"{i:03d}", random_fruit_scene(rng, rig, i), rig, rng, kind="scene",
                                 supersample=RENDER_SETTINGS["supersample"],
                                 depth_noise_mm=RENDER_SETTINGS["depth_noise_mm"])
            shutil.rmtree(d, ignore_errors=True)
            write_capture(d, cap, root / "truth")
            (d / "done").write_text("")
            log(f"rendered scene {i + 1}/{n_distinct} ({time.perf_counter() - t0:.0f} s)")
        out.append(d)
    return out


def make_session(workdir: str | Path, n_scenes: int, n_distinct: int = 4, log=print) -> tuple[Path, Path]:
    """A session with ``n_scenes`` full-resolution scenes (``n_distinct`` renders, hard-linked) and its
    calibration file. Returns (session_dir, calibration_path)."""
    workdir = Path(workdir)
    renders = render_distinct(workdir, min(n_distinct, n_scenes), log)
    sess = workdir / f"session_{n_scenes}"
    shutil.rmtree(sess, ignore_errors=True)
    rig = default_rig(RENDER_SETTINGS["scale"])
    CameraFile(camera=rig.mech).write(sess / "mech_intrinsics.yaml")
    StereoCalibrationFile(zed=rig.zed).write(sess / "zed_calibration.yaml")
    for k in range(n_scenes):
        src = renders[k % len(renders)]
        dst = sess / "scenes" / f"{k:04d}"
        dst.mkdir(parents=True)
        for f in src.iterdir():
            if f.name != "done":
                os.link(f, dst / f.name)
    # the exact extrinsic, with the uncertainty a good board calibration reports (0.002 deg, 0.02 mm per axis: the
    # demo's calibrate), so the GT sigma maps include the extrinsic term as they do for a user
    calib = CalibrationFile.known_extrinsic(Rig(zed=rig.zed, mech=rig.mech, T_zed_from_mech=rig.T_zed_from_mech),
                                            sigma_rot_deg=0.002, sigma_trans_mm=0.02)
    calib_path = workdir / "calibration.yaml"
    calib.write(calib_path)
    return sess, calib_path


def corrected_calibration(calib: Path, yaw_deg: float = 0.0005) -> Path:
    """``calib`` with calibrate-scale's correction of the right camera's yaw (``yaw_deg``), beside it."""
    from gtforge.core.camera import ScaleCorrections
    from gtforge.records.calibration import CalibrationFile

    c = CalibrationFile.read(calib)
    c.rig = c.rig.model_copy(update={"scale_corrections": ScaleCorrections(zed_right_yaw_deg=yaw_deg)})
    out = calib.with_name("calibration_right_corrected.yaml")
    c.write(out)
    return out


def machine_line() -> str:
    """Cores this process may use and the 1-minute load average when the measurement starts."""
    from gtforge.infra.scheduling import cpu_count

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return f"{cpu_count()} cores ({cpu_line()}), load average {load:.2f} at start"


def pin_to_one_core() -> None:
    """Restrict this process (and what it starts) to one of the cores it may use, as ``taskset -c`` does; a
    ``preexec_fn`` for the Open3D baselines, whose projection runs fastest on one core (bench_reproject.py)."""
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})


def cpu_line() -> str:
    """The processor as /proc/cpuinfo names it, with its family (AMD: 25 = Zen 3/4, 26 = Zen 5) and whether it has
    AVX-512: the compiled kernels ran 2.3x slower on an AVX2-only VM than on an AVX-512 one (RESULTS.md, round 9)."""
    try:
        info = Path("/proc/cpuinfo").read_text().split("\n\n", 1)[0]
    except OSError:
        return "processor unknown"
    fields = {k.strip(): v.strip() for k, v in (line.split(":", 1) for line in info.splitlines() if ":" in line)}
    flags = fields.get("flags", "").split()
    simd = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "no AVX2"
    return f"{fields.get('model name') or 'processor unknown'}, family {fields.get('cpu family') or '?'}, {simd}"


def update_results(section: str, text: str, path: Path | None = None) -> Path:
    """Replace the block between ``<!-- section:begin -->`` and ``<!-- section:end -->`` in RESULTS.md
    (appended when missing)."""
    path = path or Path(__file__).with_name("RESULTS.md")
    doc = path.read_text() if path.exists() else "# Benchmark results\n"
    begin, end = f"<!-- {section}:begin -->", f"<!-- {section}:end -->"
    block = f"{begin}\n{text.rstrip()}\n{end}"
    if begin in doc and end in doc:
        doc = doc[:doc.index(begin)] + block + doc[doc.index(end) + len(end):]
    else:
        doc = doc.rstrip() + "\n\n" + block + "\n"
    path.write_text(doc)
    return path
