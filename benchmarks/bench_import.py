"""`gtforge import` of a pair of ROS 2 recordings (a realsense-ros-like RGB-D bag and a zed-ros2-wrapper-like stereo
bag, .mcap) against decoding the same bags with the libraries alone (rosbags: read and deserialise every message,
numpy view of every image): what the import adds on top of reading the files.

The recordings are a synthetic session (gtforge.synthetic.generate_session, --scale) played by
gtforge.synthetic_recordings at --fps for --seconds: the session's captures held still in turn, with moving frames
between them, both cameras on their own clocks. Times are wall clock of one run each (the import includes hashing the
sources, decoding every colour and left frame for the stillness test, board detection and writing the captures).

    python benchmarks/bench_import.py [--seconds 60] [--fps 15] [--scale 0.25] [--workdir /tmp/gtforge_bench_import]
"""
from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import numpy as np


def decode_alone(paths: list[Path]) -> int:
    """The floor: every message read and deserialised, every Image's pixels viewed as an array."""
    from rosbags.highlevel import AnyReader

    n = 0
    with AnyReader(paths) as r:
        for conn, _, raw in r.messages():
            m = r.deserialize(raw, conn.msgtype)
            if conn.msgtype == "sensor_msgs/msg/Image":
                np.asarray(m.data).reshape(m.height, m.step)
                n += 1
    return n


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/gtforge_bench_import"))
    a = ap.parse_args()
    from gtforge.importer import import_recordings
    from gtforge.records.imports import ImportParams
    from gtforge.synthetic import generate_session
    from gtforge.synthetic_recordings import write_ros2_recordings

    hand = a.workdir / "hand"
    if not (hand / "session.yaml").is_file():
        generate_session(hand, n_board=4, n_scenes=2, scale=a.scale, seed=1, depth_noise_mm=0.0, supersample=1)
    n_caps = 6
    frames = int(a.seconds * a.fps)
    motion = 3
    still = max(3, frames // n_caps - motion)
    rec = a.workdir / "rec"
    shutil.rmtree(rec, ignore_errors=True)
    t = time.perf_counter()
    truth = write_ros2_recordings(hand, rec, fps=a.fps, still_frames=still, motion_frames=motion)
    t_write = time.perf_counter() - t
    size_mb = sum(f.stat().st_size for f in rec.rglob("*") if f.is_file()) / 1e6
    n_frames = len(truth.frame_capture)
    t = time.perf_counter()
    n_img = decode_alone([truth.rgbd_bag, truth.stereo_bag])
    t_dec = time.perf_counter() - t
    out = a.workdir / "session"
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    s = import_recordings([truth.rgbd_bag, truth.stereo_bag], out, ImportParams(clock_offset_ms=truth.clock_offset_ms))
    t_imp = time.perf_counter() - t
    print(f"recordings: {n_frames} frames per camera ({n_frames / a.fps:.0f} s at {a.fps:g} fps), {n_img} images, "
          f"{size_mb:.0f} MB (.mcap), written in {t_write:.1f} s")
    print(f"decode with rosbags + numpy alone: {t_dec:.2f} s ({n_img / t_dec:.0f} images/s)")
    print(f"gtforge import: {t_imp:.2f} s ({t_imp / t_dec:.2f}x the decode alone), {len(s.captures)} captures "
          f"({s.boards} boards, {s.scenes} scenes), dropped {s.dropped}")


if __name__ == "__main__":
    main()
