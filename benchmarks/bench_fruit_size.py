"""evaluate's added cost per scene from the fruit size figures (gtforge.core.measure.fruit_size).

Usage: python benchmarks/bench_fruit_size.py WORKDIR SCALE N_SCENES  (SCALE 1.0: the ZED's 2K, 2208x1242)
"""
import sys
import time
from pathlib import Path

from gtforge.build_dataset import build_dataset
from gtforge.core.camera import Rig
from gtforge.evaluate import evaluate
from gtforge.io.formats import read_pfm, write_pfm
from gtforge.predictors import PredictionFolder
from gtforge.records.calibration import CalibrationFile
from gtforge.synthetic import default_rig, generate_session

d = Path(sys.argv[1])
scale = float(sys.argv[2])
n = int(sys.argv[3])
if not (d / "ds").exists():
    generate_session(d / "s", n_board=0, n_scenes=n, scale=scale, seed=1, depth_noise_mm=0.03, supersample=1)
    r = default_rig(scale)
    CalibrationFile.known_extrinsic(Rig(zed=r.zed, mech=r.mech,
                                        T_zed_from_mech=r.T_zed_from_mech.tolist())).write(d / "c.yaml")
    build_dataset(d / "s", d / "c.yaml", d / "ds", workers=1)
    (d / "p").mkdir()
    for s in (d / "ds" / "scenes").iterdir():
        write_pfm(d / "p" / f"{s.name}.pfm", read_pfm(s / "disp0GT.pfm") + 0.3)
shape = read_pfm(next((d / "ds" / "scenes").iterdir()) / "disp0GT.pfm").shape
for out in (None, d / "ev"):
    for fs in (False, True, False, True):
        t, c = time.perf_counter(), time.process_time()
        rep = evaluate(d / "ds", PredictionFolder(d / "p"), out, fruit_size=fs)
        n = len(rep.scenes)
        wall, cpu = (time.perf_counter() - t) / n * 1000, (time.process_time() - c) / n * 1000
        extra = f"; fruit size alone {rep.fruit_size.time_ms_per_scene:.0f} ms/scene (median)" if fs else ""
        print(f"{shape[1]}x{shape[0]}, {'writing maps and HTML' if out else 'no output folder'}, fruit_size={fs}: "
              f"{wall:.0f} ms wall, {cpu:.0f} ms CPU per scene{extra}")
# the fruit figures alone, CPU time (a shared machine's wall clock varies more than the cost itself)
from gtforge.core.measure.fruit_size import measure_scene
from gtforge.io.formats import read_image
from gtforge.io.middlebury import SceneCalib

s = sorted((d / "ds" / "scenes").iterdir())[0]
cal, gt, reg = SceneCalib(s / "calib.txt"), read_pfm(s / "disp0GT.pfm"), read_image(s / "region.png")
measure_scene(s.name, reg, cal, gt, gt + 0.3)
c = time.process_time()
for _ in range(5):
    measure_scene(s.name, reg, cal, gt, gt + 0.3)
print(f"{shape[1]}x{shape[0]}: measure_scene (GT + prediction, one fruit): "
      f"{(time.process_time() - c) / 5 * 1000:.0f} ms CPU per scene")
