"""Middlebury's ``calib.txt``: read (``SceneCalib``) and written (``middlebury_calib_text``), as gtforge's datasets hold
one per scene."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from gtforge.core.camera import RectifiedStereo
from gtforge.errors import InputError


class SceneCalib:
    def __init__(self, path: Path):
        if not path.is_file():
            raise InputError(path, None, "a Middlebury calib.txt", "no such file",
                             "gtforge build-dataset writes one in each scene folder (docs/dataset-format.md); run it "
                             "again to rebuild an incomplete scene")
        kv = dict(re.findall(r"^(\w+)=(.*)$", path.read_text(errors="replace"), flags=re.M))
        try:
            cam0 = [float(x) for x in re.split(r"[\s;]+", kv["cam0"].strip("[] "))]
            self.f_px = cam0[0]
            self.fy_px = cam0[4]
            self.cx_px, self.cy_px = cam0[2], cam0[5]
            self.doffs_px = float(kv["doffs"])
            self.baseline_mm = float(kv["baseline"])
            self.ndisp = int(float(kv.get("ndisp", 192)))
            self.vmin = int(float(kv.get("vmin", 0)))
        except (KeyError, ValueError, IndexError) as exc:
            raise InputError(path, str(exc).strip("'"), "Middlebury keys cam0, doffs, baseline",
                             "missing/invalid", "write cam0=[f 0 cx; 0 f cy; 0 0 1], doffs=... and baseline=... (mm), "
                             "one per line, as build-dataset does (docs/dataset-format.md)") from None

    def depth(self, disp: np.ndarray) -> np.ndarray:
        d = np.asarray(disp, np.float64) + self.doffs_px
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(d > 0, self.f_px * self.baseline_mm / d, np.nan)


def middlebury_calib_text(zed: RectifiedStereo, width_px: int, height_px: int,
                          disp_range_px: tuple[float, float] | None, cx_shift_px: float = 0.0,
                          cy_shift_px: float = 0.0) -> str:
    """Middlebury's ``calib.txt``; ``disp_range_px``: the GT disparity's (min, max), None without GT; the shifts: a
    crop's top-left corner (the principal point moves by it)."""
    f, cx, cy = zed.left.fx_px, zed.left.cx_px - cx_shift_px, zed.left.cy_px - cy_shift_px
    vmin = int(np.floor(disp_range_px[0])) if disp_range_px else 0
    vmax = int(np.ceil(disp_range_px[1])) if disp_range_px else 0
    ndisp = int(max(32, 16 * np.ceil((vmax + 1) / 16)))
    return (f"cam0=[{f:.6f} 0 {cx:.6f}; 0 {zed.left.fy_px:.6f} {cy:.6f}; 0 0 1]\n"
            f"cam1=[{f:.6f} 0 {cx + zed.doffs_px:.6f}; 0 {zed.left.fy_px:.6f} {cy:.6f}; 0 0 1]\n"
            f"doffs={zed.doffs_px:.6f}\nbaseline={zed.baseline_mm:.6f}\nwidth={width_px}\nheight={height_px}\n"
            f"ndisp={ndisp}\nisint=0\nvmin={vmin}\nvmax={vmax}\ndyavg=0\ndymax=0\n")
