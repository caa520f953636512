import json
import os
import shutil

import numpy as np
import pytest

from gtforge.build_dataset import build_dataset
from gtforge.dataset.views import make_splits
from gtforge.errors import InputError
from gtforge.io.formats import read_image, read_kitti_disparity, read_pfm, write_tiff_float
from gtforge.records.dataset import BuildParams, Manifest


@pytest.mark.slow
def test_dataset_matches_exact_truth(session_dir, dataset):
    out, summary = dataset
    assert summary.ok and summary.built == ["000", "001", "002"]
    for sid in summary.built:
        tr = np.load(session_dir / "truth" / f"scene_{sid}.npz")
        s = out / "scenes" / sid
        gt = read_pfm(s / "disp0GT.pfm")
        seen = tr["seen_by_mech"]
        ok = np.isfinite(gt)
        assert ok[seen].mean() >= 0.995
        err = np.abs(gt - tr["zed_disparity_px"])
        assert np.mean(err[seen & ok]) < 0.01
        assert np.mean(err[ok] > 1.0) < 0.0005
        # masks and regions
        mask = read_image(s / "mask0nocc.png")
        assert set(np.unique(mask)) <= {0, 128, 255}
        np.testing.assert_array_equal(mask > 0, ok)
        region = read_image(s / "region.png")
        np.testing.assert_array_equal(region > 0, ok)
        fruit = (region >= 2) & ok
        truth_fruit = tr["fruit_mask"] & ok
        iou = (fruit & truth_fruit).sum() / (fruit | truth_fruit).sum()
        assert iou > 0.97, iou
        assert (region == 2).sum() > 0 and (region == 3).sum() > 0
        import tifffile

        w = tifffile.imread(s / "weight.tiff")
        np.testing.assert_allclose(np.unique(w), [0.0, 0.8, 1.0, 1.4], rtol=1e-6)
        # each pixel: its region's weight (none 0, background 0.8, fruit centre 1.0, fruit edge 1.4)
        np.testing.assert_array_equal(w, np.array([0.0, 0.8, 1.0, 1.4], np.float32)[region])
        depth = tifffile.imread(s / "depth0.tiff")
        assert depth.dtype == np.float32
        np.testing.assert_array_equal(np.isfinite(depth), ok)
        calib = (s / "calib.txt").read_text()
        for key in ("cam0=", "cam1=", "doffs=", "baseline=63.0", "width=883", "height=497", "ndisp=", "vmin=", "vmax="):
            assert key in calib
        # KITTI view round-trips within 1/512 px
        k = read_kitti_disparity(out / "kitti" / "training" / "disp_occ_0" / f"{sid}_10.png")
        np.testing.assert_array_equal(np.isfinite(k), ok)
        assert np.nanmax(np.abs(k - gt)) <= 0.5 / 256 + 1e-6
        noc = read_kitti_disparity(out / "kitti" / "training" / "disp_noc_0" / f"{sid}_10.png")
        np.testing.assert_array_equal(np.isfinite(noc), mask == 255)
        # the right view's ground truth (Middlebury disp1 / KITTI disp_occ_1), against its own exact truth
        gt1 = read_pfm(s / "disp1GT.pfm")
        seen1, ok1 = tr["seen_by_mech_right"], np.isfinite(gt1)
        assert ok1[seen1].mean() >= 0.995
        err1 = np.abs(gt1 - tr["zed_right_disparity_px"])
        assert np.mean(err1[seen1 & ok1]) < 0.01 and np.mean(err1[ok1] > 1.0) < 0.0005
        mask1 = read_image(s / "mask1nocc.png")
        np.testing.assert_array_equal(mask1 > 0, ok1)
        assert 0 < (mask1 == 128).sum() < 0.2 * ok1.sum()  # some right pixels are hidden from the left camera
        k1 = read_kitti_disparity(out / "kitti" / "training" / "disp_occ_1" / f"{sid}_10.png")
        np.testing.assert_array_equal(np.isfinite(k1), ok1)
        assert np.nanmax(np.abs(k1 - gt1)) <= 0.5 / 256 + 1e-6
        # a right pixel's match u + d lands on the left pixel whose own disparity is the same (non-occluded)
        v, u = np.nonzero(mask1 == 255)
        ul = np.round(u + gt1[v, u]).astype(int)
        inside = ul < gt.shape[1]
        assert np.nanmedian(np.abs(gt[v[inside], ul[inside]] - gt1[v[inside], u[inside]])) < 0.05
        assert (out / "eth3d" / "two_view_training" / sid / "im0.png").exists()
        assert (out / "eth3d" / "two_view_training_gt" / sid / "disp0GT.pfm").exists()


@pytest.mark.slow
def test_manifest_and_lists(dataset):
    out, _ = dataset
    m = Manifest.read(out / "manifest.json")
    assert set(m.scenes) == {"000", "001", "002"}
    st = m.scenes["000"].stats
    assert 10 < st.valid_pct < 100 and st.disp_min_px > 0 and st.over_max_disp_pct == 0.0
    assert set(m.scenes["000"].input_blake3) == {"DepthMap.tiff", "2DImage.png", "left.png", "right.png"}
    listed = []
    for split in ("train", "val", "test"):
        lines = (out / "filenames" / f"{split}.txt").read_text().split("\n")
        for line in filter(None, lines):
            l, r, d = line.split()
            assert (out / l).exists() and (out / r).exists() and (out / d).exists()
            listed.append(l.split("/")[1])
    assert sorted(listed) == ["000", "001", "002"]
    # one fruit (scenes 000 and 001 are fruit00 in the generator) never lands in two splits
    where = {s: k for k, ids in m.splits.items() for s in ids}
    assert where["000"] == where["001"]


@pytest.mark.slow
def test_split_views_for_training_repositories(dataset):
    """views/<split>/: the folder layouts RAFT-Stereo / IGEV-Stereo read from a fixed root, as relative links."""
    out, _ = dataset
    m = Manifest.read(out / "manifest.json")
    assert any(m.splits.values())  # not a pass on empty splits: some split has views to check
    for split, ids in m.splits.items():
        v = out / "views" / split
        if not ids:
            assert not v.exists()
            continue
        midd = v / "Middlebury" / "MiddEval3"
        assert (midd / "official_train.txt").read_text().split() == ids
        for sid in ids:
            for res in "FHQ":
                link = midd / f"training{res}" / sid
                assert link.is_symlink() and not os.path.isabs(os.readlink(link))
                assert (link / "disp0GT.pfm").resolve() == (out / "scenes" / sid / "disp0GT.pfm").resolve()
            y14 = v / "Middlebury" / "2014" / sid
            assert (y14 / "im1E.png").read_bytes() == (out / "scenes" / sid / "im1.png").read_bytes()
            np.testing.assert_array_equal(read_pfm(y14 / "disp0.pfm"), read_pfm(out / "scenes" / sid / "disp0GT.pfm"))
            assert (v / "ETH3D" / "two_view_training_gt" / sid / "mask0nocc.png").exists()
            for kind in ("image_2", "image_3", "disp_occ_0", "disp_noc_0", "disp_occ_1", "disp_noc_1"):
                assert (v / "KITTI" / "training" / kind / f"{sid}_10.png").exists()
    # the dataset stays relocatable: every link is relative and resolves after a move
    moved = out.parent / (out.name + "_moved")
    shutil.copytree(out, moved, symlinks=True)
    split = next(k for k, ids in m.splits.items() if ids)
    sid = m.splits[split][0]
    assert (moved / "views" / split / "Middlebury" / "2014" / sid / "im0.png").resolve().is_relative_to(moved)
    shutil.rmtree(moved)


def test_splits_group_by_fruit():
    ids = [f"{i:03d}" for i in range(20)]
    fruit = {s: f"f{int(s) // 4}" for s in ids}
    sp = make_splits(ids, fruit, BuildParams(split_train=0.6, split_val=0.2, split_seed=3))
    assert sorted(sum(sp.values(), [])) == ids
    for f in set(fruit.values()):
        members = [s for s in ids if fruit[s] == f]
        assert len({k for k, v in sp.items() for s in members if s in v}) == 1
    assert sp == make_splits(ids, fruit, BuildParams(split_train=0.6, split_val=0.2, split_seed=3))


def test_a_moved_scene_is_named_with_what_can_move_it():
    """The warning for scenes that changed split said 'adding, removing or regrouping scenes can move others', the rule
    before the per-fruit draw; since it, only a scene's own fruit id, --split or --seed (or a build from before the
    draw) moves it (the docs run-through, session 18: regrouping one scene warned as if others could have moved)."""
    from gtforge.dataset.views import moved_between_splits, moved_splits_warning

    params = BuildParams()
    ids = [f"{k:03d}" for k in range(12)]
    before = make_splits(ids, {s: "melon0" if s in ("000", "001") else None for s in ids}, params)
    after = make_splits(ids, {s: "melon0" if s == "000" else None for s in ids}, params)  # 001 its own fruit now
    moved = moved_between_splits(before, after)
    assert set(moved) <= {"001"}  # regrouping 001 moved nothing else
    text = moved_splits_warning({"001": ("val", "train")})
    assert text.startswith("1 scene(s) changed split since the last build: 001 val -> train (")
    assert "its fruit id in session.yaml, --split or --seed changed" in text and "move others" not in text
    assert "has seen" not in text  # into train: no earlier model saw it
    assert moved_splits_warning({"001": ("val", "train"), "004": ("train", "test")}).endswith(
        "per-fruit draw; a model trained on the last build's train split has seen 004)")


def test_splits_are_stable_as_fruit_come_and_go():
    """A fruit's split is its own draw: a lab adding fruit to a session (or dropping some) never moves another fruit
    between splits, so no scene of an earlier build's train split lands in a later build's val or test. The shares
    hold over many fruit (2,000 fruit of 1-4 scenes: within 2 points of 80/10/10 % of the fruit), and the seed
    draws anew."""
    from gtforge.dataset.views import fruit_draw

    rng = np.random.default_rng(7)
    ids, fruit = [], {}
    for f in range(2000):
        for k in range(int(rng.integers(1, 5))):
            ids.append(f"{f:04d}_{k}")
            fruit[ids[-1]] = f"melon{f}"
    params = BuildParams()  # 0.8 / 0.1 / 0.1
    full = make_splits(ids, fruit, params)
    where = {s: k for k, v in full.items() for s in v}
    shares = {k: len({fruit[s] for s in v}) / 2000 for k, v in full.items()}
    assert shares["train"] == pytest.approx(0.8, abs=0.02) and shares["val"] == pytest.approx(0.1, abs=0.02), shares
    for sub in (ids[: len(ids) // 3], ids[::7], [s for s in ids if int(s[:4]) % 5 != 2]):
        part = make_splits(sub, fruit, params)
        assert {s: k for k, v in part.items() for s in v} == {s: where[s] for s in sub}
    # no fruit ids: each scene its own fruit, drawn by its id; as stable
    unnamed = make_splits(ids[:50], {}, params)
    more = make_splits(ids[:50] + ids[500:520], {}, params)
    assert unnamed == {k: [s for s in v if s in ids[:50]] for k, v in more.items()}
    assert sorted(s for v in unnamed.values() for s in v) == ids[:50]
    other = make_splits(ids, fruit, BuildParams(split_seed=1))
    assert other != full and fruit_draw("melon3", 0) != fruit_draw("melon3", 1)
    assert 0.0 <= fruit_draw("melon3", 0) < 1.0


@pytest.mark.slow
def test_resume_skips_unchanged_and_rebuilds_changed(session_dir, true_calibration, tmp_path):
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    out = tmp_path / "ds"
    s1 = build_dataset(sess, true_calibration, out, scenes=["000", "001"], workers=1)
    assert s1.built == ["000", "001"]
    # a stale half-written scene from a killed run must not count
    (out / "scenes" / ".tmp-001-999").mkdir()
    s2 = build_dataset(sess, true_calibration, out, scenes=["000", "001"], workers=1)
    assert s2.built == [] and s2.skipped_unchanged == ["000", "001"]
    assert not (out / "scenes" / ".tmp-001-999").exists()
    # change one input: only that scene is rebuilt
    d = read_image(sess / "scenes" / "001" / "left.png")
    from gtforge.io.formats import write_image

    write_image(sess / "scenes" / "001" / "left.png", 255 - d)
    s3 = build_dataset(sess, true_calibration, out, scenes=["000", "001"], workers=1)
    assert s3.built == ["001"] and s3.skipped_unchanged == ["000"]
    # only the split changed: no scene is rebuilt, the lists are rewritten
    s3b = build_dataset(sess, true_calibration, out, BuildParams(split_train=0.5, split_val=0.5, split_seed=4),
                        scenes=["000", "001"], workers=1)
    assert s3b.built == [] and s3b.skipped_unchanged == ["000", "001"]
    assert Manifest.read(out / "manifest.json").params.split_seed == 4
    # parameters changed: everything rebuilt; --overwrite forces
    s4 = build_dataset(sess, true_calibration, out, BuildParams(erosion_px=9), scenes=["000", "001"], workers=2)
    assert s4.built == ["000", "001"]
    assert build_dataset(sess, true_calibration, out, BuildParams(erosion_px=9), scenes=["000"], overwrite=True,
                         workers=1).built == ["000"]


@pytest.mark.slow
def test_no_verify_build_skips_the_image_decode_and_writes_the_same_files(session_dir, true_calibration, dataset,
                                                                         tmp_path):
    """--no-verify: the ZED PNGs and the texture are checked from their headers, not decoded (nothing else reads
    their pixels); every file that does not depend on verification is byte-identical to the default build's, and a
    truncated ZED image is still refused."""
    out = tmp_path / "ds"
    s = build_dataset(session_dir, true_calibration, out, BuildParams(verification=False), scenes=["000"], workers=1)
    assert s.built == ["000"]
    ref = dataset[0] / "scenes" / "000"
    for name in ("im0.png", "im1.png", "disp0GT.pfm", "disp1GT.pfm", "mask0nocc.png", "mask1nocc.png", "region.png",
                 "weight.tiff", "depth0.tiff", "calib.txt"):
        assert (out / "scenes" / "000" / name).read_bytes() == (ref / name).read_bytes(), name
    meta = json.loads((out / "scenes" / "000" / "meta.json").read_text())
    assert meta["verification"] is None
    # a ZED image cut short is refused exactly as a decoding build refuses it
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    right = sess / "scenes" / "001" / "right.png"
    right.write_bytes(right.read_bytes()[:-5000])
    s2 = build_dataset(sess, true_calibration, tmp_path / "ds2", BuildParams(verification=False), scenes=["001"],
                       workers=1)
    assert s2.built == [] and list(s2.failures) == ["001"]
    assert "right.png [zed_right]: expected a readable image" in s2.failures["001"]


@pytest.mark.slow
def test_bad_scene_is_reported_and_others_built(session_dir, true_calibration, tmp_path):
    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    bad = sess / "scenes" / "001" / "DepthMap.tiff"
    import tifffile

    write_tiff_float(bad, tifffile.imread(bad) / 1000.0)  # metres
    out = tmp_path / "ds"
    s = build_dataset(sess, true_calibration, out, workers=1)
    assert s.built == ["000", "002"] and list(s.failures) == ["001"]
    assert "depth_unit: m" in s.failures["001"] and "session.yaml" in s.failures["001"]
    assert not (out / "scenes" / "001").exists()
    assert "001" in json.loads((out / "manifest.json").read_text())["failures"]
    with pytest.raises(InputError, match="001"):
        build_dataset(sess, true_calibration, tmp_path / "ds2", strict=True, workers=1)
    from typer.testing import CliRunner

    from gtforge.cli.commands import app

    r = CliRunner().invoke(app, ["build-dataset", str(sess), "-c", str(true_calibration), "-o", str(out),
                                 "--workers", "1"])
    assert r.exit_code == 1 and "failed 1 (001;" in r.output and "unchanged 2" in r.output
    assert r.output.count("median 0.7") == 1  # the reason is reported once


@pytest.mark.slow
def test_crop_and_ply(session_dir, true_calibration, tmp_path):
    out = tmp_path / "ds"
    build_dataset(session_dir, true_calibration, out,
                  BuildParams(crop_wh=(320, 240), ply=True, kitti=False, eth3d=False), scenes=["000"], workers=1)
    s = out / "scenes" / "000"
    assert read_pfm(s / "disp0GT.pfm").shape == (240, 320) and read_image(s / "im0.png").shape == (240, 320, 3)
    assert "width=320" in (s / "calib.txt").read_text()
    from gtforge.io.formats import read_ply_points

    pts = read_ply_points(s / "cloud.ply")
    assert len(pts) == np.isfinite(read_pfm(s / "disp0GT.pfm")).sum()
    assert not (out / "kitti").exists()


@pytest.mark.slow
def test_kill_9_leaves_no_half_written_scene(session_dir, true_calibration, tmp_path):
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "ds"
    cmd = [sys.executable, "-m", "gtforge.cli", "build-dataset", str(session_dir), "-c", str(true_calibration),
           "-o", str(out), "--workers", "1"]
    p = subprocess.Popen(cmd, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 60

    def landed():  # pathlib's "*" also matches the hidden .tmp-<id>-<token> folder a scene is written in
        return [m for m in (out / "scenes").glob("*/meta.json") if not m.parent.name.startswith(".")]

    while time.time() < deadline and not landed():
        time.sleep(0.05)
    assert landed(), "no scene landed within 60 s"
    os.killpg(p.pid, signal.SIGKILL)  # mid-run, right after the first scene landed
    p.wait()
    files = {"im0.png", "im1.png", "disp0GT.pfm", "mask0nocc.png", "region.png", "weight.tiff", "depth0.tiff",
             "calib.txt", "meta.json", "disp1GT.pfm", "mask1nocc.png", "disp0GT_sigma.pfm"}
    for d in (out / "scenes").iterdir():
        if not d.name.startswith("."):
            assert {f.name for f in d.iterdir()} == files  # every visible scene is complete
    s = build_dataset(session_dir, true_calibration, out, workers=1)
    assert sorted(s.built + s.skipped_unchanged) == ["000", "001", "002"] and s.skipped_unchanged
    assert not list((out / "scenes").glob(".*"))


@pytest.mark.slow
def test_resume_trusts_size_and_mtime_only_when_safe(session_dir, true_calibration, tmp_path, monkeypatch):
    import time
    from pathlib import Path

    import gtforge.build_dataset as bd
    from gtforge.dataset import layout

    sess = tmp_path / "sess"
    shutil.copytree(session_dir, sess)
    cap = sess / "scenes" / "000"
    old_s = time.time() - 3600
    for f in cap.iterdir():
        os.utime(f, (old_s, old_s))
    os.utime(cap / "right.png")  # modified just now: hashed within the timestamp margin
    out = tmp_path / "ds"
    assert build_dataset(sess, true_calibration, out, scenes=["000"], workers=1).built == ["000"]
    meta = bd.SceneMeta.read(out / "scenes" / "000" / "meta.json")
    assert set(meta.input_stamps) == set(meta.input_blake3) == {"2DImage.png", "DepthMap.tiff", "left.png",
                                                                 "right.png"}
    assert meta.input_stamps["left.png"].size_bytes == (cap / "left.png").stat().st_size
    hashed = []
    real_calib, real_input = bd.sha256_file, layout.blake3_file
    monkeypatch.setattr(bd, "sha256_file", lambda p: hashed.append(Path(p).name) or real_calib(p))
    monkeypatch.setattr(layout, "blake3_file", lambda p: hashed.append(Path(p).name) or real_input(p))
    s = build_dataset(sess, true_calibration, out, scenes=["000"], workers=1)
    assert s.skipped_unchanged == ["000"]
    # size + mtime trusted for the old files; the one modified near its hash is read again
    assert sorted(hashed) == ["calibration.yaml", "right.png"]
    # touched, same content: hashed, still unchanged
    hashed.clear()
    os.utime(cap / "left.png")
    assert build_dataset(sess, true_calibration, out, scenes=["000"], workers=1).skipped_unchanged == ["000"]
    assert "left.png" in hashed and "DepthMap.tiff" not in hashed
    # new content: rebuilt
    (cap / "2DImage.png").write_bytes((cap / "2DImage.png").read_bytes())  # same bytes, new mtime
    d = read_image(cap / "left.png")
    from gtforge.io.formats import write_image

    write_image(cap / "left.png", 255 - d)
    assert build_dataset(sess, true_calibration, out, scenes=["000"], workers=1).built == ["000"]


@pytest.mark.slow
def test_scene_of_an_older_meta_schema_is_rebuilt_and_its_manifest_refused(session_dir, true_calibration, tmp_path):
    """meta.json schema 1 (gtforge before the inputs' BLAKE3) recorded SHA-256s this gtforge cannot compare: a resume
    rebuilds that scene instead of trusting it, and reading such a file says which schema it has."""
    import gtforge.build_dataset as bd

    out = tmp_path / "ds"
    assert build_dataset(session_dir, true_calibration, out, scenes=["000"], workers=1).built == ["000"]
    path = out / "scenes" / "000" / "meta.json"
    meta = json.loads(path.read_text())
    assert meta["schema_version"] == 3 and len(meta["input_blake3"]["left.png"]) == 64
    meta["schema_version"] = 1
    meta["input_sha256"] = meta.pop("input_blake3")
    path.write_text(json.dumps(meta))
    with pytest.raises(InputError, match=r"meta\.json.*schema_version 1 is not supported \(this gtforge reads 3\)"):
        bd.SceneMeta.read(path)
    assert build_dataset(session_dir, true_calibration, out, scenes=["000"], workers=1).built == ["000"]
    assert bd.SceneMeta.read(path).schema_version == 3
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["schema_version"] = 1
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match=r"manifest\.json.*schema_version 1 is not supported"):
        Manifest.read(out / "manifest.json")


def test_fruit_centre_equals_the_full_image_erosion():
    """fruit_regions erodes only the fruit's bounding box (plus the element's radius): the centre must equal
    OpenCV's erosion of the whole mask, also for fruit touching the image border."""
    import cv2

    from gtforge.core.ground_truth.regions import REGION_CENTRE, REGION_EDGE, fruit_regions

    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:60, 0:80]
    n_nonempty = 0
    for _ in range(150):
        f = np.zeros((60, 80), bool)
        for _ in range(rng.integers(0, 4)):
            cy, cx, ry, rx = rng.integers(-5, 65), rng.integers(-5, 85), rng.integers(2, 20), rng.integers(2, 20)
            f |= ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 < 1
        k = 2 * int(rng.integers(1, 9)) + 1
        full = cv2.erode(f.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).astype(bool)
        region, fruit = fruit_regions(np.full((60, 80), 500.0, np.float32), None,
                                      BuildParams(erosion_px=(k - 1) // 2), user_mask=f)
        np.testing.assert_array_equal(region == REGION_CENTRE, full)
        np.testing.assert_array_equal(region == REGION_EDGE, f & ~full)
        n_nonempty += full.any()
    assert n_nonempty > 50  # measured 98: most masks keep a centre


def test_fit_plane_robust_counts_as_numpy_and_finds_the_plane():
    """The compiled hypothesis scoring counts the inliers numpy counts; with half the points off the plane the
    RANSAC + refit still returns it."""
    from gtforge.core.geometry import _inlier_counts, fit_plane_robust

    rng = np.random.default_rng(3)
    n_true = np.array([0.1, -0.45, -0.89])
    n_true /= np.linalg.norm(n_true)
    xy = rng.uniform(-400, 400, (4000, 2))
    z = (-650.0 - n_true[0] * xy[:, 0] - n_true[1] * xy[:, 1]) / n_true[2]
    pts = np.column_stack([xy, z]) + rng.normal(0, 0.3, (4000, 3))
    pts[::2, 2] -= rng.uniform(5, 80, 2000)  # half of them above the table
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    offsets = np.einsum("ij,ij->i", normals, pts[rng.integers(0, 4000, 50)])
    xyz = np.ascontiguousarray(pts.T)
    for k in (50, 6, 3):  # four planes a pass over the points, and the ones left over
        np.testing.assert_array_equal(_inlier_counts(xyz[0], xyz[1], xyz[2], normals[:k], offsets[:k], 3.0),
                                      (np.abs(pts @ normals[:k].T - offsets[:k]) < 3.0).sum(axis=0))
    n, c, inliers = fit_plane_robust(pts, 3.0, iterations=100, rng=np.random.default_rng(0))
    if c < 0:
        n, c = -n, -c
    assert abs(n @ n_true) > 0.9999 and abs(c - 650.0) < 0.5
    assert inliers[1::2].mean() > 0.99 and inliers[::2].mean() < 0.05


def test_region_kernels_equal_their_numpy_definitions():
    """fruit_regions' compiled passes: the first labels and the GT's box (``_gt_region``), the box's GT pixels
    (``_gt_pixels``) and the height test (``_above_plane``) against the numpy expressions they replace."""
    from gtforge.core.geometry import mask_bounding_box
    from gtforge.core.ground_truth.regions import REGION_BG, _above_plane, _gt_pixels, _gt_region

    rng = np.random.default_rng(4)
    for _ in range(200):
        shape = tuple(int(x) for x in rng.integers(1, 30, 2))
        depth = rng.uniform(-50, 900, shape).astype(rng.choice([np.float32, np.float64]))
        depth[rng.random(shape) < rng.choice([0.0, 0.3, 0.97, 1.0])] = np.nan
        depth[rng.random(shape) < 0.05] = rng.choice([np.inf, -np.inf])
        valid = np.isfinite(depth)
        region, box = _gt_region(depth)
        np.testing.assert_array_equal(region, valid.astype(np.uint8) * np.uint8(REGION_BG))
        assert region.dtype == np.uint8 and box == mask_bounding_box(valid)
        if box is None:
            continue
        y0, y1, x0, x1 = box
        np.testing.assert_array_equal(_gt_pixels(depth, *box), np.flatnonzero(valid[y0:y1, x0:x1]))
        a, b, thr = rng.normal(0, 1, x1 - x0), rng.normal(0, 1, y1 - y0), float(rng.normal(0, 300))
        n_p = a[None, :] + b[:, None]
        n_p *= depth[y0:y1, x0:x1]
        np.testing.assert_array_equal(_above_plane(depth, y0, x0, a, b, thr), (n_p > thr) & valid[y0:y1, x0:x1])


def test_fruit_regions_equal_the_point_cloud_computation():
    """fruit_regions builds 3-D points for the plane's sample only and works on bounding boxes; the labels must
    equal the plain computation: every GT pixel's point, its height above the same plane, components of the whole
    image."""
    import cv2

    from gtforge.core.camera import PinholeCamera, RectifiedStereo
    from gtforge.core.geometry import fit_plane_robust
    from gtforge.core.ground_truth.regions import REGION_BG, REGION_CENTRE, REGION_EDGE, fruit_regions

    H, W = 240, 320
    cam = PinholeCamera(width_px=W, height_px=H, fx_px=300.0, fy_px=300.0, cx_px=161.3, cy_px=118.7)
    zed = RectifiedStereo(left=cam, baseline_mm=120.0)
    params = BuildParams(erosion_px=4)
    rng = np.random.default_rng(2)
    v, u = np.mgrid[0:H, 0:W]
    ray_x, ray_y = (u - cam.cx_px) / cam.fx_px, (v - cam.cy_px) / cam.fy_px
    for trial in range(4):
        n_t = np.array([rng.normal(0, 0.05), -0.45, -0.89])
        n_t /= np.linalg.norm(n_t)
        z = -650.0 / (n_t[0] * ray_x + n_t[1] * ray_y + n_t[2])  # the table: n.p = -650
        for cu, cv_, r in rng.uniform([60, 60, 15], [260, 180, 45], (3, 3)):  # fruit: bumps towards the camera
            z -= 3.0 * np.sqrt(np.clip(r ** 2 - (u - cu) ** 2 - (v - cv_) ** 2, 0, None))
        depth = (z + rng.normal(0, 0.5, z.shape)).astype(np.float32)
        depth[:rng.integers(0, 40), :] = np.nan  # GT missing at the borders and in a hole
        depth[:, W - rng.integers(1, 60):] = np.nan
        depth[100:130, 20:70] = np.nan
        region, fruit = fruit_regions(depth, zed, params)
        # the plain computation, with the plane fit_plane_robust gives for the same sample
        valid = np.isfinite(depth)
        vv, uu = np.nonzero(valid)
        pts = np.stack([ray_x[vv, uu] * depth[vv, uu], ray_y[vv, uu] * depth[vv, uu], depth[vv, uu]], axis=1)
        r_ = np.random.default_rng(0)
        n, c, _ = fit_plane_robust(pts[r_.choice(len(pts), min(len(pts), 20000), replace=False)],
                                   params.plane_threshold_mm, iterations=300, rng=r_)
        if c > 0:
            n, c = -n, -c
        fg = np.zeros((H, W), bool)
        fg[vv, uu] = pts @ n - c > params.fruit_height_mm
        n_cc, labels, stats, _ = cv2.connectedComponentsWithStats(fg.astype(np.uint8), connectivity=8)
        areas = stats[1:, cv2.CC_STAT_AREA]
        keep = np.zeros(n_cc, bool)
        keep[1:] = (areas >= params.min_component_frac * areas.max()) & (areas >= 50)
        expected = keep[labels]
        np.testing.assert_array_equal(fruit, expected)
        centre = cv2.erode(expected.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (9, 9))) > 0
        np.testing.assert_array_equal(region == REGION_CENTRE, centre)
        np.testing.assert_array_equal(region == REGION_EDGE, expected & ~centre)
        np.testing.assert_array_equal(region == REGION_BG, valid & ~expected)
        assert expected.sum() > 1000, trial


def test_pool_workers_reuse_freed_memory():
    """A local pool worker keeps freed full-image arrays for the next scene (scheduling.reuse_freed_memory):
    ten rounds of three 20 MB arrays, as a scene holds several at once, cost no fresh pages (0 here); with glibc's
    defaults freed memory goes back to the kernel and is faulted in again (10,643 page faults here)."""
    import platform
    import subprocess
    import sys

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("glibc only")
    code = """
import resource, sys
import numpy as np
from gtforge.infra.scheduling import reuse_freed_memory
if sys.argv[1] == "tuned":
    assert reuse_freed_memory()
a = [np.ones(5 << 20, np.float32) for _ in range(3)]  # the first round faults its pages in either way
del a
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    a = [np.ones(5 << 20, np.float32) for _ in range(3)]  # 3 x 20 MB, every page touched
    del a
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
    faults = {mode: int(subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True,
                                       check=True).stdout) for mode in ("default", "tuned")}
    assert faults["default"] > 5000, faults  # an array of 20 MB is 5120 pages of 4 kB
    assert faults["tuned"] < 1000, faults


def _resident_pages(path) -> int:
    """How many of a file's pages are in the page cache (mmap + mincore through ctypes; Linux/glibc)."""
    import ctypes
    import mmap
    import os

    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    libc.mmap.restype = ctypes.c_void_p
    libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_long]
    libc.mincore.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_char_p]
    libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
    size = os.path.getsize(path)
    fd = os.open(path, os.O_RDONLY)
    try:
        addr = libc.mmap(None, size, mmap.PROT_READ, mmap.MAP_SHARED, fd, 0)
        assert addr not in (None, ctypes.c_void_p(-1).value), ctypes.get_errno()
        pages = (size + mmap.PAGESIZE - 1) // mmap.PAGESIZE
        vec = ctypes.create_string_buffer(pages)
        assert libc.mincore(addr, size, vec) == 0, ctypes.get_errno()
        libc.munmap(addr, size)
        return sum(b & 1 for b in vec.raw)
    finally:
        os.close(fd)


def test_written_pages_are_released_two_scenes_later(tmp_path):
    """scheduling.release_written_pages: a scene's files leave the page cache at the call two scenes later (once
    written back), newer scenes' files stay until then, and contents are untouched."""
    import os
    import platform

    from gtforge.infra.scheduling import _WRITTEN_GROUPS, release_written_pages

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        pytest.skip("Linux/glibc only (mincore through ctypes)")
    rng = np.random.default_rng(0)
    files = {name: rng.integers(0, 255, 4 << 20, dtype=np.uint8).tobytes() for name in "abc"}
    a, b, c = (tmp_path / f"{name}.bin" for name in "abc")
    pages = len(files["a"]) // 4096
    a.write_bytes(files["a"])
    b.write_bytes(files["b"])
    assert _resident_pages(a) == pages  # just written: all cached
    _WRITTEN_GROUPS.clear()
    release_written_pages([a, tmp_path / "missing.bin"])  # a's writeback starts; a missing file is no error
    release_written_pages([b])
    os.sync()  # (two scenes' compute time, in a build)
    assert _resident_pages(a) == pages and _resident_pages(b) == pages  # not dropped yet
    c.write_bytes(files["c"])
    release_written_pages([c])
    assert _resident_pages(a) == 0  # two calls later: dropped
    assert _resident_pages(b) == pages  # dropped at the next call
    assert all((tmp_path / f"{k}.bin").read_bytes() == v for k, v in files.items())
    assert _WRITTEN_GROUPS == [[str(b)], [str(c)]]


def test_dask_task_keeps_freed_memory_then_restores_the_workers_setting():
    """On a Dask worker (started with MALLOC_TRIM_THRESHOLD_=65536, which returns every freed array to the kernel)
    a gtforge task keeps freed memory while it runs and puts the worker's setting back afterwards."""
    import os
    import platform
    import subprocess
    import sys

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("glibc only")
    code = """
import resource
import numpy as np
from gtforge.infra.scheduling import _memory_kept_for_task

def faults():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        a = [np.ones(5 << 20, np.float32) for _ in range(3)]  # 3 x 20 MB, every page touched
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

a = [np.ones(5 << 20, np.float32) for _ in range(3)]
del a
outside = faults()
with _memory_kept_for_task():
    a = [np.ones(5 << 20, np.float32) for _ in range(3)]
    del a
    inside = faults()
print(outside, inside, faults())
"""
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}  # what Dask's nanny sets for its workers
    outside, inside, after = map(int, subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                                     check=True, env=env).stdout.split())
    assert outside > 5000 and after > 5000, (outside, after)  # freed arrays faulted in again (15,660 here, both)
    assert inside < 1000, inside


def test_occlusion_mask_and_disparity_summary_match_numpy():
    """The compiled occlusion mask and one-pass statistics give numpy's values exactly (NaN, +-inf, strided crops);
    calib.txt's vmin/vmax/ndisp from the range."""
    from gtforge.build_dataset import _disparity_summary
    from gtforge.core.ground_truth.regions import occlusion_mask
    from gtforge.io.middlebury import middlebury_calib_text

    rng = np.random.default_rng(3)
    disp = (rng.random((60, 80)) * 250).astype(np.float32)
    disp[rng.random(disp.shape) < 0.3] = np.nan
    disp[0, :3] = [np.inf, -np.inf, 193.0]
    noc = np.isfinite(disp) & (rng.random(disp.shape) < 0.7)
    for d, n in ((disp, noc), (disp[5:50, 7:70], noc[5:50, 7:70])):  # whole, and a crop (a strided view)
        expected = np.zeros(d.shape, np.uint8)
        expected[np.isfinite(d)] = 128
        expected[n] = 255
        np.testing.assert_array_equal(occlusion_mask(d, n), expected)
        finite = d[np.isfinite(d)]
        assert _disparity_summary(d, 192.0) == (finite.size, finite.min(), finite.max(), int((finite > 192.0).sum()))
    assert _disparity_summary(np.full((4, 5), np.nan, np.float32), 192.0)[0] == 0
    # the min and max are integer reductions over the bits in float order: negative values, subnormals, the largest
    # floats; where one of them is zero, -0.0 or +0.0 as a float min or max gives it (the first in raster order)
    for values, lo, hi in (([-3.5, -1e-40, 2.0, 3e38], -3.5, 3e38), ([-3e38, -7.0, -1e-40], -3e38, -1e-40),
                           ([0.0, -0.0, 5.0], 0.0, 5.0), ([-0.0, 0.0, 5.0], -0.0, 5.0), ([-2.0, -0.0, 0.0], -2.0, -0.0),
                           ([-2.0, 0.0, -0.0], -2.0, 0.0)):
        d = np.full((3, 7), np.nan, np.float32)
        d[1, 2:2 + len(values)] = values
        n, got_lo, got_hi, _ = _disparity_summary(d, 192.0)
        assert n == len(values) and got_lo == np.float32(lo) and got_hi == np.float32(hi)
        assert np.signbit(got_lo) == np.signbit(np.float32(lo)) and np.signbit(got_hi) == np.signbit(np.float32(hi))
    with pytest.raises(ValueError, match="float32"):  # the bits are read as int32
        _disparity_summary(np.ones((3, 4)), 192.0)
    from gtforge.core.camera import PinholeCamera, RectifiedStereo

    zed = RectifiedStereo(left=PinholeCamera(fx_px=1000.0, fy_px=1000.0, cx_px=40.0, cy_px=30.0, width_px=80,
                                             height_px=60), baseline_mm=63.0)
    text = middlebury_calib_text(zed, 80, 60, (12.5, 193.0))
    assert "vmin=12\n" in text and "vmax=193\n" in text and "ndisp=208\n" in text
    assert "vmin=0\n" in middlebury_calib_text(zed, 80, 60, None)


@pytest.mark.slow
def test_no_right_gt_rebuild_leaves_no_right_view_file(dataset, session_dir, true_calibration, tmp_path):
    """`build-dataset --no-right-gt` over a dataset built with the right view's GT: every scene is rebuilt without
    disp1GT.pfm / mask1nocc.png, the KITTI view keeps no disp_occ_1 / disp_noc_1 file from the earlier build and the
    split views link none; the left view's files are those of the first build."""
    from typer.testing import CliRunner

    from gtforge.cli.commands import app

    out, _ = dataset
    ds = tmp_path / "ds"
    shutil.copytree(out, ds, symlinks=True)
    r = CliRunner().invoke(app, ["build-dataset", str(session_dir), "-c", str(true_calibration), "-o", str(ds),
                                 "--no-right-gt", "--workers", "1"], env={"COLUMNS": "200"})
    assert r.exit_code in (0, 1), r.output  # 1: verification flagged a scene (the fixture's moved fruit)
    m = Manifest.read(ds / "manifest.json")
    assert m.params.right_gt is False and sorted(m.scenes) == sorted(Manifest.read(out / "manifest.json").scenes)
    k = ds / "kitti" / "training"
    for sid in m.scenes:
        s = ds / "scenes" / sid
        assert not (s / "disp1GT.pfm").exists() and not (s / "mask1nocc.png").exists()
        assert (s / "disp0GT.pfm").read_bytes() == (out / "scenes" / sid / "disp0GT.pfm").read_bytes()
        assert not (k / "disp_occ_1" / f"{sid}_10.png").exists() and not (k / "disp_noc_1" / f"{sid}_10.png").exists()
        assert (k / "disp_occ_0" / f"{sid}_10.png").read_bytes() == \
            (out / "kitti" / "training" / "disp_occ_0" / f"{sid}_10.png").read_bytes()
    for split, ids in m.splits.items():
        for sid in ids:
            v = ds / "views" / split / "KITTI" / "training"
            assert (v / "disp_occ_0" / f"{sid}_10.png").exists() and not (v / "disp_occ_1" / f"{sid}_10.png").exists()


@pytest.mark.slow
def test_scene_locks_are_released_per_scene_and_deleted_at_the_end(session_dir, true_calibration, tmp_path,
                                                                    monkeypatch):
    """A scene's lock is released when the scene lands but its file stays until the run's end (a file deleted per
    scene makes ext4 without a journal skip its inode at every allocation for a minute): no lock file is deleted
    while scenes are built, none is left afterwards, and a stale check meanwhile keeps them."""
    import gtforge.build_dataset as bd
    from gtforge.dataset import scene_folder

    out = tmp_path / "ds"
    seen = []  # after each scene: (lock files in scenes/, whether any is still held)
    real_run_tasks = bd.run_tasks

    def run_tasks(fn, args, on_result, **kw):
        def after(res):
            locks = sorted((out / "scenes").glob(".lock-*"))
            seen.append((len(locks), any(scene_folder.writer_alive(out / "scenes", p.name) for p in locks)))
            scene_folder.remove_stale_entries(out, locks=False)  # what the build does before the views: the locks stay
            assert len(list((out / "scenes").glob(".lock-*"))) == len(locks)
            on_result(res)
        real_run_tasks(fn, args, after, **kw)

    monkeypatch.setattr(bd, "run_tasks", run_tasks)
    s = build_dataset(session_dir, true_calibration, out, scenes=["000", "001", "002"], workers=1)
    assert s.built == ["000", "001", "002"]
    assert seen == [(1, False), (2, False), (3, False)]  # one per built scene, all released
    assert not [p.name for p in (out / "scenes").iterdir() if p.name.startswith(".")]  # none left after the run


@pytest.mark.slow
def test_a_scene_landed_by_a_worker_that_died_before_reporting_it_is_built(dataset, session_dir, true_calibration,
                                                                            tmp_path, monkeypatch):
    """A worker killed after its scene landed (before the result came back, or before the scene's views were
    written): the scene is counted as built and its views are written, byte for byte as a normal build's; a lost
    scene that did not land in this run (an older build with other options is still there) is listed as failed."""
    import gtforge.build_dataset as bd
    from gtforge.infra.scheduling import LOST_REASON

    out = tmp_path / "ds"
    build_dataset(session_dir, true_calibration, out, scenes=["002"], workers=1,
                  params=bd.BuildParams(right_gt=False))  # 002: rebuilt by the run below (other options)
    real_run_tasks = bd.run_tasks
    kitti = out / "kitti" / "training"

    def run_tasks(fn, args, on_result, lost_result=None, **kw):
        def dying(a):
            if a[2] == "001":  # landed, its views half written (the left view's, not the right's), then it died
                fn(*a)
                (kitti / "disp_occ_1" / "001_10.png").unlink()
                (kitti / "disp_noc_1" / "001_10.png").unlink()
            on_result(lost_result(a, LOST_REASON))  # 002: died before its scene landed

        real_run_tasks(fn, [a for a in args if a[2] == "000"], on_result, lost_result=lost_result, **kw)
        for a in args:
            if a[2] != "000":
                dying(a)

    monkeypatch.setattr(bd, "run_tasks", run_tasks)
    s = build_dataset(session_dir, true_calibration, out, workers=1)
    assert s.built == ["000", "001"] and list(s.failures) == ["002"] and "worker process died" in s.failures["002"]
    m = bd.Manifest.read(out / "manifest.json")
    assert sorted(m.scenes) == ["000", "001"] and list(m.failures) == ["002"]
    ref = dataset[0] / "kitti" / "training"
    for d in ("disp_occ_0", "disp_noc_0", "disp_occ_1", "disp_noc_1"):
        assert (kitti / d / "001_10.png").read_bytes() == (ref / d / "001_10.png").read_bytes()
    assert (out / "scenes" / "001" / "disp0GT.pfm").read_bytes() == \
        (dataset[0] / "scenes" / "001" / "disp0GT.pfm").read_bytes()


def test_scenes_of_a_right_corrected_calibration_are_rebuilt_after_the_resampling_changed():
    """A dataset built before the right image's one exact resampling (round 3) has the older im1: its scenes'
    recorded hash no longer matches where the calibration corrects the right camera, so a resumed build redoes them;
    without a correction the hash is the parameters' own, and nothing is rebuilt."""
    from gtforge.build_dataset import scene_params_hash
    from gtforge.core.camera import Rig, ScaleCorrections
    from gtforge.core.zed.selfcal import ZedRightCorrection, ZedSelfRectification
    from gtforge.records.calibration import CalibrationFile
    from gtforge.synthetic import default_rig

    r = default_rig(0.3)
    plain = CalibrationFile.known_extrinsic(Rig(zed=r.zed, mech=r.mech, T_zed_from_mech=r.T_zed_from_mech))
    params = BuildParams()
    assert scene_params_hash(params, plain) == params.output_hash()
    yawed = plain.model_copy(update=dict(rig=Rig.model_validate(
        {**plain.rig.model_dump(), "scale_corrections": ScaleCorrections(zed_right_yaw_deg=0.05).model_dump()})))
    selfcal = plain.model_copy(update=dict(zed_self_rectification=ZedSelfRectification(
        status="applied", reason="", correction=ZedRightCorrection(rotvec_rad=[0.001, 0.0, 0.0]))))
    for c in (yawed, selfcal):
        assert scene_params_hash(params, c) != params.output_hash()
        assert scene_params_hash(params, c) == scene_params_hash(params, c)


@pytest.mark.slow
def test_pool_from_a_warmed_fork_server_writes_the_files_of_the_one_process_build(dataset, session_dir,
                                                                                true_calibration, tmp_path):
    """`gtforge build-dataset --workers 2` (a fresh process: its pool's fork server computes the calibration, the
    session and the depth camera's ray grid once, with the serial undistortion, and the workers inherit them) writes
    every scene file byte for byte as the one-process build (the ``dataset`` fixture, ``workers=1``), and the same
    KITTI files and verification figures."""
    import subprocess
    import sys

    out, _ = dataset
    ds = tmp_path / "ds"
    r = subprocess.run([sys.executable, "-m", "gtforge.cli", "build-dataset", str(session_dir), "-c",
                        str(true_calibration), "-o", str(ds), "--workers", "2"], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode in (0, 1), r.stderr[-3000:]  # 1: verification flagged a scene (the fixture's moved fruit)
    one, pool = Manifest.read(out / "manifest.json"), Manifest.read(ds / "manifest.json")
    assert sorted(pool.scenes) == sorted(one.scenes) and len(one.scenes) == 3
    for sid in one.scenes:
        names = sorted(p.name for p in (out / "scenes" / sid).iterdir())
        assert names == sorted(p.name for p in (ds / "scenes" / sid).iterdir()) and "disp0GT.pfm" in names
        for name in names:
            if name != "meta.json":  # (its times differ)
                assert (ds / "scenes" / sid / name).read_bytes() == (out / "scenes" / sid / name).read_bytes(), name
        for d in ("disp_occ_0", "disp_noc_0", "disp_occ_1", "disp_noc_1"):
            f = f"kitti/training/{d}/{sid}_10.png"
            assert (ds / f).read_bytes() == (out / f).read_bytes()
        a, b = one.scenes[sid], pool.scenes[sid]
        assert a.verification == b.verification and a.sigma == b.sigma and a.stats == b.stats


def test_ctrl_c_counts_the_scenes_a_worker_landed_before_reporting(session_dir, true_calibration, tmp_path,
                                                                   monkeypatch):
    """A Ctrl-C after a worker landed a scene whole but before its result reached the command: the message and the
    manifest count that scene as built (the message said 0 built while the scene was complete on disk)."""
    import gtforge.build_dataset as bd
    from gtforge.errors import Interrupted

    def first_lands_then_ctrl_c(fn, arg_list, on_result, **kw):
        fn(*arg_list[0])  # the scene's files land; its result is never handed back
        raise KeyboardInterrupt

    monkeypatch.setattr(bd, "run_tasks", first_lands_then_ctrl_c)
    out = tmp_path / "ds"
    with pytest.raises(Interrupted) as stop:
        build_dataset(session_dir, true_calibration, out, workers=1)
    n = len([d for d in (session_dir / "scenes").iterdir() if d.is_dir()])
    assert str(stop.value).startswith(f"interrupted: 1 scene(s) built in this run and complete, {n - 1} not built")
    assert list(Manifest.read(out / "manifest.json").scenes) == ["000"]


@pytest.mark.slow
def test_a_resume_rewrites_views_of_an_earlier_build_and_follows_edited_fruit_ids(session_dir, true_calibration,
                                                                                dataset, tmp_path, caplog):
    """A scene that landed without its views (its worker stopped between the two) kept an earlier build's KITTI and
    ETH3D files on resume, because they existed: a resume writes them again from the scene as it is. fruit_ids edited
    in session.yaml since the build: the resume's splits and metas follow them (they kept the build's), and it names
    the scenes that changed split."""
    import yaml

    from gtforge.dataset.views import final_splits, moved_between_splits
    from gtforge.io.formats import write_pfm

    sess, out = tmp_path / "session", tmp_path / "ds"
    shutil.copytree(session_dir, sess)
    shutil.copytree(dataset[0], out)
    man = Manifest.read(out / "manifest.json")
    ids = sorted(man.scenes)
    # scene ids[0] as another build landed it: other labels (new files), its views still the earlier build's
    s = out / "scenes" / ids[0]
    disp = read_pfm(s / "disp0GT.pfm")
    newer = np.where(np.isfinite(disp), disp + 0.25, disp).astype(np.float32)
    (s / "disp0GT.pfm").unlink()
    write_pfm(s / "disp0GT.pfm", newer)
    eth = out / "eth3d" / "two_view_training_gt" / ids[0] / "disp0GT.pfm"
    kitti = out / "kitti" / "training" / "disp_occ_0" / f"{ids[0]}_10.png"
    assert np.nanmax(np.abs(read_pfm(eth) - newer)) == pytest.approx(0.25, abs=1e-5)
    cfg = yaml.safe_load((sess / "session.yaml").read_text())
    fruit = {sid: f"melon{k}" for k, sid in enumerate(ids)}  # every scene its own fruit now
    assert {sid: man.scenes[sid].fruit_id for sid in ids} != fruit
    cfg["fruit_ids"] = fruit
    (sess / "session.yaml").write_text(yaml.safe_dump(cfg))
    before = man.splits
    summary = build_dataset(sess, true_calibration, out, workers=1)
    assert summary.built == [] and summary.skipped_unchanged == ids
    assert os.path.samefile(eth, s / "disp0GT.pfm")
    k = read_kitti_disparity(kitti)  # (KITTI's 1/256 px steps)
    assert np.array_equal(np.isfinite(k), np.isfinite(newer)) and np.nanmax(np.abs(k - newer)) <= 1 / 512
    man = Manifest.read(out / "manifest.json")
    assert {sid: man.scenes[sid].fruit_id for sid in ids} == fruit
    assert man.splits == final_splits(ids, fruit, man.params, [])
    moved = moved_between_splits(before, man.splits)
    assert moved and f"{len(moved)} scene(s) changed split since the last build: " + ", ".join(
        f"{sid} {a} -> {b}" for sid, (a, b) in moved.items()) in caplog.text
    assert json.loads((s / "meta.json").read_text())["fruit_id"] == fruit[ids[0]]


def test_scenes_the_session_no_longer_holds_are_named(session_dir, true_calibration, dataset, tmp_path, caplog):
    """A capture deleted from the session after its scene was built: the rebuild leaves it out of the manifest and
    the splits, as before, and now says that its folders stay in scenes/, kitti/ and eth3d/ (where RAFT-Stereo's
    KITTI reader, which lists kitti/training itself, would still train on it)."""
    sess, out = tmp_path / "session", tmp_path / "ds"
    shutil.copytree(session_dir, sess)
    shutil.copytree(dataset[0], out)
    ids = sorted(Manifest.read(out / "manifest.json").scenes)
    shutil.rmtree(sess / "scenes" / ids[-1])
    summary = build_dataset(sess, true_calibration, out, workers=1)
    assert summary.built == [] and summary.skipped_unchanged == ids[:-1]
    assert sorted(Manifest.read(out / "manifest.json").scenes) == ids[:-1]
    assert f"1 scene(s) in {out / 'scenes'} are no longer in the session ({ids[-1]}): left out of the manifest" \
        in caplog.text
    caplog.clear()
    build_dataset(session_dir, true_calibration, out, workers=1)  # the session whole again: the scene is its own
    assert "no longer in the session" not in caplog.text


def test_disparities_beyond_kittis_16_bits_are_named(dataset, caplog):
    """A scene whose ground truth reaches 256 px (a ZED 2 at 2K closer than about half a metre): its KITTI PNGs hold
    those pixels as invalid (a clip made them valid 255.996 px labels), and the build says which scenes."""
    from gtforge.build_dataset import _warn_of_kitti_range
    from gtforge.io.formats import KITTI_MAX_DISPARITY_PX

    metas = Manifest.read(dataset[0] / "manifest.json").scenes
    ids = sorted(metas)
    assert all(m.stats.disp_max_px < KITTI_MAX_DISPARITY_PX for m in metas.values())
    _warn_of_kitti_range(metas, BuildParams())
    assert "KITTI" not in caplog.text
    near = dict(metas)
    near[ids[1]] = metas[ids[1]].model_copy(update={"stats": metas[ids[1]].stats.model_copy(
        update={"disp_max_px": 300.04})})
    _warn_of_kitti_range(near, BuildParams(kitti=False))
    assert "KITTI" not in caplog.text
    _warn_of_kitti_range(near, BuildParams())
    assert f"1 scene(s) hold disparities beyond the 255.998 px a KITTI 16-bit PNG can store ({ids[1]} up to " \
        "300.0 px): kitti/ marks those pixels invalid (0)" in caplog.text


def test_scene_ids_that_mislead_openstereos_right_view_reader_are_named(dataset, tmp_path, caplog):
    """OpenStereo's KittiDataset finds disp_occ_1's file by str.replace('c_0', 'c_1') over the whole path: scene
    sc_001's right view would be read from sc_101's file. The build names such ids (and a dataset path with c_0)."""
    from gtforge.build_dataset import _warn_of_openstereo_right_paths

    out = tmp_path / "ds"
    _warn_of_openstereo_right_paths(out, ["000", "sc_1", "abc_2"], BuildParams())
    assert "OpenStereo" not in caplog.text
    _warn_of_openstereo_right_paths(out, ["000", "sc_001", "sc_101"], BuildParams(right_gt=False))
    assert "OpenStereo" not in caplog.text
    _warn_of_openstereo_right_paths(out, ["000", "sc_001", "sc_101"], BuildParams())
    assert "replaces every 'c_0' in a path with 'c_1' to find the right view's ground truth: scene id(s) sc_001 hold " \
        "'c_0'" in caplog.text and "rename those capture folders" in caplog.text
    caplog.clear()
    _warn_of_openstereo_right_paths(tmp_path / "proc_0" / "ds", ["000"], BuildParams())
    assert f"the dataset's path {(tmp_path / 'proc_0' / 'ds').resolve()} holds 'c_0'" in caplog.text


def test_fruit_ids_that_name_no_scene_or_leave_scenes_out_are_said(session_dir, true_calibration, dataset, tmp_path,
                                                                  caplog):
    """fruit_ids {'01': ...} meant for scene 001 was ignored without a word: 001 became a fruit of its own and could
    land in test while the rest of its fruit trained (a run-through). The build names such keys, and the scenes a
    partial grouping leaves out."""
    import yaml

    sess, out = tmp_path / "session", tmp_path / "ds"
    shutil.copytree(session_dir, sess)
    shutil.copytree(dataset[0], out)
    ids = sorted(Manifest.read(out / "manifest.json").scenes)
    cfg = yaml.safe_load((sess / "session.yaml").read_text())
    cfg["fruit_ids"] = {ids[0]: "melon03", ids[1][1:]: "melon03"}  # the second's id with a digit missing
    (sess / "session.yaml").write_text(yaml.safe_dump(cfg))
    build_dataset(sess, true_calibration, out, workers=1)
    said = [r.getMessage() for r in caplog.records]
    assert f"{sess / 'session.yaml'}: fruit_ids names {ids[1][1:]}, which is no scene (the scenes: " \
        f"{', '.join(ids)}): ignored" in " ".join(said)
    assert f"{sess / 'session.yaml'}: fruit_ids names no fruit for {len(ids) - 1} scene(s): " \
        f"{', '.join(ids[1:])}: each is a fruit of its own" in " ".join(said)
    caplog.clear()
    cfg["fruit_ids"] = {s: "melon03" for s in ids}
    (sess / "session.yaml").write_text(yaml.safe_dump(cfg))
    build_dataset(sess, true_calibration, out, workers=1)
    assert "fruit_ids names" not in caplog.text


def test_split_and_crop_refusals_carry_a_hint(session_dir, true_calibration, tmp_path):
    """build-dataset's refusals of --split ratios over 1 and of a --crop larger than the images are one line with a
    hint, as every bad-input error (docs/conventions.md, "Errors"): both said only expected and got."""
    with pytest.raises(InputError) as e:
        build_dataset(session_dir, tmp_path / "none.yaml", tmp_path / "ds", BuildParams(split_train=0.9, split_val=0.2))
    assert e.value.field == "--split" and e.value.actual == "0.9 + 0.2"
    assert e.value.hint == "test gets the rest (1 - train - val): e.g. --split 0.8,0.1"
    for train, val in ((-0.1, 0.5), (0.5, -0.2), (float("nan"), 0.1)):  # a negative share was built (train empty)
        with pytest.raises(InputError, match=r"^--split: expected train and val ratios in \[0, 1\]"):
            build_dataset(session_dir, tmp_path / "none.yaml", tmp_path / "ds",
                          BuildParams(split_train=train, split_val=val))
    with pytest.raises(InputError) as e:
        build_dataset(session_dir, true_calibration, tmp_path / "ds", BuildParams(crop_wh=(1242, 375)), workers=1)
    assert e.value.field == "--crop" and e.value.actual == "1242x375 px"
    assert e.value.hint == "give --crop WxH within 883x497, or build without --crop (--crop kitti is 1242x375)"
    assert not (tmp_path / "ds").exists()


@pytest.mark.parametrize("erosion_px", [249, 100000])
def test_an_erosion_wider_than_the_image_is_refused_before_work(session_dir, true_calibration, tmp_path, erosion_px):
    """--erosion-px 100000 reached OpenCV (a 40 GB kernel: its out-of-memory traceback); beyond half the image's
    shorter side every fruit is eroded away."""
    with pytest.raises(InputError) as e:
        build_dataset(session_dir, true_calibration, tmp_path / "ds", BuildParams(erosion_px=erosion_px), workers=1)
    assert e.value.field == "--erosion-px" and e.value.expected == "at most half the ZED image's shorter side, 248 px"
    assert not (tmp_path / "ds").exists()
