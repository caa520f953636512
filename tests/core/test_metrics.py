import numpy as np
import pytest

from gtforge.core.measure.metrics import Accumulator, disparity_metrics, mean_of
from gtforge.training import sgra_loss, smooth_l1, weighted_smooth_l1


def test_metrics_by_hand():
    gt = np.array([[1.0, 2.0, np.nan, 4.0], [5.0, 6.0, 7.0, 8.0]])
    pred = np.array([[1.2, np.nan, 3.0, 4.0], [7.0, 6.3, np.inf, 8.9]])
    m = disparity_metrics(pred, gt)
    # GT pixels: 7; valid predictions among them: 1.2, 4.0, 7.0, 6.3, 8.9 -> errors 0.2, 0, 2, 0.3, 0.9
    assert m.n_gt == 7 and m.n_valid == 5
    assert m.coverage_pct == pytest.approx(500 / 7)
    assert m.epe_px == pytest.approx(3.4 / 5)
    assert m.rmse_px == pytest.approx(np.sqrt((0.04 + 0 + 4 + 0.09 + 0.81) / 5))
    assert m.bad_0_5_pct == pytest.approx(40.0)  # 2 and 0.9
    assert m.bad_1_0_pct == pytest.approx(20.0)  # 2 only
    assert m.bad_2_0_pct == pytest.approx(0.0)  # 2 is not > 2
    assert m.bad_0_5_all_pct == pytest.approx(400 / 7)  # + 2 invalid predictions counted as bad
    assert m.a50_px == pytest.approx(0.3)


def test_region_and_max_disp():
    gt = np.array([[1.0, 2.0], [300.0, 4.0]])
    pred = np.array([[1.5, 2.0], [0.0, 5.0]])
    region = np.array([[True, False], [True, True]])
    m = disparity_metrics(pred, gt, region, max_disp_px=192)
    assert m.n_gt == 2 and m.epe_px == pytest.approx(0.75)
    with pytest.raises(ValueError, match="shape"):
        disparity_metrics(pred[:1], gt)


def test_depth_error():
    gt = np.array([[10.0, 20.0]])
    pred = np.array([[10.5, 20.0]])
    m = disparity_metrics(pred, gt, depth_fn=lambda d: 1000.0 * 60.0 / d)
    assert m.depth_mae_mm == pytest.approx((6000.0 - 60000.0 / 10.5) / 2)


def test_pooled_vs_per_image():
    a = disparity_metrics(np.array([1.0, 1.0]), np.array([0.0, 0.0]))  # 2 pixels, EPE 1
    b = disparity_metrics(np.array([0.0] * 6), np.array([0.5] * 6))  # 6 pixels, EPE 0.5
    acc = Accumulator()
    acc.add(np.array([1.0, 1.0]), 2)
    acc.add(np.full(6, 0.5), 6)
    assert acc.result().epe_px == pytest.approx((2 + 3) / 8)
    assert mean_of([a, b]).epe_px == pytest.approx(0.75)
    assert acc.result().a50_px == pytest.approx(0.5, rel=0.005)


def test_sgra_loss_by_hand():
    gt = np.array([0.0, 0.0, 0.0, np.nan])
    w = np.array([1.4, 1.0, 0.8, 1.0])
    init = np.array([0.5, 2.0, 0.0, 9.0])
    resid = np.array([0.0, 0.5, 3.0, 9.0])
    np.testing.assert_allclose(smooth_l1(np.array([0.5, 2.0])), [0.125, 1.5])
    l_init = (1.4 * 0.125 + 1.0 * 1.5 + 0.8 * 0.0) / 3.2
    l_res = (1.4 * 0.0 + 1.0 * 0.125 + 0.8 * 2.5) / 3.2
    assert weighted_smooth_l1(init, gt, w) == pytest.approx(l_init)
    assert sgra_loss(init, resid, gt, w, gamma1=0.3, gamma2=1.0) == pytest.approx(0.3 * l_init + l_res)
    # a non-finite prediction where the label counts: NaN (inf), as the torch loss gives, not left out (the numpy
    # reference skipped it and read 0.3 * l_init + 0.125 / 2.4 where torch read NaN); where the label is NaN: ignored
    for bad, expect in ((np.nan, np.isnan), (np.inf, np.isposinf)):
        r = resid.copy()
        r[2] = bad
        assert expect(sgra_loss(init, r, gt, w, gamma1=0.3, gamma2=1.0))
        r = resid.copy()
        r[3] = bad
        assert sgra_loss(init, r, gt, w, gamma1=0.3, gamma2=1.0) == pytest.approx(0.3 * l_init + l_res)


def test_max_gt_sigma_by_hand():
    gt = np.array([[1.0, 2.0, np.nan, 4.0], [5.0, 6.0, 7.0, 8.0]])
    pred = np.array([[1.5, 2.0, 3.0, 9.0], [5.25, np.nan, 7.0, 8.0]])
    sigma = np.array([[0.1, 0.2, np.nan, 0.9], [0.3, 0.05, np.nan, 0.5]])
    # GT pixels: 7. sigma < 0.5 keeps (0,0) (0,1) (1,0) (1,1); left out: (0,3) 0.9, (1,2) no sigma,
    # (1,3) 0.5 (not below)
    m = disparity_metrics(pred, gt, gt_sigma_px=sigma, max_gt_sigma_px=0.5)
    assert (m.n_gt, m.n_gt_sigma_left_out, m.n_valid) == (4, 3, 3)
    assert m.epe_px == pytest.approx((0.5 + 0.0 + 0.25) / 3) and m.coverage_pct == pytest.approx(75.0)
    region = np.array([[True, False, True, True], [False, False, True, True]])
    r = disparity_metrics(pred, gt, region, gt_sigma_px=sigma, max_gt_sigma_px=0.5)
    assert (r.n_gt, r.n_gt_sigma_left_out) == (1, 3)
    # without the limit nothing is left out; per-image means add the counts up
    assert disparity_metrics(pred, gt).n_gt_sigma_left_out == 0
    assert mean_of([m, r]).n_gt_sigma_left_out == 6
    with pytest.raises(ValueError, match="gt_sigma_px"):
        disparity_metrics(pred, gt, max_gt_sigma_px=0.5)
