import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from gtforge.cli import app
from gtforge.errors import InputError
from gtforge.evaluate import EvalReport, compare, evaluate
from gtforge.io.formats import read_image, read_pfm, write_kitti_disparity, write_pfm
from gtforge.predictors import SGBM, OnnxModel, PredictionFolder
from gtforge.training import StereoDataset


def constant_onnx(path, value: float, six_channels=False):
    import onnx
    from onnx import TensorProto, helper

    zero = helper.make_tensor("zero", TensorProto.FLOAT, [], [0.0])
    c = helper.make_tensor("c", TensorProto.FLOAT, [], [value])
    axes = helper.make_tensor("axes", TensorProto.INT64, [1], [1])
    if six_channels:
        inputs = [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 6, "H", "W"])]
        nodes = [helper.make_node("Mul", ["x", "zero"], ["z"])]
    else:
        inputs = [helper.make_tensor_value_info("left", TensorProto.FLOAT, ["N", 3, "H", "W"]),
                  helper.make_tensor_value_info("right", TensorProto.FLOAT, ["N", 3, "H", "W"])]
        nodes = [helper.make_node("Add", ["left", "right"], ["s"]), helper.make_node("Mul", ["s", "zero"], ["z"])]
    nodes += [helper.make_node("ReduceSum", ["z", "axes"], ["r"], keepdims=0), helper.make_node("Add", ["r", "c"], ["disp"])]
    graph = helper.make_graph(nodes, "const", inputs, [helper.make_tensor_value_info("disp", TensorProto.FLOAT, ["N", "H", "W"])],
                              initializer=[zero, c, axes])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, path)
    return path


def _expected_epe(ds, value):
    errs = []
    for s in sorted((ds / "scenes").iterdir()):
        gt = read_pfm(s / "disp0GT.pfm")
        m = (read_image(s / "mask0nocc.png") > 0) & np.isfinite(gt)
        errs.append(np.abs(value - gt[m]))
    return float(np.concatenate(errs).mean())


def test_onnx_model_end_to_end_through_the_cli(dataset, tmp_path):
    ds, _ = dataset
    model = constant_onnx(tmp_path / "const.onnx", 35.0)
    r = CliRunner().invoke(app, ["evaluate", str(ds), "--onnx", str(model), "-o", str(tmp_path / "ev"), "--no-clouds"])
    assert r.exit_code == 0, r.output
    rep = EvalReport.read(tmp_path / "ev" / "results.json")
    assert rep.pooled["all"].epe_px == pytest.approx(_expected_epe(ds, 35.0), rel=1e-5)
    assert rep.pooled["all"].coverage_pct == 100.0
    assert rep.time_ms_median is not None and rep.time_ms_median > 0
    md = (tmp_path / "ev" / "results.md").read_text()
    assert "| const | fruit_edge |" in md and "Bad-0.5" in md
    assert (tmp_path / "ev" / "results.csv").read_text().count("\n") == 5
    assert len(list((tmp_path / "ev" / "heatmaps").glob("*.png"))) == 6


def test_six_channel_onnx_and_resize(dataset, tmp_path):
    ds, _ = dataset
    from gtforge.predictors import InputConvention

    m = OnnxModel(constant_onnx(tmp_path / "c6.onnx", 20.0, six_channels=True),
                  InputConvention(fit="resize", resize_wh=(320, 192)))
    s = ds / "scenes" / "000"
    d = m.predict("000", read_image(s / "im0.png"), read_image(s / "im1.png"))
    # resized back to full width, disparity scaled by the width ratio
    assert d.shape == (497, 883) and d[10, 10] == pytest.approx(20.0 * 883 / 320, rel=1e-5)


def test_onnx_with_unexpected_inputs_is_refused(tmp_path):
    import onnx
    from onnx import TensorProto, helper

    g = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g",
                          [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3])],
                          [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3])])
    mdl = helper.make_model(g, opset_imports=[helper.make_opsetid("", 13)])
    mdl.ir_version = 8
    onnx.save(mdl, tmp_path / "bad.onnx")
    with pytest.raises(InputError, match=r"inputs.*two NCHW inputs.*x\[1, 3\]"):
        OnnxModel(tmp_path / "bad.onnx")


def test_sgbm_baseline_is_plausible(dataset, tmp_path):
    ds, _ = dataset
    rep = evaluate(ds, SGBM(), tmp_path, write_clouds=True)
    allm = rep.pooled["all"]
    assert allm.coverage_pct > 80 and 0 < allm.epe_px < 1.0
    assert rep.pooled["fruit"].depth_mae_mm is not None and 0 < rep.pooled["fruit"].depth_mae_mm < 20
    assert len(list((tmp_path / "clouds").glob("*.ply"))) == 3
    html = (tmp_path / "results.html").read_text()
    assert "Per scene, worst first" in html and html.count("data:image/png;base64") == 6
    table = compare([tmp_path / "results.json", tmp_path / "results.json"], tmp_path / "cmp")
    assert table.count("| SGBM | all |") == 2


def test_prediction_folder_with_missing_and_wrong_size(dataset, tmp_path):
    ds, _ = dataset
    preds = tmp_path / "preds"
    preds.mkdir()
    gt0 = read_pfm(ds / "scenes" / "000" / "disp0GT.pfm")
    write_pfm(preds / "000.pfm", gt0 + 0.25)
    write_kitti_disparity(preds / "001_10.png", np.ones((10, 10), np.float32))  # wrong size
    rep = evaluate(ds, PredictionFolder(preds), tmp_path / "ev")
    assert rep.scenes == ["000"] and set(rep.missing) == {"001", "002"}
    assert "883x497" in rep.missing["001"] and "missing" in rep.missing["002"]
    assert rep.pooled["all"].epe_px == pytest.approx(0.25, abs=1e-5)
    r = subprocess.run([sys.executable, "-m", "gtforge.cli", "evaluate", str(ds), "--predictions", str(preds),
                        "-o", str(tmp_path / "ev2"), "--no-clouds"], capture_output=True, text=True)
    assert r.returncode == 1 and "2 scene(s) excluded" in r.stdout and "Traceback" not in r.stderr


def test_loader_yields_training_arrays(dataset):
    ds, _ = dataset
    items = list(StereoDataset(ds, split=None))
    assert len(items) == 3
    it = items[0]
    assert it["left"].shape == (497, 883, 3) and it["disparity"].dtype == np.float32
    np.testing.assert_array_equal(it["valid"], np.isfinite(it["disparity"]))
    assert set(np.unique(it["weight"][it["valid"]])) <= {np.float32(0.8), np.float32(1.0), np.float32(1.4)}
