"""Gauge objects (VDI/VDE 2634-2) measured on the ground truth: gtforge.core.measure.gauges against the generator's
exact sizes."""
import shutil
import subprocess
import sys

import numpy as np
import pytest
import yaml

from gtforge.core.camera import Rig
from gtforge.core.measure.gauges import GaugeParams, GaugesFile, GaugesResult, read_gauges_file, summary_lines
from gtforge.core.ground_truth.uncertainty import DepthNoiseModel
from gtforge.errors import InputError
from gtforge.io.captures import read_depth
from gtforge.io.formats import write_tiff_float
from gtforge.records.calibration import CalibrationFile
from gtforge.core.geometry import perturb_left
from gtforge.synthetic import default_rig, generate_gauges, generate_session
from gtforge.validate import validate_gauges

SCALE = 0.3  # ZED 662x373, structured light 576x360
NOISE_MM = 0.05


def _session(root, noise):
    generate_session(root, n_board=0, n_scenes=0, scale=SCALE, seed=3, depth_noise_mm=noise, image_noise=1.0,
                     supersample=1)
    generate_gauges(root, scale=SCALE, seed=3, depth_noise_mm=noise)
    return root


def _calib(path, T_zed_from_mech=None):
    r = default_rig(SCALE)
    T_zed_from_mech = r.T_zed_from_mech if T_zed_from_mech is None else T_zed_from_mech
    CalibrationFile.known_extrinsic(Rig(zed=r.zed, mech=r.mech, T_zed_from_mech=T_zed_from_mech.tolist())).write(path)
    return path


@pytest.fixture(scope="module")
def exact(tmp_path_factory):
    """Noise-free gauge captures, the exact extrinsic: (session, calibration, report)."""
    root = tmp_path_factory.mktemp("gauges")
    s = _session(root / "session", 0.0)
    c = _calib(root / "calib.yaml")
    return s, c, validate_gauges(s, c, root / "out")


def _by(rep):
    return {g.capture: g for g in rep.gauges}


@pytest.mark.slow
def test_generator_writes_gauges_yaml_with_the_exact_sizes(exact):
    s, _, _ = exact
    g = GaugesFile.read(s / "gauges" / "gauges.yaml")
    assert [(x.capture, x.kind, x.diameter_mm, x.centre_distance_mm) for x in g.gauges] == [
        ("sphere", "sphere", 100.0, None), ("sphere_pair", "sphere_pair", 80.0, 240.0), ("plane", "plane", None, None)]
    with np.load(s / "truth" / "gauge_sphere_pair.npz") as z:
        assert np.linalg.norm(np.diff(z["centres_zed_mm"], axis=0)) == pytest.approx(240.0, abs=1e-9)


@pytest.mark.slow
def test_exact_extrinsic_gives_sizes_within_005_mm(exact):
    s, _, rep = exact
    g = _by(rep)
    assert rep.status == "PASS" and all(x.status == "PASS" for x in rep.gauges)
    spheres = g["sphere"].gt.spheres + g["sphere_pair"].gt.spheres
    assert len(spheres) == 3
    for sp in spheres:
        assert abs(sp.size_error_mm) <= 0.05 and sp.n_points > 500
        assert sp.form_range_mm <= 0.05  # mesh interpolation only (no noise put in)
    # the fitted centres are the generator's to 0.05 mm
    with np.load(s / "truth" / "gauge_sphere_pair.npz") as z:
        truth = z["centres_zed_mm"]
    got = np.array([sp.centre_mm for sp in g["sphere_pair"].gt.spheres])
    assert np.min([np.abs(got - truth).max(), np.abs(got[::-1] - truth).max()]) <= 0.05
    assert abs(g["sphere_pair"].gt.spacing_error_mm) <= 0.05
    assert g["plane"].gt.flatness_mm <= 0.01 and g["plane"].gt.n_points > 1000
    # the raw depth (noise-free, exact rig) is exact
    for sp in g["sphere"].raw.spheres + g["sphere_pair"].raw.spheres:
        assert abs(sp.size_error_mm) <= 0.002
    assert abs(g["sphere_pair"].raw.spacing_error_mm) <= 0.002
    assert (rep_path := s.parent / "out" / "gauges.json").is_file()
    assert GaugesResult.read(rep_path).gauges[1].gt.spacing_error_mm == g["sphere_pair"].gt.spacing_error_mm
    page = (s.parent / "out" / "gauges.html").read_text()
    assert "sphere-spacing error SD" in page and "gauge residual map and histogram" in page
    assert any("spacing error" in line for line in summary_lines(rep))


def _copy_with_depth(src, dst, fn):
    shutil.copytree(src, dst)
    for g in ("sphere", "sphere_pair", "plane"):
        f = dst / "gauges" / g / "DepthMap.tiff"
        write_tiff_float(f, fn(read_depth(f)).astype(np.float32))
    return dst


@pytest.mark.slow
def test_form_error_is_what_the_depth_noise_and_the_sigma_map_predict(exact, tmp_path):
    """Depth noise of 0.05 mm put in (Gaussian along the depth camera's z, as the generator adds it): the raw depth's
    radial RMS is the noise model's, the GT's the sigma map's."""
    s0, c, _ = exact
    rng = np.random.default_rng(0)
    s = _copy_with_depth(s0, tmp_path / "noisy", lambda d: d + rng.normal(0, NOISE_MM, d.shape))
    rep = validate_gauges(s, c, None,
                          GaugeParams(depth_noise=DepthNoiseModel(a_mm=NOISE_MM, b_mm_per_m2=0.0)))
    g = _by(rep)
    for src in ("gt", "raw"):
        tol = 0.1 if src == "gt" else 0.05
        for sp in getattr(g["sphere"], src).spheres + getattr(g["sphere_pair"], src).spheres:
            assert sp.form_rms_mm == pytest.approx(sp.form_rms_predicted_mm, rel=tol)
            assert 0.7 < sp.form_range_mm / sp.form_range_predicted_mm < 1.5
            assert abs(sp.size_error_mm) <= 0.1
        p = getattr(g["plane"], src)
        assert p.plane_rms_mm == pytest.approx(p.plane_rms_predicted_mm, rel=tol)
    # the interpolated GT is smoother than the raw depth it is built from
    assert g["sphere"].gt.spheres[0].form_rms_mm < g["sphere"].raw.spheres[0].form_rms_mm


@pytest.mark.slow
def test_depth_scale_error_of_01_pct_shows_in_size_and_spacing_as_predicted(exact, tmp_path):
    """Depth x 1.001 scales every point about the depth camera by 1.001: diameters +0.1 %, spacing +0.24 mm."""
    s0, c, rep0 = exact
    s = _copy_with_depth(s0, tmp_path / "scaled", lambda d: d * np.float32(1.001))
    rep = validate_gauges(s, c, None)
    a, b = _by(rep0), _by(rep)
    for name in ("sphere", "sphere_pair"):
        for src in ("gt", "raw"):
            for s0_, s1_ in zip(getattr(a[name], src).spheres, getattr(b[name], src).spheres):
                assert s1_.size_error_mm - s0_.size_error_mm == pytest.approx(0.001 * s0_.diameter_mm, abs=0.01)
    for src in ("gt", "raw"):
        d = getattr(b["sphere_pair"], src).spacing_error_mm - getattr(a["sphere_pair"], src).spacing_error_mm
        assert d == pytest.approx(0.001 * getattr(a["sphere_pair"], src).centre_distance_mm, abs=0.02)
    assert b["sphere_pair"].gt.spacing_error_mm == pytest.approx(0.24, abs=0.05)


@pytest.mark.slow
def test_extrinsic_error_of_005_deg_moves_the_gauges_rigidly(exact, tmp_path):
    """A 0.05 deg rotation error of T_zed_from_mech moves the labels rigidly: size, form and spacing do not change
    (these figures cannot see it), and the sphere centres move to exp(w) (c - t) + t as predicted."""
    s, _, rep0 = exact
    T_zed_from_mech = default_rig(SCALE).T_zed_from_mech
    w = np.radians(0.05) * np.array([0.6, 0.8, 0.0])
    T_zed_from_mech_error = perturb_left(T_zed_from_mech, np.r_[w, 0.0, 0.0, 0.0])
    rep = validate_gauges(s, _calib(tmp_path / "c.yaml", T_zed_from_mech_error), None)
    a, b = _by(rep0), _by(rep)
    R_w = T_zed_from_mech_error[:3, :3] @ T_zed_from_mech[:3, :3].T
    for name in ("sphere", "sphere_pair"):
        for s0_, s1_ in zip(a[name].gt.spheres, b[name].gt.spheres):
            assert abs(s1_.size_error_mm - s0_.size_error_mm) <= 0.01
            assert abs(s1_.form_range_mm - s0_.form_range_mm) <= 0.01
            want = R_w @ (np.array(s0_.centre_mm) - T_zed_from_mech[:3, 3]) + T_zed_from_mech[:3, 3]
            moved = np.linalg.norm(np.array(s1_.centre_mm) - s0_.centre_mm)
            assert moved > 0.3  # the labels did move (0.05 deg at about 650 mm)
            assert np.abs(np.array(s1_.centre_mm) - want).max() <= 0.02
    assert abs(b["sphere_pair"].gt.spacing_error_mm - a["sphere_pair"].gt.spacing_error_mm) <= 0.01


def _with_gauges_yaml(src, dst, gauges):
    shutil.copytree(src, dst)
    (dst / "gauges" / "gauges.yaml").write_text(yaml.safe_dump({"schema_version": 1, "gauges": gauges}))
    return dst


@pytest.mark.slow
def test_unmeasurable_gauges_are_reported_per_object(exact, tmp_path):
    s0, c, _ = exact
    s = _with_gauges_yaml(s0, tmp_path / "s", [
        {"capture": "sphere", "kind": "sphere_pair", "diameter_mm": 100.0, "centre_distance_mm": 240.0},
        {"capture": "plane", "kind": "plane"}])
    rep = validate_gauges(s, c, None)
    g = _by(rep)
    assert g["sphere"].status == "NOT MEASURABLE" and not g["sphere"].gt.measurable
    assert g["sphere"].gt.reason == "1 object(s) found above the table, 2 expected"
    assert g["plane"].status == "PASS" and rep.status == "NOT MEASURABLE"
    rep = validate_gauges(s0, c, None, GaugeParams(min_points=100000))
    assert all(x.status == "NOT MEASURABLE" and "too few points" in x.gt.reason for x in rep.gauges)
    assert any("NOT MEASURABLE" in line for line in summary_lines(rep))


@pytest.mark.parametrize("gauge, field, says", [
    ({"capture": "sphere", "kind": "sphere"}, "gauges.0", "needs diameter_mm"),
    ({"capture": "sphere", "kind": "sphere", "diameter_mm": -100.0}, "gauges.0.diameter_mm", "greater than 0"),
    ({"capture": "sphere_pair", "kind": "sphere_pair", "diameter_mm": 80.0}, "gauges.0", "needs centre_distance_mm"),
])
@pytest.mark.slow
def test_bad_gauges_yaml_is_a_one_line_error(exact, tmp_path, gauge, field, says):
    s0, c, _ = exact
    s = _with_gauges_yaml(s0, tmp_path / "s", [gauge])
    with pytest.raises(InputError) as e:
        read_gauges_file(s)
    assert e.value.field == field and says in str(e.value) and "gauges.yaml" in str(e.value)
    if says == "greater than 0":  # the command line once (a process start costs seconds)
        r = subprocess.run([sys.executable, "-m", "gtforge.cli", "validate", str(s), "-c", str(c), "--gauges-only",
                            "-o", str(tmp_path / "out")], capture_output=True, text=True)
        msg = (r.stdout + r.stderr).strip()
        assert r.returncode == 2 and says in msg and "Traceback" not in msg and len(msg.splitlines()) == 1, msg


def test_limits_out_of_order_are_refused(tmp_path):
    """A pass limit above its warn limit made an error between the two PASS while a smaller one warned (a
    run-through: size_pass_mm 0.5, size_warn_mm 0.3 reported a -0.43 mm size error as PASS): one line naming both."""
    (tmp_path / "gauges" / "sphere").mkdir(parents=True)
    (tmp_path / "gauges" / "gauges.yaml").write_text(yaml.safe_dump({
        "schema_version": 1, "gauges": [{"capture": "sphere", "kind": "sphere", "diameter_mm": 100.0}],
        "limits": {"size_pass_mm": 0.5}}))
    with pytest.raises(InputError) as e:
        read_gauges_file(tmp_path)
    assert "gauges.yaml" in str(e.value) and "size_pass_mm 0.5 must not exceed size_warn_mm 0.3" in str(e.value)
    (tmp_path / "gauges" / "gauges.yaml").write_text(yaml.safe_dump({
        "schema_version": 1, "gauges": [{"capture": "sphere", "kind": "sphere", "diameter_mm": 100.0}],
        "limits": {"size_pass_mm": 0.3, "flatness_warn_mm": 0.7}}))
    assert read_gauges_file(tmp_path).limits.size_pass_mm == 0.3  # equal limits: no WARN band, allowed


@pytest.mark.parametrize("entry, field", [
    ({"gauges": [{"capture": "sphere", "kind": "sphere", "diameter_mm": float("inf")}]}, "gauges.0.diameter_mm"),
    ({"gauges": [{"capture": "sphere_pair", "kind": "sphere_pair", "diameter_mm": 80.0,
                  "centre_distance_mm": float("inf")}]}, "gauges.0.centre_distance_mm"),
    ({"limits": {"size_warn_mm": float("inf")}}, "limits.size_warn_mm"),
    ({"params": {"gate_mm": float("inf")}}, "params.gate_mm"),
    ({"params": {"depth_noise": {"b_mm_per_m2": float("inf")}}}, "params.depth_noise.b_mm_per_m2"),
])
def test_infinite_sizes_limits_and_params_are_refused(tmp_path, entry, field):
    """gauges.yaml's ``diameter_mm: .inf`` passed ``gt=0``: validate measured the sphere NOT MEASURABLE with a size
    error of -inf, exited 0, and wrote gauges.json with Infinity (no JSON); now every number is refused unless finite,
    one line naming the field."""
    (tmp_path / "gauges" / "sphere").mkdir(parents=True)
    (tmp_path / "gauges" / "sphere_pair").mkdir(parents=True)
    doc = {"schema_version": 1, "gauges": [{"capture": "sphere", "kind": "sphere", "diameter_mm": 100.0}], **entry}
    (tmp_path / "gauges" / "gauges.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError) as e:
        read_gauges_file(tmp_path)
    assert e.value.field == field and "finite number" in str(e.value) and "gauges.yaml" in str(e.value)


@pytest.mark.slow
def test_gauges_only_on_the_command_line(exact, tmp_path):
    s, c, _ = exact
    from typer.testing import CliRunner

    from gtforge.cli.commands import app

    r = CliRunner().invoke(app, ["validate", str(s), "-c", str(c), "--gauges-only", "-o", str(tmp_path / "v")])
    assert r.exit_code == 0, r.output
    assert "Gauge objects (VDI/VDE 2634-2, ground truth): PASS" in r.output and "spacing error" in r.output
    assert (tmp_path / "v" / "gauges.json").is_file() and (tmp_path / "v" / "gauges.html").is_file()


@pytest.mark.slow
def test_validation_page_has_the_gauge_section(exact):
    """validate() puts the gauge report into validation.json (``gauges``) and this section into validation.html."""
    from types import SimpleNamespace

    from gtforge.records.validation import ValidationResult
    from gtforge.reports.validation import SECTIONS, gauges_section

    _, _, rep = exact
    assert gauges_section in SECTIONS and ValidationResult.model_fields["gauges"].default is None
    sec = gauges_section(SimpleNamespace(gauges=rep), None)
    assert sec.heading == "Gauge objects (VDI/VDE 2634-2): PASS" and sec.status == "pass"
    assert "sphere_pair (sphere_pair): PASS" in sec.body and "gauges.html" in sec.body
    assert gauges_section(SimpleNamespace(gauges=None), None) is None


@pytest.mark.slow
def test_predicted_size_and_spacing_sigmas(exact, tmp_path):
    """With 0.05 mm depth noise the raw depth's size and spacing errors are within 4 predicted sigmas (no bias in the
    raw depth), and the sigmas shrink with the number of points."""
    s0, c, _ = exact
    rng = np.random.default_rng(1)
    s = _copy_with_depth(s0, tmp_path / "noisy", lambda d: d + rng.normal(0, NOISE_MM, d.shape))
    rep = validate_gauges(s, c, None, GaugeParams(depth_noise=DepthNoiseModel(a_mm=NOISE_MM, b_mm_per_m2=0.0)))
    g = _by(rep)
    raw = g["sphere"].raw.spheres + g["sphere_pair"].raw.spheres
    for sp in raw:
        assert 0.001 < sp.size_sigma_predicted_mm < 0.02
        assert abs(sp.size_error_mm) <= 4 * sp.size_sigma_predicted_mm
    pair = g["sphere_pair"].raw
    assert (0 < pair.spacing_sigma_predicted_mm < 0.02
            and abs(pair.spacing_error_mm) <= 4 * pair.spacing_sigma_predicted_mm)
    big, small = g["sphere"].raw.spheres[0], g["sphere_pair"].raw.spheres[0]
    assert big.n_points > small.n_points and big.size_sigma_predicted_mm < small.size_sigma_predicted_mm


@pytest.mark.slow
def test_synth_writes_gauges_and_validate_refuses_to_write_into_them(exact, tmp_path):
    from typer.testing import CliRunner

    from gtforge.cli.commands import app

    r = CliRunner().invoke(app, ["synth", str(tmp_path / "s"), "--boards", "0", "--scenes", "0", "--scale", "0.1",
                                 "--gauges"])
    assert r.exit_code == 0, r.output
    assert len(GaugesFile.read(tmp_path / "s" / "gauges" / "gauges.yaml").gauges) == 3
    assert (tmp_path / "s" / "gauges" / "sphere_pair" / "DepthMap.tiff").is_file()
    s, c, _ = exact
    with pytest.raises(InputError, match="--output"):
        validate_gauges(s, c, s / "gauges" / "out")


@pytest.mark.slow
def test_validate_measures_the_gauges_beside_the_boards(session_dir, true_calibration, tmp_path):
    """gtforge validate on a session with boards and gauges: the board checks and the gauge figures in one run
    (validation.json ``gauges``, the validation.html section, the console lines)."""
    from typer.testing import CliRunner

    from gtforge.cli.commands import app
    from gtforge.records.validation import ValidationResult

    s = tmp_path / "s"
    shutil.copytree(session_dir, s, ignore=shutil.ignore_patterns("scenes"))
    generate_gauges(s, scale=0.4, seed=11, names=("sphere",))
    r = CliRunner().invoke(app, ["validate", str(s), "-c", str(true_calibration), "--captures", "000", "-o",
                                 str(tmp_path / "v")])
    assert r.exit_code == 0, r.output
    assert "XY reprojection" in r.output and "Gauge objects (VDI/VDE 2634-2, ground truth): PASS" in r.output
    rep = ValidationResult.read(tmp_path / "v" / "validation.json")
    assert [g.capture for g in rep.gauges.gauges] == ["sphere"]
    assert abs(rep.gauges.gauges[0].gt.spheres[0].size_error_mm) <= 0.05
    assert "Gauge objects (VDI/VDE 2634-2): PASS" in (tmp_path / "v" / "validation.html").read_text()
    assert (tmp_path / "v" / "gauges.html").is_file()


@pytest.mark.slow
def test_gauges_yaml_params_set_the_prediction(exact, tmp_path):
    s0, c, rep0 = exact
    s = _with_gauges_yaml(s0, tmp_path / "s", [{"capture": "sphere", "kind": "sphere", "diameter_mm": 100.0}])
    y = yaml.safe_load((s / "gauges" / "gauges.yaml").read_text())
    y["params"] = {"depth_noise": {"a_mm": 0.05, "b_mm_per_m2": 0.0}, "erosion_px": 4}
    (s / "gauges" / "gauges.yaml").write_text(yaml.safe_dump(y))
    rep = validate_gauges(s, c, None)
    assert rep.params.erosion_px == 4 and rep.params.depth_noise.a_mm == 0.05
    sp, sp0 = rep.gauges[0].gt.spheres[0], rep0.gauges[0].gt.spheres[0]
    # the default model: 0.05 mm at 1 m growing with Z^2 (0.02 mm at 650 mm); here 0.05 mm at any distance
    assert sp.n_points < sp0.n_points and sp.form_rms_predicted_mm > 2 * sp0.form_rms_predicted_mm


@pytest.mark.slow
def test_ball_bar_whose_bar_joins_the_spheres(tmp_path):
    """Two 80 mm spheres 240 mm apart on a 12 mm bar: one component above the table, split in two, each sphere found
    among the bar's points by RANSAC of the calibrated size; the figures as without the bar."""
    s = tmp_path / "s"
    generate_session(s, n_board=0, n_scenes=0, scale=SCALE, seed=3, depth_noise_mm=0.0, image_noise=1.0, supersample=1)
    generate_gauges(s, scale=SCALE, seed=3, names=("sphere_pair",), pair_bar_mm=12.0)
    rep = validate_gauges(s, _calib(tmp_path / "c.yaml"), None)
    g = rep.gauges[0]
    assert g.status == "PASS", g.reasons
    for sp in g.gt.spheres:
        assert abs(sp.size_error_mm) <= 0.05 and sp.form_range_mm <= 0.05
    assert abs(g.gt.spacing_error_mm) <= 0.05 and abs(g.raw.spacing_error_mm) <= 0.005


def test_gauges_are_rendered_with_the_sessions_rig(tmp_path):
    """generate_gauges rendered with the plain one-camera rig whatever the session's: `synth --gauges
    --separate-depth-camera` wrote gauge depth maps of the texture camera's size (576x360 at 0.3x), which validate
    refused (a run-through), and a depth scale error put in the session left the gauges' depth exact. Now the
    session's rig (truth/rig_truth.yaml) renders them: the depth camera's size, the depth scale to the last bit."""
    from gtforge.io.cameras import CameraFile

    two = generate_session(tmp_path / "two", n_board=0, n_scenes=0, scale=0.2, seed=1, depth_noise_mm=0.0,
                           two_camera=True, supersample=1)
    generate_gauges(two, scale=0.2, seed=1, names=("sphere",))
    cam = CameraFile.read(two / "depth_intrinsics.yaml").camera
    assert read_depth(two / "gauges" / "sphere" / "DepthMap.tiff").shape == (cam.height_px, cam.width_px)
    depth = {}
    for k in (0.0, 0.01):
        s = generate_session(tmp_path / f"k{k}", n_board=0, n_scenes=0, scale=0.2, seed=1, depth_noise_mm=0.0,
                             depth_scale_error_frac=k, supersample=1)
        generate_gauges(s, scale=0.2, seed=1, names=("sphere",))
        depth[k] = read_depth(s / "gauges" / "sphere" / "DepthMap.tiff")
    ok = np.isfinite(depth[0.0])
    assert ok.sum() > 1000 and np.array_equal(np.isfinite(depth[0.01]), ok)
    np.testing.assert_allclose(depth[0.01][ok], (np.float32(1.01) * depth[0.0][ok]), rtol=1e-6)


@pytest.mark.parametrize("gauges,field,says", [
    ([{"capture": "../scenes/000", "kind": "sphere", "diameter_mm": 100.0}], "gauges.0.capture", "not a path"),
    ([{"capture": "/abs/sphere", "kind": "sphere", "diameter_mm": 100.0}], "gauges.0.capture", "not a path"),
    ([{"capture": "sphere", "kind": "sphere", "diameter_mm": 100.0},
      {"capture": "sphere", "kind": "sphere", "diameter_mm": 50.0}], "gauges", "sphere is listed 2 times"),
])
def test_a_gauge_capture_is_a_folder_of_gauges_listed_once(tmp_path, gauges, field, says):
    """``capture: ../scenes/000`` measured a scene as a gauge (a path outside gauges/), and one capture listed twice
    was measured twice; both are refused, one line naming the field."""
    (tmp_path / "gauges" / "sphere").mkdir(parents=True)
    doc = {"schema_version": 1, "gauges": gauges}
    (tmp_path / "gauges" / "gauges.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError) as e:
        read_gauges_file(tmp_path)
    assert e.value.field == field and says in str(e.value) and e.value.hint, str(e.value)


@pytest.mark.slow
def test_gauges_only_into_a_whole_validation_updates_its_gauge_section(tmp_path):
    """``validate --gauges-only`` into the folder of an earlier whole validation left its validation.json (and page)
    with the earlier gauge figures beside the new gauges.json, the two disagreeing. Now the whole validation's gauge
    section is replaced (same session and calibration); another calibration's folder is refused before measuring."""
    from gtforge.records.validation import ValidationResult
    from gtforge.validate import validate

    s = tmp_path / "session"
    generate_session(s, n_board=3, n_scenes=0, scale=SCALE, seed=3, depth_noise_mm=0.0, image_noise=1.0,
                     supersample=1)
    generate_gauges(s, scale=SCALE, seed=3, depth_noise_mm=0.0)
    c = _calib(tmp_path / "calib.yaml")
    out = tmp_path / "v"
    whole = validate(s, c, out)
    assert whole.gauges is not None and whole.gauges.params.erosion_px == 3
    board_figures = whole.xy_mean_px, whole.z_error_mean_pct
    again = validate_gauges(s, c, out, params=GaugeParams(erosion_px=5))
    now = ValidationResult.read(out / "validation.json")
    assert now.gauges == GaugesResult.read(out / "gauges.json") == again and now.gauges.params.erosion_px == 5
    assert (now.xy_mean_px, now.z_error_mean_pct) == board_figures
    assert "validation.html" in {p.name for p in out.iterdir()}
    other = tmp_path / "other.yaml"
    shutil.copy(c, other)
    before = (out / "gauges.json").read_bytes()
    with pytest.raises(InputError) as e:
        validate_gauges(s, other, out)
    assert e.value.field == "--output" and "calib.yaml" in str(e.value) and e.value.hint
    assert (out / "gauges.json").read_bytes() == before
    # a report of those names that gtforge did not write is refused, not overwritten (validate wrote over any before)
    theirs = tmp_path / "theirs"
    shutil.copytree(out, theirs)
    (theirs / "gauges.json").write_text('{"gauges": "measured by hand"}')
    alone = tmp_path / "alone"
    alone.mkdir()
    (alone / "validation.html").write_text("<p>another tool's page</p>")
    for folder, name, needle in ((theirs, "gauges.json", "got a file gtforge validate did not write"),
                                 (alone, "validation.html", "got validation.html without validation.json")):
        kept = {p.name: p.read_bytes() for p in folder.iterdir()}
        for call in (lambda: validate(s, c, folder), lambda: validate_gauges(s, c, folder)):
            with pytest.raises(InputError) as e:
                call()
            assert e.value.field == "--output" and name in str(e.value) and needle in str(e.value), str(e.value)
            assert "give --output a folder of its own" in e.value.hint
        assert {p.name: p.read_bytes() for p in folder.iterdir()} == kept
