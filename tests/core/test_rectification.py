"""Rectification quality and the SN.conf reading, against a raw ZED session with exact truth.

One raw session (VGA ZED: 672x376 per eye, distorted, fx != fy, off-centre principal points) is rendered
once; its SN.conf is written under the rtabmap reading (``neg-all``). The same images then serve every
reading: each candidate's conf encodes the same true (R, T), so gtforge must recover the reading from
the images alone.
"""
import shutil

import cv2
import numpy as np
import pytest
from conftest import synthetic_session
from made_once import session_spec

from gtforge.core.targets.board import BoardSpec
from gtforge.core.geometry import make_T, transform_points
from gtforge.core.zed.rectification import (
    TIE_PX,
    RectificationMeter,
    board_pose_vertical_disparity,
    rectify_points,
    scene_vertical_disparity,
)
from gtforge.errors import InputError
from gtforge.io.cameras import ZED_CONF_READINGS, read_zed_conf
from gtforge.io.captures import open_session
from gtforge.io.zed_rectification import (
    RawBoardPair,
    choose_reading,
    detect_raw_pairs,
    rectified_by,
    score_readings,
    settle_zed_conf_reading,
)
from gtforge.synthetic import (
    RawZed,
    SyntheticTruth,
    default_raw_zed,
    raw_zed_rig,
    write_raw_zed_conf,
    zed_conf_values,
)

BOARD = BoardSpec()
SESSION_READING = "neg-all"


RAW_SPEC = session_spec("raw_session", "raw_zed", raw_zed=True, reading=SESSION_READING, n_board=4, n_scenes=1, seed=5,
                        supersample=2)


@pytest.fixture(scope="module")
def raw_session(request):
    return synthetic_session(request, RAW_SPEC)


@pytest.fixture(scope="module")
def raw_pairs(raw_session):
    s = open_session(raw_session)
    pairs, skipped = detect_raw_pairs(s, s.capture_dirs("board"), BOARD)
    assert not skipped and len(pairs) == 4
    return pairs


@pytest.fixture(scope="module")
def calibration(raw_session, tmp_path_factory):
    from gtforge.calibrate import calibrate
    from gtforge.records.calibration import CalibrateParams

    path = tmp_path_factory.mktemp("raw_calib") / "calibration.yaml"
    return path, calibrate(raw_session, path, CalibrateParams(leave_one_out=False))


def _true_raw_corners(raw_session, raw: RawZed, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact corners of board capture ``name``: raw left, raw right, rectified left (from truth/)."""
    tr = np.load(raw_session / "truth" / f"board_{name}.npz")
    rig = raw_zed_rig(raw)
    _, R1, _ = raw.rectified()
    X_zed = transform_points(rig.T_zed_from_mech @ tr["T_mech_from_board"], BOARD.corners_board())
    X_left = transform_points(make_T(R1.T, np.zeros(3)), X_zed)
    X_right = transform_points(make_T(raw.R, raw.T_mm), X_left)
    return raw.left.project(X_left), raw.right.project(X_right), tr["corners_zed_uv"]


def test_conf_values_decode_exactly_and_readings_differ(tmp_path):
    raw = default_raw_zed()
    decoded = {}
    for reading in ZED_CONF_READINGS:
        f = read_zed_conf(write_raw_zed_conf(tmp_path / f"{reading}.conf", raw, reading), 672)
        R, T_mm = f.R_t_right_from_left(reading)
        np.testing.assert_allclose(R, raw.R, atol=1e-12)
        np.testing.assert_allclose(T_mm, raw.T_mm, atol=1e-9)
        decoded[reading] = {r: f.R_t_right_from_left(r) for r in ZED_CONF_READINGS}
    # the Stereolabs-sample encoding is the plain one: Baseline = -T_x, TY = T_y, TZ = T_z, (RX, CV, RZ) = rotvec(R)
    v = zed_conf_values(raw, "neg-x")
    assert (v["Baseline"], v["TY"], v["TZ"]) == (63.0, 0.21, -0.35)
    np.testing.assert_allclose([v["RX"], v["CV"], v["RZ"]], [0.0031, -0.0042, 0.0011], atol=1e-12)
    assert zed_conf_values(raw, "as-is")["Baseline"] == -63.0  # T_x itself: the right camera sits at +x
    # under a conf written for one reading, every other reading decodes a different (R, T)
    for reading, dec in decoded.items():
        for other, (R, T_mm) in dec.items():
            if other != reading:
                assert np.abs(R - raw.R).max() > 1e-3 or np.abs(T_mm - raw.T_mm).max() > 0.1, (reading, other)
    # gtforge's rectification under the true reading is the truth's rectification
    stereo, R1, R2 = raw.rectified()
    f = read_zed_conf(write_raw_zed_conf(tmp_path / "x.conf", raw, "right-centre+inv-rot"), 672)
    rect = f.rectification("right-centre+inv-rot")
    np.testing.assert_allclose(rect.R_rect_from_raw_left, R1, atol=1e-12)
    np.testing.assert_allclose(rect.R_rect_from_raw_right, R2, atol=1e-12)
    assert rect.stereo.left.fx_px == pytest.approx(stereo.left.fx_px, abs=1e-9)
    assert rect.stereo.baseline_mm == pytest.approx(stereo.baseline_mm, abs=1e-9)
    # a reading that puts the right camera at -x is refused with a pointer to the fix
    with pytest.raises(InputError, match="right camera at \\+x.*as-is"):
        f.rectification("as-is")


@pytest.mark.slow
def test_every_encoding_is_recognised_from_the_images(raw_session, raw_pairs, tmp_path):
    raw = default_raw_zed()
    for reading in ZED_CONF_READINGS:
        f = read_zed_conf(write_raw_zed_conf(tmp_path / f"SN_{reading}.conf", raw, reading), 672)
        choice = choose_reading(f, raw_pairs, BOARD)
        assert choice.reading == reading and choice.chosen_by == "board images", (reading, choice.reading)
        assert choice.warnings == []
        assert len(choice.candidates) == 8 and choice.candidates[0].reading == reading
        best = choice.candidates[0].vertical
        assert best.fit_mean_abs_px <= 0.05 and best.mean_abs_px <= 0.12
        # the runner-up is a different rectification and measurably worse; a reading that puts the right camera
        # on the left (same rectification as one eligible reading, opposite baseline) is never eligible
        eligible = [c for c in choice.candidates if c.eligible]
        assert len(eligible) == (2 if reading.startswith("as-is") else 6)  # as-is needs Baseline < 0 here
        assert eligible[1].vertical.fit_mean_abs_px > best.fit_mean_abs_px + TIE_PX
        assert all(c.baseline_mm < 0 for c in choice.candidates if not c.eligible)
        # wrong translations cost ~0.3 px at this resolution, an inverted rotation > 1 px
        worst_tr = [c for c in eligible if c.reading.endswith("+inv-rot") != reading.endswith("+inv-rot")]
        assert min(c.vertical.fit_mean_abs_px for c in worst_tr) > 1.0
    # the chosen rectification is exact: true raw corners land on the true rectified corners, on one row
    f = read_zed_conf(raw_session / "SN12345.conf", 672)
    sr = f.stereo_rectify(SESSION_READING)
    for p in raw_pairs:
        uv_l, uv_r, uv_rect = _true_raw_corners(raw_session, raw, p.capture)
        ul = rectify_points(f.left, uv_l, sr.R_rect_from_raw_left, sr.P_left)
        ur = rectify_points(f.right, uv_r, sr.R_rect_from_raw_right, sr.P_right)
        np.testing.assert_allclose(ul, uv_rect, atol=1e-6)
        assert np.abs(ul[:, 1] - ur[:, 1]).max() < 1e-6
        # ... and matches cv2.undistortPoints where that converges
        cv = cv2.undistortPointsIter(uv_l.reshape(-1, 1, 2), f.left.K, f.left.dist, sr.R_rect_from_raw_left,
                                     sr.P_left, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
        np.testing.assert_allclose(cv.reshape(-1, 2), ul, atol=1e-4)


@pytest.mark.slow
def test_calibrate_chooses_records_and_the_ground_truth_is_exact(raw_session, calibration, tmp_path):
    from gtforge.build_dataset import build_dataset
    from gtforge.io.formats import read_pfm
    from gtforge.records.calibration import CalibrationFile
    from gtforge.reports.calibration import write_calibration_report

    path, res = calibration
    raw = default_raw_zed()
    truth_stereo, _, _ = raw.rectified()
    assert res.zed_conf.reading == SESSION_READING and res.zed_conf.chosen_by == "board images"
    assert res.zed_conf.captures == ["000", "001", "002", "003"] and not res.zed_conf.warnings
    assert res.zed_conf.candidates[0].vertical.fit_mean_abs_px <= 0.05
    # the files are exact: self-rectification finds nothing to correct and leaves the images alone
    sr = res.zed_self_rectification
    assert sr.status == "not needed" and sr.correction is None and sr.median_abs_before_px < 0.05, sr.reason
    # the rig's rectified ZED is the true one
    z = res.rig.zed
    assert z.left.fx_px == pytest.approx(truth_stereo.left.fx_px, abs=1e-6)
    assert (z.left.cx_px, z.left.cy_px) == pytest.approx((truth_stereo.left.cx_px, truth_stereo.left.cy_px), abs=1e-6)
    assert z.baseline_mm == pytest.approx(63.0013, abs=1e-3)
    # rectification quality measured on the images gtforge rectified with it
    q = res.rectification
    assert SESSION_READING in q.rectified_by and len(q.poses) == 4 and q.overall.n_points == 4 * BOARD.n_corners
    assert q.overall.fit_mean_abs_px <= 0.05 and q.overall.mean_abs_px <= 0.12 and abs(q.overall.mean_px) < 0.03
    assert sum(r.n_points for r in q.by_region_left.values()) == q.overall.n_points
    assert q.poses[0].fit_mean_abs_px == max(p.fit_mean_abs_px for p in q.poses)  # worst first
    again = CalibrationFile.read(path)
    assert again.zed_conf.reading == SESSION_READING
    assert again.rectification.overall.fit_mean_abs_px == pytest.approx(q.overall.fit_mean_abs_px)
    html = write_calibration_report(res, tmp_path / "report").read_text()
    assert "vertical disparity" in html.lower() and SESSION_READING in html
    # ground truth with the exact extrinsic (as tests/conftest.py): the chosen rectification makes it exact
    T_zed_from_mech_true = np.array(SyntheticTruth.read(raw_session / "truth" / "rig_truth.yaml").T_zed_from_mech)
    c = CalibrationFile.read(path)
    c.rig = c.rig.with_extrinsic(T_zed_from_mech_true)
    c.write(tmp_path / "true_calibration.yaml")
    out = tmp_path / "dataset"
    summary = build_dataset(raw_session, tmp_path / "true_calibration.yaml", out, workers=1)
    assert summary.ok and summary.built == ["000"]
    tr = np.load(raw_session / "truth" / "scene_000.npz")
    gt = read_pfm(out / "scenes" / "000" / "disp0GT.pfm")
    seen, ok = tr["seen_by_mech"], np.isfinite(gt)
    assert ok[seen].mean() >= 0.99
    assert np.mean(np.abs(gt - tr["zed_disparity_px"])[seen & ok]) <= 0.01


@pytest.mark.slow
def test_reading_from_feature_matches_without_a_board(raw_session):
    """No board seen whole in both raw images: every reading is scored on raw feature matches (scenes and boards
    alike). The conf was written under neg-all: neg-all wins (as-is gives the same maps but a right camera at -x), the
    TY/TZ-flipped neg-x is 0.1-0.5 px worse, the inverse rotations are far off."""
    from gtforge.io.zed_rectification import choose_reading_by_matches, raw_matches

    s = open_session(raw_session)
    factory = s.rectification.factory
    matches = raw_matches(s, s.capture_dirs("scenes") + s.capture_dirs("board")[:1])
    choice = choose_reading_by_matches(factory, matches)
    assert choice.chosen_by == "scene matches" and choice.reading == SESSION_READING, choice
    by = {c.reading: c for c in choice.candidates}
    assert not by["as-is"].eligible and by[SESSION_READING].vertical.mean_abs_px < 0.06
    assert by["neg-x"].vertical.mean_abs_px > by[SESSION_READING].vertical.mean_abs_px + 0.05
    assert min(by[r].vertical.mean_abs_px for r in by if r.endswith("+inv-rot")) > 0.5
    assert choose_reading_by_matches(factory, [m for m in matches][:1][:0]) is None  # no matches: not decided


def test_real_zed_mini_reading_from_feature_matches():
    """The real ZED Mini view (../shared/data): the inverse-rotation readings leave 3.6 px, the others 0.5 px (the
    rest is the unit's residual rotation, which self-rectification removes: tests/core/test_selfcal.py)."""
    from conftest import shared_data

    from gtforge.core.zed.rectification import match_points
    from gtforge.io.formats import read_image
    from gtforge.io.zed_rectification import RawBoardPair, choose_reading_by_matches

    d = shared_data("zed-mini-raw-pair")
    factory = read_zed_conf(d / "SN10027514.conf", 1280)
    pl, pr = match_points(read_image(d / "left_raw.png"), read_image(d / "right_raw.png"), rectified=False)
    choice = choose_reading_by_matches(factory, [RawBoardPair("corridor", pl, pr)])
    by = {c.reading: c.vertical.mean_abs_px for c in choice.candidates}
    assert len(pl) > 100 and not choice.reading.endswith("+inv-rot") and by[choice.reading] < 0.6
    assert min(v for r, v in by.items() if r.endswith("+inv-rot")) > 3.0


@pytest.mark.slow
def test_scene_vertical_disparity_follows_the_reading(raw_session):
    right_reading = open_session(raw_session, SESSION_READING)
    cap = right_reading.load_capture(right_reading.capture_dirs("scenes")[0])
    good = scene_vertical_disparity(cap.zed_left, cap.zed_right)
    assert good is not None and good.n_points >= 50
    assert abs(good.median_px) < 0.05
    # the Stereolabs-sample reading of this conf flips TY/TZ: the scene rows drift by about 0.3 px
    wrong = open_session(raw_session, "neg-x")
    capw = wrong.load_capture(wrong.capture_dirs("scenes")[0])
    bad = scene_vertical_disparity(capw.zed_left, capw.zed_right)
    assert bad is not None and 0.2 < abs(bad.median_px) < 0.5
    # a known vertical shift of the right image comes back with its sign (v_left - v_right)
    shifted = cv2.warpAffine(cap.zed_right, np.float64([[1, 0, 0], [0, 1, 0.5]]), cap.zed_right.shape[1::-1],
                             flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    moved = scene_vertical_disparity(cap.zed_left, shifted)
    assert moved.median_px == pytest.approx(good.median_px - 0.5, abs=0.05)


@pytest.mark.slow
def test_meter_measures_a_known_misalignment(raw_session, raw_pairs):
    s = open_session(raw_session, SESSION_READING)
    assert "neg-all" in rectified_by(s)
    meter, shifted = (RectificationMeter(BOARD, s.zed.left, rectified_by(s)) for _ in range(2))
    for d in s.capture_dirs("board"):
        cap = s.load_capture(d)
        meter.add(d.name, cap.zed_right, left_image=cap.zed_left)
        right = cv2.warpAffine(cap.zed_right, np.float64([[1, 0, 0], [0, 1, 0.4]]), cap.zed_right.shape[1::-1],
                               flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        shifted.add(d.name, right, left_image=cap.zed_left)
    q, qs = meter.result(), shifted.result()
    assert q.overall.fit_mean_abs_px <= 0.05 and not q.warnings
    assert qs.overall.mean_px == pytest.approx(q.overall.mean_px - 0.4, abs=0.03)
    assert qs.overall.fit_mean_abs_px == pytest.approx(0.4, abs=0.05)
    assert qs.warnings and "0.15 px" in qs.warnings[0]
    # the figures of one pose by hand: a uniform 0.25 px row offset, exactly
    uv = raw_pairs[0].left_uv
    pv, pts = board_pose_vertical_disparity("x", uv, uv + [3.0, 0.25], BOARD)
    assert pv.mean_px == pytest.approx(-0.25) and pv.fit_max_abs_px == pytest.approx(0.25, abs=1e-6)
    assert pv.disparity_median_px == pytest.approx(-3.0) and pts.shape == (BOARD.n_corners, 3)


@pytest.mark.slow
def test_a_conf_from_another_camera_is_reported(raw_pairs, tmp_path):
    raw = default_raw_zed()
    other = RawZed(raw.resolution, raw.left, raw.right,
                   cv2.Rodrigues(np.array([[0.0031 + 0.004], [-0.0042], [0.0011]]))[0], raw.T_mm)
    f = read_zed_conf(write_raw_zed_conf(tmp_path / "SN1.conf", other, "neg-x"), 672)
    choice = choose_reading(f, raw_pairs, BOARD)
    assert choice.candidates[0].vertical.fit_mean_abs_px > 0.15
    assert any("another camera or resolution" in w for w in choice.warnings)
    # left and right swapped: every eligible reading sees negative disparities
    swapped = [RawBoardPair(p.capture, p.right_uv, p.left_uv) for p in raw_pairs]
    f = read_zed_conf(write_raw_zed_conf(tmp_path / "SN2.conf", raw, "neg-x"), 672)
    with pytest.raises(InputError, match="swapped"):
        choose_reading(f, swapped, BOARD)
    _, per_corner = score_readings(f, raw_pairs, BOARD, ("neg-all", "as-is"))
    np.testing.assert_allclose(per_corner["neg-all"], per_corner["as-is"], atol=1e-9)  # one line, two signs


@pytest.mark.slow
def test_session_yaml_override_is_used_scored_and_checked(raw_session, tmp_path):
    d = tmp_path / "s"
    d.mkdir()
    for name in ("board", "scenes"):
        (d / name).symlink_to(raw_session / name)
    for name in ("SN12345.conf", "mech_intrinsics.yaml"):
        shutil.copy(raw_session / name, d / name)
    text = (raw_session / "session.yaml").read_text()
    (d / "session.yaml").write_text(text + "zed_conf_reading: neg-x\n")
    s = open_session(d)
    assert s.rectification.reading == "neg-x"
    s2, choice = settle_zed_conf_reading(s, s.capture_dirs("board")[:2], BOARD)
    assert s2.rectification.reading == "neg-x" and choice.chosen_by == "session.yaml"
    assert choice.candidates[0].reading == SESSION_READING
    assert any("'neg-all' would leave" in w for w in choice.warnings)
    # a calibration that recorded another reading cannot be applied to this session silently
    with pytest.raises(InputError, match="zed_conf_reading.*neg-all.*neg-x"):
        open_session(d, zed_conf_reading="neg-all")
    # an unknown reading is a one-line input error
    (d / "session.yaml").write_text(text + "zed_conf_reading: minus-x\n")
    with pytest.raises(InputError, match="zed_conf_reading"):
        open_session(d)
