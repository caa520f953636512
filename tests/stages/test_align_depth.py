"""gtforge align-depth (gtforge.align_depth, gtforge.core.alignment.edge_alignment.align_captures): a separate depth
camera's pose refined from every capture's edges together.

Exact truth: gtforge.synthetic's two-camera rig (the depth camera 45 mm beside the texture camera) with session.yaml's
T_mech_from_depth turned by POSE_ERROR_DEG (0.97 deg about a diagonal axis: the depth edges lie (+6.8, +5.6) px off the
texture's edges), one board and three scenes at 0.3x. The correction is recovered within 2 sigma on each axis and the
labels' EPE returns to the exact pose's figure. Bad input: one-line errors, or a capture left out / flagged with the
reason.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gtforge.align_depth import align_depth, summary_lines
from gtforge.core.camera import Rig, ScaleCorrections
from gtforge.core.alignment.edge_alignment import EdgeAlignmentParams, EdgeCapture, align_captures
from gtforge.core.geometry import perturb_left, pose_difference
from gtforge.core.zed.scale_corrections import depth_pose_jacobian_image, depth_pose_sigma_px
from gtforge.dataset.ground_truth import build_scene_arrays
from gtforge.errors import InputError
from gtforge.io.formats import write_png16
from gtforge.io.captures import open_session
from gtforge.records.calibration import CalibrationFile, RefinementInfo
from gtforge.records.dataset import BuildParams
from gtforge.synthetic import SyntheticTruth, generate_session, two_camera_rig

pytestmark = pytest.mark.slow  # one synthetic two-camera session (~12 s), shared by the module

POSE_ERROR_DEG = (0.6, -0.7, 0.3)
SCALE = 0.3


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("align_depth") / "s"
    generate_session(d, n_board=1, n_scenes=3, scale=SCALE, seed=5, supersample=1, two_camera=True,
                     depth_pose_error_deg=POSE_ERROR_DEG)
    return d


def _calibration(session: Path, out: Path, T_mech_from_depth: np.ndarray | None = None) -> Path:
    """A calibration with the exact extrinsic and the session's (factory) depth camera pose, or the one given."""
    s = open_session(session)
    tr = SyntheticTruth.read(session / "truth" / "rig_truth.yaml")
    T_mech_from_depth = s.T_mech_from_depth if T_mech_from_depth is None else T_mech_from_depth
    rig = Rig(zed=s.zed, mech=s.mech, depth_cam=s.depth_cam, T_mech_from_depth=T_mech_from_depth,
              T_zed_from_mech=np.array(tr.T_zed_from_mech))
    return CalibrationFile.known_extrinsic(rig).write(out)


def _epe(session: Path, rig: Rig) -> list[float]:
    """Per scene (the first two): mean |GT - the exact disparity| (px) over the pixels the texture camera saw."""
    s = open_session(session)
    out = []
    for d in s.select("scenes", None)[:2]:
        cap = s.load_capture(d)
        sd, _, _ = build_scene_arrays(cap.depth_mm, rig, BuildParams(), cap.fruit_mask)
        t = np.load(session / "truth" / f"scene_{d.name}.npz")
        m = np.isfinite(sd.disparity_px) & np.isfinite(t["zed_disparity_px"]) & t["seen_by_mech"] & sd.nonoccluded
        out.append(float(np.mean(np.abs(sd.disparity_px[m] - t["zed_disparity_px"][m]))))
    return out


@pytest.fixture(scope="module")
def aligned(session, tmp_path_factory):
    d = tmp_path_factory.mktemp("aligned")
    start = _calibration(session, d / "start.yaml")
    return start, align_depth(session, start, d / "aligned.yaml"), d / "aligned.yaml"


def test_a_diagonal_one_degree_error_is_recovered(session, aligned):
    start, res, path = aligned
    info = res.depth_alignment
    r = info.result
    assert r.decision == "applied" and r.search_interior and r.search_px > 6  # the first +-6 px grid was too small
    truth = -np.array(POSE_ERROR_DEG)
    est, sig = np.array(r.omega_deg), np.array(r.sigma_omega_deg)
    # the session's captures have the depth camera's own image (IR.png): its edges join the silhouettes'; measured
    # (-0.6008, +0.7015, -0.3017) +- (0.0056, 0.0056, 0.0060) deg against (-0.6, +0.7, -0.3)
    assert r.edge_kinds == ["silhouettes", "texture"] and "(IR.png)" in info.method
    assert np.all(np.abs(est - truth) <= 2 * sig), (est, sig)
    assert r.status[:2] == ["determined", "determined"] and r.status[2] in ("determined", "estimated")
    # the pixel offsets: (+6.81, +5.61) px before, (+0.01, -0.00) after; every capture within 0.3 px after
    assert np.hypot(*r.offset_before_px) > 5 and np.hypot(*r.offset_after_px) < 0.1
    assert len(r.captures) == 4 and not any(c.disagrees or c.excluded for c in r.captures)
    assert all(np.hypot(*c.offset_before_px) > 5 and np.hypot(*c.offset_after_px) < 0.3 for c in r.captures)
    # written: the corrected pose in the rig, the file's kept, the covariance of the applied rotation (rad)
    back = CalibrationFile.read(path)
    T_mech_from_depth_file = np.array(back.depth_alignment.T_mech_from_depth_file)
    np.testing.assert_allclose(back.rig.T_mech_from_depth,
                               perturb_left(T_mech_from_depth_file, np.r_[np.radians(est), 0, 0, 0]), atol=1e-9)
    C = np.array(back.depth_alignment.result.covariance_rad_mm)
    np.testing.assert_allclose(np.degrees(np.sqrt(np.diag(C)[:3])), sig, rtol=1e-9)
    assert "applied" in summary_lines(back.depth_alignment)[0]
    # the labels' EPE: measured 0.26 px with the factory pose, 0.0012 after, 0.001 with the exact pose
    true_T = two_camera_rig(SCALE).T_mech_from_depth
    exact = _epe(session, CalibrationFile.read(_calibration(session, path.parent / "exact.yaml", true_T)).rig)
    before, after = _epe(session, CalibrationFile.read(start).rig), _epe(session, back.rig)
    assert min(before) > 0.2 and max(abs(a - e) for a, e in zip(after, exact)) < 0.005, (before, after, exact)


def test_the_depth_cameras_own_image_sharpens_the_pose(session, aligned, tmp_path):
    """The silhouettes alone (--edges silhouettes: what align-depth used before it read IR.png) against the
    silhouettes and the infrared image's edges: the roll, which a few silhouettes barely determine, is found ten
    times better, and the pose lands ten times nearer the truth. Measured: 0.032 -> 0.0024 deg from the true pose,
    roll sigma 0.075 -> 0.006 deg. Without IR.png --edges texture is refused naming the file; an IR.png that is not
    on the depth grid too."""
    import shutil

    start, res, _ = aligned
    truth = two_camera_rig(SCALE).T_mech_from_depth
    sil = align_depth(session, start, None, EdgeAlignmentParams(edges="silhouettes"))
    r_sil, r_both = sil.depth_alignment.result, res.depth_alignment.result
    assert r_sil.edge_kinds == ["silhouettes"] and "IR.png" not in sil.depth_alignment.method
    off = {k: pose_difference(np.array(c.rig.T_mech_from_depth), truth)[0] for k, c in (("sil", sil), ("both", res))}
    assert off["both"] < 0.01 and off["sil"] > 2 * off["both"], off
    assert r_both.sigma_omega_deg[2] < 0.02 < 0.05 < r_sil.sigma_omega_deg[2], (r_both.sigma_omega_deg,
                                                                                r_sil.sigma_omega_deg)
    copy = tmp_path / "s"
    shutil.copytree(session, copy, ignore=shutil.ignore_patterns("truth"))
    ir = copy / "scenes" / "001" / "IR.png"
    ir.unlink()
    with pytest.raises(InputError) as err:
        align_depth(copy, start, None, EdgeAlignmentParams(edges="texture"))
    assert str(err.value).startswith(f"{ir}: expected the depth camera's own image for --edges texture, got no such")
    # auto, capture by capture: a capture without the image gives its silhouettes alone
    r = align_depth(copy, start, None, captures=["001"], use_boards=False).depth_alignment.result
    assert r.edge_kinds == ["silhouettes"]
    write_png16(ir, np.zeros((10, 12), np.uint16))
    with pytest.raises(InputError, match=r"IR.png \[size\]: expected \d+x\d+ px \(the depth map's"):
        align_depth(copy, start, None)


def test_the_sigma_map_carries_the_rotations_covariance(session, aligned):
    _, res, _ = aligned
    s = open_session(session)
    cap = s.load_capture(s.select("scenes", None)[0])
    sd, _, _ = build_scene_arrays(cap.depth_mm, res.rig, BuildParams(), cap.fruit_mask)
    m = np.isfinite(sd.disparity_px)
    C = np.array(res.depth_alignment.result.covariance_rad_mm)
    got = depth_pose_sigma_px(sd.depth_mm, res.rig, C)[m]
    J = depth_pose_jacobian_image(sd.depth_mm, res.rig)[m]
    np.testing.assert_allclose(got, np.sqrt(np.einsum("ni,ij,nj->n", J, C[:3, :3], J)), rtol=1e-9)
    assert 0.001 < np.median(got) < 0.2


def test_the_exact_pose_is_kept(session, tmp_path):
    """With the true pose in the calibration the correction is not significant and the pose is kept. (The fruits'
    silhouettes lie 0.4-0.5 px right of their colour edges at the exact pose, the board's on them: a curved object's
    limb, seen from two viewpoints, meshed from a grazing depth. It is what edge_bias_px and apply_z = 3 are for.)"""
    true_T = two_camera_rig(SCALE).T_mech_from_depth
    start = _calibration(session, tmp_path / "exact.yaml", true_T)
    r = align_depth(session, start, params=EdgeAlignmentParams(edges="silhouettes")).depth_alignment.result
    assert r.search_px == 6 and np.hypot(*r.offset_before_px) < 0.3  # measured (+0.21, -0.06) px
    assert r.decision == "not significant" and r.significance_sigma < 3, r
    np.testing.assert_array_equal(r.T_color_from_depth, true_T)
    assert np.all(np.abs(r.omega_deg) <= 2 * np.array(r.sigma_omega_deg)), (r.omega_deg, r.sigma_omega_deg)


def _captures(session: Path):
    s = open_session(session)
    caps = [s.load_capture(d, need_right=False) for d in s.select("board", None) + s.select("scenes", None)]
    return s, [EdgeCapture(c.folder.name + str(i), c.depth_mm, s.depth_camera, c.mech_texture)
               for i, c in enumerate(caps)]


def test_a_knocked_capture_shows(session):
    """One capture's depth shifted by 4 depth pixels (the rig knocked between captures): flagged, left out of the
    fit with the reason and its offset; the others then fit alone and stay within 0.3 px."""
    s, caps = _captures(session)
    caps[2].depth_mm = np.roll(caps[2].depth_mm, 4, axis=1)
    r = align_captures(caps, s.mech, s.T_mech_from_depth)
    flagged = [c.name for c in r.captures if c.disagrees]
    assert flagged == [caps[2].name] and any(caps[2].name in w for w in r.warnings)
    # left out of the fit, which the other three then make alone: they land within 0.3 px, it stays ~6 px off
    knocked = r.captures[2]
    assert "left out of the fit" in knocked.excluded and np.hypot(*knocked.offset_after_px) > 3
    assert all(np.hypot(*c.offset_after_px) < 0.3 for c in r.captures if c is not knocked)
    assert r.decision == "applied" and len(r.captures) == 4


def test_bad_input(session, tmp_path):
    s, caps = _captures(session)
    # a blank colour image: refused alone, left out (with the reason) among others
    blank = EdgeCapture("blank", caps[1].depth_mm, s.depth_camera, np.full_like(caps[1].color_rgb, 90))
    with pytest.raises(InputError, match="blank"):
        align_captures([blank], s.mech, s.T_mech_from_depth)
    r = align_captures([blank] + caps[1:], s.mech, s.T_mech_from_depth, EdgeAlignmentParams())
    assert "blank" in r.captures[0].excluded and r.decision == "applied"
    # a depth map of another size than its intrinsics
    small = EdgeCapture("small", caps[1].depth_mm[:-4], s.depth_camera, caps[1].color_rgb)
    with pytest.raises(InputError, match="depth map of capture small"):
        align_captures([small], s.mech, s.T_mech_from_depth)
    # too few edges: a flat depth map
    flat = EdgeCapture("flat", np.full_like(caps[1].depth_mm, 700.0), s.depth_camera, caps[1].color_rgb)
    with pytest.raises(InputError, match="depth edges"):
        align_captures([flat], s.mech, s.T_mech_from_depth)
    # a one-camera rig, and the input calibration as the output
    start = _calibration(session, tmp_path / "start.yaml")
    one = CalibrationFile.read(start)
    one = one.model_copy(update={"rig": Rig.model_validate({**one.rig.model_dump(), "depth_cam": None,
                                                              "T_mech_from_depth": None})})
    with pytest.raises(InputError):
        align_depth(session, one.write(tmp_path / "one.yaml"))
    with pytest.raises(InputError, match="input calibration"):
        align_depth(session, start, start)
    # a calibration calibrate-scale or refine made: they estimated through the depth camera's pose it would change
    c = CalibrationFile.read(start)
    scaled = c.model_copy(update={"rig": c.rig.model_copy(update={"scale_corrections": ScaleCorrections()})})
    refined = c.model_copy(update={"refinement": RefinementInfo(refined_from="a.yaml", scenes_used=["000"],
                                                                change_rot_deg=0.0, change_trans_mm=0.0)})
    for name, made, field in (("scaled", scaled, "scale_calibration"), ("refined", refined, "refinement")):
        stage = {"scaled": "calibrate-scale", "refined": "refine"}[name]
        with pytest.raises(InputError, match=rf"{name}.yaml \[{field}\]: expected a calibration from before {stage} "
                                             rf".*got one {stage} wrote.*run align-depth on the calibration calibrate "
                                             rf"wrote"):
            align_depth(session, made.write(tmp_path / f"{name}.yaml"), tmp_path / "out.yaml")
        assert not (tmp_path / "out.yaml").exists()


def test_the_command(session, tmp_path, monkeypatch, capsys):
    import sys

    from gtforge.cli import main

    start = _calibration(session, tmp_path / "start.yaml")
    for args, code in (([str(tmp_path / "a.yaml"), "--scenes", "000"], 0), ([str(start)], 2),
                       ([str(tmp_path / "b.yaml"), "--max-scenes", "2"], 0)):
        monkeypatch.setattr(sys, "argv", ["gtforge", "align-depth", str(session), "-c", str(start), "-o"] + args)
        with pytest.raises(SystemExit) as e:
            main()
        assert e.value.code == code
    cap = capsys.readouterr()
    assert "edge offset (colour - depth) all captures: before" in cap.out and (tmp_path / "a.yaml").is_file()
    # the page: the decision, the offsets before and after (all captures and per capture), each rotation
    info = CalibrationFile.read(tmp_path / "a.yaml").depth_alignment
    page = (tmp_path / "a_report.html").read_text()
    r = info.result
    assert r.decision in page and "omega_x" in page and "scenes/000" in page
    assert f"{r.offset_before_px[0]:+.2f}" in page and f"{r.offset_after_px[1]:+.2f}" in page
    assert cap.err.strip().startswith("error:") and len(cap.err.strip().splitlines()) == 1
    # --max-scenes 2 (EdgeAlignmentParams.max_scenes): of the 3 scenes the first and the last, beside the board
    two = CalibrationFile.read(tmp_path / "b.yaml").depth_alignment
    assert [c.name for c in two.result.captures] == ["board/000", "scenes/000", "scenes/002"]
    assert two.scenes_not_selected == 1 and info.scenes_not_selected == 0 and two.params.max_scenes == 2
    assert "  1 more scene(s) of the session not used (--max-scenes: those used evenly spread)" in cap.out


def test_build_dataset_adds_the_rotations_sigma(session, aligned, tmp_path):
    """build-dataset with the aligned calibration: disp0GT_sigma.pfm is the one without ``depth_alignment`` (same rig)
    with ``depth_pose_sigma_px`` added in quadrature."""
    from gtforge.build_dataset import build_dataset
    from gtforge.io.formats import read_pfm

    _, res, path = aligned
    plain = res.model_copy(update={"depth_alignment": None}).write(tmp_path / "plain.yaml")
    params = BuildParams(verification=False, right_gt=False)
    sig = {}
    for name, calib in (("aligned", path), ("plain", plain)):
        build_dataset(session, calib, tmp_path / name, params, workers=1, scenes=["000"])
        sig[name] = read_pfm(tmp_path / name / "scenes" / "000" / "disp0GT_sigma.pfm").astype(np.float64)
    m = np.isfinite(sig["plain"])
    assert np.all(sig["aligned"][m] >= sig["plain"][m] - 1e-6) and np.median(sig["aligned"][m] - sig["plain"][m]) > 0


def test_run_aligns_the_depth_camera_and_certifies_it(session, aligned, tmp_path):
    """gtforge run on a two-camera session: align-depth runs after calibrate (here the calibration is given with -c)
    and every later stage reads aligned.yaml; its figures are in the certificate; a rerun redoes nothing; on a
    one-camera session the stage does not apply."""
    from gtforge.records.run import RunState
    from gtforge.run import RunOptions, run_session

    import shutil

    start = aligned[0]
    small = tmp_path / "s"  # the board and one scene (the stages after align-depth on one scene: time)
    shutil.copytree(session, small, ignore=shutil.ignore_patterns("001", "002"))
    said: list[str] = []
    opts = RunOptions(calibration=str(start), loo=False, workers=1, refine=False)
    run = run_session(small, tmp_path / "run", opts, say=said.append)
    assert run.redone[0] == "align-depth" and "calibrate-scale" in run.redone, said
    st = RunState.read(tmp_path / "run" / "run_state.json").stages
    assert st["align-depth"].status == "done" and st["align-depth"].verdict == "PASS"
    back = CalibrationFile.read(tmp_path / "run" / "aligned.yaml")
    r = back.depth_alignment.result  # the correction within 2 sigma of the truth
    assert np.all(np.abs(np.array(r.omega_deg) + POSE_ERROR_DEG) <= 2 * np.array(r.sigma_omega_deg)), r
    assert "out/aligned.yaml" in st["validate"].inputs or "out/aligned.yaml" in st["calibrate-scale"].inputs
    assert (tmp_path / "run" / "aligned_report.html").is_file()
    sec = next(s for s in run.certificate.sections if s.title == "Depth camera pose (align-depth)")
    fig = {f.name: f for f in sec.figures}
    assert fig["decision"].value == "applied" and fig["omega_y correction"].source_file == "aligned.yaml"
    assert fig["omega_y correction"].value == pytest.approx(r.omega_deg[1], abs=1e-9)
    assert "edges: silhouettes and texture" in sec.notes
    assert "Depth camera pose (align-depth)" in (tmp_path / "run" / "index.html").read_text()
    said = []
    assert run_session(small, tmp_path / "run", opts, say=said.append).redone == [], said
