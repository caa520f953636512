"""The baseline for build-dataset's speed: the plain script a user would write instead of gtforge.

One process, tifffile + OpenCV + Open3D, one scene after another: read the depth TIFF, undistort it
(``cv2.remap`` with nearest-neighbour maps computed once, as a careful user does), back-project and
transform it and render it into the rectified ZED-left camera with Open3D's tensor API
(``create_from_depth_image`` + ``project_to_depth_image``), turn depth into disparity, then write what
stereo training code reads: ``im0.png``/``im1.png`` (``cv2.imwrite`` of the decoded ZED images),
``disp0GT.pfm`` and a KITTI uint16 disparity PNG. No occlusion mask, regions, weights, verification,
hashing, resume or atomic writes: the least a user gets away with.

    python benchmarks/baseline_open3d_script.py SESSION CALIBRATION OUT

SESSION is a gtforge capture session with ``scenes/*/{DepthMap.tiff,left.png,right.png}`` and
CALIBRATION a gtforge calibration YAML (read with PyYAML only, as a user would read their own numbers).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import tifffile
import yaml


def load_rig(calibration: Path):
    rig = yaml.safe_load(calibration.read_text())["rig"]
    mech, zed = rig["mech"], rig["zed"]

    def K(c):
        return np.array([[c["fx_px"], 0, c["cx_px"]], [0, c["fy_px"], c["cy_px"]], [0, 0, 1]], np.float64)

    return dict(K_mech=K(mech), dist_mech=np.array(mech.get("dist_coeffs") or [0.0] * 5, np.float64),
                mech_wh=(mech["width_px"], mech["height_px"]), K_zed=K(zed["left"]),
                zed_wh=(zed["left"]["width_px"], zed["left"]["height_px"]), baseline_mm=zed["baseline_mm"],
                doffs_px=zed.get("doffs_px", 0.0), T_zed_from_mech=np.array(rig["T_zed_from_mech"], np.float64))


def write_pfm(path: Path, disp: np.ndarray) -> None:
    d = np.where(np.isfinite(disp), disp, np.inf).astype("<f4")
    with open(path, "wb") as f:
        f.write(f"Pf\n{d.shape[1]} {d.shape[0]}\n-1.0\n".encode())
        f.write(np.flipud(d).tobytes())


def main(session: Path, calibration: Path, out: Path) -> int:
    rig = load_rig(calibration)
    map1, map2 = cv2.initUndistortRectifyMap(rig["K_mech"], rig["dist_mech"], None, rig["K_mech"], rig["mech_wh"],
                                             cv2.CV_32FC1)
    K_m = o3d.core.Tensor(rig["K_mech"])
    K_z = o3d.core.Tensor(rig["K_zed"])
    I4 = o3d.core.Tensor(np.eye(4))
    T_zed_from_mech = o3d.core.Tensor(rig["T_zed_from_mech"])
    W, H = rig["zed_wh"]
    fB = rig["K_zed"][0, 0] * rig["baseline_mm"]
    scenes = sorted(p for p in (session / "scenes").iterdir() if p.is_dir())
    for cap in scenes:
        depth = tifffile.imread(cap / "DepthMap.tiff").astype(np.float32)
        depth[~np.isfinite(depth)] = 0.0
        depth = cv2.remap(depth, map1, map2, cv2.INTER_NEAREST)
        pcd = o3d.t.geometry.PointCloud.create_from_depth_image(o3d.t.geometry.Image(depth), K_m, I4,
                                                                depth_scale=1.0, depth_max=1e5)
        z = pcd.project_to_depth_image(W, H, K_z, T_zed_from_mech, depth_scale=1.0,
                                       depth_max=1e5).as_tensor().numpy()[..., 0]
        disp = np.full(z.shape, np.nan, np.float32)
        ok = z > 0
        disp[ok] = fB / z[ok] - rig["doffs_px"]
        dst = out / cap.name
        dst.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(dst / "im0.png"), cv2.imread(str(cap / "left.png")))
        cv2.imwrite(str(dst / "im1.png"), cv2.imread(str(cap / "right.png")))
        write_pfm(dst / "disp0GT.pfm", disp)
        kitti = np.where(ok, np.clip(np.round(disp * 256), 1, 65535), 0).astype(np.uint16)
        cv2.imwrite(str(dst / "disp_10.png"), kitti)
    return len(scenes)


if __name__ == "__main__":
    t0 = time.perf_counter()
    n = main(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]))
    print(f"{n} scenes in {time.perf_counter() - t0:.1f} s")
