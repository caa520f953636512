"""evaluate's added cost per scene from the fruit size figures (gtforge.fruit_size).

Usage: python benchmarks/bench_fruit_size.py WORKDIR SCALE N_SCENES  (SCALE 1.0: the ZED's 2K, 2208x1242)
"""
import sys, time, numpy as np
from pathlib import Path
from gtforge.synthetic import generate_session, default_rig
from gtforge.camera import Rig
from gtforge.calibrate import CalibrationFile
from gtforge.build_dataset import build_dataset
from gtforge.evaluate import evaluate
from gtforge.predictors import PredictionFolder
from gtforge.io.formats import read_pfm, write_pfm
d = Path(sys.argv[1]); scale = float(sys.argv[2]); n = int(sys.argv[3])
if not (d / "ds").exists():
    generate_session(d / "s", n_board=0, n_scenes=n, scale=scale, seed=1, depth_noise_mm=0.03, supersample=1)
    r = default_rig(scale)
    CalibrationFile.known_extrinsic(Rig(zed=r.zed, mech=r.mech, T_zed_from_mech=r.T_zed_from_mech.tolist())).write(d / "c.yaml")
    build_dataset(d / "s", d / "c.yaml", d / "ds", workers=1)
    (d / "p").mkdir()
    for s in (d / "ds" / "scenes").iterdir():
        write_pfm(d / "p" / f"{s.name}.pfm", read_pfm(s / "disp0GT.pfm") + 0.3)
for fs in (False, True, False, True):
    t = time.perf_counter()
    rep = evaluate(d / "ds", PredictionFolder(d / "p"), None, fruit_size=fs)
    dt = (time.perf_counter() - t) / len(rep.scenes) * 1000
    extra = f", fruit size {rep.fruit_size.time_ms_per_scene:.0f} ms/scene (median)" if fs else ""
    print(f"scale {scale} ({rep.per_scene and read_pfm(d/'ds'/'scenes'/rep.scenes[0]/'disp0GT.pfm').shape}): evaluate fruit_size={fs}: {dt:.0f} ms/scene{extra}")
