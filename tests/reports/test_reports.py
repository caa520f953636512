"""The calibration and validation reports (issue 11 items 11-12): content checked in the HTML, no browser needed."""
import re

import numpy as np
import pytest

from gtforge.calibrate import calibrate
from gtforge.records.calibration import CalibrateParams
from gtforge.reports import calibration as calib_report
from gtforge.reports import validation as val_report
from gtforge.reports.html import MISSING, Section, fmt_value, table
from gtforge.validate import validate


def _cells(html: str) -> list[str]:
    return re.findall(r"<td>(.*?)</td>", html, flags=re.S)


def _row(html: str, label: str) -> list[str]:
    m = re.search(r"<tr><td>" + re.escape(label) + r"</td>(.*?)</tr>", html, flags=re.S)
    assert m, label
    return re.findall(r"<td>(.*?)</td>", m.group(1), flags=re.S)


@pytest.fixture(scope="module")
def depth_calibration(session_dir, tmp_path_factory):
    """A --use-depth calibration on four poses (the depth method's extrinsic is the one written)."""
    out = tmp_path_factory.mktemp("calib_depth")
    res = calibrate(session_dir, out / "calibration.yaml", CalibrateParams(use_depth=True),
                    captures=["000", "002", "004", "006"])
    return res, calib_report.write_calibration_report(res, out / "report").read_text()


def test_cells_never_print_none_or_nan():
    html = table(["a", "b", "c"], [[None, float("nan"), 1.23456]], fmt=[None, None, "{:.2f}"])
    assert _cells(html) == [MISSING, MISSING, "1.23"]
    assert fmt_value(np.float32(np.inf)) == MISSING and fmt_value(3) == "3"


@pytest.mark.slow
def test_calibration_summary_describes_the_written_calibration(depth_calibration):
    res, html = depth_calibration
    assert res.method == "depth" and [m.method for m in res.methods] == ["reprojection", "depth"]
    depth = res.methods[1]
    # the written method's RMS in the ZED image, not the reprojection solve's RMS over both cameras
    assert _row(html, "RMS residual in the ZED-left image, written calibration (px)") == [f"{depth.rms_zed_px:.4f}"]
    assert _row(html, "RMS residual, both cameras (px)") == [f"{res.rms_px:.4f}"]
    assert "calibration written" in html and "depth: the depth camera&#x27;s 3-D board corners" in html
    # which solve the sigmas and the leave-one-out figures describe
    sm = calib_report.sigma_method(res)
    assert _row(html, f"1-sigma rotation x / y / z (deg), {sm} solve") == [
        " / ".join(f"{v:.4f}" for v in res.sigma_rot_xyz_deg)]
    assert _row(html, "leave-one-pose-out transfer mean / max (px), reprojection solve") == [
        f"{res.loo_transfer_mean_px:.3f} / {res.loo_transfer_max_px:.3f}"]
    # the written matrix is the depth method's
    assert f"{depth.T_zed_from_mech[0][3]:+10.3f}" in html


@pytest.mark.slow
def test_calibration_report_verdict_units_and_no_none(depth_calibration):
    res, html = depth_calibration
    assert f'<h2 class="{res.verdict.lower()}">Verdict: {res.verdict}</h2>' in html
    for r in res.verdict_reasons:  # four poses: at least "only 4 poses" is a reason to warn
        assert r.replace("'", "&#x27;") in html
    assert res.verdict_reasons and res.verdict in ("WARN", "FAIL")
    assert "None" not in "".join(_cells(html)) and "nan" not in "".join(_cells(html))
    heads = re.search(r"<h2>Poses, worst first</h2><table><thead><tr>(.*?)</tr>", html).group(1)
    heads = re.findall(r"<th>(.*?)</th>", heads)
    unitless = {"capture", "status", "reason", "blurred"}
    assert all(h in unitless or h.endswith("(px)") for h in heads), heads
    assert "key arrow" in html and "ZED-left residual vectors per view" in html
    assert re.search(r"<h2>Residual histogram \(reprojection solve\)</h2><img [^>]*src=\"data:image/png;base64,", html)
    assert re.search(r"<h2>ZED-left residual vectors per view</h2><p class=\"note\">[^<]*</p>"
                     r"<img [^>]*src=\"data:image/png", html)


@pytest.mark.slow
def test_calibration_report_is_a_list_of_sections(calibration, tmp_path):
    _, res = calibration

    def extra(c):
        return Section("Rectification quality", f"<p>{len(c.captures_used)} poses</p>", status="warn")

    html = calib_report.write_calibration_report(res, tmp_path, sections=[*calib_report.SECTIONS, extra]).read_text()
    assert html.index("Verdict:") < html.index("<h2>Summary</h2>") < html.index("Rectification quality")
    assert f'<h2 class="warn">Rectification quality</h2><p>{len(res.captures_used)} poses</p>' in html
    # the reprojection method was written: the summary's RMS is the reprojection solve's ZED RMS
    assert res.method == "reprojection"
    assert _row(html, "RMS residual in the ZED-left image, written calibration (px)") == [
        f"{res.methods[0].rms_zed_px:.4f}"]
    assert "Reprojection solve (the calibration written)" in html


@pytest.mark.slow
def test_validation_report(session_dir, true_calibration, tmp_path):
    rep = validate(session_dir, true_calibration, tmp_path, captures=["001", "005"])
    html = (tmp_path / "validation.html").read_text()
    assert '<h2 class="pass">Verdict: PASS</h2>' in html
    assert "Li et al., MI-ACVNet (MDPI, 2026)" in html
    # per-pose means against the thresholds, and the field-of-view plot: two figures
    for heading in ("Per pose against the thresholds", "Where in the field of view"):
        assert re.search(f"<h2>{heading}</h2><img [^>]*src=\"data:image/png;base64,", html), heading
    for p in rep.poses:  # D calc / D true to 0.01 mm
        row = _row(html, p.capture)
        assert row[6] == f"{p.z_diagonal_calc_mm:.2f}" and row[7] == f"{p.z_diagonal_true_mm:.2f}"
    assert "None" not in "".join(_cells(html))
    # a FAIL is coloured too
    rep2 = rep.model_copy(update={"passed": False, "pass_xy": False})
    out = val_report.write_validation_report(rep2, tmp_path / "fail", session_zed_camera(session_dir))
    assert '<h2 class="fail">Verdict: FAIL</h2>' in out.read_text()


def session_zed_camera(session_dir):
    from gtforge.io.captures import open_session

    return open_session(session_dir).zed.left


def test_error_maps_are_matplotlibs_colours_and_bars_are_drawn_once():
    """heatmap_rgb looks colours up in the colour map's byte table: the same pixels as matplotlib's float RGBA
    image cast to bytes (float32 and float64 errors, values at and above the top, NaN, inf); colorbar_strip hands out
    copies of the bar drawn first for the same arguments, equal to a fresh drawing."""
    import matplotlib

    from gtforge.reports import evaluation as ev

    rng = np.random.default_rng(3)
    cmap = matplotlib.colormaps[ev.ERROR_CMAP]
    for dtype, vmax in ((np.float32, 2.0), (np.float64, 3.7), (np.float32, 0.3)):
        err = (rng.random((61, 300)) * 1.3 * vmax).astype(dtype)
        err[0, :5] = [vmax, 0.0, np.nan, np.inf, vmax * (1 - 1e-7)]
        err[1, :256] = np.arange(256) / 256 * vmax  # every entry boundary
        with np.errstate(over="ignore"):  # inf: nan_to_num's largest float over vmax < 1
            want = (cmap(np.clip(np.nan_to_num(err, nan=0.0) / vmax, 0, 1))[..., :3] * 255).astype(np.uint8)
            got = ev.heatmap_rgb(err, vmax)
        want[~np.isfinite(err)] = 0
        np.testing.assert_array_equal(got, want)
    a = ev.colorbar_strip(320, 2.0, "|disparity error| (px)", 56)
    a[:] = 0  # a caller's change does not reach the one kept
    b = ev.colorbar_strip(320, 2.0, "|disparity error| (px)", 56)
    fresh = ev._colorbar_strip.__wrapped__(320, 2.0, "|disparity error| (px)", 56)
    assert b.shape == (56, 320, 3) and b.any()
    np.testing.assert_array_equal(b, fresh)


def test_sigma_thumbnail_pixels(tmp_path, monkeypatch):
    """The thumbnail's image before JPEG: turbo colours of sigma over 0..vmax, black where sigma is NaN or inf, the
    map resized to 640 px wide by nearest neighbour."""
    import cv2

    from gtforge.reports import build

    rng = np.random.default_rng(5)
    sigma = rng.uniform(0, 0.15, (90, 1280)).astype(np.float32)
    sigma[rng.random(sigma.shape) < 0.3] = np.nan
    sigma[::7, ::5] = np.inf
    sigma[3, ::3] = -np.inf
    written = {}
    monkeypatch.setattr(build, "write_image", lambda path, img: written.setdefault("rgb", img))
    build.write_sigma_thumbnail(tmp_path / "s.jpg", sigma)
    s = cv2.resize(sigma, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_NEAREST)
    grey = np.round(np.clip(np.where(np.isfinite(s), s, 0) / 0.1, 0, 1) * 255).astype(np.uint8)
    want = cv2.applyColorMap(grey, cv2.COLORMAP_TURBO)[..., ::-1] * np.isfinite(s)[..., None]
    assert written["rgb"].shape == (45, 640, 3) and (~np.isfinite(s)).any()
    np.testing.assert_array_equal(written["rgb"], want)


def test_comparison_and_results_pages_never_round_a_share_onto_100(tmp_path):
    """compare's comparison.html (and evaluate's results.html) showed a coverage of 99.997 % as '100' (4 significant
    digits) while results.json and comparison.md said 99.997: an incomplete coverage read as complete."""
    from gtforge.core.measure.metrics import Metrics
    from gtforge.records.evaluation import EvalResult, SceneResult
    from gtforge.reports.evaluation import tables_markdown, write_comparison_html, write_eval_html

    def metrics(cov):
        return Metrics(n_gt=300000, n_valid=299991, coverage_pct=cov, epe_px=0.17, rmse_px=0.28, bad_0_5_pct=1.244,
                       bad_1_0_pct=0.0002, bad_2_0_pct=0.0, bad_4_0_pct=0.0, bad_0_5_all_pct=None,
                       bad_1_0_all_pct=None, bad_2_0_all_pct=None, bad_4_0_all_pct=None, a50_px=None, a90_px=None,
                       a95_px=None, a99_px=None)

    regions = {r: metrics(99.997) for r in ("all", "fruit", "fruit_edge", "fruit_centre")}
    rep = EvalResult(model="m", provider="cpu", dataset_dir="/d", scenes=["000"], pooled=regions,
                     per_image_mean=regions, per_scene=[SceneResult(scene="000", time_ms=1.0, metrics=regions)])
    page = write_comparison_html([rep], [tmp_path / "results.json"], ["m"], [], tmp_path / "comparison.html")
    row = _row(page.read_text(), "m")
    # region, GT pixels, EPE, RMSE, Bad-0.5, Bad-1.0, Bad-2.0, coverage, depth MAE, time
    assert row[4:8] == ["1.244", "&lt; 0.001", "0.000", "99.997"]
    md_row = next(line for line in tables_markdown([rep]).splitlines() if line.startswith("| m | all |"))
    assert md_row.split(" | ")[5:9] == ["1.244", "< 0.001", "0.000", "99.997"]
    rep.pooled["all"] = rep.per_scene[0].metrics["all"] = metrics(99.9996)
    (tmp_path / "ev").mkdir()
    page = write_eval_html(rep, tmp_path / "ev").read_text()
    assert _row(page, "all")[-2] == "&gt; 99.999"  # the pooled table's coverage (then depth MAE)
    assert _row(page, "000")[4] == "&gt; 99.999"  # the per-scene table's


def test_params_count_shows_in_every_table(tmp_path):
    """evaluate --params-count N ('Parameter count for the table') reached results.json only: results.md/.csv/.html and
    compare's tables showed no size (the docs run-through, session 18). A column where some result has it."""
    import csv

    from gtforge.core.measure.metrics import Metrics
    from gtforge.records.evaluation import EvalResult, SceneResult
    from gtforge.reports.evaluation import tables_markdown, write_comparison_html, write_eval_html, write_tables

    m = Metrics(n_gt=100, n_valid=100, coverage_pct=100.0, epe_px=0.17, rmse_px=0.28, bad_0_5_pct=1.0,
                bad_1_0_pct=0.5, bad_2_0_pct=0.0, bad_4_0_pct=0.0, bad_0_5_all_pct=None, bad_1_0_all_pct=None,
                bad_2_0_all_pct=None, bad_4_0_all_pct=None, a50_px=None, a90_px=None, a95_px=None, a99_px=None)
    regions = {r: m for r in ("all", "fruit", "fruit_edge", "fruit_centre")}

    def result(name, n):
        return EvalResult(model=name, provider="cpu", dataset_dir="/d", scenes=["000"], pooled=regions,
                          per_image_mean=regions, per_scene=[SceneResult(scene="000", time_ms=1.0, metrics=regions)],
                          time_ms_median=2.0, params_count=n)

    big, sgbm = result("net", 1234567), result("sgbm", None)
    md = tables_markdown([big, sgbm]).splitlines()
    head = next(line for line in md if line.startswith("| model |")).split(" | ")
    assert head[-1] == "parameters |"
    assert next(line for line in md if line.startswith("| net | all |")).endswith("| 2.000 | 1234567 |")
    assert next(line for line in md if line.startswith("| sgbm | all |")).endswith("| 2.000 | - |")
    write_tables([big, sgbm], tmp_path)
    rows = list(csv.reader((tmp_path / "results.csv").open()))
    assert rows[0][-2:] == ["time (ms/frame)", "parameters"] and rows[1][-1] == "1234567" and rows[-1][-1] == ""
    page = write_comparison_html([big, sgbm], [tmp_path / "a.json", tmp_path / "b.json"], ["net", "sgbm"], [],
                                 tmp_path / "comparison.html").read_text()
    assert _row(page, "net")[-1] == "1234567" and _row(page, "sgbm")[-1] == MISSING
    (tmp_path / "ev").mkdir()
    page = write_eval_html(big, tmp_path / "ev").read_text()
    assert "1,234,567 parameters" in page and _row(page, "all")[-1] == MISSING  # depth MAE last, as before
    # without --params-count the tables are as they were
    assert "parameters" not in tables_markdown([sgbm])


def test_rectification_line_counts_one_pose_as_one():
    """validate --holdout 1 measures one pose: 'on 1 pose', not 'on 1 poses' (the docs run-through, session 18)."""
    from types import SimpleNamespace

    from gtforge.reports.rectification import summary_lines

    overall = SimpleNamespace(fit_mean_abs_px=0.009, mean_abs_px=0.047, max_abs_px=0.157)
    one = summary_lines(SimpleNamespace(overall=overall, poses=["004"], threshold_px=0.15))
    two = summary_lines(SimpleNamespace(overall=overall, poses=["003", "004"], threshold_px=0.15))
    assert one == ["ZED vertical disparity on 1 pose: mean 0.009 px (fitted corners), 0.047 px (detected; "
                   "max 0.157 px); threshold 0.15 px"]
    assert two[0].startswith("ZED vertical disparity on 2 poses: mean 0.009 px")
