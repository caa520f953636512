"""The disparity-scale terms (gtforge.scale_calibration, issue #25) against the generator's exact truth: ZED baseline
scale, the right camera's yaw, the depth camera's scale and offset; estimated from scenes and boards, stored in the
calibration file and applied by every stage."""
from pathlib import Path

import numpy as np
import pytest
from conftest import synthetic_session
from made_once import session_spec

from gtforge.core.camera import Rig, ScaleCorrections
from gtforge.core.zed.scale_corrections import (
    apply_homography,
    corrected_right_image,
    scale_sigma_px,
    shown_disparity_px,
    yaw_homography,
)
from gtforge.core.zed.selfcal import corrected_right
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.dataset.scene_verification import verify_scene
from gtforge.errors import InputError
from gtforge.io.calibrated_session import open_with_calibration
from gtforge.io.captures import open_session
from gtforge.io.middlebury import middlebury_calib_text
from gtforge.records.calibration import CalibrationFile, RefinementInfo, ScaleParams
from gtforge.records.dataset import BuildParams
from gtforge.scale_calibration import calibrate_scale
from gtforge.synthetic import SyntheticTruth, default_rig

# the combined errors of the session below, at the limits: baseline +0.3 %, right-camera yaw 0.15 deg,
# depth scale -0.2 % and offset +0.5 mm
# half the default pixels a scene: the tests' sessions are small and the budget tight
FAST = ScaleParams(points_per_scene=20000)
ERRORS = dict(zed_baseline_error_frac=0.003, right_yaw_deg=0.15, depth_scale_error_frac=-0.002, depth_offset_mm=0.5)


def _known_calibration(session: Path, out: Path) -> Path:
    """The calibration file a perfect board calibration would give: the exact extrinsic, the files' ZED (so every
    error left is one of the scale terms)."""
    s = open_session(session)
    tr = SyntheticTruth.read(session / "truth" / "rig_truth.yaml")
    rig = Rig(zed=s.zed, mech=s.mech, depth_cam=s.depth_cam, T_mech_from_depth=s.T_mech_from_depth,
              T_zed_from_mech=np.array(tr.T_zed_from_mech))
    return CalibrationFile.known_extrinsic(rig).write(out)


def _gt_epe(session: Path, calib: CalibrationFile) -> list[float]:
    """Per scene: mean |GT - what the images show| (px) over the pixels the depth camera saw, the GT built with
    ``calib`` and the right image re-rectified with its yaw (as build-dataset writes im1)."""
    s = open_session(session)
    yaw_true = SyntheticTruth.read(session / "truth" / "rig_truth.yaml").zed_right_yaw_deg
    out = []
    for d in s.select("scenes", None):
        cap = s.load_capture(d)
        sd, _, _ = build_scene_arrays(cap.depth_mm, calib.rig, BuildParams(), cap.fruit_mask)
        t = np.load(session / "truth" / f"scene_{d.name}.npz")
        shown = shown_disparity_px(t["zed_disparity_px"], calib.rig, yaw_true)
        m = np.isfinite(sd.disparity_px) & np.isfinite(shown) & t["seen_by_mech"] & sd.nonoccluded
        out.append(float(np.mean(np.abs(sd.disparity_px[m] - shown[m]))))
    return out


ERRORS_SESSION_SPEC = session_spec("errors_session", "scale_errors", n_board=5, n_scenes=3, scale=0.3, seed=5,
                                   depth_noise_mm=0.03, image_noise=1.0, supersample=2, **ERRORS)


@pytest.fixture(scope="module")
def errors_session(request):
    """5 board poses + 3 fruit scenes at 0.3x (ZED 662x373) with every error kind at once."""
    return synthetic_session(request, ERRORS_SESSION_SPEC)


@pytest.fixture(scope="module")
def errors_calibrated(errors_session, tmp_path_factory):
    out = tmp_path_factory.mktemp("scale_cal")
    start = _known_calibration(errors_session, out / "start.yaml")
    return start, calibrate_scale(errors_session, start, out / "scaled.yaml", FAST)


@pytest.mark.slow
def test_combined_errors_with_boards_are_each_recovered(errors_session, errors_calibrated):
    start, res = errors_calibrated
    info = res.scale_calibration
    truth = dict(zed_baseline_frac=ERRORS["zed_baseline_error_frac"], zed_right_yaw_deg=ERRORS["right_yaw_deg"],
                 depth_scale_frac=ERRORS["depth_scale_error_frac"], depth_offset_mm=ERRORS["depth_offset_mm"])
    for name, t in info.terms.items():
        # five board poses at 0.3x leave the offset's sigma near 0.2 mm: it may be reported "not significant"
        # (within 2 sigma of 0) and not applied; every estimate within 3 sigma of the truth, every term with a board
        # source besides the scenes
        assert t.status in ("applied", "not significant"), (name, t)
        assert abs(t.estimate - truth[name]) < 3 * t.sigma, (name, t.estimate, t.sigma)
        assert any(s.startswith("boards") for s in t.sources)
        assert t.status == "applied" or t.value == 0.0  # what is not applied is held at 0
        if t.status == "applied":  # a reason only where the all-free estimate alone is not significant
            assert (t.reason == "") == (abs(t.estimate) > 2 * t.sigma), (name, t)
    # the poses each board measurement used, named apart (the console's "board poses N (ZED pair a, depth map b)":
    # a pose one camera alone saw counts where it was used); together the poses used
    by = info.board_poses_by_measurement
    assert sorted(by) == ["depth_map", "zed_pair"] and all(by.values())
    assert sorted(set(by["zed_pair"]) | set(by["depth_map"])) == info.board_poses_used
    # the covariance is a covariance, its diagonal the sigmas
    C = np.array(info.covariance)
    np.testing.assert_allclose(np.sqrt(np.diag(C)), [info.terms[n].sigma for n in info.terms], rtol=1e-9)
    assert np.all(np.linalg.eigvalsh(C) > 0)
    # applied through the rig: the baseline, the depth correction and the yaw
    assert res.rig.zed.baseline_mm == pytest.approx(63.0 * (1 + info.terms["zed_baseline_frac"].value))
    assert res.rig.scale_corrections.depth_scale == pytest.approx(1 + info.terms["depth_scale_frac"].value)
    # the ground truth built with it matches what the images show (0.88 px before, the yaw's 0.15 deg dominating)
    before, after = _gt_epe(errors_session, CalibrationFile.read(start)), _gt_epe(errors_session, res)
    assert min(before) > 0.5 and max(after) <= 0.02, (before, after)
    # written and read back
    again = CalibrationFile.read(Path(start).parent / "scaled.yaml")
    assert again.scale_calibration == info and again.rig == res.rig


@pytest.mark.slow
def test_a_correction_beyond_what_a_rigs_files_can_be_off_by_is_refused(errors_session, tmp_path):
    """A baseline written in metres made calibrate-scale apply +190,000 % and a 6 deg yaw, verdict PASS (a newcomer's
    run-through, round 4). The errors session's yaw (0.15 deg) against a limit of 0.1 deg: refused, naming the term
    and its value, nothing written; within the default limits (0.5 deg) applied as before."""
    start = _known_calibration(errors_session, tmp_path / "start.yaml")
    with pytest.raises(InputError) as e:
        calibrate_scale(errors_session, start, tmp_path / "scaled.yaml", FAST.model_copy(update={"max_yaw_deg": 0.1}))
    assert e.value.file == str(start) and e.value.field == "zed_right_yaw_deg", e.value
    assert e.value.expected.startswith("a correction within +-0.1 deg") and e.value.actual.startswith("+0.1"), e.value
    assert "the ZED baseline here is 63 mm" in e.value.hint and "nothing was written" in e.value.hint
    assert not (tmp_path / "scaled.yaml").exists()


@pytest.mark.slow
def test_verification_reads_no_stereo_bias_after_the_correction(errors_session, errors_calibrated):
    """verify's stereo check, with the corrected rig and the right image the calibration's session gives (the yaw
    applied in its one resampling, as build-dataset writes im1)."""
    start, res = errors_calibrated
    biases = {}
    for name, calib in (("before", CalibrationFile.read(start)), ("after", res)):
        s = open_with_calibration(errors_session, calib)
        cap = s.load_capture(s.select("scenes", None)[0])
        rig = calib.rig
        sd, region, _ = build_scene_arrays(cap.depth_mm, rig, BuildParams(), cap.fruit_mask)
        ver, _ = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, cap.zed_left, cap.zed_right,
                              cap.mech_texture, rig)
        biases[name] = ver.stereo["all"].disparity_bias_px
    assert abs(biases["before"]) > 0.2 and abs(biases["after"]) < 0.02, biases


@pytest.mark.slow
def test_build_dataset_writes_the_corrected_geometry(errors_session, errors_calibrated, tmp_path):
    """calib.txt's baseline is the corrected one, im1 the right image corrected for the yaw (the session's one
    resampling: for these images, rectified before gtforge with the yaw alone, exactly calibrate-scale's former
    re-rectification), the labels the corrected GT, the scene's verification reads no stereo bias and the sigma map
    carries the scale terms."""
    from gtforge.build_dataset import build_dataset
    from gtforge.core.zed.scale_corrections import scale_sigma_px
    from gtforge.io.formats import read_image, read_pfm

    start, res = errors_calibrated
    scaled = Path(start).parent / "scaled.yaml"
    out = tmp_path / "ds"
    build_dataset(errors_session, scaled, out, workers=1, scenes=["000"])
    sc = out / "scenes" / "000"
    calib_txt = dict(line.split("=", 1) for line in (sc / "calib.txt").read_text().splitlines())
    assert float(calib_txt["baseline"]) == pytest.approx(res.rig.zed.baseline_mm, abs=1e-6)
    s = open_session(errors_session)
    cap = s.load_capture(s.select("scenes", None)[0])
    np.testing.assert_array_equal(read_image(sc / "im1.png"), corrected_right_image(cap.zed_right, res.rig))
    corrected = open_with_calibration(errors_session, res).load_capture(s.select("scenes", None)[0])
    np.testing.assert_array_equal(read_image(sc / "im1.png"), corrected.zed_right)
    np.testing.assert_array_equal(read_image(sc / "im0.png"), cap.zed_left)
    assert (sc / "im0.png").read_bytes() == (errors_session / "scenes" / "000" / "left.png").read_bytes()  # copied
    sd, _, _ = build_scene_arrays(cap.depth_mm, res.rig, BuildParams(), cap.fruit_mask)
    np.testing.assert_array_equal(read_pfm(sc / "disp0GT.pfm"), sd.disparity_px)
    meta = __import__("json").loads((sc / "meta.json").read_text())
    assert abs(meta["verification"]["stereo"]["all"]["disparity_bias_px"]) < 0.02
    sigma = read_pfm(sc / "disp0GT_sigma.pfm")
    m = np.isfinite(sigma)
    assert np.all(sigma[m] >= scale_sigma_px(sd.depth_mm, res.rig, res.scale_calibration)[m] * (1 - 1e-6))
    # gtforge verify on the dataset compares against the same re-rectified right image
    from gtforge.verify import verify_dataset

    rep = verify_dataset(out, workers=1)
    assert abs(rep.scenes["000"].stereo["all"].disparity_bias_px) < 0.02


@pytest.mark.slow
def test_without_boards_baseline_and_depth_scale_are_not_separable(errors_session, errors_calibrated, tmp_path):
    """Through the CLI, --no-boards."""
    from typer.testing import CliRunner

    from gtforge.cli.commands import app

    start, _ = errors_calibrated
    r = CliRunner().invoke(app, ["calibrate-scale", str(errors_session), "-c", str(start), "-o",
                                 str(tmp_path / "noboards.yaml"), "--no-boards"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert "not separable" in r.output
    res = CalibrationFile.read(tmp_path / "noboards.yaml")
    t = res.scale_calibration.terms
    assert t["depth_scale_frac"].status == "not separable" and t["depth_scale_frac"].sigma is None
    assert res.rig.scale_corrections.depth_scale == 1.0
    # the sum is applied to the baseline (and said so): b + k = +0.1 %
    assert t["zed_baseline_frac"].status == "applied" and "sum" in t["zed_baseline_frac"].reason
    s = res.scale_calibration.combined_scale_frac
    assert abs(s - (ERRORS["zed_baseline_error_frac"] + ERRORS["depth_scale_error_frac"])) < \
        4 * res.scale_calibration.combined_scale_sigma_frac
    assert t["depth_offset_mm"].sources == ["scenes: stereo consistency"]
    # the disparity labels are right to first order whichever carries the sum (the depth scale's lateral shift of
    # the points is left)
    assert max(_gt_epe(errors_session, res)) <= 0.02


@pytest.mark.slow
def test_no_error_leaves_the_ground_truth_unchanged(session_dir, tmp_path):
    """The shared error-free session: every correction within 2 sigma of zero, the GT unchanged within 0.002 px."""
    start = _known_calibration(session_dir, tmp_path / "start.yaml")
    res = calibrate_scale(session_dir, start, tmp_path / "scaled.yaml", FAST)
    for name, t in res.scale_calibration.terms.items():
        # every estimate within 2 sigma of 0 (a term left alone once the others are held at 0 may still be applied:
        # its conditional sigma is smaller; its change to the GT is then tiny, checked below)
        assert t.status in ("applied", "not significant") and abs(t.estimate) <= 2 * t.sigma, (name, t)
        if t.status == "applied":  # the line says which figures decided it (the estimate beside it does not)
            assert t.reason.startswith("significant with the terms not applied held at 0: "), (name, t.reason)
            assert t.reason.endswith("with every term free within 2 sigma of 0")
    c0 = CalibrationFile.read(start)
    s = open_session(session_dir)
    for d in s.select("scenes", None):
        cap = s.load_capture(d)
        a = build_scene_arrays(cap.depth_mm, c0.rig, BuildParams(), cap.fruit_mask)[0].disparity_px
        b = build_scene_arrays(cap.depth_mm, res.rig, BuildParams(), cap.fruit_mask)[0].disparity_px
        m = np.isfinite(a) & np.isfinite(b)
        assert np.mean(np.abs(a[m] - b[m])) < 0.002


@pytest.mark.slow
def test_without_named_scenes_at_most_max_scenes_evenly_spread_are_used(session_dir, tmp_path):
    """ScaleParams.max_scenes (the CLI's --max-scenes): of the shared session's 3 scenes the first and the last, the
    third counted as not selected, on the command's line too."""
    from typer.testing import CliRunner

    from gtforge.cli.commands import app

    start = _known_calibration(session_dir, tmp_path / "start.yaml")
    r = CliRunner().invoke(app, ["calibrate-scale", str(session_dir), "-c", str(start), "-o",
                                 str(tmp_path / "scaled.yaml"), "--max-scenes", "2"])
    assert r.exit_code == 0, r.output
    info = CalibrationFile.read(tmp_path / "scaled.yaml").scale_calibration
    assert info.scenes_used == ["000", "002"] and info.scenes_not_selected == 1
    assert "scenes 000, 002 (1 more scene(s) of the session not used: --max-scenes, those used evenly spread)" \
        in r.output, r.output


# ---- both corrections of the right camera: the self-rectification and the yaw, in one resampling -----------------
BOTH_SESSION_SPEC = session_spec("both_session", "both_errors", n_board=5, n_scenes=2, scale=0.3, seed=5,
                                 depth_noise_mm=0.03, image_noise=1.0, supersample=2, right_yaw_deg=0.15,
                                 zed_right_rotation_error_rad=tuple(np.radians([0.1, 0.05, -0.08])))


@pytest.fixture(scope="module")
def both_session(request):
    """5 board poses + 2 fruit scenes at 0.3x whose right camera is turned by a yaw of 0.15 deg and then by a residual
    rotation (0.1, 0.05, -0.08) deg: the self-rectification's and calibrate-scale's errors at once."""
    return synthetic_session(request, BOTH_SESSION_SPEC)


@pytest.mark.slow
def test_both_corrections_resample_the_right_image_once(both_session, tmp_path):
    """A session with both errors through self-rectification, calibrate-scale, build-dataset and verify: calibrate-scale
    measures its yaw on the self-rectified images (the session it opens has no yaw), build-dataset's im1 is the
    session's one resampling, and verify's stereo check of the dataset reads as well as the former two-pass im1
    (self-rectified, then re-rectified for the yaw), checked on the same labels.

    Measured with this session (verify, region "all", scenes 000 / 001): disparity bias +0.0007 / -0.0018 px (one
    resampling) against -0.0012 / -0.0026 px (two, both by cubic B-spline), vertical disparity -0.0022 / -0.0016 px
    against -0.0014 / -0.0027 px; the terms: yaw 0.2025 +- 0.0020 deg (truth 0.20), baseline, depth scale and offset
    within 1.2 sigma of 0. With OpenCV's bilinear first pass and the three-parameter self-rectification (before the
    yaw became its nuisance) the bias was -0.0070 / -0.0075 px and the yaw 0.171 deg. (The CLI chain calibrate,
    calibrate-scale, build-dataset,
    verify on the same errors with 6 poses and 3 scenes, the commit before against this one: bias -0.0041, -0.0062,
    -0.0049 -> -0.0060, -0.0060, -0.0058 px; vertical -0.0129, -0.0145, -0.0133 -> -0.0047, -0.0073, -0.0061 px; the
    fruit's bias +0.078, +0.081, +0.085 -> +0.070, +0.072, +0.076 px; im1's mean gradient energy 26.5-27.0 ->
    31.7-32.4.)"""
    from gtforge.build_dataset import build_dataset
    from gtforge.io.formats import read_image
    from gtforge.io.zed_rectification import self_rectify
    from gtforge.verify import verify_dataset

    s = open_session(both_session)
    selfcal = self_rectify(s, s.capture_dirs("board") + s.capture_dirs("scenes"))
    assert selfcal.status == "applied", selfcal.reason
    start = CalibrationFile.read(_known_calibration(both_session, tmp_path / "known.yaml"))
    start.zed_self_rectification = selfcal
    start.write(tmp_path / "start.yaml")
    # calibrate-scale opens the session with the self-rectification and without a yaw
    opened = open_with_calibration(both_session, start)
    assert opened.rectification.correction == selfcal.correction and not hasattr(opened.rectification, "right_yaw_deg")
    res = calibrate_scale(both_session, tmp_path / "start.yaml", tmp_path / "scaled.yaml", FAST)
    yaw = res.rig.zed_right_yaw_deg
    # the yaw the disparities show: 0.15 deg and the residual rotation's 0.05 deg about y, which the self-rectification
    # fits from the rows but leaves to calibrate-scale; no baseline or depth error (each within 3 sigma of 0)
    terms = res.scale_calibration.terms
    print({k: (t.estimate, t.sigma, t.status) for k, t in terms.items()})
    assert terms["zed_right_yaw_deg"].status == "applied"
    assert abs(terms["zed_right_yaw_deg"].estimate - 0.20) < 3 * terms["zed_right_yaw_deg"].sigma + 0.001, yaw
    for k in ("zed_baseline_frac", "depth_scale_frac", "depth_offset_mm"):
        assert terms[k].estimate is None or abs(terms[k].estimate) < 3 * terms[k].sigma, (k, terms[k])
    out = tmp_path / "ds"
    build_dataset(both_session, tmp_path / "scaled.yaml", out, workers=1)
    rep = verify_dataset(out, workers=1)
    once = open_with_calibration(both_session, res)
    assert once.rectification.right_yaw_deg == yaw and once.rectification.correction == selfcal.correction
    self_only = open_with_calibration(both_session, res, right_yaw=False)
    for d in s.select("scenes", None):
        cap = once.load_capture(d)
        np.testing.assert_array_equal(read_image(out / "scenes" / d.name / "im1.png"), cap.zed_right)
        two = corrected_right_image(self_only.load_capture(d).zed_right, res.rig)
        sd, region, _ = build_scene_arrays(cap.depth_mm, res.rig, BuildParams(), cap.fruit_mask)
        ver_two, _ = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, cap.zed_left, two,
                                  cap.mech_texture, res.rig)
        a, b = rep.scenes[d.name].stereo["all"], ver_two.stereo["all"]
        print(f"scene {d.name}: bias {a.disparity_bias_px:+.4f} px (one resampling) "
              f"{b.disparity_bias_px:+.4f} px (two); "
              f"vertical {a.vertical_px:+.4f} / {b.vertical_px:+.4f} px; bad matches {a.bad_match_pct:.2f} / "
              f"{b.bad_match_pct:.2f} %")
        assert abs(a.disparity_bias_px) < 0.02 and abs(a.disparity_bias_px) <= abs(b.disparity_bias_px) + 0.003
        assert abs(a.vertical_px) <= abs(b.vertical_px) + 0.002 and a.bad_match_pct <= b.bad_match_pct + 0.1


def test_a_calibration_without_the_fields_changes_nothing(tmp_path):
    """Old files: no scale_corrections, no scale_calibration -> the depth and the right image pass through as they
    are, calib.txt as before."""
    sr = default_rig(0.3)
    rig = Rig(zed=sr.zed, mech=sr.mech, T_zed_from_mech=sr.T_zed_from_mech)
    c = CalibrationFile.known_extrinsic(rig)
    data = c.model_dump(mode="json")
    del data["scale_calibration"], data["rig"]["scale_corrections"]
    old = CalibrationFile.from_dict(data)
    assert old.scale_calibration is None and old.rig.scale_corrections is None
    depth = np.full((4, 5), 600.0, np.float32)
    assert old.rig.corrected_depth_mm(depth) is depth
    img = np.zeros((8, 9, 3), np.uint8)
    assert corrected_right_image(img, old.rig) is img
    # the session's rectification: none, as before (no self-rectification, no yaw)
    assert old.zed_right_correction is None and old.rig.zed_right_yaw_deg == 0.0
    assert corrected_right(None, old.rig.zed, old.zed_right_correction, old.rig.zed_right_yaw_deg) is None
    assert middlebury_calib_text(old.rig.zed, 10, 10, None) == middlebury_calib_text(sr.zed, 10, 10, None)
    # a second correction on a corrected file is refused (they would compound)
    p = CalibrationFile.model_validate({**c.model_dump(), "rig": {**c.rig.model_dump(),
                                                                  "scale_corrections": {"depth_scale": 1.001}}})
    with pytest.raises(InputError, match="scale_calibration"):
        calibrate_scale(tmp_path, p.write(tmp_path / "c.yaml"), None)
    # and one refine has moved: refine fitted its extrinsic through the uncorrected depth, so the terms found here would
    # correct a second time what it took up; the hint names the file refine started from
    refined = c.model_copy(update={"refinement": RefinementInfo(refined_from="/lab/scaled_before.yaml",
                                                                scenes_used=["000"], change_rot_deg=0.01,
                                                                change_trans_mm=0.3)})
    with pytest.raises(InputError, match=r"\[refinement\]: expected a calibration refine has not moved.*got one "
                                         r"refined from /lab/scaled_before.yaml.*run calibrate-scale on "
                                         r"/lab/scaled_before.yaml, then refine its output"):
        calibrate_scale(tmp_path, refined.write(tmp_path / "r.yaml"), None)


def test_yaw_homography_is_the_turned_cameras_projection():
    """A point's pixel in the right camera turned by the yaw (the generator's R_y) is H applied to its rectified
    pixel; the re-rectified image samples there."""
    sr = default_rig(0.3)
    sr.right_yaw_rad = np.radians(0.15)
    rig = Rig(zed=sr.zed, mech=sr.mech, T_zed_from_mech=sr.T_zed_from_mech)
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.uniform(-200, 200, 50), rng.uniform(-100, 100, 50), rng.uniform(400, 800, 50)])
    Xr = X - [sr.zed.baseline_mm, 0, 0]
    ideal = sr.zed.right.project(Xr)
    actual = sr.zed.right.project(Xr @ sr.T_zedr_actual_from_zedr[:3, :3].T)
    u, v = apply_homography(yaw_homography(rig, sr.right_yaw_rad), ideal[:, 0], ideal[:, 1])
    np.testing.assert_allclose(np.column_stack([u, v]), actual, atol=1e-9)
    # a linear ramp is re-rectified to within the output's rounding (cubic B-splines reproduce linear functions)
    rig = rig.model_copy(update={"scale_corrections": ScaleCorrections(zed_right_yaw_deg=0.15)})
    h, w = 40, 60
    ramp = np.arange(w)[None, :] * 2 + np.arange(h)[:, None] + 10
    out = corrected_right_image(ramp.astype(np.uint8), rig)
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    us, vs = apply_homography(yaw_homography(rig, np.radians(0.15)), uu.ravel(), vv.ravel())
    inner = ((us > 6) & (us < w - 7) & (vs > 6) & (vs < h - 7)).reshape(h, w)  # (the spline's mirrored borders)
    expect = us.reshape(h, w) * 2.0 + vs.reshape(h, w) + 10
    assert np.abs(out[inner] - expect[inner]).max() <= 0.5 + 1e-9


def test_scale_sigma_is_the_covariance_propagated():
    sr = default_rig(0.3)
    rig = Rig(zed=sr.zed, mech=sr.mech, T_zed_from_mech=sr.T_zed_from_mech)
    from gtforge.records.calibration import ScaleCalibration

    C = np.diag([1e-8, 1e-6, 0.0, 0.01])  # 1e-4 in b, 1e-3 deg yaw, 0.1 mm offset
    info = ScaleCalibration(calibrated_from="x", terms={}, covariance=C.tolist(), combined_scale_frac=0.0,
                            combined_scale_sigma_frac=None, baseline_file_mm=63.0, scenes_used=[])
    z = np.full((3, rig.zed.left.width_px), 600.0)
    s = scale_sigma_px(z, rig, info)
    fb, f = rig.zed.f_px * rig.zed.baseline_mm, rig.zed.f_px
    x = (np.arange(z.shape[1]) - rig.zed.left.cx_px) / f
    expect = np.sqrt((1e-4 * fb / 600) ** 2 + (np.radians(1e-3) * f * (1 + x * x)) ** 2 + (0.1 * fb / 600 ** 2) ** 2)
    np.testing.assert_allclose(s[1], expect, rtol=1e-12)


# ---- a separate depth camera's pose (issue #25): session.yaml's T_mech_from_depth turned by this (deg)
POSE_ERROR_DEG = (0.1, -0.15, 0.1)


POSE_SESSION_SPEC = session_spec("pose_session", "scale_pose", n_board=5, n_scenes=3, scale=0.3, seed=5,
                                 depth_noise_mm=0.03, image_noise=1.0, supersample=2, two_camera=True,
                                 depth_pose_error_deg=POSE_ERROR_DEG, **ERRORS)


@pytest.fixture(scope="module")
def pose_session(request):
    """A rig with a separate depth camera (``two_camera_rig``, 45 mm beside the texture camera) whose session.yaml
    pose is turned by POSE_ERROR_DEG, on top of every error of ERRORS; 5 boards + 3 scenes at 0.3x."""
    return synthetic_session(request, POSE_SESSION_SPEC)


def test_depth_pose_jacobian_is_the_ground_truths_change(pose_session):
    """``depth_pose_jacobian_px`` against the GT rebuilt with the depth camera turned (0.05 deg about each axis in
    turn): the first-order change at every smooth GT pixel."""
    from gtforge.core.geometry import perturb_left
    from gtforge.core.alignment.photometric import interior_mask, smooth_depth_mask
    from gtforge.core.zed.scale_corrections import depth_pose_jacobian_px

    rig = CalibrationFile.read(_known_calibration(pose_session, pose_session.parent / "jac.yaml")).rig
    s = open_session(pose_session)
    cap = s.load_capture(s.select("scenes", None)[0])
    sd, _, _ = build_scene_arrays(cap.depth_mm, rig, BuildParams(), cap.fruit_mask)
    d = sd.disparity_px.astype(np.float64)
    ok = interior_mask(np.isfinite(d) & sd.nonoccluded, 3) & smooth_depth_mask(sd.disparity_px)
    v, u = np.nonzero(ok)
    J = depth_pose_jacobian_px(u, v, sd.depth_mm[v, u], 0.5 * (d[v, u + 1] - d[v, u - 1]),
                               0.5 * (d[v + 1, u] - d[v - 1, u]), rig)
    h = np.radians(0.05)
    for axis in range(3):
        w = np.zeros(6)
        w[axis] = h
        turned = Rig.model_validate({**rig.model_dump(), "T_mech_from_depth": perturb_left(rig.T_mech_from_depth, w)})
        sd2, _, _ = build_scene_arrays(cap.depth_mm, turned, BuildParams(), cap.fruit_mask)
        change = sd2.disparity_px[v, u].astype(np.float64) - d[v, u]
        fin = np.isfinite(change)
        predicted = J[fin, axis] * h
        # the change is 0.01-0.03 px RMS; the first-order prediction within 5 % of it (the GT slopes by central
        # differences of a meshed, noisy depth)
        rms = np.sqrt(np.mean(change[fin] ** 2))
        assert rms > 0.002, (axis, rms)  # (about z the surface only slides along itself: the slopes see it)
        assert np.sqrt(np.mean((change[fin] - predicted) ** 2)) < 0.05 * rms, axis


@pytest.mark.slow
@pytest.mark.parametrize("boards", [True, False])
def test_separate_depth_cameras_pose_is_recovered(pose_session, tmp_path, boards):
    """Every error of ERRORS plus the depth camera turned by POSE_ERROR_DEG: calibrate-scale estimates its rotation
    (the correction is the inverse turn) with the four other terms, and the labels match what the images show."""
    start = _known_calibration(pose_session, tmp_path / "start.yaml")
    res = calibrate_scale(pose_session, start, tmp_path / "scaled.yaml", FAST.model_copy(update={"use_boards": boards}))
    info = res.scale_calibration
    truth = dict(zed_baseline_frac=ERRORS["zed_baseline_error_frac"], zed_right_yaw_deg=ERRORS["right_yaw_deg"],
                 depth_scale_frac=ERRORS["depth_scale_error_frac"], depth_offset_mm=ERRORS["depth_offset_mm"],
                 depth_pose_rx_deg=-POSE_ERROR_DEG[0], depth_pose_ry_deg=-POSE_ERROR_DEG[1],
                 depth_pose_rz_deg=-POSE_ERROR_DEG[2])
    if not boards:  # the scenes see only the sum of the two scales, carried by the baseline
        truth["zed_baseline_frac"] += truth.pop("depth_scale_frac")
        assert info.terms["depth_scale_frac"].status == "not separable"
    for name, t in truth.items():
        term = info.terms[name]
        assert term.status in ("applied", "not significant"), (name, term)
        assert abs(term.estimate - t) < 3 * term.sigma, (name, term.estimate, term.sigma, t)
    for axis in "xy":  # the two the scenes see through the surface's depth: applied
        assert info.terms[f"depth_pose_r{axis}_deg"].status == "applied"
    C = np.array(info.covariance)
    assert C.shape == (7, 7)
    np.testing.assert_allclose(np.sqrt(np.diag(C)), [info.terms[n].sigma or 0.0 for n in info.terms], rtol=1e-9)
    # applied through the rig's depth camera pose, the file's kept
    applied = np.radians([info.terms[f"depth_pose_r{a}_deg"].value for a in "xyz"])
    from gtforge.core.geometry import perturb_left

    file_T = np.array(info.T_mech_from_depth_file)
    np.testing.assert_allclose(res.rig.T_mech_from_depth, perturb_left(file_T, np.r_[applied, 0, 0, 0]), atol=1e-12)
    before, after = _gt_epe(pose_session, CalibrationFile.read(start)), _gt_epe(pose_session, res)
    assert min(before) > 0.5 and max(after) <= 0.01, (before, after)
    # the sigma map carries the rotation's covariance: the pose block alone gives |J_pose| sigma (deg -> rad)
    from gtforge.core.zed.scale_corrections import depth_pose_jacobian_image

    pose_only = np.zeros((7, 7))
    pose_only[4:, 4:] = C[4:, 4:]
    s = open_session(pose_session)
    cap = s.load_capture(s.select("scenes", None)[0])
    sd, _, _ = build_scene_arrays(cap.depth_mm, res.rig, BuildParams(), cap.fruit_mask)
    m = np.isfinite(sd.disparity_px)
    got = scale_sigma_px(sd.depth_mm, res.rig, info.model_copy(update={"covariance": pose_only.tolist()}))[m]
    Jp = depth_pose_jacobian_image(sd.depth_mm, res.rig)[m] * np.pi / 180
    np.testing.assert_allclose(got, np.sqrt(np.einsum("ni,ij,nj->n", Jp, C[4:, 4:], Jp)), rtol=1e-9)
    assert 0.001 < np.median(got) < 0.05  # the rotation's sigma, tens of mdeg, in px


def test_pnp_pose_covariance_is_the_poses_scatter_under_corner_noise():
    """A PnP pose's covariance from its own residuals matches the scatter of poses solved from noisy corners."""
    import cv2

    from gtforge.core.geometry import transform_points
    from gtforge.core.targets.board import solve_pnp
    from gtforge.scale_calibration import pnp_pose_covariance

    cam = default_rig(0.5).zed.left
    gx, gy = np.meshgrid(np.arange(11) * 20.0, np.arange(8) * 20.0)
    board = np.stack([gx.ravel() - 100, gy.ravel() - 70, np.zeros(gx.size)], 1)
    rot = cv2.Rodrigues(np.array([0.3, -0.2, 0.05]))[0]
    X_true = board @ rot.T + np.array([15.0, -10.0, 600.0])
    uv_true = cam.project(X_true)
    rng = np.random.default_rng(3)
    deltas, covs = [], []
    for _ in range(300):
        uv = uv_true + rng.normal(0, 0.2, uv_true.shape)
        T_cam_from_board = solve_pnp(board, uv, cam)
        X = transform_points(T_cam_from_board, board)
        covs.append(pnp_pose_covariance(X, uv, cam))
        # the pose's error as a left perturbation X -> R_err X + tau: R_err = R R_true^T, tau = t - R_err t_true
        R_err = T_cam_from_board[:3, :3] @ rot.T
        deltas.append(np.r_[cv2.Rodrigues(R_err)[0].ravel(),
                            T_cam_from_board[:3, 3] - R_err @ np.array([15.0, -10.0, 600.0])])
    scatter = np.cov(np.array(deltas).T)
    model = np.mean(covs, axis=0)
    # the depth of a corner (what calibrate-scale uses): its variance as the scatter and as the model say
    along = np.array([-10.0, -15.0, 0.0, 0.0, 0.0, 1.0])  # dz/d(omega, tau) at the centre (15, -10, 600): (y, -x, 0...)
    assert along @ model @ along == pytest.approx(along @ scatter @ along, rel=0.2)
    assert np.sqrt(np.diag(model)) == pytest.approx(np.sqrt(np.diag(scatter)), rel=0.2)


def test_few_poses_covariance_describes_the_error_the_clustered_one_misses():
    """A fit over 5 poses whose errors move all their points together: the pose-clustered covariance alone (5
    clusters, 3 parameters) is now and then far too small (errors over 3 of its sigmas ten times as often as a
    Gaussian's); with each pose's own covariance carried through, the normalised errors have an RMS near 1."""
    from gtforge.scale_calibration import _cluster_ls

    rng = np.random.default_rng(7)
    G, n = 5, 40
    z_alone, z_model = [], []
    for _ in range(400):
        J, r, cl, K, P = [], [], [], [], []
        for g in range(G):
            t = rng.uniform(-1, 1, n)
            Jg = np.stack([np.ones(n) * rng.uniform(0.5, 1.5), t, t * t], 1)
            Kg = np.stack([np.ones(n), t], 1)  # a pose's 2 error terms: an offset and a slope on its points
            Pg = np.diag([0.04, 0.01])
            J.append(Jg), K.append(Kg), P.append(Pg), cl.append(np.full(n, g))
            r.append(Kg @ rng.multivariate_normal(np.zeros(2), Pg) + rng.normal(0, 0.05, n))
        J, r, cl = np.concatenate(J), np.concatenate(r), np.concatenate(cl)
        x1, C1 = _cluster_ls(J, r, cl)
        x2, C2 = _cluster_ls(J, r, cl, K, P)
        assert np.allclose(x1, x2)  # the estimate is the same least squares
        z_alone.append(x1[0] / np.sqrt(C1[0, 0]))
        z_model.append(x2[0] / np.sqrt(C2[0, 0]))
    z_alone, z_model = np.abs(z_alone), np.abs(z_model)
    assert np.mean(z_alone > 3) > 0.015  # 2.75 % here; a Gaussian's 0.27 %
    # (a little on the safe side: the residuals' own scatter includes the poses' part)
    assert 0.7 < np.sqrt(np.mean(z_model ** 2)) < 1.2 and np.mean(z_model > 3) < 0.005
