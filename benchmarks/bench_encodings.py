"""Output encodings of build-dataset, measured on one full-resolution scene's real outputs (2208x1242).

* label PNGs (mask0nocc.png, region.png, KITTI disp_occ_0 uint16): OpenCV's default PNG settings against
  zlib levels / strategies / filters: encode time, size, decode time (OpenCV and Pillow, what training code
  uses). These files are written once and read every epoch.
* float32 TIFF (depth0.tiff, weight.tiff): uncompressed against zlib level 1 and tifffile's default level.
* SHA-256 throughput (input hashing for resume).

Times are this thread's CPU time (robust on a shared machine), median of --repeat.

    python benchmarks/bench_encodings.py [--repeat 7] [--write] [--workdir /tmp/gtforge_bench]
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import statistics
import time
from pathlib import Path

from fullres_session import machine_line, make_session, update_results


def cpu_ms(fn, repeat):
    fn()
    ts = []
    for _ in range(repeat):
        t = time.thread_time()
        fn()
        ts.append(time.thread_time() - t)
    return statistics.median(ts) * 1e3


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--workdir", default="/tmp/gtforge_bench")
    ap.add_argument("--write", action="store_true")
    args = ap.parse_args()
    from gtforge.infra.scheduling import limit_threads

    limit_threads(1)
    import cv2
    import numpy as np
    import tifffile
    from PIL import Image

    from gtforge import build_dataset as bd
    from gtforge.io.captures import open_session
    from gtforge.io.formats import _kitti_quantize, encode_label_png, write_tiff_float
    from gtforge.records.calibration import CalibrationFile

    wd = Path(args.workdir)
    sess, calib = make_session(wd, 1, 1)
    session = open_session(sess)
    rig = CalibrationFile.read(calib).rig
    params = bd.BuildParams()
    cap = session.load_capture(sess / "scenes" / "0000")
    sd, region, _ = bd.build_scene_arrays(cap.depth_mm, rig, params, None)
    mask = np.zeros(region.shape, np.uint8)
    mask[np.isfinite(sd.disparity_px)] = 128
    mask[sd.nonoccluded] = 255
    kitti = _kitti_quantize(sd.disparity_px, np.ones(sd.disparity_px.shape, bool))
    tmp = wd / "encodings"
    tmp.mkdir(parents=True, exist_ok=True)
    r = args.repeat

    S, F = cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_FILTER
    opencv_settings = [
        ("OpenCV default (level 1, RLE strategy, adaptive filters; round 1)", []),
        ("OpenCV level 0 (stored)", [cv2.IMWRITE_PNG_COMPRESSION, 0]),
        ("OpenCV level 1, default strategy, no filter (until 2026-11-25)",
         [cv2.IMWRITE_PNG_COMPRESSION, 1, S, cv2.IMWRITE_PNG_STRATEGY_DEFAULT, F, cv2.IMWRITE_PNG_FILTER_NONE]),
        ("OpenCV level 1, default strategy, sub filter",
         [cv2.IMWRITE_PNG_COMPRESSION, 1, S, cv2.IMWRITE_PNG_STRATEGY_DEFAULT, F, cv2.IMWRITE_PNG_FILTER_SUB]),
        ("OpenCV level 1, default strategy, paeth filter", [cv2.IMWRITE_PNG_COMPRESSION, 1, S,
                                                            cv2.IMWRITE_PNG_STRATEGY_DEFAULT, F,
                                                            cv2.IMWRITE_PNG_FILTER_PAETH]),
        ("OpenCV level 1, RLE strategy, no filter", [cv2.IMWRITE_PNG_COMPRESSION, 1, S, cv2.IMWRITE_PNG_STRATEGY_RLE,
                                                     F, cv2.IMWRITE_PNG_FILTER_NONE]),
        ("OpenCV level 3, default strategy, no filter",
         [cv2.IMWRITE_PNG_COMPRESSION, 3, S, cv2.IMWRITE_PNG_STRATEGY_DEFAULT, F, cv2.IMWRITE_PNG_FILTER_NONE]),
        ("OpenCV level 6, default strategy, adaptive filters", [cv2.IMWRITE_PNG_COMPRESSION, 6]),
    ]
    # (name, encoder: array -> PNG bytes)
    png_settings = [(n, lambda a, prm=prm: cv2.imencode(".png", a, prm)[1].tobytes()) for n, prm in opencv_settings]
    png_settings.append(("zlib-ng level 1, no filter (`encode_label_png`, **chosen**)", encode_label_png))
    lines = [f"Measured {datetime.date.today()} with `python benchmarks/bench_encodings.py --repeat {r}`: "
             f"{machine_line()}; one thread, CPU ms (median of {r}); one full-resolution scene's real outputs.",
             "", "Label PNGs (written once, decoded every epoch):", "",
             "| file | PNG settings | encode ms | MB | decode ms (OpenCV) | decode ms (Pillow) |",
             "|---|---|---|---|---|---|"]
    for name, a in (("disp_occ_0 (uint16)", kitti), ("mask0nocc.png", mask), ("region.png", region)):
        for sname, encode in png_settings:
            buf = encode(a)
            p = tmp / "t.png"
            p.write_bytes(buf)
            if not np.array_equal(cv2.imread(str(p), cv2.IMREAD_UNCHANGED), a):
                raise RuntimeError(f"{sname}: PNG round trip changed {name}")
            lines.append(f"| {name} | {sname} | {cpu_ms(lambda: encode(a), r):.1f} | "
                         f"{len(buf) / 1e6:.3f} | {cpu_ms(lambda: cv2.imread(str(p), cv2.IMREAD_UNCHANGED), r):.1f} | "
                         f"{cpu_ms(lambda: np.asarray(Image.open(p)), r):.1f} |")
    lines += ["", "float32 TIFF:", "", "| file | compression | encode ms | MB | decode ms (tifffile) |",
              "|---|---|---|---|---|"]
    weight = bd.sgra_weights(region, params)
    for name, a in (("depth0.tiff", sd.depth_mm), ("weight.tiff", weight)):
        for cname, kw in (("none", {}), ("zlib level 1", {"compression": "zlib", "compressionargs": {"level": 1}}),
                          ("zlib, tifffile's default level (before)", {"compression": "zlib"})):
            p = tmp / "t.tiff"
            enc = cpu_ms(lambda: tifffile.imwrite(p, a, **kw), r)
            lines.append(f"| {name} | {cname} | {enc:.1f} | {p.stat().st_size / 1e6:.2f} | "
                         f"{cpu_ms(lambda: tifffile.imread(p), r):.1f} |")
        enc = cpu_ms(lambda: write_tiff_float(p, a, compression="zlib"), r)
        lines.append(f"| {name} | zlib-ng level 1, 64-row strips (`write_tiff_float(compression=\"zlib\")`) | "
                     f"{enc:.1f} | {p.stat().st_size / 1e6:.2f} | {cpu_ms(lambda: tifffile.imread(p), r):.1f} |")
    data = np.random.default_rng(0).integers(0, 255, 64 << 20, np.uint8).tobytes()
    t = cpu_ms(lambda: hashlib.sha256(data).hexdigest(), max(3, r // 2))
    lines += ["", f"SHA-256: {len(data) / t / 1e6:.2f} GB/s (64 MiB in memory, one thread)."]
    text = "\n".join(lines)
    print(text)
    if args.write:
        print("written to", update_results("bench_encodings", text))


if __name__ == "__main__":
    main()
