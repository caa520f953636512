"""Where one full-resolution scene's time goes in build-dataset (ZED 2K 2208x1242, 1920x1200 depth).

Times every step a build worker runs, each alone on the same inputs (median of --repeat runs, wall and
this thread's CPU time), next to the whole worker call (``build_one_scene``, default options, views
included). Threads: what a build worker gets with ``--workers`` = cores (``scheduling.threads_per_worker``),
unless --threads. Writes the table into benchmarks/RESULTS.md (section ``profile_scene``) with --write.

    python benchmarks/profile_scene.py [--repeat 5] [--threads N] [--write] [--workdir /tmp/gtforge_bench]
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import os
import shutil
import statistics
import time
from pathlib import Path

from fullres_session import corrected_calibration, machine_line, make_session, update_results


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None, help="numba/OpenCV threads (default: a build worker's)")
    ap.add_argument("--workdir", default="/tmp/gtforge_bench")
    ap.add_argument("--write", action="store_true", help="write the table into benchmarks/RESULTS.md")
    args = ap.parse_args()

    from gtforge.infra.scheduling import cpu_count, limit_threads, threads_per_worker

    n_threads = args.threads or threads_per_worker(cpu_count())
    limit_threads(n_threads)
    try:  # what a local pool worker does at start (gtforge >= issue 12's round 3)
        from gtforge.infra.scheduling import reuse_freed_memory

        reuse_freed_memory()
    except ImportError:
        pass
    import numpy as np

    from gtforge import build_dataset as bd
    from gtforge.core.ground_truth.regions import fruit_regions
    from gtforge.dataset.views import _link
    from gtforge.core.ground_truth.reproject import project_depth_to_camera
    from gtforge.io.captures import open_session, read_depth, read_texture
    from gtforge.io.formats import read_image, write_kitti_disparity, write_pfm, write_tiff_float
    from gtforge.records.calibration import CalibrationFile

    try:
        from gtforge.core.ground_truth.reproject import disparity_and_nonoccluded
    except ImportError:  # older gtforge: two numpy steps
        from gtforge.core.ground_truth.reproject import nonoccluded_mask

        def disparity_and_nonoccluded(dl, dr, zed, rel_tol):
            d = zed.depth_to_disparity(dl)
            return d, nonoccluded_mask(dl, d, dr, rel_tol)

    wd = Path(args.workdir)
    sess_dir, calib_path = make_session(wd, 1, 1)
    session = open_session(sess_dir)
    rig = CalibrationFile.read(calib_path).rig
    params = bd.BuildParams()
    rp = params.reproject_params()
    cap_dir = sess_dir / "scenes" / "0000"
    f = session.config.files
    cap = session.load_capture(cap_dir)
    zed = rig.zed
    out = wd / "profile_out"
    shutil.rmtree(out, ignore_errors=True)
    (out / "scenes").mkdir(parents=True)
    tmp = out / "scenes" / ".tmp-profile"
    tmp.mkdir()

    rows: list[tuple[str, str, float, float]] = []  # (group, step, wall ms, cpu ms)

    def measure(group, name, fn, before_each=None):
        """``before_each``: run (untimed) before every call; a write step's files are deleted before each (a build
        writes new files: writing over existing ones costs ext4 a forced block allocation, 5 ms for a KITTI PNG)."""
        if before_each is None and group == "write":
            existing = set(tmp.iterdir())
            fn()  # warm-up: numba compile, caches
            own = set(tmp.iterdir()) - existing

            def before_each():
                for q in own:
                    q.unlink(missing_ok=True)
        else:
            (before_each or (lambda: None))()
            fn()  # warm-up: numba compile, caches
        wall, cpu = [], []
        for _ in range(args.repeat):
            if before_each is not None:
                before_each()
            t, c = time.perf_counter(), time.thread_time()
            fn()
            cpu.append(time.thread_time() - c)
            wall.append(time.perf_counter() - t)
        rows.append((group, name, statistics.median(wall) * 1e3, statistics.median(cpu) * 1e3))
        if before_each is not None:
            before_each()
        return fn()

    # ---- read
    depth_in = measure("read", f"depth {f.mech_depth} (float32 TIFF)", lambda: read_depth(cap_dir / f.mech_depth))
    measure("read", f"texture {f.mech_texture}", lambda: read_texture(cap_dir / f.mech_texture))
    T_zed_from_depth = rig.T_zed_from_depth
    T_zedr_from_depth = zed.T_zedr_from_zed @ T_zed_from_depth
    try:  # gtforge >= issue 12's round 5: a build decodes the ZED images down to the rows verification reads
        from gtforge.dataset.scene_verification import zed_rows_used

        zed_rows = zed_rows_used(project_depth_to_camera(depth_in, rig.depth_camera, T_zed_from_depth, zed.left, rp),
                                 params.verify)
        h_zed = f" (decode, rows 0-{zed_rows} of {zed.left.height_px})"
        measure("read", f"ZED left {f.zed_left}{h_zed}", lambda: read_image(cap_dir / f.zed_left, rows=zed_rows))
        measure("read", f"ZED right {f.zed_right}{h_zed}", lambda: read_image(cap_dir / f.zed_right, rows=zed_rows))
    except ImportError:
        measure("read", f"ZED left {f.zed_left} (decode)", lambda: read_image(cap_dir / f.zed_left))
        measure("read", f"ZED right {f.zed_right} (decode)", lambda: read_image(cap_dir / f.zed_right))
    # ---- compute
    if getattr(params, "sigma", False) and rp.mode == "mesh":  # the build asks for the span (sigma maps)
        depth_l, depth_span = measure("compute", "reproject left (mesh, with span_mm)", lambda: project_depth_to_camera(
            depth_in, rig.depth_camera, T_zed_from_depth, zed.left, rp, return_span=True))
    else:
        depth_l = measure("compute", f"reproject left ({rp.mode})",
                          lambda: project_depth_to_camera(depth_in, rig.depth_camera, T_zed_from_depth, zed.left, rp))
    depth_r = measure("compute", f"reproject right ({rp.mode}, occlusion test)",
                      lambda: project_depth_to_camera(depth_in, rig.depth_camera, T_zedr_from_depth, zed.right, rp))
    disp, noc = measure("compute", "disparity + occlusion (non-occluded mask)",
                        lambda: disparity_and_nonoccluded(depth_l, depth_r, zed, params.occlusion_rel_tol))
    region, _ = measure("compute", "regions (table plane, fruit, erosion)",
                            lambda: fruit_regions(depth_l, zed, params, cap.fruit_mask))
    weight = measure("compute", "SGRA weights", lambda: bd.sgra_weights(region, params))
    if getattr(params, "verification", False):
        from gtforge.dataset.scene_verification import verify_scene

        measure("compute", "verification (texture alignment + stereo consistency)",
                lambda: verify_scene(depth_l, disp, noc, region, cap.zed_left, cap.zed_right, cap.mech_texture, rig,
                                     params.verify))
    if getattr(params, "sigma", False):
        from gtforge.core.ground_truth.uncertainty import disparity_sigma

        calib = CalibrationFile.read(calib_path)
        sigma = measure("compute", "GT sigma map (disp0GT_sigma)",
                        lambda: disparity_sigma(disp, depth_l, rig, calib.cov_extrinsic_rad_mm, params.uncertainty,
                                                depth_span, None))
        measure("compute", "sigma statistics per region (meta.json)", lambda: bd.region_sigma_stats(sigma, region))
    if getattr(params, "right_gt", False):
        from gtforge.core.ground_truth.reproject import right_view_disparity

        disp1, noc1 = measure("compute", "right-view disparity + occlusion (disp1GT)",
                              lambda: right_view_disparity(depth_l, depth_r, zed, params.occlusion_rel_tol))
    # ---- hashing
    files = [p for p in cap.input_files if p.exists()]
    size_mb = sum(p.stat().st_size for p in files) / 1e6
    try:  # gtforge >= issue 12's round 5: BLAKE3
        from gtforge.infra.digest import blake3_hex

        blobs = [p.read_bytes() for p in files]
        measure("hash", f"BLAKE3 of the inputs' bytes as read ({len(files)} files, {size_mb:.0f} MB)",
                lambda: [blake3_hex(b) for b in blobs])
    except ImportError:
        blake3_hex = None
    if blake3_hex is None and getattr(cap, "read_records", None):  # issue 12's round 4: hashed as read, not re-read
        import hashlib

        blobs = [p.read_bytes() for p in files]
        measure("hash", f"sha256 of the inputs' bytes as read ({len(files)} files, {size_mb:.0f} MB)",
                lambda: [hashlib.sha256(b).hexdigest() for b in blobs])
    elif blake3_hex is None:
        measure("hash", f"sha256 of the inputs ({len(files)} files, {size_mb:.0f} MB)",
                lambda: [bd.sha256_file(p) for p in files])
    # ---- write
    writes = contextlib.ExitStack()  # closed once the write steps are done
    try:  # gtforge >= issue 12's round 6: a view's two KITTI files written together (row blocks shared), and the
        # scene's files written straight into its private temporary folder, as the build does
        from gtforge.infra.atomic import private_folder
        from gtforge.io.formats import write_kitti_disparity_pair as kitti_pair

        writes.enter_context(private_folder(tmp))
    except ImportError:
        def kitti_pair(path_occ, path_noc, d, m):
            return write_kitti_disparity(path_occ, d), write_kitti_disparity(path_noc, d, m)
    valid = np.isfinite(disp)
    mask = np.zeros(disp.shape, np.uint8)
    mask[valid] = 128
    mask[noc] = 255
    measure("write", "im0.png + im1.png (copies of the input PNGs)",
            lambda: [shutil.copyfile(cap_dir / n, tmp / o)
                     for n, o in ((f.zed_left, "im0.png"), (f.zed_right, "im1.png"))])
    measure("write", "disp0GT.pfm", lambda: write_pfm(tmp / "disp0GT.pfm", disp))
    png_writer = getattr(__import__("gtforge.io.formats", fromlist=["x"]), "write_label_png", None)
    if png_writer is None:  # older gtforge
        from gtforge.io.formats import write_image as png_writer
    measure("write", "mask0nocc.png", lambda: png_writer(tmp / "mask0nocc.png", mask))
    measure("write", "region.png", lambda: png_writer(tmp / "region.png", region))
    if "compression" in write_tiff_float.__code__.co_varnames:
        measure("write", "weight.tiff (deflate level 1)", lambda: write_tiff_float(tmp / "weight.tiff", weight, "zlib"))
        measure("write", "depth0.tiff (uncompressed)", lambda: write_tiff_float(tmp / "depth0.tiff", depth_l))
    else:
        measure("write", "weight.tiff", lambda: write_tiff_float(tmp / "weight.tiff", weight))
        measure("write", "depth0.tiff", lambda: write_tiff_float(tmp / "depth0.tiff", depth_l))
    measure("write", "KITTI disp_occ_0 + disp_noc_0 (uint16 PNG)",
            lambda: kitti_pair(tmp / "occ.png", tmp / "noc.png", disp, noc))
    if getattr(params, "right_gt", False):
        measure("write", "disp1GT.pfm + mask1nocc.png + KITTI disp_occ_1 + disp_noc_1",
                lambda: (write_pfm(tmp / "disp1GT.pfm", disp1),
                         png_writer(tmp / "mask1nocc.png", bd.occlusion_mask(disp1, noc1)),
                         kitti_pair(tmp / "occ1.png", tmp / "noc1.png", disp1, noc1)))
    if getattr(params, "sigma", False):
        measure("write", "disp0GT_sigma.pfm + sigma thumbnail JPG",
                lambda: (write_pfm(tmp / "disp0GT_sigma.pfm", sigma),
                         bd.write_sigma_thumbnail(tmp / "sigma.jpg", sigma)))
    measure("write", "calib.txt", lambda: bd.atomic_write_text(
        tmp / "calib.txt", bd.middlebury_calib_text(zed, disp.shape[1], disp.shape[0],
                                                    (np.nanmin(disp), np.nanmax(disp)))))

    def no_links():
        for view in ("kitti", "eth3d"):
            shutil.rmtree(out / view, ignore_errors=True)

    def links():
        for name in ("im0.png", "im1.png", "calib.txt", "disp0GT.pfm", "mask0nocc.png"):
            _link(tmp / name, out / "eth3d" / "x" / name)
        for name in ("im0.png", "im1.png"):
            _link(tmp / name, out / "kitti" / name)

    measure("write", "view links (KITTI + ETH3D hard links)", links, no_links)

    writes.close()

    # ---- the whole worker call
    args_scene = (str(sess_dir.resolve()), str(cap_dir.resolve()), "0000", str(calib_path.resolve()),
                  bd.sha256_file(calib_path), str(out.resolve()), params.model_dump_json())

    calls = iter(range(10 ** 6))

    def new_scene():  # each call builds a new scene id: a build writes new files (see measure)
        for view in ("scenes", "kitti", "eth3d", "report"):
            shutil.rmtree(out / view, ignore_errors=True)
        (out / "scenes").mkdir()
        args_scene[2] = f"p{next(calls)}"

    def whole():
        r = bd.build_one_scene(*args_scene)
        if r[1]:
            raise RuntimeError(r[1])

    args_scene = list(args_scene)
    measure("total", "build_one_scene (the worker's whole call, default options)", whole, new_scene)
    total = rows[-1][2]
    total_cpu = rows[-1][3]
    # the same with a calibration that corrects the right camera (calibrate-scale's yaw, as every user's after
    # calibrate-scale): the right image resampled once (gtforge.core.bspline) and written again
    corrected = corrected_calibration(calib_path)
    args_scene[3], args_scene[4] = str(corrected.resolve()), bd.sha256_file(corrected)
    measure("total", "build_one_scene, a calibration that corrects the right camera (the right image resampled)",
            whole, new_scene)

    parts = [r for r in rows if r[0] != "total"]
    lines = [f"Measured {datetime.date.today()} with `python benchmarks/profile_scene.py --repeat {args.repeat}"
             f"{' --threads ' + str(args.threads) if args.threads else ''}`: {machine_line()}, "
             f"{n_threads} numba/OpenCV thread(s) (a build worker's share with --workers = cores); median of "
             f"{args.repeat}; CPU = this thread's CPU time.",
             "",
             "| group | step | ms | CPU ms | share of the worker call (CPU) |",
             "|---|---|---|---|---|"]
    for g, name, ms, cms in parts:
        lines.append(f"| {g} | {name} | {ms:.1f} | {cms:.1f} | {100 * cms / total_cpu:.0f} % |")
    s_ms, s_cpu = sum(r[2] for r in parts), sum(r[3] for r in parts)
    lines.append(f"| | **sum of the steps** | **{s_ms:.0f}** | **{s_cpu:.0f}** | {100 * s_cpu / total_cpu:.0f} % |")
    default, corrected_row = rows[-2], rows[-1]
    lines.append(f"| total | **{default[1]}** | **{total:.0f}** | **{total_cpu:.0f}** | 100 % |")
    lines.append(f"| total | {corrected_row[1]} | {corrected_row[2]:.0f} | {corrected_row[3]:.0f} | "
                 f"{100 * corrected_row[3] / total_cpu:.0f} % |")
    lines.append("")
    lines.append(f"Not in the steps: pydantic meta/manifest, scene statistics, masks, the atomic renames "
                 f"(whole call minus the "
                 f"steps: {total_cpu - s_cpu:+.0f} CPU ms, {total - s_ms:+.0f} ms of wall). Each write step is timed "
                 f"alone; the whole call also gives its written pages back (scheduling.release_written_pages).")
    text = "\n".join(lines)
    print(text)
    if args.write:
        print("written to", update_results("profile_scene", text))
    shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONHASHSEED", "0")
    main()
