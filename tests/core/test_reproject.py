"""Reprojection core against exact truth from the generator."""
import numpy as np
import pytest

from gtforge.core.camera import PinholeCamera, RectifiedStereo
from gtforge.core.geometry import T_from_rotvec
from gtforge.core.ground_truth.reproject import ReprojectParams, project_depth_to_camera, reproject_to_zed
from gtforge.synthetic import default_rig, random_fruit_scene, render_capture


@pytest.fixture(scope="module")
def fruit_cap():
    rig = default_rig(0.35)
    rng = np.random.default_rng(21)
    cap = render_capture("s", random_fruit_scene(rng, rig, 21), rig, rng, kind="scene", supersample=1)
    return rig, cap


def test_mesh_accuracy_and_coverage(fruit_cap):
    rig, cap = fruit_cap
    sd = reproject_to_zed(cap.depth_mm, rig.mech, rig.T_zed_from_mech, rig.zed)
    seen = cap.seen_by_mech
    got = np.isfinite(sd.disparity_px)
    err = np.abs(sd.disparity_px - cap.zed_disparity_px)
    assert got[seen].mean() >= 0.995  # coverage of what the depth camera really saw
    assert np.mean(err[seen & got]) < 0.01  # EPE, noise-free depth and exact extrinsic
    assert np.mean(err[got] > 1.0) < 0.0005  # no foreground/background mixing
    assert not np.any(got & ~np.isfinite(cap.zed_disparity_px))  # nothing invented where nothing exists
    assert sd.depth_mm.dtype == np.float32 and sd.disparity_px.dtype == np.float32


def test_splat_rounds_to_nearest_pixel():
    # one depth sample that lands at u = 10.4, v = 5.6 in the target: the nearest pixel is (10, 6)
    mech = PinholeCamera(width_px=3, height_px=3, fx_px=100.0, fy_px=100.0, cx_px=1.0, cy_px=1.0)
    cam = PinholeCamera(width_px=20, height_px=12, fx_px=100.0, fy_px=100.0, cx_px=10.4, cy_px=5.6)
    depth = np.full((3, 3), np.nan, np.float32)
    depth[1, 1] = 500.0
    out = project_depth_to_camera(depth, mech, np.eye(4), cam, ReprojectParams(mode="splat"))
    assert np.isfinite(out).sum() == 1 and out[6, 10] == 500.0


def test_zbuffer_keeps_nearest_and_mesh_is_exact_on_planes():
    cam = PinholeCamera(width_px=64, height_px=48, fx_px=80.0, fy_px=75.0, cx_px=31.3, cy_px=22.8)
    v, u = np.mgrid[0:48, 0:64]
    # a slanted plane z = 600 + 0.8 x (in the depth camera); mesh must reproduce it exactly
    x = (u - cam.cx_px) / cam.fx_px
    depth = (600.0 / (1 - 0.8 * x)).astype(np.float32)
    T_cam_from_depth = T_from_rotvec([0.0, 0.02, 0.0], [5.0, 0.0, 0.0])
    out = project_depth_to_camera(depth, cam, T_cam_from_depth, cam, ReprojectParams(mode="mesh", max_slant_deg=89))
    ok = np.isfinite(out)
    assert ok.mean() > 0.8
    # truth: intersect each target ray with the transformed plane
    Rt, t = T_cam_from_depth[:3, :3], T_cam_from_depth[:3, 3]
    n_m = np.array([-0.8, 0.0, 1.0])  # plane n.p = 600 in the depth camera
    n_c = Rt @ n_m
    c_c = 600.0 + n_c @ t
    rays = np.stack([(u - cam.cx_px) / cam.fx_px, (v - cam.cy_px) / cam.fy_px, np.ones_like(u, float)], axis=-1)
    z_true = c_c / (rays @ n_c)
    np.testing.assert_allclose(out[ok], z_true[ok], rtol=2e-5)
    # a nearer square in front: the z-buffer keeps it
    depth2 = depth.copy()
    depth2[20:30, 20:30] = 300.0
    out2 = project_depth_to_camera(depth2, cam, np.eye(4), cam, ReprojectParams(mode="splat"))
    assert np.nanmax(out2[22:28, 22:28]) == pytest.approx(300.0)


def test_mesh_fills_holes_of_a_sparse_depth_camera(fruit_cap):
    rig, cap = fruit_cap
    # the same scene seen by a depth camera 3x sparser than before: splatting leaves holes, mesh does not
    sparse = rig.mech.scaled(1 / 3)
    from gtforge.synthetic import lit_mask, raycast_depth

    rng = np.random.default_rng(21)
    scene = random_fruit_scene(rng, rig, 21)
    z, _, p = raycast_depth(scene, sparse, rig.T_mech_from_world)
    hit = np.isfinite(z)
    lit = np.zeros_like(hit)
    lit[hit] = lit_mask(scene, rig, p[hit])
    depth = np.where(hit & lit, z, np.nan).astype(np.float32)
    seen = cap.seen_by_mech
    splat = project_depth_to_camera(depth, sparse, rig.T_zed_from_mech, rig.zed.left, ReprojectParams(mode="splat"))
    mesh = project_depth_to_camera(depth, sparse, rig.T_zed_from_mech, rig.zed.left, ReprojectParams(mode="mesh"))
    assert np.isfinite(splat)[seen].mean() < 0.7
    assert np.isfinite(mesh)[seen].mean() > 0.98
    d_mesh = rig.zed.depth_to_disparity(mesh)
    assert np.nanmean(np.abs(d_mesh - cap.zed_disparity_px)[seen]) < 0.02


def test_nonoccluded_mask_marks_right_view_occlusions():
    # a depth camera on the LEFT of the ZED sees table next to the box that the ZED right camera cannot
    cam = PinholeCamera(width_px=120, height_px=80, fx_px=100.0, fy_px=100.0, cx_px=59.5, cy_px=39.5)
    zed = RectifiedStereo(left=cam, baseline_mm=63.0)
    depth = np.full((80, 120), 1000.0, np.float32)
    depth[30:50, 50:70] = 500.0  # box in front of a wall
    T_zed_from_depth = np.eye(4)  # depth camera = ZED left
    sd = reproject_to_zed(depth, cam, T_zed_from_depth, zed, ReprojectParams(mode="mesh"))
    valid = np.isfinite(sd.disparity_px)
    occ = valid & ~sd.nonoccluded
    # the wall just left of the box is hidden from the right camera by (12.6 - 6.3) = 6.3 px
    assert occ[35:45, 44:49].all()
    assert not occ[35:45, 55:65].any() and not occ[35:45, 75:100].any()


def test_mesh_span_is_the_winning_triangles_z_range():
    # a plane whose depth changes along x only, seen by the same camera shifted by a fraction of a pixel:
    # every target pixel centre lies inside a quad of columns (c, c+1) with c = u - 1, and both triangles
    # of that quad have corners in both columns, so span = z(column u) - z(column u - 1)
    mech = PinholeCamera(width_px=64, height_px=48, fx_px=80.0, fy_px=75.0, cx_px=31.3, cy_px=22.8)
    cam = mech.model_copy(update=dict(cx_px=mech.cx_px + 0.37, cy_px=mech.cy_px + 0.41))
    v, u = np.mgrid[0:48, 0:64]
    x = (u - mech.cx_px) / mech.fx_px
    depth = (600.0 / (1 - 0.8 * x)).astype(np.float32)
    z, span = project_depth_to_camera(depth, mech, np.eye(4), cam, ReprojectParams(max_slant_deg=89), return_span=True)
    np.testing.assert_array_equal(np.isfinite(span), np.isfinite(z))
    ok = np.isfinite(z)
    assert ok[1:-1, 1:-1].all()
    expected = np.full(z.shape, np.nan)
    expected[:, 1:] = depth[0, 1:].astype(np.float64) - depth[0, :-1]
    np.testing.assert_allclose(span[ok], expected[ok], rtol=1e-5)
    # the same depth without the span
    np.testing.assert_array_equal(project_depth_to_camera(depth, mech, np.eye(4), cam,
                                                          ReprojectParams(max_slant_deg=89)), z)
    with pytest.raises(ValueError, match="mesh"):
        project_depth_to_camera(depth, mech, np.eye(4), cam, ReprojectParams(mode="splat"), return_span=True)


@pytest.mark.slow
def test_result_does_not_depend_on_the_thread_count(fruit_cap, monkeypatch):
    # one thread rasterises straight into the image; several rasterise row chunks into windows and merge
    import numba

    import gtforge.core.ground_truth.reproject as rp

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip(f"numba has {numba.config.NUMBA_NUM_THREADS} thread here (one core): the windowed path needs 2; "
                    "NUMBA_NUM_THREADS=2 runs it on one core")
    monkeypatch.setattr(rp, "MIN_PARALLEL_THREADS", 2)  # the windowed path with 2 threads
    rig, cap = fruit_cap
    before = numba.get_num_threads()
    out = {}
    try:
        for n in (1, 2):
            numba.set_num_threads(n)
            out[n] = [project_depth_to_camera(cap.depth_mm, rig.mech, rig.T_zed_from_mech, rig.zed.left,
                                              ReprojectParams(mode="mesh"), return_span=True),
                      project_depth_to_camera(cap.depth_mm, rig.mech, rig.T_zed_from_mech, rig.zed.left,
                                              ReprojectParams(mode="splat"))]
    finally:
        numba.set_num_threads(before)
    (z1, s1), p1 = out[1]
    (z2, s2), p2 = out[2]
    assert np.isfinite(z1).mean() > 0.2 and np.isfinite(p1).mean() > 0.2
    np.testing.assert_array_equal(z1, z2)
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_array_equal(p1, p2)


def test_both_views_in_one_pass_are_the_two_single_views(fruit_cap, monkeypatch):
    """A build worker (one thread) rasterises the ZED's left and right views in one pass over the grid, deciding once
    which triangles are drawn: the same depth, span and right-view images as one call per view, with a ZED whose
    right camera has its own cx (doffs) and with the parallel path forced for the single views."""
    import numba

    import gtforge.core.ground_truth.reproject as rp

    rig, cap = fruit_cap
    zed = rig.zed.model_copy(update={"doffs_px": 3.25})
    T_zed_from_mech = rig.T_zed_from_mech
    for params in (ReprojectParams(), ReprojectParams(max_slant_deg=70.0, abs_tol_mm=0.2)):
        left, span, right = rp._project_depth_to_stereo(cap.depth_mm, rig.mech, T_zed_from_mech,
                                                        zed.T_zedr_from_zed @ T_zed_from_mech, zed, params, True)
        z1, s1 = project_depth_to_camera(cap.depth_mm, rig.mech, T_zed_from_mech, zed.left, params, return_span=True)
        r1 = project_depth_to_camera(cap.depth_mm, rig.mech, zed.T_zedr_from_zed @ T_zed_from_mech, zed.right, params)
        assert np.isfinite(left).mean() > 0.2 and np.isfinite(right).mean() > 0.2
        assert not np.array_equal(left, right, equal_nan=True)
        np.testing.assert_array_equal(left, z1)
        np.testing.assert_array_equal(span, s1)
        np.testing.assert_array_equal(right, r1)
    # reproject_to_zed takes the one-pass path with one thread, and the single views with several
    sd = reproject_to_zed(cap.depth_mm, rig.mech, T_zed_from_mech, zed, left_span=True)
    if numba.config.NUMBA_NUM_THREADS >= 2:
        monkeypatch.setattr(rp, "MIN_PARALLEL_THREADS", 2)
        before = numba.get_num_threads()
        numba.set_num_threads(2)
        try:
            sd2 = reproject_to_zed(cap.depth_mm, rig.mech, T_zed_from_mech, zed, left_span=True)
        finally:
            numba.set_num_threads(before)
        for a, b in ((sd.depth_mm, sd2.depth_mm), (sd.span_mm, sd2.span_mm), (sd.depth_right_mm, sd2.depth_right_mm),
                     (sd.nonoccluded, sd2.nonoccluded)):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="translation along x"):
        rp._project_depth_to_stereo(cap.depth_mm, rig.mech, T_zed_from_mech,
                                    T_from_rotvec([0.0, 0.01, 0.0], [-60.0, 0, 0]) @ T_zed_from_mech,
                                    zed, ReprojectParams(), False)


def test_fused_disparity_and_occlusion_match_their_definitions():
    # reproject_to_zed computes disparity and the non-occluded mask in one pass; they must equal
    # RectifiedStereo.depth_to_disparity and nonoccluded_mask (here with doffs and real occlusions)
    from gtforge.core.geometry import finite_box
    from gtforge.core.ground_truth.reproject import disparity_and_nonoccluded, nonoccluded_mask, right_view_disparity

    cam = PinholeCamera(width_px=150, height_px=90, fx_px=110.0, fy_px=104.0, cx_px=71.2, cy_px=47.9)
    zed = RectifiedStereo(left=cam, baseline_mm=63.0, doffs_px=2.5)
    rng = np.random.default_rng(5)
    depth = np.full((90, 150), 900.0, np.float32) + rng.normal(0, 2, (90, 150)).astype(np.float32)
    depth[20:60, 40:80] = 400.0
    depth[rng.random((90, 150)) < 0.05] = np.nan
    sd = reproject_to_zed(depth, cam, T_from_rotvec([0.0, 0.01, 0.0], [-20.0, 0.0, 0.0]), zed)
    disp_ref = zed.depth_to_disparity(sd.depth_mm)
    noc_ref = nonoccluded_mask(sd.depth_mm, disp_ref, sd.depth_right_mm)
    np.testing.assert_array_equal(sd.disparity_px, disp_ref)
    np.testing.assert_array_equal(sd.nonoccluded, noc_ref)
    assert (np.isfinite(disp_ref) & ~noc_ref).sum() > 100  # there are occlusions to get right
    d2, n2 = disparity_and_nonoccluded(sd.depth_mm, sd.depth_right_mm, zed, 0.05, 2.0)
    np.testing.assert_array_equal(d2, disp_ref)
    np.testing.assert_array_equal(n2, nonoccluded_mask(sd.depth_mm, disp_ref, sd.depth_right_mm, 0.05, 2.0))
    # the pass runs on the ground truth's bounding box only: a depth camera that fills a part of the image (box
    # inside the image, touching no border) and one whose GT touches the right border, as the definitions give
    occluded_right = 0
    for window in ((slice(12, 71), slice(25, 118)), (slice(0, 90), slice(60, 150))):
        part = np.full_like(depth, np.nan)
        part[window] = depth[window]
        sd = reproject_to_zed(part, cam, T_from_rotvec([0.0, 0.01, 0.0], [-20.0, 0.0, 0.0]), zed)
        box = finite_box(sd.depth_mm)
        assert 0 < (box[1] - box[0]) * (box[3] - box[2]) < 0.9 * sd.depth_mm.size, box
        disp_ref = zed.depth_to_disparity(sd.depth_mm)
        np.testing.assert_array_equal(sd.disparity_px, disp_ref)
        np.testing.assert_array_equal(sd.nonoccluded, nonoccluded_mask(sd.depth_mm, disp_ref, sd.depth_right_mm))
        # the right view: the same computation on both images mirrored left-right, mirrored back
        d1, n1 = right_view_disparity(sd.depth_mm, sd.depth_right_mm, zed)
        dm, nm = disparity_and_nonoccluded(sd.depth_right_mm[:, ::-1], sd.depth_mm[:, ::-1], zed)
        np.testing.assert_array_equal(d1, dm[:, ::-1])
        np.testing.assert_array_equal(n1, nm[:, ::-1])
        assert np.isfinite(d1).sum() > 1000
        occluded_right += (np.isfinite(d1) & ~n1).sum()
    assert occluded_right > 0  # there are right-view occlusions to get right


def test_disparity_and_occlusion_at_the_image_borders_and_odd_depths():
    # the occlusion test reads one table a row (the nearer of each pair of neighbouring other-view samples) at the
    # match column clamped to the image: matches beyond both borders, images 1-15 px wide, and depths that are NaN,
    # infinite, zero, negative or tiny, against the numpy definitions; the right view against the mirrored left view
    from gtforge.core.ground_truth.reproject import disparity_and_nonoccluded, nonoccluded_mask, right_view_disparity

    rng = np.random.default_rng(11)
    n_noc = n_occ = 0
    for _ in range(300):
        H, W = (int(x) for x in rng.integers(1, 16, 2))
        cam = PinholeCamera(width_px=W, height_px=H, fx_px=float(rng.choice([2.0, 20.0])), fy_px=20.0,
                            cx_px=W / 2, cy_px=H / 2)
        zed = RectifiedStereo(left=cam, baseline_mm=float(rng.choice([60.0, 300.0])),
                              doffs_px=float(rng.choice([0.0, 2.5, -3.0])))
        dl, dr = (rng.uniform(20, 400, (H, W)).astype(np.float32) for _ in range(2))
        for a in (dl, dr):
            a[rng.random((H, W)) < rng.choice([0.0, 0.2, 0.9])] = np.nan
            a[rng.random((H, W)) < 0.05] = rng.choice([-np.inf, 0.0, -5.0, 1e-30])
        dr[rng.random((H, W)) < 0.05] = np.inf  # (an infinite depth of its own is outside the kernel's box: no GT)
        rel, tol = float(rng.choice([0.0, 0.01, 0.2])), float(rng.choice([0.0, 0.5, 30.0]))
        d, n = disparity_and_nonoccluded(dl, dr, zed, rel, tol)
        d_ref = zed.depth_to_disparity(dl)
        np.testing.assert_array_equal(d, d_ref)
        with np.errstate(invalid="ignore"):  # (the definition casts a huge match column to int64 before clipping)
            np.testing.assert_array_equal(n, nonoccluded_mask(dl, d_ref, dr, rel, tol))
        d1, n1 = right_view_disparity(dl, dr, zed, rel, tol)
        dm, nm = disparity_and_nonoccluded(dr[:, ::-1], dl[:, ::-1], zed, rel, tol)
        np.testing.assert_array_equal(d1, dm[:, ::-1])
        np.testing.assert_array_equal(n1, nm[:, ::-1])
        n_noc += n.sum()
        n_occ += (np.isfinite(d) & ~n).sum()
    assert n_noc > 1000 and n_occ > 1000


def test_finite_box_is_the_bounding_box_of_the_finite_values():
    from gtforge.core.geometry import finite_box, mask_bounding_box

    rng = np.random.default_rng(2)
    for shape, p in (((40, 70), 0.001), ((40, 70), 0.3), ((1, 9), 0.5), ((9, 1), 0.5)):
        a = np.full(shape, np.nan, np.float32)
        a[rng.random(shape) < p] = 1.0
        a[rng.random(shape) < 0.1] = np.inf  # inf is not finite
        box = mask_bounding_box(np.isfinite(a))
        assert finite_box(a) == (box if box else (0, 0, 0, 0)), shape
    assert finite_box(np.full((5, 6), np.nan)) == (0, 0, 0, 0)
    a = np.full((5, 6), np.nan)
    a[4, 5] = -2.0
    assert finite_box(a) == (4, 5, 5, 6)
    # the search reads rows from both ends and, in the rows between, only the columns outside the box found so far:
    # boxes widened left and right by later rows, single values, full and empty rows, views with other strides
    for _ in range(400):
        shape = tuple(rng.integers(1, 25, 2))
        a = np.full(shape, np.nan, rng.choice([np.float32, np.float64]))
        a[rng.random(shape) < rng.choice([0.002, 0.02, 0.2, 1.0])] = rng.normal()
        a[rng.random(shape) < 0.05] = rng.choice([np.inf, -np.inf])
        for view in (a, a.T, a[:, ::-1]):
            box = mask_bounding_box(np.isfinite(view))
            assert finite_box(view) == (box if box else (0, 0, 0, 0))
