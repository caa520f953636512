"""The gauge figures of docs/metrics.md ("Gauge objects"): a synthetic session with gauges, validated with the exact
extrinsic and a depth noise model equal to the noise put in.

Usage: PYTHONPATH=src python benchmarks/gauge_figures.py WORKDIR SCALE DEPTH_NOISE_MM   (docs: 0.3 0.0 and 0.3 0.05)
"""
import sys
from pathlib import Path

from gtforge.core.camera import Rig
from gtforge.core.measure.gauges import GaugeParams
from gtforge.core.ground_truth.uncertainty import DepthNoiseModel
from gtforge.records.calibration import CalibrationFile
from gtforge.synthetic import default_rig, generate_gauges, generate_session
from gtforge.validate import validate_gauges

d, scale, noise = Path(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
if not (d / "s").exists():
    generate_session(d / "s", n_board=0, n_scenes=0, scale=scale, seed=3, depth_noise_mm=noise, image_noise=1.0,
                     supersample=1)
    generate_gauges(d / "s", scale=scale, seed=3, depth_noise_mm=noise)
r = default_rig(scale)
CalibrationFile.known_extrinsic(Rig(zed=r.zed, mech=r.mech,
                                    T_zed_from_mech=r.T_zed_from_mech.tolist())).write(d / "c.yaml")
model = DepthNoiseModel(a_mm=noise, b_mm_per_m2=0.0)  # the noise put in (0: the sigma map's mesh term alone)
rep = validate_gauges(d / "s", d / "c.yaml", d / "out", GaugeParams(depth_noise=model))


def f(x, fmt="{:+.4f}"):
    return "-" if x is None else fmt.format(x)


for g in rep.gauges:
    for src in (g.gt, g.raw):
        if src is None or not src.measurable:
            print(g.capture, getattr(src, "source", "raw"), "not measurable", getattr(src, "reason", ""))
            continue
        for k, s in enumerate(src.spheres):
            print(f"{g.capture} {src.source} sphere {k + 1}: PS {f(s.size_error_mm)} "
                  f"(1-sigma {f(s.size_sigma_predicted_mm, '{:.4f}')}) "
                  f"PF {s.form_range_mm:.4f} (pred {f(s.form_range_predicted_mm, '{:.4f}')}) RMS {s.form_rms_mm:.4f} "
                  f"(pred {f(s.form_rms_predicted_mm, '{:.4f}')}) n {s.n_points} outliers {s.n_outliers}")
        if src.spacing_error_mm is not None:
            print(f"{g.capture} {src.source}: SD {src.spacing_error_mm:+.4f} "
                  f"(1-sigma {f(src.spacing_sigma_predicted_mm, '{:.4f}')})")
        if src.flatness_mm is not None:
            print(f"{g.capture} {src.source}: F {src.flatness_mm:.4f} (pred {f(src.flatness_predicted_mm, '{:.4f}')}) "
                  f"RMS {src.plane_rms_mm:.4f} (pred {f(src.plane_rms_predicted_mm, '{:.4f}')}) n {src.n_points}")
print("status", rep.status, f"{rep.time_s:.1f} s")
