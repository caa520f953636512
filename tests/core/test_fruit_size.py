"""Per-fruit size, volume and grade (gtforge.core.measure.fruit_size, evaluate's fruit_size) and the shape fits behind
them."""
import json

import numpy as np
import pytest

from gtforge.core.measure.fruit_size import (
    FruitSize,
    GradeBins,
    fruit_instances,
    measure_fruit,
    parse_grades,
    points_from_disparity,
    table_plane,
)
from gtforge.core.measure.shapefit import fit_plane_lsq, fit_resting_ellipsoid, fit_sphere
from gtforge.errors import InputError
from gtforge.evaluate import compare, evaluate
from gtforge.io.formats import read_image, read_pfm, write_pfm
from gtforge.io.middlebury import SceneCalib
from gtforge.predictors import PredictionFolder
from gtforge.records.evaluation import EvalResult


# ---- shape fits -----------------------------------------------------------------------------------
def _cap(n, rng, z_max=-0.2):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d[d[:, 2] < z_max]


def test_sphere_fit_recovers_size_and_form_of_noisy_cap():
    rng = np.random.default_rng(0)
    d = _cap(4000, rng)
    noise = rng.normal(0, 0.02, len(d))
    p = np.array([10.0, -20.0, 600.0]) + (50.0 + noise)[:, None] * d  # radial noise only: residuals = noise
    f = fit_sphere(p)
    assert f.ok and f.n_points == len(d)
    assert f.diameter_mm == pytest.approx(100.0, abs=0.005)
    assert np.allclose(f.centre_mm, [10, -20, 600], atol=0.01)
    assert f.rms_mm == pytest.approx(np.std(noise), rel=0.02)
    assert f.form_range_mm == pytest.approx(np.ptp(noise), rel=0.05)


def test_plane_fit_flatness_is_the_range_of_the_distances():
    rng = np.random.default_rng(1)
    uv = rng.uniform(-100, 100, (500, 2))
    h = rng.uniform(-0.1, 0.1, 500)
    n = np.array([0.0, 0.6, -0.8])
    e1, e2 = np.array([1.0, 0, 0]), np.array([0, 0.8, 0.6])
    p = np.array([0, 0, 700.0]) + uv[:, :1] * e1 + uv[:, 1:] * e2 + h[:, None] * n
    f = fit_plane_lsq(p)
    assert f.ok and np.allclose(f.normal, n, atol=1e-3)
    assert f.flatness_mm == pytest.approx(np.ptp(h), abs=0.01)


def test_fits_say_why_they_cannot_measure():
    rng = np.random.default_rng(2)
    f = fit_sphere(rng.normal(size=(5, 3)))
    assert not f.ok and "too few points (5 < 20)" in f.reason
    flat = np.column_stack([rng.uniform(0, 100, (200, 2)), np.full(200, 500.0)])
    f = fit_sphere(flat)
    assert not f.ok and ("flat" in f.reason or "converge" in f.reason)
    assert not fit_plane_lsq(np.zeros((3, 3))).ok
    e = fit_resting_ellipsoid(rng.normal(size=(10, 3)), np.array([0, 0, -1.0]), -700.0)
    assert not e.ok and "too few points" in e.reason


def test_resting_ellipsoid_is_exact_on_its_visible_half():
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.45, 0.1, 0.0]).as_matrix()
    n = R @ np.array([0, 0, -1.0])  # table normal towards the camera
    foot = np.array([15.0, -10.0, 700.0])
    e1, e2 = R @ np.array([1.0, 0, 0]), R @ np.array([0, 1.0, 0])
    a, b, c, yaw = 104.0, 92.0, 81.0, 0.7
    A1, A2 = np.cos(yaw) * e1 + np.sin(yaw) * e2, -np.sin(yaw) * e1 + np.cos(yaw) * e2
    C = foot + c * n
    u = _cap(6000, np.random.default_rng(3), z_max=2.0)
    u = u[u[:, 2] > -0.2]  # the top and a little below the equator
    p = C + np.outer(a * u[:, 0], A1) + np.outer(b * u[:, 1], A2) + np.outer(c * u[:, 2], n)
    f = fit_resting_ellipsoid(p, n, float(n @ foot))
    assert f.ok
    assert np.allclose(f.radii_mm, [a, b, c], atol=1e-6)
    assert f.volume_ml == pytest.approx(4 / 3 * np.pi * a * b * c / 1000, rel=1e-9)
    assert f.diameter_mm == pytest.approx(2 * np.sqrt(a * b), rel=1e-9)
    assert abs(f.axes[:, 0] @ A1) == pytest.approx(1.0, abs=1e-9)


def test_a_robust_loss_keeps_gross_limb_outliers_from_moving_the_resting_ellipsoid():
    """2 % of the points, at the limb, 5-40 mm behind the surface along their rays (gross outliers): the plain
    least-squares fit (the default) grows the diameter by most of a millimetre, the Cauchy refit keeps it within
    0.05 mm."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec([0.45, 0.1, 0.0]).as_matrix()
    n = R @ np.array([0, 0, -1.0])
    foot = np.array([15.0, -10.0, 700.0])
    e1, e2 = R @ np.array([1.0, 0, 0]), R @ np.array([0, 1.0, 0])
    a, b, c, yaw = 104.0, 92.0, 81.0, 0.7
    A1, A2 = np.cos(yaw) * e1 + np.sin(yaw) * e2, -np.sin(yaw) * e1 + np.cos(yaw) * e2
    rng = np.random.default_rng(0)
    u = _cap(8000, rng, z_max=2.0)
    u = u[u[:, 2] > -0.2]
    p = foot + c * n + np.outer(a * u[:, 0], A1) + np.outer(b * u[:, 1], A2) + np.outer(c * u[:, 2], n)
    p += rng.normal(0, 0.3, p.shape)
    k = len(p) // 50
    idx = rng.choice(np.argsort((p - foot) @ n)[:4 * k], k, replace=False)  # among the lowest points: the limb
    p[idx] += p[idx] / np.linalg.norm(p[idx], axis=1, keepdims=True) * rng.uniform(5, 40, k)[:, None]
    true_mm = 2 * np.sqrt(a * b)
    plain = fit_resting_ellipsoid(p, n, float(n @ foot))
    robust = fit_resting_ellipsoid(p, n, float(n @ foot), loss="cauchy")
    assert plain.ok and robust.ok
    assert plain.diameter_mm - true_mm > 0.5, plain.diameter_mm
    assert abs(robust.diameter_mm - true_mm) < 0.05, robust.diameter_mm
    assert np.allclose(robust.radii_mm, [a, b, c], atol=0.1), robust.radii_mm
    with pytest.raises(ValueError, match="loss 'l2'"):
        fit_resting_ellipsoid(p, n, float(n @ foot), loss="l2")


# ---- grades ---------------------------------------------------------------------------------------
def test_grade_bins_and_their_parsing():
    g = parse_grades("diameter_mm:180,200,220")
    assert g == GradeBins(quantity="diameter_mm", edges=[180, 200, 220])
    assert [g.grade(x) for x in (150, 180, 199.9, 200, 230, float("nan"))] == [0, 1, 1, 2, 3, None]
    assert g.labels() == ["<180", "180-200", "200-220", ">=220"]
    for bad in ("diameter:180", "diameter_mm:200,180", "volume_ml:", "volume_ml:-5,3", "diameter_mm:1,x"):
        with pytest.raises(InputError, match=r"--grades"):
            parse_grades(bad)


def test_bad_grades_on_the_command_line_is_a_one_line_error(tmp_path):
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "gtforge.cli", "evaluate", str(tmp_path), "--sgbm", "--grades",
                        "diameter_mm:200,180"], capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    msg = (r.stdout + r.stderr).strip()
    assert "--grades" in msg and "increasing" in msg and "Traceback" not in msg and len(msg.splitlines()) == 1


# ---- on a built synthetic dataset ---------------------------------------------------------------
@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    """3 noise-free fruit scenes at 0.25x (ZED 552x310), built with the exact extrinsic; the generator's fruit
    ellipsoids in truth/."""
    from gtforge.build_dataset import build_dataset
    from gtforge.core.camera import Rig
    from gtforge.records.calibration import CalibrationFile
    from gtforge.synthetic import default_rig, generate_session

    root = tmp_path_factory.mktemp("fruit")
    generate_session(root / "session", n_board=0, n_scenes=3, scale=0.25, seed=5, depth_noise_mm=0.0,
                     image_noise=1.0, supersample=1)
    r = default_rig(0.25)
    CalibrationFile.known_extrinsic(Rig(zed=r.zed, mech=r.mech, T_zed_from_mech=r.T_zed_from_mech.tolist())).write(
        root / "calib.yaml")
    build_dataset(root / "session", root / "calib.yaml", root / "ds", workers=1)
    return root


def _scenes(root):
    return sorted(p for p in (root / "ds" / "scenes").iterdir() if p.is_dir())


def _write_predictions(root, name, fn):
    d = root / name
    d.mkdir(exist_ok=True)
    for s in _scenes(root):
        write_pfm(d / f"{s.name}.pfm", fn(s, read_pfm(s / "disp0GT.pfm"), SceneCalib(s / "calib.txt")))
    return d


@pytest.mark.slow
def test_gt_fruit_size_matches_the_generators_fruit(small_dataset, tmp_path):
    """The ground truth labels' fitted fruit: diameter within 0.1 mm, volume within 0.5 % of the generator's."""
    pred = _write_predictions(small_dataset, "pred_gt", lambda s, gt, cal: gt)
    rep = evaluate(small_dataset / "ds", PredictionFolder(pred, "gt"), tmp_path / "ev")
    f = rep.fruit_size
    assert len(f.fruit) == 3 and all(r.truth is not None and r.gt.ok for r in f.fruit)
    for r in f.fruit:
        assert abs(r.gt_diameter_error_mm) <= 0.1
        assert abs(r.gt_volume_error_pct) <= 0.5
        assert abs(r.gt.height_mm - r.truth.height_mm) <= 0.2
        assert r.diameter_error_mm == 0.0 and r.volume_error_pct == 0.0  # the prediction is the GT
    assert f.diameter_gt_vs_truth.n == 3 and f.diameter_gt_vs_truth.max_abs_mm <= 0.1
    assert f.diameter_model_vs_gt.mae_mm == 0.0
    assert f.time_ms_per_scene is not None and f.time_ms_per_scene > 0
    # results.json round trip; results.html has the section and its scatter plot
    again = EvalResult.read(tmp_path / "ev" / "results.json")
    assert again.fruit_size.fruit[0].gt.diameter_mm == f.fruit[0].gt.diameter_mm
    page = (tmp_path / "ev" / "results.html").read_text()
    assert "Fruit size, volume and grade" in page and "predicted vs GT fruit diameter" in page
    rows = (tmp_path / "ev" / "fruit_size.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[0].startswith("scene,fruit,n_pixels,gt_ok,gt_diameter_mm")
    assert float(rows[1].split(",")[4]) == f.fruit[0].gt.diameter_mm


@pytest.mark.slow
def test_disparity_scale_error_scales_every_size_exactly_and_grades_follow(small_dataset, tmp_path):
    """A prediction whose d + doffs is the GT's divided by s puts every point at s times its distance: diameters
    x s, volumes x s^3, exactly; the grades are those of s * D_GT."""
    s_scale = 1.02
    base = evaluate(small_dataset / "ds", PredictionFolder(_write_predictions(small_dataset, "p1", lambda s, gt, c: gt),
                                                           "gt"), None)
    D = np.array([r.gt.diameter_mm for r in base.fruit_size.fruit])
    # bin edges between the fruit and between each fruit and its scaled size: every fruit moves up one grade
    edges = sorted(list(D * (1 + (s_scale - 1) / 2)) + [D.min() * 0.9])
    bins = GradeBins(quantity="diameter_mm", edges=edges)
    pred = _write_predictions(small_dataset, "p_scale", lambda s, gt, c: (gt + c.doffs_px) / s_scale - c.doffs_px)
    rep = evaluate(small_dataset / "ds", PredictionFolder(pred, "scaled"), tmp_path / "ev", grades=bins)
    f = rep.fruit_size
    for r in f.fruit:
        assert r.pred.diameter_mm / r.gt.diameter_mm == pytest.approx(s_scale, rel=2e-6)
        assert r.pred.volume_ml / r.gt.volume_ml == pytest.approx(s_scale ** 3, rel=6e-6)
        assert r.diameter_error_mm == pytest.approx((s_scale - 1) * r.gt.diameter_mm, abs=1e-3)
        assert r.grade_pred == r.grade_gt + 1
    assert f.volume_model_vs_gt.mape_pct == pytest.approx((s_scale ** 3 - 1) * 100, rel=1e-4)
    assert f.diameter_model_vs_gt.max_abs_mm == pytest.approx((s_scale - 1) * D.max(), abs=1e-3)
    g = f.grades_model_vs_gt
    assert g.n == 3 and g.changed_pct == 100.0
    cm = np.array(g.confusion)
    assert cm.sum() == 3 and np.trace(cm) == 0 and np.trace(cm, offset=1) == 3
    assert (tmp_path / "ev" / "results.md").read_text().count("GT \\ model") == 1
    # compare shows the fruit table for both results
    base_dir = tmp_path / "base"
    evaluate(small_dataset / "ds", PredictionFolder(small_dataset / "p1", "gt"), base_dir)
    table, _ = compare([tmp_path / "ev" / "results.json", base_dir / "results.json"], tmp_path / "cmp")
    assert "diameter MAE (mm)" in table and "| scaled | 3 |" in table and "| gt | 3 | 0.000 |" in table
    assert "Fruit size, volume and grade" in (tmp_path / "cmp" / "comparison.html").read_text()


@pytest.mark.slow
def test_constant_disparity_offset_gives_the_predicted_diameter_change(small_dataset):
    """A constant offset delta maps each point X to X / (1 + delta Z / (f B)) (a projective map, not a scaling).
    evaluate's figures equal the same fit on the generator's exact depth with the offset added (the prediction,
    independent of the GT labels) to 0.1 mm, and the change is close to the first-order -D delta / (d + doffs)."""
    delta = 0.5
    pred = _write_predictions(small_dataset, "p_off", lambda s, gt, c: gt + delta)
    rep = evaluate(small_dataset / "ds", PredictionFolder(pred, "offset"), None)
    by_scene = {r.scene: r for r in rep.fruit_size.fruit}
    for s in _scenes(small_dataset):
        cal = SceneCalib(s / "calib.txt")
        with np.load(small_dataset / "session" / "truth" / f"scene_{s.name}.npz") as z:
            exact = cal.f_px * cal.baseline_mm / z["zed_depth_mm"].astype(np.float64) - cal.doffs_px
        region = read_image(s / "region.png")
        m = fruit_instances(region)[0]
        want = measure_fruit(exact + delta, cal, m, region == 1)
        got = by_scene[s.name]
        assert got.pred.diameter_mm == pytest.approx(want.diameter_mm, abs=0.1)
        assert got.pred.volume_ml == pytest.approx(want.volume_ml, rel=0.005)
        first_order = -got.gt.diameter_mm * delta / (np.nanmedian(read_pfm(s / "disp0GT.pfm")[m]) + cal.doffs_px)
        assert got.diameter_error_mm < 0 and 0.6 < got.diameter_error_mm / first_order < 1.1


def test_a_prediction_invalid_on_every_other_row_is_still_measured(small_dataset):
    """The fit's pixels were taken on a grid before the invalid ones were dropped: a prediction invalid on every
    other row (as an interlaced or row-skipping output is) left the grid on its holes only, and the fruit 'too few
    table pixels' (a run-through). Now such a grid falls back to every pixel: the same fruit as from the complete GT
    to within what half its rows change (0.2 mm), while the GT itself is measured on the grid as before."""
    s = _scenes(small_dataset)[0]
    cal = SceneCalib(s / "calib.txt")
    gt = read_pfm(s / "disp0GT.pfm")
    region = read_image(s / "region.png")
    m = fruit_instances(region)[0]
    holes = gt.copy()
    holes[::2] = np.inf  # the rows a grid of step 2 starts on
    step = 2
    assert len(points_from_disparity(holes, cal, m, step)) == len(points_from_disparity(holes, cal, m, 1))
    grid = m & (np.indices(m.shape) % step == 0).all(0)
    assert np.array_equal(points_from_disparity(gt, cal, m, step), points_from_disparity(gt, cal, grid, 1))
    assert len(points_from_disparity(gt, cal, m, step)) < len(points_from_disparity(gt, cal, m, 1)) / 3
    full, half = measure_fruit(gt, cal, m, region == 1), measure_fruit(holes, cal, m, region == 1)
    assert full.ok and half.ok, half.reason
    assert half.diameter_mm == pytest.approx(full.diameter_mm, abs=0.2)


@pytest.mark.slow
def test_results_without_fruit_size_still_load(small_dataset, tmp_path):
    pred = _write_predictions(small_dataset, "p_old", lambda s, gt, c: gt)
    rep = evaluate(small_dataset / "ds", PredictionFolder(pred, "old"), tmp_path / "ev", fruit_size=False)
    assert rep.fruit_size is None
    data = json.loads((tmp_path / "ev" / "results.json").read_text())
    data.pop("fruit_size", None)  # as written before the field existed
    assert EvalResult.from_dict(data).fruit_size is None
    assert "diameter MAE" not in (tmp_path / "ev" / "results.md").read_text()


@pytest.mark.slow
def test_too_little_table_makes_a_fruit_not_measurable(small_dataset):
    s = _scenes(small_dataset)[0]
    cal = SceneCalib(s / "calib.txt")
    region = read_image(s / "region.png")
    gt = read_pfm(s / "disp0GT.pfm")
    m = fruit_instances(region)[0]
    size = measure_fruit(gt, cal, m, np.zeros_like(m))
    assert not size.ok and "table" in size.reason
    assert table_plane(gt, cal, region == 1, m) is not None
    assert len(points_from_disparity(gt, cal, m)) == int(np.isfinite(gt[m]).sum())
    assert FruitSize.from_radii([90, 100, 80], [0, 0, 0]).length_mm == 200.0
