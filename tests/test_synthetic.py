"""The generator's truth is exact: corners agree with OpenCV detections, disparity is f*B/Z."""
import numpy as np
import pytest

from gtforge.core.targets.board import BoardSpec, check_board_spec, detect_corners
from gtforge.errors import InputError
from gtforge.synthetic import (
    default_rig,
    random_fruit_scene,
    raycast_depth,
    render_capture,
)


@pytest.fixture(scope="module")
def board_caps(session_dir):
    """Three board captures of the shared session (the generator's defaults: 0.4x, 3x3 rays a pixel) as the generator
    wrote them: images and, from truth/, the exact corners."""
    from types import SimpleNamespace

    from gtforge.io.formats import read_image

    caps = []
    for name in ("000", "001", "002"):
        tr = np.load(session_dir / "truth" / f"board_{name}.npz")
        caps.append(SimpleNamespace(mech_texture=read_image(session_dir / "board" / name / "2DImage.png"),
                                    zed_left=read_image(session_dir / "board" / name / "left.png"),
                                    corners_mech_uv=tr["corners_mech_uv"], corners_zed_uv=tr["corners_zed_uv"]))
    return default_rig(0.4), BoardSpec(), caps


@pytest.mark.slow
def test_truth_corners_match_opencv_detection(board_caps):
    rig, b, caps = board_caps
    errs = []
    for cap in caps:
        for img, uv in ((cap.mech_texture, cap.corners_mech_uv), (cap.zed_left, cap.corners_zed_uv)):
            det = detect_corners(img, b)
            assert det is not None
            errs.append(np.linalg.norm(det.corners_uv - uv, axis=1))
    e = np.concatenate(errs)
    assert e.mean() < 0.1, e.mean()
    assert np.median(e) < 0.1
    assert e.max() < 0.5  # also proves the corner order matches the truth order in both cameras


@pytest.mark.slow
def test_corner_order_survives_180_degree_turn(board_caps):
    rig, b, caps = board_caps
    cap = caps[0]
    img = cap.zed_left[::-1, ::-1].copy()  # the board seen upside down
    H, W = img.shape[:2]
    det = detect_corners(img, b)
    turned_truth = np.stack([W - 1 - cap.corners_zed_uv[:, 0], H - 1 - cap.corners_zed_uv[:, 1]], axis=1)
    assert np.linalg.norm(det.corners_uv - turned_truth, axis=1).max() < 0.5


def test_symmetric_board_refused():
    with pytest.raises(InputError, match="180 degrees"):
        check_board_spec(BoardSpec(cols=8, rows=6))


def test_truth_disparity_is_f_b_over_z():
    rig = default_rig(0.25)
    rng = np.random.default_rng(0)
    scene = random_fruit_scene(rng, rig, 5)
    cap = render_capture("s", scene, rig, rng, kind="scene", supersample=1)
    z, ids, _ = raycast_depth(scene, rig.zed.left, rig.T_zed_from_world)
    hit = np.isfinite(z)
    np.testing.assert_allclose(cap.zed_disparity_px[hit],
                               rig.zed.f_px * rig.zed.baseline_mm / z[hit] - rig.zed.doffs_px, rtol=1e-6)
    assert np.all(np.isnan(cap.zed_disparity_px[~hit]))
    # the fruit is nearer than the table: larger disparity
    assert (np.nanmedian(cap.zed_disparity_px[cap.fruit_mask])
            > np.nanmedian(cap.zed_disparity_px[hit & ~cap.fruit_mask]))
    # projector shadows: some depth is missing, and the seen mask excludes pixels the depth camera cannot see
    assert 0.002 < np.isnan(cap.depth_mm).mean() < 0.5
    assert 0.05 < cap.seen_by_mech.mean() < 0.95


def test_generator_is_deterministic_by_seed():
    rig = default_rig(0.2)
    a = render_capture("s", random_fruit_scene(np.random.default_rng(1), rig, 1), rig, np.random.default_rng(2),
                       kind="scene", supersample=1, depth_noise_mm=0.1)
    b = render_capture("s", random_fruit_scene(np.random.default_rng(1), rig, 1), rig, np.random.default_rng(2),
                       kind="scene", supersample=1, depth_noise_mm=0.1)
    np.testing.assert_array_equal(a.zed_left, b.zed_left)
    np.testing.assert_array_equal(a.depth_mm, b.depth_mm)
