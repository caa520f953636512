"""Motion-compensated ground truth (issue #37): a scene whose fruit moved between the structured-light exposure and the
ZED exposure, rebuilt with each fruit moved by its estimated rigid motion, against the exact truth at the ZED's
exposure (gtforge.synthetic's ``fruit_rigid_motion``). Full resolution: benchmarks/bench_motion_compensation.py."""
import json
import shutil

import cv2
import numpy as np
import pytest
import tifffile
from conftest import synthetic_session
from made_once import session_spec

from gtforge.build_dataset import build_dataset
from gtforge.core.alignment.fruit_motion import FruitMotionEstimate
from gtforge.core.camera import Rig
from gtforge.core.geometry import invert_T, make_T, transform_points
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.dataset.motion_compensation import verify_and_compensate
from gtforge.io.captures import open_session
from gtforge.io.formats import read_image, read_pfm
from gtforge.records.calibration import CalibrationFile
from gtforge.records.dataset import BuildParams, Manifest, SceneMeta
from gtforge.records.verification import MotionParams, VerificationResult
from gtforge.synthetic import (
    OBJ_FRUIT,
    RigidlyMoved,
    Scene,
    SpheroidObject,
    SyntheticTruth,
    fruit_motion_T,
)
from gtforge.verify import verify_dataset

CHI2_6_999 = 22.46  # chi-square, 6 degrees of freedom, 99.9 %
STILL = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
MOTION_SESSION_SPEC = session_spec(
    "motion_session", "motion", n_board=0, n_scenes=2, scale=0.4, seed=37, depth_noise_mm=0.03, image_noise=1.5,
    supersample=2, partly_out_of_view=False,
    fruit_rigid_motion={0: [((1.5, -0.8, 0.3), (0.6, -0.8, 1.0)), STILL, ((-1.2, 1.6, -0.2), (-1.0, 0.5, 0.8))],
                        1: [((12.0, 8.0, 0.0), (0.0, 0.0, 4.0))]})


@pytest.fixture(scope="module")
def motion_session(request):
    """Scene 000: three melons, two moved by 1.7 / 2.0 mm and 1.4 / 1.4 deg between the exposures, one still;
    001: one melon rolled 14 mm and turned 4 deg (0.4x, the shared rig, 2x2 rays a pixel)."""
    return synthetic_session(request, MOTION_SESSION_SPEC)


@pytest.fixture(scope="module")
def motion_datasets(motion_session, tmp_path_factory):
    """The session built with the exact extrinsic, with motion compensation (the default) and without (000)."""
    s = open_session(motion_session)
    truth = SyntheticTruth.read(motion_session / "truth" / "rig_truth.yaml")
    root = tmp_path_factory.mktemp("motion")
    calib = CalibrationFile.known_extrinsic(Rig(zed=s.zed, mech=s.mech, T_zed_from_mech=truth.T_zed_from_mech),
                                            sigma_rot_deg=0.01, sigma_trans_mm=0.1).write(root / "calib.yaml")
    # at 0.4x the moved fruit's motion sigma is 0.010-0.013 px (fewer points): over the default bound (0.01, set at
    # full resolution), so the bound of a coarser dataset
    on = build_dataset(motion_session, calib, root / "on", BuildParams(motion=MotionParams(max_sigma_px=0.02)),
                       workers=1)
    off = build_dataset(motion_session, calib, root / "off", BuildParams(motion=MotionParams(compensate=False)),
                        workers=1, scenes=["000"])
    return on, off, calib


def test_rigidly_moved_object_is_the_object_moved():
    """The generator's rigid motion of a fruit: a translation ray-casts as the translated spheroid, a quarter turn
    about the vertical as the spheroid with its x and y semi-axes swapped; the texture moves with the fruit."""
    c, r = np.array([10.0, -5.0, 60.0]), np.array([70.0, 55.0, 60.0])
    fruit = SpheroidObject(OBJ_FRUIT, c, r, 8, 0.3, 1)
    rng = np.random.default_rng(0)
    o = np.array([0.0, 0.0, 700.0]) + rng.normal(0, 5, (500, 3))
    d = (c + rng.uniform(-60, 60, (500, 3))) - o
    moved = RigidlyMoved(fruit, fruit_motion_T(c, (3.0, -2.0, 1.0), (0.0, 0.0, 0.0)))
    shifted = SpheroidObject(OBJ_FRUIT, c + [3.0, -2.0, 1.0], r, 8, 0.3, 1)
    t1, t2 = moved.intersect(o, d), shifted.intersect(o, d)
    assert np.isfinite(t1).sum() > 200 and np.allclose(t1, t2, rtol=0, atol=1e-9, equal_nan=True)
    turned = RigidlyMoved(fruit, fruit_motion_T(c, (0.0, 0.0, 0.0), (0.0, 0.0, 90.0)))
    swapped = SpheroidObject(OBJ_FRUIT, c, r[[1, 0, 2]], 8, 0.3, 1)
    np.testing.assert_allclose(turned.intersect(o, d), swapped.intersect(o, d), rtol=0, atol=1e-9)
    hit = np.isfinite(t1)
    p = o[hit] + t1[hit, None] * d[hit]
    np.testing.assert_array_equal(moved.shade(p), fruit.shade(p - [3.0, -2.0, 1.0]))
    # a scene of several fruit shades each by its own texture (not the last fruit's)
    other = SpheroidObject(OBJ_FRUIT, c + [300.0, 0, 0], r, 11, 2.0, 2)
    t, ids = Scene([fruit, other], shade_by_object=True).raycast(o, d)
    assert set(np.unique(ids[np.isfinite(t)])) == {1}  # 1 + the index of the fruit hit
    light = np.array([0.0, 0.0, 1.0])
    np.testing.assert_array_equal(Scene([fruit, other], shade_by_object=True).shade(p, np.ones(len(p), np.int8),
                                                                                     light),
                                  Scene([fruit]).shade(p, np.full(len(p), OBJ_FRUIT, np.int8), light))


@pytest.mark.slow
def test_generator_writes_the_truth_at_the_zed_exposure(motion_session):
    """Each fruit's exact motion in the ZED-left frame beside the truth at the ZED's exposure: the still fruit's is the
    identity, a moved fruit's maps its centre at the depth exposure onto its centre at the ZED's; the disparity
    differs from the still scene's only where a moved fruit is, or was."""
    z = np.load(motion_session / "truth" / "scene_000.npz")
    T_zed_moved_from_zed_true = z["fruit_T_zed_moved_from_zed"]
    assert T_zed_moved_from_zed_true.shape == (3, 4, 4) and np.allclose(T_zed_moved_from_zed_true[1], np.eye(4),
                                                                         atol=1e-9)
    rig_T = z["T_zed_from_world"]
    for k in (0, 2):
        t_mm, r_deg = z["fruit_motion_translation_mm"][k], z["fruit_motion_rotvec_deg"][k]
        c_after = z["fruit_centre_zed_mm"][k]
        c_before = transform_points(invert_T(T_zed_moved_from_zed_true[k]), c_after[None])[0]
        np.testing.assert_allclose(c_after - c_before, rig_T[:3, :3] @ t_mm, atol=1e-9)  # turned about its centre
        R = T_zed_moved_from_zed_true[k][:3, :3]
        np.testing.assert_allclose(np.degrees(np.linalg.norm(cv2.Rodrigues(R)[0])), np.linalg.norm(r_deg), atol=1e-9)
    diff = ~np.isclose(z["zed_disparity_px"], z["still_zed_disparity_px"], rtol=0, atol=1e-6, equal_nan=True)
    assert diff.any() and not diff[~_dilate(z["fruit_mask"], 6)].any()  # (2 mm: under 2 px here)


def _dilate(m, r):
    return cv2.dilate(m.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)).astype(bool)


def _epe(disp, truth, mask):
    m = mask & np.isfinite(disp) & np.isfinite(truth)
    return float(np.abs(disp[m] - truth[m]).mean()), int(m.sum())


@pytest.mark.slow
def test_moved_fruit_are_compensated(motion_datasets, motion_session):
    """Scene 000: each moved fruit's estimated motion within its covariance of the truth (squared Mahalanobis
    distance under chi-square(6)'s 99.9 % bound), the still fruit judged still; the rebuilt ground truth on the fruit
    within 0.01 px of the truth at the ZED's exposure (under 0.15 of the uncompensated error); it
    says so in meta.json, verification.json/html (before/after overlays), the manifest, the lists, the build report,
    and the sigma map (the motion's covariance on the moved fruit only)."""
    on, off, _ = motion_datasets
    out, out_off = on.out_dir, off.out_dir
    assert on.compensated == ["000"] and "000" not in on.flagged
    meta = SceneMeta.read(out / "scenes" / "000" / "meta.json")
    mc = meta.verification.motion_compensation
    assert meta.verification.status == "ok" and mc.status == "compensated" and mc.before.status == "flagged"
    z = np.load(motion_session / "truth" / "scene_000.npz")
    T_zed_moved_from_zed_true = z["fruit_T_zed_moved_from_zed"]
    before = [transform_points(invert_T(T_zed_moved_from_zed), c[None])[0]
              for T_zed_moved_from_zed, c in zip(T_zed_moved_from_zed_true, z["fruit_centre_zed_mm"])]
    status = {}
    for f in mc.fruit:
        j = int(np.argmin([np.linalg.norm(b - f.centre_zed_mm) for b in before]))
        status[j] = f.status
        e = FruitMotionEstimate(np.array(f.centre_zed_mm), np.radians(f.rotvec_deg), np.array(f.translation_mm),
                                np.array(f.cov_rad_mm), f.n_pixels, 0, True, 0.0, None, np.zeros((0, 3)))
        assert e.mahalanobis_sq(T_zed_moved_from_zed_true[j]) < CHI2_6_999, (j, f)
        if j != 1:  # the motion recovered to a fraction of itself
            assert np.linalg.norm(np.array(f.translation_mm)
                                  - e.params_from_T(T_zed_moved_from_zed_true[j])[3:]) < 0.25, f
    assert status == {0: "moved", 1: "still", 2: "moved"}
    truth = z["zed_disparity_px"]
    fruit_truth = z["fruit_mask"]
    d_on, d_off = read_pfm(out / "scenes" / "000" / "disp0GT.pfm"), read_pfm(out_off / "scenes" / "000" / "disp0GT.pfm")
    e_on, n_on = _epe(d_on, truth, fruit_truth)
    e_off, n_off = _epe(d_off, truth, fruit_truth)
    assert e_on < 0.15 * e_off and e_on < 0.01 and n_on > 0.97 * n_off, (e_on, e_off, n_on, n_off)
    # the lists, the manifest, the reports
    assert (out / "filenames" / "compensated.txt").read_text() == "000\n"
    assert Manifest.read(out / "manifest.json").compensated == ["000"]
    rep = VerificationResult.read(out / "verification.json")
    assert rep.scenes["000"].compensated and not rep.scenes["001"].compensated
    html = (out / "verification.html").read_text()
    assert "verification/000_motion_before.jpg" in html and "verification/000_motion_after.jpg" in html
    assert (out / "verification" / "000_motion_before.jpg").exists() and "compensated" in html
    f = rep.scenes["000"].motion_compensation.fruit[0]  # sigmas unsigned, the motion signed
    assert " / ".join(f"{a:.3f}" for a in f.sigma_translation_mm) in html and " / ".join(
        f"{a:+.3f}" for a in f.translation_mm) in html
    assert "compensated" in (out / "build_report.html").read_text()
    # sigma: larger on the fruit by the motion's share; on the table (whose sigma follows the texture shift
    # verification measures, here the rebuilt scene's) the same within 1 %
    s_on, s_off = (read_pfm(d / "scenes" / "000" / "disp0GT_sigma.pfm") for d in (out, out_off))
    r_on, r_off = (read_image(d / "scenes" / "000" / "region.png") for d in (out, out_off))
    fr, far = (r_on >= 2) & (r_off >= 2), _far_from_fruit(r_on, r_off)
    assert np.median(s_on[fr]) > 1.2 * np.median(s_off[fr]) and far.sum() > 10000
    np.testing.assert_allclose(s_on[far], s_off[far], rtol=0.01)
    # gtforge verify on the dataset: the compensated scene stays verified (its fruit seen where they moved to)
    rep = verify_dataset(out, scenes=["000"], workers=1)
    assert rep.scenes["000"].status == "ok" and rep.scenes["000"].compensated, rep.scenes["000"].reasons



@pytest.mark.slow
def test_too_uncertain_fruit_lose_their_ground_truth(motion_session, motion_datasets, tmp_path):
    """A moved fruit whose motion's disparity sigma exceeds ``MotionParams.max_sigma_px`` is not compensated, and the
    scene is not lost for it: that fruit's pixels become holes (no disparity, not non-occluded; still fruit in
    the fruit mask; region.png 0, as wherever there is no ground truth) with the reason per fruit, while the rest is
    compensated. With the bound below every moved fruit's
    sigma: both moved fruit of scene 000 are holes where the ZED saw them, the still fruit keeps the disparity it had
    (the same reprojection of its points), the scene verifies ok."""
    s = open_session(motion_session)
    truth = SyntheticTruth.read(motion_session / "truth" / "rig_truth.yaml")
    rig = Rig(zed=s.zed, mech=s.mech, T_zed_from_mech=truth.T_zed_from_mech)
    cap = s.load_capture(s.root / "scenes" / "000")
    params = BuildParams(motion=MotionParams(max_sigma_px=1e-4))
    sd, region, fruit = build_scene_arrays(cap.depth_mm, rig, params, None)
    ch = verify_and_compensate(cap.depth_mm, rig, params, sd, region, fruit, cap.zed_left, cap.zed_right,
                               cap.mech_texture)
    mc = ch.verification.motion_compensation
    assert ch.verification.status == "ok" and mc.status == "compensated", mc.reasons
    assert ch.verification.compensated_label == " (fruit motion compensated; 2 fruit too uncertain: no ground truth)"
    assert sorted(f.status for f in mc.fruit) == ["no ground truth", "no ground truth", "still"], mc.fruit
    assert all("no ground truth (holes)" in f.reason and f.disparity_sigma_px > 1e-4
               for f in mc.fruit if f.status == "no ground truth")
    z = np.load(motion_session / "truth" / "scene_000.npz")
    fm = z["fruit_mask"]
    v, u = np.nonzero(fm)
    P = rig.zed.left.unproject(np.stack([u, v], 1), z["zed_depth_mm"][v, u])
    who = np.argmin(np.linalg.norm(P[:, None] - z["fruit_centre_zed_mm"][None], axis=2), axis=1)
    inner = cv2.erode(fm.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)[v, u]
    for j in (0, 2):  # the moved fruit, where the ZED saw them (to their limb: the ring): holes, fruit in the mask
        vj, uj = v[who == j], u[who == j]
        assert len(vj) > 1000 and np.isnan(ch.sd.disparity_px[vj, uj]).all() and not ch.sd.nonoccluded[vj, uj].any()
        assert ch.fruit[v[(who == j) & inner], u[(who == j) & inner]].mean() > 0.99
    # region.png and weight.tiff: 0 exactly where disp0GT has no value (the holes and the ring around moved fruit)
    assert np.array_equal(ch.region == 0, np.isnan(ch.sd.disparity_px))
    v, u, who = v[inner], u[inner], who[inner]
    vs, us = v[who == 1], u[who == 1]
    d0, d1 = sd.disparity_px[vs, us], ch.sd.disparity_px[vs, us]
    assert len(vs) > 1000 and np.isfinite(d1).mean() > 0.99
    np.testing.assert_array_equal(d1[np.isfinite(d1)], d0[np.isfinite(d1)])
    # build-dataset and gtforge verify: the scene compensated, its reports say how many fruit have no ground truth
    out = build_dataset(motion_session, motion_datasets[2], tmp_path / "out", params, workers=1, scenes=["000"]).out_dir
    written = read_pfm(out / "scenes" / "000" / "disp0GT.pfm")
    assert np.array_equal(np.isfinite(written), np.isfinite(ch.sd.disparity_px))
    weight = tifffile.imread(out / "scenes" / "000" / "weight.tiff")
    assert np.array_equal(weight > 0, np.isfinite(written))  # docs/dataset-format.md: weight 0 where no GT
    rep = verify_dataset(out, scenes=["000"], workers=1)
    label = " (fruit motion compensated; 2 fruit too uncertain: no ground truth)"
    assert rep.scenes["000"].status == "ok" and rep.scenes["000"].compensated_label == label, rep.scenes["000"].reasons
    assert "ok" + label in (out / "verification.html").read_text() and "no ground truth (holes)" in \
        (out / "verification.html").read_text() and "ok" + label in (out / "build_report.html").read_text()

def _far_from_fruit(*regions):
    near = np.zeros(regions[0].shape, bool)
    for r in regions:
        near |= _dilate(r >= 2, 12)
    return ~near & (regions[0] == 1) & (regions[1] == 1)


@pytest.mark.slow
def test_unmoved_scene_is_unchanged_by_the_feature(dataset, session_dir, true_calibration, tmp_path):
    """A scene verification does not flag (the shared dataset, built with motion compensation on, the default): the
    same files when built without it, byte for byte; no motion_compensation record, no list of compensated scenes."""
    out, _ = dataset
    off = build_dataset(session_dir, true_calibration, tmp_path / "off",
                        BuildParams(motion=MotionParams(compensate=False)), workers=1, scenes=["001"])
    a, b = out / "scenes" / "001", off.out_dir / "scenes" / "001"
    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir()) and "disp0GT.pfm" in names
    for n in names:
        if n != "meta.json":  # (its times differ)
            assert (a / n).read_bytes() == (b / n).read_bytes(), n
    ma, mb = (json.loads((d / "meta.json").read_text()) for d in (a, b))
    assert ma["verification"] == mb["verification"] and ma["verification"]["motion_compensation"] is None
    assert ma["stats"] == mb["stats"] and ma["sigma"] == mb["sigma"]
    # the same params_hash: a resumed build with compensation toggled keeps the scene (the test below)
    assert ma["params_hash"] == mb["params_hash"]
    assert not (out / "filenames" / "compensated.txt").exists()
    assert Manifest.read(out / "manifest.json").compensated == []


def test_toggling_compensation_rebuilds_only_the_scenes_whose_fruit_moved(dataset, session_dir, true_calibration,
                                                                           motion_datasets, motion_session, tmp_path):
    """A resumed build with compensation off (or other motion limits) rebuilds only the scenes whose verification
    suspected fruit motion, the only files the setting changes: the shared dataset's scenes (none suspected) are kept;
    the motion session's two are rebuilt, as a fresh build without compensation writes them; turned on again, they
    are rebuilt again."""
    out, first = dataset
    kept = tmp_path / "kept"
    shutil.copytree(out, kept)
    before = {p: p.read_bytes() for p in (kept / "scenes").rglob("*") if p.is_file()}
    off = build_dataset(session_dir, true_calibration, kept, BuildParams(motion=MotionParams(compensate=False)),
                        workers=1)
    assert off.built == [] and sorted(off.skipped_unchanged) == sorted(first.built), off
    assert {p: p.read_bytes() for p in (kept / "scenes").rglob("*") if p.is_file()} == before
    other = build_dataset(session_dir, true_calibration, kept, BuildParams(motion=MotionParams(max_sigma_px=0.05)),
                          workers=1)
    assert other.built == []

    on, fresh_off, calib = motion_datasets
    moved = tmp_path / "moved"
    shutil.copytree(on.out_dir, moved)
    res = build_dataset(motion_session, calib, moved, BuildParams(motion=MotionParams(compensate=False)), workers=1)
    assert sorted(res.built) == ["000", "001"] and res.compensated == [], res
    a, b = moved / "scenes" / "000", fresh_off.out_dir / "scenes" / "000"
    for f in sorted(p.name for p in b.iterdir()):
        if f != "meta.json":
            assert (a / f).read_bytes() == (b / f).read_bytes(), f
    ma, mb = (json.loads((d / "meta.json").read_text()) for d in (a, b))
    assert ma["verification"] == mb["verification"] and ma["params_hash"] == mb["params_hash"]
    again = build_dataset(motion_session, calib, moved, BuildParams(motion=MotionParams(max_sigma_px=0.02)),
                          workers=1)
    assert sorted(again.built) == ["000", "001"] and again.compensated == on.compensated


@pytest.mark.slow
def test_motion_beyond_the_limits_stays_flagged(motion_datasets):
    """A melon rolled 14 mm and turned 4 deg: never rebuilt (the ZED sees surface the depth camera never saw); the
    scene stays flagged with the reason, its ground truth as built."""
    on, _, _ = motion_datasets
    assert "001" in on.flagged and "001" not in on.compensated
    meta = SceneMeta.read(on.out_dir / "scenes" / "001" / "meta.json")
    mc = meta.verification.motion_compensation
    assert mc.status == "not compensated" and mc.before is None
    assert any("beyond limit" in r for r in mc.reasons), mc.reasons
    assert any(r.startswith("fruit motion not compensated: ") for r in meta.verification.reasons)
    assert [f.status for f in mc.fruit if f.status == "beyond limit"]


def test_motion_record_round_trips_and_old_files_are_refused(tmp_path):
    """meta.json of schema 3 carries the record; a schema-2 verification.json is refused with the version named."""
    from gtforge.errors import InputError
    from gtforge.records.verification import FruitMotion, MotionCompensation, SceneVerification, VerifyParams

    v = SceneVerification(status="ok", motion_compensation=MotionCompensation(
        status="compensated", fruit=[FruitMotion(component=1, status="moved", translation_mm=[1.0, 0.0, 0.0],
                                                 T_zed_moved_from_zed=make_T(np.eye(3), [1.0, 0, 0]).tolist())],
        before=SceneVerification(status="flagged", reasons=["texture shift over the fruit 0.40 px > 0.25 px"])))
    rep = VerificationResult(dataset_dir=str(tmp_path), params=VerifyParams(), scenes={"000": v})
    rep.write(tmp_path / "verification.json")
    back = VerificationResult.read(tmp_path / "verification.json")
    assert back == rep and back.scenes["000"].compensated and back.schema_version == 3
    d = json.loads((tmp_path / "verification.json").read_text())
    d["schema_version"] = 2
    (tmp_path / "verification.json").write_text(json.dumps(d))
    with pytest.raises(InputError, match="schema_version 2 is not supported"):
        VerificationResult.read(tmp_path / "verification.json")
    shutil.rmtree(tmp_path)


def test_synth_moves_the_last_scenes_fruit(tmp_path):
    """`gtforge synth --moved-fruit-mm 2`: the last scene holds four fruit, three moved by 2 mm and 1.33 deg (one
    partly out of the depth camera's view), one still, with each one's exact motion in truth/; without scenes, a
    one-line error."""
    from typer.testing import CliRunner

    from gtforge.cli.commands import app
    from gtforge.errors import InputError

    r = CliRunner().invoke(app, ["synth", str(tmp_path / "s"), "--boards", "0", "--scenes", "1", "--scale", "0.1",
                                 "--moved-fruit-mm", "2"])
    assert r.exit_code == 0, r.output
    z = np.load(tmp_path / "s" / "truth" / "scene_000.npz")
    np.testing.assert_allclose(np.linalg.norm(z["fruit_motion_translation_mm"], axis=1), [2, 0, 2, 2], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(z["fruit_motion_rotvec_deg"], axis=1), [4 / 3, 0, 4 / 3, 4 / 3],
                               atol=1e-12)
    assert z["fruit_T_zed_moved_from_zed"].shape == (4, 4, 4) and np.allclose(z["fruit_T_zed_moved_from_zed"][1],
                                                                             np.eye(4), atol=1e-9)
    r = CliRunner().invoke(app, ["synth", str(tmp_path / "t"), "--boards", "0", "--scenes", "0",
                                 "--moved-fruit-mm", "2"])
    assert isinstance(r.exception, InputError) and "--moved-fruit-mm" in str(r.exception)
