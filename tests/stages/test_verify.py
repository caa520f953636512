"""Per-scene verification against exact truth: texture alignment and stereo consistency (gtforge.verify)."""
import json
import shutil

import numpy as np
import pytest
from conftest import synthetic_session
from made_once import session_spec

from gtforge.core.geometry import T_from_rotvec
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.dataset.scene_verification import predicted_shift, verify_scene
from gtforge.io.captures import open_session
from gtforge.records.calibration import CalibrationFile
from gtforge.records.dataset import BuildParams, Manifest
from gtforge.records.verification import VerificationResult, VerifyParams
from gtforge.verify import verify_dataset

MOVED_SESSION_SPEC = session_spec("moved_session", "moved", n_board=0, n_scenes=2, scale=0.4, seed=21,
                                  depth_noise_mm=0.03, image_noise=1.5, fruit_motion_mm={0: (0.5, 0.0, 0.0), 1: (0.3,
                                  -0.4, 0.0)}, supersample=2)


@pytest.fixture(scope="module")
def moved_session(request):
    """Two fruit scenes whose fruit rolled between the structured-light and the ZED capture (0.5 mm in the table
    plane), same rig as the shared session (0.4x)."""
    return synthetic_session(request, MOVED_SESSION_SPEC)


def _verify(session_dir, sid, rig, params=None):
    s = open_session(session_dir)
    cap = s.load_capture(s.root / "scenes" / sid)
    sd, region, _ = build_scene_arrays(cap.depth_mm, rig, BuildParams(), None)
    ver, _ = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, cap.zed_left, cap.zed_right,
                          cap.mech_texture, rig, params)
    return ver, sd, cap


@pytest.mark.slow
def test_exact_extrinsic_scenes_verify_at_zero(dataset):
    out, summary = dataset
    rep = VerificationResult.read(out / "verification.json")
    assert sorted(rep.scenes) == ["000", "001", "002"]
    for sid, v in rep.scenes.items():
        assert v.status == "ok", (sid, v.reasons)
        for e in (v.texture_all, v.texture_fruit):  # issue target: within 0.05 px of zero on every scene
            assert e.magnitude_px < 0.05, (sid, e)
            assert e.correlation > 0.9 and e.n_pixels > 1000
        for region in ("all", "fruit", "background"):
            st = v.stereo[region]
            assert abs(st.disparity_bias_px) < 0.03 and abs(st.vertical_px) < 0.03, (sid, region, st)
            # issue 41: zero within the noise floor each figure reports (a few thousandths of a pixel here)
            assert 0 < st.disparity_bias_noise_px < 0.01 and 0 < st.vertical_noise_px < 0.01, (sid, region, st)
            assert abs(st.disparity_bias_px) < 4 * st.disparity_bias_noise_px + 0.005, (sid, region, st)
            assert abs(st.vertical_px) < 4 * st.vertical_noise_px + 0.005, (sid, region, st)
        for e in (v.texture_all, v.texture_fruit):
            assert 0 < e.dx_noise_px < 0.02 and 0 < e.dy_noise_px < 0.02 and 0 < e.correlation_noise < 0.02, (sid, e)
            assert abs(e.dx_px) < 4 * e.dx_noise_px + 0.005 and abs(e.dy_px) < 4 * e.dy_noise_px + 0.005, (sid, e)
        assert v.stereo["all"].bad_match_pct < 1.0
    man = Manifest.read(out / "manifest.json")
    assert man.flagged == {} and man.scenes["000"].verification.status == "ok"
    # the build decoded the ZED images only down to the rows the checks read: the same figures as the whole images give
    rig = CalibrationFile.read(man.calibration_path).rig
    for sid in rep.scenes:
        assert rep.scenes[sid] == _verify(man.session_dir, sid, rig)[0]
    html = (out / "verification.html").read_text()
    assert "0 flagged" in html and "Per scene, worst first" in html


@pytest.mark.slow
def test_moved_fruit_is_flagged_with_the_right_shift(moved_session, true_calibration, tmp_path):
    rig = CalibrationFile.read(true_calibration).rig
    for sid, motion in (("000", (0.5, 0.0, 0.0)), ("001", (0.3, -0.4, 0.0))):
        ver, sd, _ = _verify(moved_session, sid, rig)
        assert ver.status == "flagged" and any("fruit" in r for r in ver.reasons), ver.reasons
        # expected image shift of the fruit: project its surface points before and after the move
        tr = np.load(moved_session / "truth" / f"scene_{sid}.npz")
        fruit = tr["fruit_mask"] & np.isfinite(sd.depth_mm)
        v, u = np.nonzero(fruit)
        cam = rig.zed.left
        z = tr["zed_depth_mm"][v, u].astype(float)
        P = np.stack([(u - cam.cx_px) / cam.fx_px * z, (v - cam.cy_px) / cam.fy_px * z, z], axis=1)
        from gtforge.synthetic import default_rig

        T_zed_from_world = default_rig(0.4).T_zed_from_world
        back = cam.project(P - T_zed_from_world[:3, :3] @ np.array(motion))  # where GT (pre-move) puts them
        expect = (np.stack([u, v], 1) - back).mean(0)  # ZED position minus GT position
        got = np.array([ver.texture_fruit.dx_px, ver.texture_fruit.dy_px])
        assert np.linalg.norm(got - expect) < 0.08, (sid, got, expect)
        assert ver.texture_all.magnitude_px < 0.1  # the table did not move
        assert ver.texture_tiles and len(ver.texture_tiles) == 12  # shift map for flagged scenes


@pytest.mark.slow
def test_flagged_scene_overlay_at_a_reduced_work_resolution(moved_session, true_calibration, tmp_path):
    """At full resolution the checks run at half size: the flagged scene's overlay must still be drawn (it
    crashed on the shapes before). A work width of 300 px forces a factor 3 on this 883 px wide scene."""
    import cv2

    from gtforge.dataset.scene_verification import write_verification_overlay

    rig = CalibrationFile.read(true_calibration).rig
    s = open_session(moved_session)
    cap = s.load_capture(s.root / "scenes" / "000")
    sd, region, _ = build_scene_arrays(cap.depth_mm, rig, BuildParams(), None)
    ver, rendered = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, cap.zed_left, cap.zed_right,
                                 cap.mech_texture, rig, VerifyParams(work_width_px=300))
    assert ver.status == "flagged" and rendered.shape == (sd.depth_mm.shape[0] // 3, sd.depth_mm.shape[1] // 3)
    assert ver.texture_fruit.magnitude_px > 0.3  # the 0.5 mm roll, measured at a third of the resolution
    p = tmp_path / "overlay.jpg"
    write_verification_overlay(p, cap.zed_left, rendered)
    assert cv2.imread(str(p)).shape[:2] == rendered.shape


@pytest.mark.parametrize("work_width_px", [1200, 300])
@pytest.mark.slow
def test_checks_read_the_zed_images_only_down_to_zed_rows_used(session_dir, true_calibration, work_width_px):
    """A build decodes the ZED images only down to zed_rows_used (the window around the GT, at factor 1 and 3 here):
    images cut there give exactly the figures of the whole images; one row shorter they are refused."""
    from gtforge.dataset.scene_verification import zed_rows_used

    rig = CalibrationFile.read(true_calibration).rig
    s = open_session(session_dir)
    cap = s.load_capture(s.root / "scenes" / "001")
    sd, region, _ = build_scene_arrays(cap.depth_mm, rig, BuildParams(), None)
    depth, disp = sd.depth_mm.copy(), sd.disparity_px.copy()
    H = depth.shape[0]
    depth[int(0.7 * H):] = np.nan  # the depth camera sees less than the ZED (the GT ends above its last rows)
    disp[int(0.7 * H):] = np.nan
    noc = sd.nonoccluded & np.isfinite(disp)
    params = VerifyParams(work_width_px=work_width_px)
    n = zed_rows_used(depth, params)
    assert int(0.7 * H) < n < H
    whole, _ = verify_scene(depth, disp, noc, region, cap.zed_left, cap.zed_right, cap.mech_texture, rig, params)
    cut, _ = verify_scene(depth, disp, noc, region, cap.zed_left[:n], cap.zed_right[:n], cap.mech_texture, rig,
                          params)
    assert whole.status == "ok" and whole.texture_all.n_pixels > 1000 and whole.texture_fruit.dx_px is not None
    assert whole.stereo["all"].n_pixels > 1000
    assert cut == whole
    with pytest.raises(ValueError, match=rf"zed_right.shape=\({n - 1}, .* but the checks read its first {n} rows"):
        verify_scene(depth, disp, noc, region, cap.zed_left, cap.zed_right[:n - 1], cap.mech_texture, rig, params)
    f = -(-depth.shape[1] // work_width_px)  # the work factor: 1 and 3
    assert zed_rows_used(np.full_like(depth, np.nan), params) == H // f * f  # no GT: the whole image is the window


@pytest.mark.slow
def test_extrinsic_error_shows_as_the_predicted_shift(session_dir, true_calibration, T_zed_from_mech_true):
    base = CalibrationFile.read(true_calibration).rig
    for axis in ([0.0, 0.05, 0.0], [0.05, 0.0, 0.0]):
        T_zed_from_mech_wrong = T_from_rotvec(np.radians(axis), [0, 0, 0]) @ T_zed_from_mech_true
        rig = base.with_extrinsic(T_zed_from_mech_wrong)
        ver, sd, _ = _verify(session_dir, "001", rig)
        predicted = predicted_shift(sd.depth_mm, rig, T_zed_from_mech_true)
        got = np.array([ver.texture_all.dx_px, ver.texture_all.dy_px])
        assert np.linalg.norm(predicted) > 0.3  # 0.05 deg at f = 426 px
        assert np.linalg.norm(got - predicted) < 0.05, (axis, got, predicted)  # issue target


@pytest.mark.slow
def test_changed_content_and_bad_stereo_are_flagged(session_dir, true_calibration):
    rig = CalibrationFile.read(true_calibration).rig
    s = open_session(session_dir)
    a = s.load_capture(s.root / "scenes" / "000")
    b = s.load_capture(s.root / "scenes" / "002")
    sd, region, _ = build_scene_arrays(a.depth_mm, rig, BuildParams(), None)
    # the ZED pair of another scene: the texture no longer matches at all
    ver, _ = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, b.zed_left, b.zed_right,
                          a.mech_texture, rig)
    assert ver.status == "flagged" and any("correlation" in r for r in ver.reasons), ver.reasons
    # a disparity ground truth biased by 0.3 px: the stereo check measures it
    ver, _ = verify_scene(sd.depth_mm, sd.disparity_px + 0.3, sd.nonoccluded, region, a.zed_left, a.zed_right,
                          a.mech_texture, rig)
    assert ver.stereo["all"].disparity_bias_px == pytest.approx(-0.3, abs=0.03)
    assert ver.status == "flagged" and any("disparity bias" in r for r in ver.reasons)
    # ground truth off by more than the Gauss-Newton reaches from it (a baseline 29 % off gave labels 5-8 px small and a
    # reported bias of +0.2 +- 0.005 px: a newcomer's run-through, round 4): the search before it finds the offset
    for offset in (6.0, -15.0):
        ver, _ = verify_scene(sd.depth_mm, sd.disparity_px + offset, sd.nonoccluded, region, a.zed_left, a.zed_right,
                              a.mech_texture, rig)
        for name in ("all", "fruit", "background"):
            assert ver.stereo[name].disparity_bias_px == pytest.approx(-offset, abs=0.03), (offset, name, ver.stereo)
        assert ver.status == "flagged" and any("disparity bias over the whole area" in r for r in ver.reasons)
    # beyond the search (24 px at this scale): no bias fitted (a tiny one from a local minimum before), flagged for it
    ver, _ = verify_scene(sd.depth_mm, sd.disparity_px + 40.0, sd.nonoccluded, region, a.zed_left, a.zed_right,
                          a.mech_texture, rig)
    assert ver.status == "flagged" and all(ver.stereo[k].disparity_bias_px is None for k in ver.stereo), ver.stereo
    assert any(r.startswith(f"stereo: no disparity bias found over the whole area's {ver.stereo['all'].n_pixels} "
                            "textured pixels (the right image matches the labels nowhere within +-24 px")
               for r in ver.reasons), ver.reasons
    # a right image 0.4 px lower than the rectification says
    import cv2

    M = np.float32([[1, 0, 0], [0, 1, 0.4]])
    right_low = cv2.warpAffine(a.zed_right, M, a.zed_right.shape[1::-1], flags=cv2.INTER_CUBIC,
                               borderMode=cv2.BORDER_REPLICATE)
    ver, _ = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, a.zed_left, right_low,
                          a.mech_texture, rig)
    assert ver.stereo["all"].vertical_px == pytest.approx(-0.4, abs=0.05)  # v_left - v_right
    assert any("vertical" in r for r in ver.reasons)
    # no texture contrast: not verifiable, with the reason
    ver, _ = verify_scene(sd.depth_mm, sd.disparity_px, sd.nonoccluded, region, a.zed_left, a.zed_right,
                          np.full_like(a.mech_texture, 90), rig)
    assert ver.status == "not verifiable" and "blank" in ver.reasons[0]


@pytest.mark.slow
def test_build_flags_and_quarantines_and_verify_cli(moved_session, session_dir, true_calibration, tmp_path):
    from typer.testing import CliRunner

    from gtforge.cli.commands import app

    # a session of one clean and two moved scenes, built without motion compensation (tests/stages/
    # test_motion_compensation.py: with it)
    sess = tmp_path / "sess"
    shutil.copytree(moved_session, sess)
    shutil.copytree(session_dir / "scenes" / "002", sess / "scenes" / "clean")
    out = tmp_path / "ds"
    r = CliRunner().invoke(app, ["build-dataset", str(sess), "-c", str(true_calibration), "-o", str(out),
                                 "--workers", "1", "--quarantine", "--split", "1.0,0.0", "--no-motion-compensation"])
    assert r.exit_code == 0, r.output
    assert "verification: 2 scene(s) flagged (left out of the split lists: --quarantine): 000, 001" in r.output
    man = Manifest.read(out / "manifest.json")
    assert sorted(man.flagged) == ["000", "001"] and man.quarantined == ["000", "001"]
    assert (out / "filenames" / "train.txt").read_text().split()[0] == "scenes/clean/im0.png"
    assert (out / "scenes" / "000" / "disp0GT.pfm").exists()  # quarantined, never deleted
    assert ((out / "verification" / "000_overlay.jpg").exists()
            and not (out / "verification" / "clean_overlay.jpg").exists())
    html = (out / "verification.html").read_text()
    assert "2 flagged" in html and "verification/000_overlay.jpg" in html and html.index("000") < html.index("clean")
    # verify an existing dataset again: same verdicts, exit 1 because scenes are flagged; without --quarantine the
    # lists get every scene back
    r = CliRunner().invoke(app, ["verify", str(out), "--workers", "1"])
    assert r.exit_code == 1 and "2 flagged" in r.output
    assert len((out / "filenames" / "train.txt").read_text().split("\n")) == 4
    assert json.loads((out / "manifest.json").read_text())["quarantined"] == []
    # a looser threshold lets them through
    r = CliRunner().invoke(app, ["verify", str(out), "--workers", "1", "--max-shift-px", "2"])
    assert r.exit_code == 0 and "0 flagged" in r.output
    # one scene checked again: the count says so (it said 3, the scenes the merged report holds)
    r = CliRunner().invoke(app, ["verify", str(out), "--workers", "1", "--max-shift-px", "2", "--scenes", "001"])
    assert r.exit_code == 0 and "verified 1 scene(s), the report holds 3: 0 flagged" in r.output, r.output
    # a verification.json of schema 1 (figures before issue 41) cannot be merged: verifying one scene verifies all
    old = json.loads((out / "verification.json").read_text())
    old["schema_version"] = 1
    (out / "verification.json").write_text(json.dumps(old))
    rep = verify_dataset(out, VerifyParams(), scenes=["clean"], workers=1)
    assert sorted(rep.scenes) == ["000", "001", "clean"] and sorted(rep.flagged) == ["000", "001"]
    assert VerificationResult.read(out / "verification.json").schema_version == 3
    # a scene folder of the dataset deleted: not verifiable, and the hint says what writes it again
    shutil.move(out / "scenes" / "001", tmp_path / "001_aside")
    rep = verify_dataset(out, VerifyParams(), scenes=["001"], workers=1)
    assert rep.scenes["001"].status == "not verifiable"
    assert "no such folder (hint: rerun gtforge build-dataset with the same options" in rep.scenes["001"].reasons[0]
    shutil.move(tmp_path / "001_aside", out / "scenes" / "001")
    # the captures moved away: a per-scene reason, no traceback; a missing session: one-line error, exit 2
    shutil.rmtree(sess / "scenes" / "clean")
    rep = verify_dataset(out, VerifyParams(), scenes=["clean"], workers=1)
    assert rep.scenes["clean"].status == "not verifiable" and "no such folder" in rep.scenes["clean"].reasons[0]
    shutil.rmtree(sess)
    from gtforge.errors import InputError

    r = CliRunner().invoke(app, ["verify", str(out)])
    assert isinstance(r.exception, InputError) and "session_dir" in str(r.exception)  # main() prints it, exit 2
    with pytest.raises(InputError, match="session_dir.*no such folder.*--session"):
        verify_dataset(out)


def test_local_normalize_is_the_numpy_expression():
    """The compiled pass after the blurs gives the numpy expression's float32 values exactly: with and without a mask,
    with NaN and inf in the image, flat areas and a mask whose weights fall to 0 (division by zero)."""
    import cv2

    from gtforge.core.alignment.photometric import local_normalize

    def reference(img, mask, sigma_px):  # gtforge's numpy implementation before the compiled pass
        k = (0, 0)
        x = np.asarray(img, np.float32) if mask is None else np.where(mask, img, 0).astype(np.float32)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            if mask is None:
                mean = cv2.GaussianBlur(x, k, sigma_px)
                var = cv2.GaussianBlur(x * x, k, sigma_px) - mean * mean
            else:
                w = cv2.GaussianBlur(mask.astype(np.float32), k, sigma_px)
                mean = cv2.GaussianBlur(x, k, sigma_px) / w
                var = cv2.GaussianBlur(x * x, k, sigma_px) / w - mean * mean
            out = (x - mean) / np.sqrt(np.maximum(var, 1e-6) + 1.0)
        if mask is not None:
            out[~mask | ~(w > 0.5)] = 0.0
        return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)

    rng = np.random.default_rng(4)
    img = (rng.random((90, 130)) * 255).astype(np.float32)
    img[:, :20] = 17.0  # flat: the variance floor
    img[40, 50], img[41, 51] = np.nan, np.inf
    mask = rng.random(img.shape) > 0.3
    mask[60:, :] = False  # no weight at all far from the mask: 0 / 0
    for m in (None, mask):
        for sigma in (1.0, 3.0):
            got, ref = local_normalize(img, m, sigma), reference(img, m, sigma)
            assert got.dtype == np.float32 and np.abs(got).max() > 1.0
            np.testing.assert_array_equal(got, ref)


def test_work_array_helpers_are_the_numpy_expressions():
    """The compiled helpers of the work arrays give what the numpy steps they replace give: the GT's rows
    (``mask_bounding_box`` of the finite values), the disparity and its finite range (``depth_to_disparity``: NaN,
    zero, negative and infinite depths), and a 2x2 block's non-occlusion (its area mean equal to 1)."""
    import cv2

    from gtforge.core.camera import PinholeCamera, RectifiedStereo
    from gtforge.core.geometry import finite_rows, mask_bounding_box
    from gtforge.dataset.scene_verification import _all_of_2x2, _disparity_and_range

    rng = np.random.default_rng(5)
    a = np.full((40, 30), np.nan, np.float32)
    assert finite_rows(a) == (0, 0)
    for (v, u), val in (((0, 0), 1.0), ((39, 29), -2.0), ((17, 3), 0.0), ((5, 29), 3.0)):
        b = a.copy()
        b[v, u] = val
        b[25, 7] = np.inf  # not finite: not a row of the GT
        box = mask_bounding_box(np.isfinite(b))
        assert finite_rows(b) == (box[0], box[1])
    b = (rng.random((40, 30)) * 900 + 300).astype(np.float32)
    b[:6], b[33:], b[10, :] = np.nan, np.nan, np.nan
    assert finite_rows(b) == (6, 33)

    zed = RectifiedStereo(left=PinholeCamera(fx_px=701.5, fy_px=701.5, cx_px=640.2, cy_px=360.7, width_px=1280,
                                          height_px=720), baseline_mm=63.1, doffs_px=1.75)
    depth = (rng.random((23, 37)) * 1500 + 200).astype(np.float32)
    depth[3, :5] = [np.nan, 0.0, -40.0, np.inf, -np.inf]
    out = np.empty(depth.shape, np.float32)
    n, lo, hi = _disparity_and_range(depth, zed.f_px * zed.baseline_mm, zed.doffs_px, out)
    with np.errstate(invalid="ignore"):
        ref = zed.depth_to_disparity(depth)
    np.testing.assert_array_equal(out, ref)
    fin = ref[np.isfinite(ref)]
    assert (n, lo, hi) == (fin.size, fin.min(), fin.max())
    assert _disparity_and_range(np.full((3, 4), np.nan, np.float32), 1.0, 0.0, np.empty((3, 4), np.float32))[0] == 0

    noc = rng.random((30, 44)) > 0.1
    got = np.empty((15, 22), bool)
    _all_of_2x2(noc, 0, 0, got)
    np.testing.assert_array_equal(got, cv2.resize(noc.astype(np.float32), (22, 15), interpolation=cv2.INTER_AREA) == 1)
    got = np.empty((13, 19), bool)
    _all_of_2x2(noc, 2, 4, got)  # a window whose first pixel is (2, 4)
    np.testing.assert_array_equal(got, cv2.resize(noc[2:28, 4:42].astype(np.float32), (19, 13),
                                                  interpolation=cv2.INTER_AREA) == 1)


def test_pixels_of_is_numpys_nonzero():
    """``pixels_of``'s compiled pass lists ``np.nonzero``'s pixels and flat indices, in its order, for bool and
    integer masks, a view, an empty mask and a full one."""
    from gtforge.core.alignment.photometric import pixels_of

    rng = np.random.default_rng(6)
    m = rng.random((37, 61)) < 0.6
    for mask in (m, m.astype(np.uint8) * 7, m[::2, 5:], np.zeros((4, 5), bool), np.ones((3, 2), bool)):
        v, u, idx = pixels_of(mask)
        rv, ru = np.nonzero(mask)
        assert v.dtype == u.dtype == idx.dtype == np.int64
        np.testing.assert_array_equal(v, rv)
        np.testing.assert_array_equal(u, ru)
        np.testing.assert_array_equal(idx, np.flatnonzero(mask))


def test_smooth_depth_mask_and_stereo_pixels_are_the_numpy_expressions():
    """The compiled passes of ``smooth_depth_mask`` and of the stereo check's per-pixel inputs give what the numpy
    expressions they replace give: NaN and inf disparities, a float64 disparity beyond float32's range, a view, other
    radii and a range not representable in float32 (compared in float32, as numpy compares)."""
    import cv2

    from gtforge.core.alignment.photometric import smooth_depth_mask
    from gtforge.dataset.scene_verification import _stereo_pixels

    def smooth_reference(disparity_px, radius_px=3, max_range_px=1.0):
        k = np.ones((2 * radius_px + 1,) * 2, np.uint8)
        with np.errstate(over="ignore"):
            d = disparity_px.astype(np.float32)
        hi = cv2.dilate(np.where(np.isfinite(d), d, -1e6).astype(np.float32), k)
        lo = cv2.erode(np.where(np.isfinite(d), d, 1e6).astype(np.float32), k)
        return (hi - lo) < max_range_px

    rng = np.random.default_rng(7)
    a = (rng.random((50, 60)) * 40).astype(np.float32)
    holes = rng.random(a.shape) < 0.2
    holes[14:36, 14:36] = False
    a[holes] = np.nan
    a[14:36, 14:36] = 17.3 + rng.random((22, 22)).astype(np.float32) * 0.2  # a smooth patch
    a[3, 4], a[40, 50] = np.inf, -np.inf
    b = a.astype(np.float64)
    b[7, 7] = 1e39  # inf once rounded to float32
    for x in (a, b, a[::2, 3:]):
        for r, mr in ((3, 1.0), (1, 0.1), (2, 2.5)):
            got = smooth_depth_mask(x, r, mr)
            assert got.any() and not got.all()
            np.testing.assert_array_equal(got, smooth_reference(x, r, mr))

    noc = rng.random(a.shape) < 0.8
    for disp in (a, b):
        x0, y0, width, height = 40, 2, 100, 55
        ok, d, x_match, inside = (np.empty(a.shape, t) for t in (np.bool_, np.float32, np.float32, np.bool_))
        _stereo_pixels(noc, disp, x0, y0, width, height, ok, d, x_match, inside)
        ok_ref = noc & np.isfinite(disp)
        with np.errstate(over="ignore"):
            d_ref = np.where(ok_ref, disp, 0).astype(np.float32)
        xm_ref = np.arange(x0, x0 + a.shape[1], dtype=np.float32) - d_ref
        v_img = np.arange(y0, y0 + a.shape[0], dtype=np.float32)[:, None]
        in_ref = (xm_ref > 3) & (xm_ref < width - 4) & (v_img > 3) & (v_img < height - 4)
        assert in_ref.any() and not in_ref.all()
        for got, ref in ((ok, ok_ref), (d, d_ref), (x_match, xm_ref), (inside, in_ref)):
            assert got.dtype == ref.dtype
            np.testing.assert_array_equal(got, ref)


def test_block_noise_solves_the_bands_as_one_solve_each():
    """``block_noise`` solves its bands' normal equations in one batched call: the same standard errors, to the bit, as
    a solve per band, for C- and F-ordered models; None when a band's system is singular."""
    import itertools
    import math

    from gtforge.core.alignment.photometric import NOISE_BLOCKS, block_noise

    def reference(A, r, n_params):
        edges = np.linspace(0, len(r), NOISE_BLOCKS + 1).astype(np.int64)
        sols = [np.linalg.solve(A[a:b].T @ A[a:b], -(A[a:b].T @ r[a:b]))[:n_params]
                for a, b in itertools.pairwise(edges)]
        return np.std(np.array(sols), axis=0, ddof=1) / math.sqrt(NOISE_BLOCKS)

    rng = np.random.default_rng(8)
    for n, p in ((300, 4), (5001, 2), (30000, 4), (777, 3)):
        A = rng.normal(size=(n, p)) * rng.uniform(0.01, 100, size=p)
        r = rng.normal(size=n)
        for a in (A, np.asfortranarray(A)):
            got = block_noise(a, r, 2)
            assert got.shape == (2,)
            np.testing.assert_array_equal(got, reference(a, r, 2))
    A = np.zeros((1000, 4))
    A[:, 0] = 1.0
    assert block_noise(A, np.ones(1000), 2) is None
    assert block_noise(A[:100], np.ones(100), 2) is None  # too few rows


def test_interior_mask_and_offset_indices():
    """``interior_mask`` erodes a bool mask's bytes as they are: what the uint8 copy gave, also for a view and for an
    integer mask; ``_offset_flat`` gives the flat indices in a window of the pixels."""
    import cv2

    from gtforge.core.alignment.photometric import interior_mask, pixels_of
    from gtforge.dataset.scene_verification import _offset_flat

    rng = np.random.default_rng(9)
    m = rng.random((60, 70)) < 0.9
    m[10:50, 10:64] = True
    for mask in (m, m[3:, ::2], m.astype(np.uint8) * 255):
        for r in (1, 2, 6):
            got = interior_mask(mask, r)
            ref = cv2.erode(mask.astype(np.uint8), np.ones((2 * r + 1,) * 2, np.uint8)).astype(bool)
            assert got.dtype == np.bool_ and got.any()
            np.testing.assert_array_equal(got, ref)
    v, u, _ = pixels_of(m[10:50, 12:60])
    v, u = v + 10, u + 12
    out = np.empty(len(v), np.int64)
    _offset_flat(v, u, 8, 11, 55, out)
    np.testing.assert_array_equal(out, (v - 8) * 55 + (u - 11))


@pytest.mark.slow
def test_verify_gives_the_builds_figures_and_flags_a_depth_changed_after_it(dataset, tmp_path):
    """verify checks the depth the build checked (depth0.tiff, where disp0GT.pfm agrees with it): every scene's
    figures are the build's to the last digit (verify derived the depth from disp0GT.pfm, 1e-7 away, which moved the
    demo's scene 003 from -0.0042 to -0.0010 px). A depth0.tiff changed after the build flags its scene."""
    from gtforge.io.captures import read_depth
    from gtforge.io.formats import write_tiff_float

    out = tmp_path / "ds"
    shutil.copytree(dataset[0], out)
    built = VerificationResult.read(out / "verification.json").scenes
    rep = verify_dataset(out, VerifyParams(), workers=1)
    for sid, v in rep.scenes.items():
        assert v.model_dump(exclude={"time_s"}) == built[sid].model_dump(exclude={"time_s"}), sid
    z = read_depth(out / "scenes" / "001" / "depth0.tiff")
    v, u = np.argwhere(np.isfinite(z))[len(np.argwhere(np.isfinite(z))) // 2]
    z[v, u] *= 1.001  # one pixel, 0.1 % deeper
    write_tiff_float(out / "scenes" / "001" / "depth0.tiff", z)
    rep = verify_dataset(out, VerifyParams(), scenes=["001"], workers=1)
    v1 = rep.scenes["001"]
    assert v1.status == "flagged" and v1.reasons[-1].startswith(
        "depth0.tiff and disp0GT.pfm disagree at 1 pixel(s) (more than 1e-06 apart or one without a value)")
    # checked on the labels' own depth (as before this check): within the noise of the build's figures
    assert abs(v1.texture_all.dx_px - built["001"].texture_all.dx_px) < 0.01
    f = out / "scenes" / "002" / "depth0.tiff"
    f.write_bytes(f.read_bytes()[:1000])  # cut short: the labels are still checked, the scene flagged
    v2 = verify_dataset(out, VerifyParams(), scenes=["002"], workers=1).scenes["002"]
    assert v2.status == "flagged" and v2.reasons[-1].startswith("depth0.tiff is unreadable (")
    assert v2.reasons[-1].endswith("): checked on the disparity's depth") and v2.texture_all.dx_px is not None


@pytest.mark.slow
def test_the_builds_figures_are_taken_only_as_given_and_with_the_builds_thresholds(dataset, tmp_path):
    """``build_figures`` (what ``gtforge run`` passes for the scenes its build just wrote): a scene's figures are taken
    as given, not computed, when the thresholds are the build's; with other thresholds every scene is computed.
    ``build_checks`` gives each scene's ``meta.json`` verification, except where the build tried motion compensation
    (verify checks such a scene on the fruit it finds moved in the files)."""
    from gtforge.records.verification import MotionCompensation, SceneVerification
    from gtforge.verify import build_checks

    out = tmp_path / "ds"
    shutil.copytree(dataset[0], out)
    built = VerificationResult.read(out / "verification.json").scenes
    checks = build_checks(out, ["000", "001", "002"])
    assert checks == {sid: built[sid] for sid in ("000", "001", "002")}
    meta = out / "scenes" / "002" / "meta.json"
    m = json.loads(meta.read_text())
    m["verification"]["motion_compensation"] = MotionCompensation(status="not compensated").model_dump(mode="json")
    meta.write_text(json.dumps(m))
    assert sorted(build_checks(out, ["000", "001", "002", "999"])) == ["000", "001"]
    # a figure no computation gives: taken for 001 (so 001 was not computed), 000 and 002 computed as the build did
    marked = SceneVerification(status="flagged", reasons=["as given"])
    rep = verify_dataset(out, scenes=["000", "001", "002"], workers=1, build_figures={"001": marked})
    assert rep.scenes["001"] == marked and Manifest.read(out / "manifest.json").flagged == {"001": ["as given"]}
    for sid in ("000", "002"):
        assert rep.scenes[sid].model_dump(exclude={"time_s"}) == built[sid].model_dump(exclude={"time_s"}), sid
    # other thresholds than the build's: nothing taken
    rep = verify_dataset(out, VerifyParams(max_shift_px=0.4), scenes=["001"], workers=1,
                         build_figures={"001": marked})
    assert rep.scenes["001"].status == "ok" and rep.scenes["001"].reasons == []


@pytest.mark.slow
def test_an_interrupted_verify_resumes_with_the_scenes_it_had_checked(dataset, tmp_path):
    """Ctrl-C keeps the scenes already checked (.verify-partial.json); the next verify checks only the others, and
    again a kept scene whose files changed since; its report is the uninterrupted one's, and the journal goes (a
    verify of other scenes alone leaves it)."""
    import os

    from gtforge.errors import Interrupted
    from gtforge.records.verification import VerifyJournal

    out = tmp_path / "ds"
    shutil.copytree(dataset[0], out)
    ids = sorted(Manifest.read(out / "manifest.json").scenes)
    assert len(ids) >= 3
    whole = verify_dataset(out, VerifyParams(), workers=1).scenes
    checked: list[str] = []

    def stop_after_two(msg):
        if msg.startswith("verified "):
            checked.append(msg.split()[1])
            if len(checked) == 2:
                raise KeyboardInterrupt

    with pytest.raises(Interrupted, match=rf"interrupted: 2 of {len(ids)} scene\(s\) verified, kept in "):
        verify_dataset(out, VerifyParams(), workers=1, progress=stop_after_two)
    journal = VerifyJournal.read(out / ".verify-partial.json")
    assert sorted(journal.scenes) == sorted(checked) == ids[:2]
    # a thresholds change takes nothing over
    checked.clear()
    with pytest.raises(Interrupted):
        verify_dataset(out, VerifyParams(max_shift_px=0.9), workers=1, progress=stop_after_two)
    assert checked == ids[:2]
    # the record is now that run's (other thresholds): interrupted again with the first ones, then a kept scene's
    # labels file changes (its time), so that it must be checked again
    checked.clear()
    with pytest.raises(Interrupted):
        verify_dataset(out, VerifyParams(), workers=1, progress=stop_after_two)
    st = (out / "scenes" / ids[0] / "disp0GT.pfm").stat()
    os.utime(out / "scenes" / ids[0] / "disp0GT.pfm", ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    verify_dataset(out, VerifyParams(), scenes=[ids[-1]], workers=1)  # another scene alone: the record stays
    assert sorted(VerifyJournal.read(out / ".verify-partial.json").scenes) == ids[:2]
    said: list[str] = []
    rep = verify_dataset(out, VerifyParams(), workers=1, progress=said.append)
    assert said[0].startswith("1 scene(s) verified before an interruption, their files unchanged: kept")
    assert [m.split()[1] for m in said[1:]] == [ids[0], *ids[2:]]
    assert {s: v.model_dump() for s, v in rep.scenes.items()} == {s: v.model_dump() for s, v in whole.items()}
    assert not (out / ".verify-partial.json").exists()
    assert VerificationResult.read(out / "verification.json").scenes.keys() == whole.keys()
    # a --scenes run stopped in its turn keeps the record's other scenes beside its own
    checked.clear()
    with pytest.raises(Interrupted):
        verify_dataset(out, VerifyParams(), workers=1, progress=stop_after_two)
    checked.clear()
    checked.append("(one before)")
    with pytest.raises(Interrupted, match=r"interrupted: 1 of 1 scene\(s\) verified"):
        verify_dataset(out, VerifyParams(), scenes=[ids[-1]], workers=1, progress=stop_after_two)
    assert sorted(VerifyJournal.read(out / ".verify-partial.json").scenes) == [*ids[:2], ids[-1]]


def test_verify_removes_the_overlays_of_scenes_no_longer_flagged(dataset, tmp_path):
    """verify writes verification/<id>_overlay.jpg for flagged scenes only (docs/dataset-format.md), as build-dataset
    does: a scene flagged by one verify and passing the next loses its overlay (it stayed, showing a flag the
    dataset no longer has)."""
    out = tmp_path / "ds"
    shutil.copytree(dataset[0], out)
    ids = sorted(Manifest.read(out / "manifest.json").scenes)
    overlays = out / "verification"
    assert not list(overlays.glob("*_overlay.jpg"))
    rep = verify_dataset(out, VerifyParams(max_shift_px=1e-9), workers=1)  # every scene's shift is over it
    assert sorted(rep.flagged) == ids
    # the shift shown with the decimals the limit needs (it read "0.00 px > 1e-09 px")
    import re

    for sid in ids:
        shown = [re.fullmatch(r"texture shift over the whole area (\d+\.\d{6}) px > 1e-09 px \(dx [-+]\d+\.\d{6}, "
                              r"dy [-+]\d+\.\d{6}\)", r) for r in rep.flagged[sid]]
        assert any(m and float(m.group(1)) > 0 for m in shown), rep.flagged[sid]
    assert sorted(p.name for p in overlays.glob("*_overlay.jpg")) == [f"{i}_overlay.jpg" for i in ids]
    rep = verify_dataset(out, VerifyParams(), scenes=[ids[1]], workers=1)  # it passes: its overlay goes, not others'
    assert sorted(rep.flagged) == [ids[0], *ids[2:]]
    assert sorted(p.name for p in overlays.glob("*_overlay.jpg")) == [f"{i}_overlay.jpg" for i in rep.flagged]


def test_a_figure_is_shown_with_the_decimals_its_limit_needs():
    from gtforge.dataset.scene_verification import _decimals

    assert [_decimals(x, 2) for x in (0.25, 0.1, 0.05, 0.002, 1e-9, 3.0)] == [2, 2, 3, 4, 6, 2]
    assert [_decimals(x, 3) for x in (0.1, 0.01, 0.005)] == [3, 3, 4]
