"""`gtforge import` of a pair of ROS 2 recordings (a realsense-ros-like RGB-D bag and a zed-ros2-wrapper-like stereo
bag, .mcap) against decoding the same bags with the libraries alone (rosbags: read and deserialise every message,
numpy view of every image): what the import adds on top of reading the files.

The recordings are a synthetic session (gtforge.synthetic.generate_session, --scale) played by
gtforge.synthetic_recordings at --fps for --seconds: the session's captures held still in turn, with moving frames
between them, both cameras on their own clocks. Times are wall clock of one run each (the import includes hashing the
sources, decoding every colour and left frame for the stillness test, board detection and writing the captures).

``--svo2``: the stereo camera is a ZED ``.svo2`` instead (H.264 side-by-side video of a raw-ZED session at VGA,
gtforge.synthetic.generate_raw_zed_session, --scale ignored), and the floor decodes it with mcap + PyAV alone (every
frame to RGB). CPU seconds (this process) are printed beside the wall times: the machine may be shared.

    python benchmarks/bench_import.py [--seconds 60] [--fps 15] [--scale 0.25] [--svo2] [--workdir DIR]
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


def decode_svo2_alone(path: Path) -> int:
    """The floor of an .svo2: every side-by-side message read (mcap) and decoded to RGB (PyAV), in order."""
    import av
    from mcap.reader import make_reader

    from gtforge.io.zed_svo import annexb_payload, video_codec

    n, ctx = 0, None
    with open(path, "rb") as f:
        for _, ch, m in make_reader(f).iter_messages():
            if not ch.topic.endswith("/side_by_side"):
                continue
            payload = annexb_payload(m.data)
            ctx = ctx or av.CodecContext.create(video_codec(payload), "r")
            for fr in ctx.decode(av.Packet(payload)):
                fr.to_ndarray(format="rgb24")
                n += 1
    for fr in ctx.decode(None):
        fr.to_ndarray(format="rgb24")
        n += 1
    return n


def _clock() -> tuple[float, float]:
    return time.perf_counter(), time.process_time()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--svo2", action="store_true", help="the stereo camera as a ZED .svo2 (H.264)")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/gtforge_bench_import"))
    a = ap.parse_args()
    from gtforge.importer import import_recordings
    from gtforge.io.ros_recordings import Topics
    from gtforge.records.imports import ImportParams
    from gtforge.synthetic import generate_raw_zed_session, generate_session
    from gtforge.synthetic_recordings import write_ros2_recordings

    hand = a.workdir / ("hand_raw" if a.svo2 else "hand")
    if not (hand / "session.yaml").is_file():
        if a.svo2:
            generate_raw_zed_session(hand, n_board=4, n_scenes=2, seed=1, supersample=1)
        else:
            generate_session(hand, n_board=4, n_scenes=2, scale=a.scale, seed=1, depth_noise_mm=0.0, supersample=1)
    n_caps = 6
    frames = int(a.seconds * a.fps)
    motion = 3
    still = max(3, frames // n_caps - motion)
    rec = a.workdir / "rec"
    shutil.rmtree(rec, ignore_errors=True)
    t = time.perf_counter()
    truth = write_ros2_recordings(hand, rec, fps=a.fps, still_frames=still, motion_frames=motion,
                                  svo2_codec="h264" if a.svo2 else None)
    t_write = time.perf_counter() - t
    size_mb = sum(f.stat().st_size for f in rec.rglob("*") if f.is_file()) / 1e6
    n_frames = len(truth.frame_capture)
    t, c = _clock()
    if a.svo2:
        n_img = decode_alone([truth.rgbd_bag]) + decode_svo2_alone(truth.stereo_bag)
        floor = "rosbags + numpy (RGB-D bag), mcap + PyAV (.svo2)"
    else:
        n_img = decode_alone([truth.rgbd_bag, truth.stereo_bag])
        floor = "rosbags + numpy"
    t_dec, c_dec = time.perf_counter() - t, time.process_time() - c
    out = a.workdir / "session"
    shutil.rmtree(out, ignore_errors=True)
    t, c = _clock()
    topics = Topics(zed_calibration=hand / "SN12345.conf") if a.svo2 else None
    s = import_recordings([truth.rgbd_bag, truth.stereo_bag], out, ImportParams(clock_offset_ms=truth.clock_offset_ms),
                          topics)
    t_imp, c_imp = time.perf_counter() - t, time.process_time() - c
    print(f"recordings: {n_frames} frames per camera ({n_frames / a.fps:.0f} s at {a.fps:g} fps), {n_img} images "
          f"(an .svo2 frame: one side-by-side image), {size_mb:.0f} MB, written in {t_write:.1f} s")
    print(f"decode with {floor} alone: {t_dec:.2f} s wall, {c_dec:.2f} s CPU ({n_img / t_dec:.0f} images/s)")
    print(f"gtforge import: {t_imp:.2f} s wall, {c_imp:.2f} s CPU ({t_imp / t_dec:.2f}x the decode alone wall, "
          f"{c_imp / c_dec:.2f}x CPU), {len(s.captures)} captures ({s.boards} boards, {s.scenes} scenes), "
          f"dropped {s.dropped}")


if __name__ == "__main__":
    main()
