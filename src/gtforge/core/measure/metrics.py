"""Stereo metrics following the ETH3D / Middlebury definitions.

* The **GT set** is every pixel with finite ground truth inside the region (and below ``max_disp_px``
  when given, as training repos do).
* A prediction is **valid** when finite (readers turn each format's invalid code into NaN).
* ``epe_px``, ``rmse_px``, ``bad_*_pct`` and ``a*_px`` are computed over GT pixels with a valid
  prediction; invalid predictions lower ``coverage_pct`` instead. The ``bad_*_all_pct`` variant
  counts invalid predictions as bad (the Middlebury "all" convention).
* ``bad_t`` = share of pixels with ``|pred - gt| > t``; ``aNN`` = the NN % quantile of ``|pred - gt|``.
* With ``max_gt_sigma_px``, GT pixels whose ground-truth sigma (``disp0GT_sigma.pfm``) is not below it are
  left out of the GT set and counted in ``n_gt_sigma_left_out`` instead.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gtforge.core.schema import GTModel

BAD_THRESHOLDS_PX = (0.5, 1.0, 2.0, 4.0)
QUANTILES = (50, 90, 95, 99)
_HIST_EDGES = np.concatenate([[0.0], np.logspace(-4, 3, 7001)])  # pooled quantiles, 0.23 % bin width


class Metrics(GTModel):
    n_gt: int
    n_valid: int
    coverage_pct: float
    epe_px: float | None
    rmse_px: float | None
    bad_0_5_pct: float | None
    bad_1_0_pct: float | None
    bad_2_0_pct: float | None
    bad_4_0_pct: float | None
    bad_0_5_all_pct: float | None
    bad_1_0_all_pct: float | None
    bad_2_0_all_pct: float | None
    bad_4_0_all_pct: float | None
    a50_px: float | None
    a90_px: float | None
    a95_px: float | None
    a99_px: float | None
    depth_mae_mm: float | None = None
    n_gt_sigma_left_out: int = 0  # GT pixels left out because their sigma was not below max_gt_sigma_px


def _key(t: float) -> str:
    return f"{t:.1f}".replace(".", "_")


class Accumulator:
    """Pooled statistics over many images (sums + an error histogram for quantiles)."""

    def __init__(self) -> None:
        self.n_gt = 0
        self.n_valid = 0
        self.sum_e = 0.0
        self.sum_e2 = 0.0
        self.bad = dict.fromkeys(BAD_THRESHOLDS_PX, 0)
        self.hist = np.zeros(len(_HIST_EDGES) - 1, np.int64)
        self.sum_depth_e = 0.0
        self.n_depth = 0
        self.n_gt_sigma_left_out = 0

    def add(self, err: np.ndarray, n_gt: int, depth_err: np.ndarray | None = None,
            n_gt_sigma_left_out: int = 0) -> None:
        self.n_gt += n_gt
        self.n_gt_sigma_left_out += n_gt_sigma_left_out
        self.n_valid += err.size
        self.sum_e += float(err.sum())
        self.sum_e2 += float((err.astype(np.float64) ** 2).sum())
        for t in BAD_THRESHOLDS_PX:
            self.bad[t] += int((err > t).sum())
        self.hist += np.histogram(np.clip(err, 0, _HIST_EDGES[-1]), _HIST_EDGES)[0]
        if depth_err is not None:
            self.sum_depth_e += float(depth_err.sum())
            self.n_depth += depth_err.size

    def result(self) -> Metrics:
        n, g = self.n_valid, self.n_gt
        q = {}
        if n:
            cdf = np.cumsum(self.hist) / n
            for p in QUANTILES:
                q[p] = float(_HIST_EDGES[1:][np.searchsorted(cdf, p / 100.0)])
        kw = {}
        for t in BAD_THRESHOLDS_PX:
            kw[f"bad_{_key(t)}_pct"] = 100.0 * self.bad[t] / n if n else None
            kw[f"bad_{_key(t)}_all_pct"] = 100.0 * (self.bad[t] + g - n) / g if g else None
        return Metrics(n_gt=g, n_valid=n, coverage_pct=100.0 * n / g if g else 0.0,
                       epe_px=self.sum_e / n if n else None, rmse_px=float(np.sqrt(self.sum_e2 / n)) if n else None,
                       a50_px=q.get(50), a90_px=q.get(90), a95_px=q.get(95), a99_px=q.get(99),
                       depth_mae_mm=self.sum_depth_e / self.n_depth if self.n_depth else None,
                       n_gt_sigma_left_out=self.n_gt_sigma_left_out, **kw)


class RegionErrors(NamedTuple):
    err: np.ndarray  # |pred - gt| (px) over GT pixels with a valid prediction
    n_gt: int  # GT pixels scored
    depth_err: np.ndarray | None  # |Z_pred - Z_gt| (mm) over the same pixels, when a depth function is given
    n_gt_sigma_left_out: int  # GT pixels left out by max_gt_sigma_px


def region_errors(pred_px: np.ndarray, gt_px: np.ndarray, region: np.ndarray | None = None,
                  max_disp_px: float | None = None, depth_fn=None, gt_sigma_px: np.ndarray | None = None,
                  max_gt_sigma_px: float | None = None) -> RegionErrors:
    """Errors of one image over its GT set (see the module docstring). ``gt_sigma_px``: ``(H, W)`` ground-truth
    sigma (NaN = none); with ``max_gt_sigma_px`` only GT pixels with ``sigma < max_gt_sigma_px`` are scored."""
    pred = np.asarray(pred_px, np.float64)
    gt = np.asarray(gt_px, np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"{pred.shape=} but expected {gt.shape} (the ground truth's shape)")
    S = np.isfinite(gt)
    if region is not None:
        S &= region
    if max_disp_px is not None:
        S &= gt < max_disp_px
    n_left_out = 0
    if max_gt_sigma_px is not None:
        if gt_sigma_px is None or np.shape(gt_sigma_px) != gt.shape:
            raise ValueError(f"max_gt_sigma_px needs gt_sigma_px of shape {gt.shape}, got "
                             f"{None if gt_sigma_px is None else np.shape(gt_sigma_px)}")
        with np.errstate(invalid="ignore"):
            certain = np.asarray(gt_sigma_px) < max_gt_sigma_px  # NaN (no sigma) is not certain
        n_left_out = int((S & ~certain).sum())
        S &= certain
    V = S & np.isfinite(pred)
    err = np.abs(pred[V] - gt[V])
    derr = None
    if depth_fn is not None:
        zp, zg = depth_fn(pred[V]), depth_fn(gt[V])
        ok = np.isfinite(zp) & np.isfinite(zg)
        derr = np.abs(zp[ok] - zg[ok])
    return RegionErrors(err, int(S.sum()), derr, n_left_out)


def metrics_from_errors(err: np.ndarray, n_gt: int, depth_err: np.ndarray | None = None,
                        n_gt_sigma_left_out: int = 0) -> Metrics:
    """One image's metrics from its errors (exact quantiles)."""
    acc = Accumulator()
    acc.add(err, n_gt, depth_err, n_gt_sigma_left_out)
    m = acc.result()
    if err.size:
        qs = np.percentile(err, QUANTILES)
        m = m.model_copy(update={f"a{p}_px": float(v) for p, v in zip(QUANTILES, qs)})
    return m


def disparity_metrics(pred_px: np.ndarray, gt_px: np.ndarray, region: np.ndarray | None = None,
                      max_disp_px: float | None = None, depth_fn=None, gt_sigma_px: np.ndarray | None = None,
                      max_gt_sigma_px: float | None = None) -> Metrics:
    """Metrics of one image. ``pred_px``/``gt_px``: ``(H, W)`` float, NaN/inf invalid. ``region``: bool mask.
    ``depth_fn``: disparity -> depth (mm); adds the mean absolute depth error. ``gt_sigma_px`` +
    ``max_gt_sigma_px``: score only GT pixels whose sigma is below the limit."""
    return metrics_from_errors(*region_errors(pred_px, gt_px, region, max_disp_px, depth_fn, gt_sigma_px,
                                              max_gt_sigma_px))


def mean_of(metrics: list[Metrics]) -> Metrics:
    """Average per image (each image weighs the same); None where no image has a value."""
    out = {}
    for f in Metrics.model_fields:
        vals = [getattr(m, f) for m in metrics if getattr(m, f) is not None]
        if f in ("n_gt", "n_valid", "n_gt_sigma_left_out"):
            out[f] = int(sum(vals))
        else:
            out[f] = float(np.mean(vals)) if vals else None
    if out["coverage_pct"] is None:
        out["coverage_pct"] = 0.0
    return Metrics(**out)
