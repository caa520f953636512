import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import gtforge, one_line_error
from typer.testing import CliRunner

from gtforge.cli.commands import app
from gtforge.errors import InputError
from gtforge.evaluate import compare, evaluate
from gtforge.io.formats import read_image, read_pfm, write_kitti_disparity, write_pfm
from gtforge.predictors import SGBM, OnnxModel, PredictionFolder
from gtforge.records.evaluation import EvalResult
from gtforge.training import StereoDataset


def constant_onnx(path, value: float, six_channels=False, elem_type=None, dims=("N", 3, "H", "W"), step=1):
    """A stereo "network" whose disparity is ``value`` everywhere. ``elem_type``: its inputs' ONNX type (float32 by
    default; others are cast to float inside); ``dims``: each input's shape; ``step``: its output has every
    ``step``-th row and column of the input's (a 1/step-size disparity)."""
    import onnx
    from onnx import TensorProto, helper

    elem_type = TensorProto.FLOAT if elem_type is None else elem_type
    zero = helper.make_tensor("zero", TensorProto.FLOAT, [], [0.0])
    c = helper.make_tensor("c", TensorProto.FLOAT, [], [value])
    axes = helper.make_tensor("axes", TensorProto.INT64, [1], [1])
    big = helper.make_tensor("big", TensorProto.INT64, [2], [1 << 30, 1 << 30])
    start = helper.make_tensor("start", TensorProto.INT64, [2], [0, 0])
    hw = helper.make_tensor("hw", TensorProto.INT64, [2], [2, 3])
    steps = helper.make_tensor("steps", TensorProto.INT64, [2], [step, step])
    if six_channels:
        inputs = [helper.make_tensor_value_info("x", elem_type, ["N", 6, "H", "W"])]
        nodes = [helper.make_node("Cast", ["x"], ["s"], to=TensorProto.FLOAT)]
    else:
        inputs = [helper.make_tensor_value_info("left", elem_type, list(dims)),
                  helper.make_tensor_value_info("right", elem_type, list(dims))]
        nodes = [helper.make_node("Cast", ["left"], ["lf"], to=TensorProto.FLOAT),
                 helper.make_node("Cast", ["right"], ["rf"], to=TensorProto.FLOAT),
                 helper.make_node("Add", ["lf", "rf"], ["s"])]
    nodes += [helper.make_node("Mul", ["s", "zero"], ["z0"]),
              helper.make_node("Slice", ["z0", "start", "big", "hw", "steps"], ["z"]),
              helper.make_node("ReduceSum", ["z", "axes"], ["r"], keepdims=0),
              helper.make_node("Add", ["r", "c"], ["disp"])]
    graph = helper.make_graph(nodes, "const", inputs,
                              [helper.make_tensor_value_info("disp", TensorProto.FLOAT, ["N", "h", "w"])],
                              initializer=[zero, c, axes, big, start, hw, steps])
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


@pytest.mark.slow
def test_onnx_model_end_to_end_through_the_cli(dataset, tmp_path):
    ds, _ = dataset
    model = constant_onnx(tmp_path / "const.onnx", 35.0)
    r = CliRunner().invoke(app, ["evaluate", str(ds), "--onnx", str(model), "-o", str(tmp_path / "ev"), "--no-clouds"])
    assert r.exit_code == 0, r.output
    rep = EvalResult.read(tmp_path / "ev" / "results.json")
    assert rep.pooled["all"].epe_px == pytest.approx(_expected_epe(ds, 35.0), rel=1e-5)
    assert rep.pooled["all"].coverage_pct == 100.0
    assert rep.time_ms_median is not None and rep.time_ms_median > 0
    md = (tmp_path / "ev" / "results.md").read_text()
    assert "| const | fruit_edge |" in md and "Bad-0.5" in md
    assert (tmp_path / "ev" / "results.csv").read_text().count("\n") == 5
    assert len(list((tmp_path / "ev" / "heatmaps").glob("*.png"))) == 6


@pytest.mark.slow
def test_six_channel_onnx_and_resize(dataset, tmp_path):
    ds, _ = dataset
    from gtforge.predictors import InputConvention

    m = OnnxModel(constant_onnx(tmp_path / "c6.onnx", 20.0, six_channels=True),
                  InputConvention(fit="resize", resize_wh=(320, 192)))
    s = ds / "scenes" / "000"
    d = m.predict("000", read_image(s / "im0.png"), read_image(s / "im1.png"))
    # resized back to full width, disparity scaled by the width ratio
    assert d.shape == (497, 883) and d[10, 10] == pytest.approx(20.0 * 883 / 320, rel=1e-5)


def test_onnx_inputs_named_right_then_left_get_those_images(tmp_path):
    """Inputs were fed by position only: a graph whose inputs are (right, left) got the left image as 'right' (a
    run-through). The names decide where they say so."""
    import onnx
    from onnx import TensorProto, helper

    from gtforge.predictors import InputConvention

    def red_of(name, inputs):  # a "network" whose disparity is one input's first channel
        axes = helper.make_tensor("axes", TensorProto.INT64, [1], [1])
        one = helper.make_tensor("one", TensorProto.INT64, [1], [1])
        zero = helper.make_tensor("zero", TensorProto.INT64, [1], [0])
        g = helper.make_graph([helper.make_node("Slice", [name, "zero", "one", "axes"], ["disp"])], "g",
                              [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["N", 3, "H", "W"]) for n in inputs],
                              [helper.make_tensor_value_info("disp", TensorProto.FLOAT, ["N", 1, "H", "W"])],
                              initializer=[axes, one, zero])
        mdl = helper.make_model(g, opset_imports=[helper.make_opsetid("", 13)])
        mdl.ir_version = 8
        onnx.save(mdl, tmp_path / f"{name}_{'_'.join(inputs)}.onnx")
        return OnnxModel(tmp_path / f"{name}_{'_'.join(inputs)}.onnx", InputConvention(normalize="0-255"))

    rng = np.random.default_rng(3)
    left, right = (rng.integers(0, 255, (40, 64, 3)).astype(np.uint8) for _ in range(2))
    for m, want in ((red_of("left_img", ["right_img", "left_img"]), left),  # named the other way round
                    (red_of("left", ["left", "right"]), left), (red_of("a", ["a", "b"]), left),  # in order
                    (red_of("b", ["a", "b"]), right)):
        np.testing.assert_array_equal(m.predict("x", left, right), want[..., 0].astype(np.float32))


def test_evaluate_options_that_do_not_apply_are_said(dataset, tmp_path):
    """--grades with --no-fruit-size, a negative --params-count: refused in one line; a network's input options
    with --predictions or --sgbm: a warning (all were silently ignored or stored; a run-through)."""

    ds, _ = dataset
    r = CliRunner().invoke(app, ["evaluate", str(ds), "--sgbm", "--no-fruit-size", "--grades", "diameter_mm:180,200",
                                 "-o", str(tmp_path / "ev")])
    assert type(r.exception).__name__ == "InputError" and str(r.exception).startswith(
        "--grades: expected the fruit measured"), r.output  # (the command prints it in one line, exit code 2)
    r = CliRunner().invoke(app, ["evaluate", str(ds), "--sgbm", "--params-count", "-3", "-o", str(tmp_path / "ev")])
    assert r.exit_code == 2 and "--params-count" in r.output and not (tmp_path / "ev").exists()
    r = CliRunner().invoke(app, ["evaluate", str(ds), "--sgbm", "--channels", "BGR", "--fit", "resize", "--resize",
                                 "320x192", "--no-fruit-size", "-o", str(tmp_path / "ev_sgbm")])
    assert r.exit_code == 0, r.output
    assert "--channels, --fit, --resize shape a network's input (--onnx, --torchscript): ignored for --sgbm" in \
        r.output


def tiny_dataset(root: Path, built: list[str], listed: list[str]) -> Path:
    """A dataset laid out by hand, fast: scenes ``built`` (16x8 px, ground truth 4.0 px, all background) and a
    manifest.json that lists ``listed``."""
    from gtforge.io.formats import write_image

    for sid in built:
        s = root / "scenes" / sid
        s.mkdir(parents=True)
        rgb = np.full((8, 16, 3), 100, np.uint8)
        write_image(s / "im0.png", rgb)
        write_image(s / "im1.png", rgb)
        write_pfm(s / "disp0GT.pfm", np.full((8, 16), 4.0, np.float32))
        write_image(s / "region.png", np.ones((8, 16), np.uint8))
        write_image(s / "mask0nocc.png", np.full((8, 16), 255, np.uint8))
        (s / "calib.txt").write_text("cam0=[100 0 8; 0 100 4; 0 0 1]\ncam1=[100 0 8; 0 100 4; 0 0 1]\ndoffs=0\n"
                                     "baseline=63\nwidth=16\nheight=8\nndisp=16\n")
    (root / "manifest.json").write_text(json.dumps({"scenes": {sid: {} for sid in listed}}))
    return root


def constant_predictions(folder: Path, ids: list[str], value: float) -> PredictionFolder:
    folder.mkdir()
    for sid in ids:
        write_pfm(folder / f"{sid}.pfm", np.full((8, 16), value, np.float32))
    return PredictionFolder(folder)


@pytest.mark.parametrize("text, got", [
    ("{", "a parse error at line 1, column 2: Expecting property name enclosed in double quotes"),
    ("[1, 2]", "a JSON list, not a mapping"),
    ("", "a parse error at line 1, column 1: Expecting value")])
def test_a_manifest_that_is_no_json_mapping_is_refused_before_any_output(tmp_path, text, got):
    """A dataset whose manifest.json is cut short or overwritten: one line naming it, nothing written (it was read as
    {} and the scenes scored, exit 0, nothing said: no check of the output against the session the dataset came
    from, flagged and quarantined scenes not named, no content hash for compare)."""
    ds = tiny_dataset(tmp_path / "ds", ["000"], ["000"])
    pred = constant_predictions(tmp_path / "pred", ["000"], 4.5)
    assert evaluate(ds, pred, None, fruit_size=False).pooled["all"].epe_px == pytest.approx(0.5)  # the JSON one
    (ds / "manifest.json").write_text(text)
    with pytest.raises(InputError) as e:
        evaluate(ds, pred, tmp_path / "eval", fruit_size=False)
    assert e.value.file == str(ds / "manifest.json") and e.value.actual.startswith(got)
    assert "build-dataset" in e.value.hint and not (tmp_path / "eval").exists()


def test_a_scene_the_manifest_lists_whose_folder_is_gone_is_not_scored_and_named(tmp_path, caplog):
    """Evaluating every scene of a dataset one of whose scene folders was deleted: that scene is listed as not scored
    (exit 1), the hint naming build-dataset, as a split that lists it already did; it was left out silently, exit 0,
    the results pooled over the others as if they were the dataset."""
    import logging

    ds = tiny_dataset(tmp_path / "ds", ["000", "002"], ["000", "001", "002"])
    pred = constant_predictions(tmp_path / "pred", ["000", "001", "002"], 4.5)
    with caplog.at_level(logging.ERROR, logger="gtforge"):
        rep = evaluate(ds, pred, None, fruit_size=False)
    assert rep.scenes == ["000", "002"] and list(rep.missing) == ["001"]
    assert rep.missing["001"].startswith(f"{ds / 'scenes' / '001'}: expected the scene's folder (manifest.json lists "
                                         "it), got no such folder") and "build-dataset" in rep.missing["001"]
    assert [r.getMessage() for r in caplog.records] == [f"scene 001: {rep.missing['001']}"]
    assert rep.pooled["all"].epe_px == pytest.approx(0.5) and rep.pooled["all"].n_gt == 2 * 8 * 16
    r = CliRunner().invoke(app, ["evaluate", str(ds), "--predictions", str(tmp_path / "pred"), "-o",
                                 str(tmp_path / "eval")])
    assert r.exit_code == 1, r.output
    for sid in ("000", "002"):  # no prediction for the others: said as before, the gone scene on its own
        (tmp_path / "pred" / f"{sid}.pfm").unlink()
    with pytest.raises(InputError, match=r"got none for the 2 scene\(s\) \(000, 002\)"):
        evaluate(ds, pred, None, fruit_size=False)


def test_a_cut_off_build_and_a_low_resolution_output_are_said(dataset, tmp_path, caplog):
    """Scene folders a stopped build landed without listing them in manifest.json are scored with a warning (they
    are neither verified nor split); a dataset file missing names the build as the fix (it said 'check the capture
    folder / session.yaml'); with --fit resize an output smaller than the resized input is read in its own pixels,
    said once (a run-through of each)."""
    import logging

    from gtforge.predictors import InputConvention

    ds0, _ = dataset
    ds = tmp_path / "ds"
    shutil.copytree(ds0, ds)
    man = json.loads((ds / "manifest.json").read_text())
    del man["scenes"]["002"]
    (ds / "manifest.json").write_text(json.dumps(man))
    (ds / "scenes" / "001" / "region.png").unlink()
    model = OnnxModel(constant_onnx(tmp_path / "half.onnx", 10.0, step=2),
                      InputConvention(fit="resize", resize_wh=(320, 192)))
    with caplog.at_level(logging.WARNING, logger="gtforge"):
        rep = evaluate(ds, model, None, fruit_size=False)
    said = [r.getMessage() for r in caplog.records]
    assert any(m.startswith("1 of 3 scene(s) are not in ") and ", so not verified nor in a split: 002; scored like "
               "the others. Either a build stopped before it finished (run build-dataset again to finish it) or the "
               "session no longer holds their captures" in m for m in said)
    assert rep.scenes == ["000", "002"] and "run build-dataset again" in rep.missing["001"]
    assert "check the capture folder" not in rep.missing["001"]
    low = [m for m in said if "its output is 160x96 px, not its input's 320x192" in m]
    assert len(low) == 1 and "scaled by 5.519" in low[0], said  # 883 / 160
    assert rep.pooled["all"].epe_px == pytest.approx(
        float(np.mean(np.concatenate([np.abs(10.0 * 883 / 160 - g[m]) for g, m in (
            (read_pfm(ds / "scenes" / s / "disp0GT.pfm"), (read_image(ds / "scenes" / s / "mask0nocc.png") > 0)
             & np.isfinite(read_pfm(ds / "scenes" / s / "disp0GT.pfm"))) for s in ("000", "002"))]))), rel=1e-4)


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


def test_bgr_input_is_normalised_with_each_colours_own_statistics():
    """--channels BGR --normalize imagenet: the channels flipped, then each normalised with its own colour's
    ImageNet mean and std (the blue channel took red's before: a run-through measured the shift)."""
    from gtforge.predictors import InputConvention

    img = np.array([[[200, 100, 50]]], np.uint8)  # R, G, B
    rgb = InputConvention(channels="RGB").prepare(img)[0, :, 0, 0]
    bgr = InputConvention(channels="BGR").prepare(img)[0, :, 0, 0]
    want = {"R": (200 / 255 - 0.485) / 0.229, "G": (100 / 255 - 0.456) / 0.224, "B": (50 / 255 - 0.406) / 0.225}
    np.testing.assert_allclose(rgb, [want["R"], want["G"], want["B"]], rtol=1e-6)
    np.testing.assert_allclose(bgr, [want["B"], want["G"], want["R"]], rtol=1e-6)


@pytest.mark.parametrize("normalize,pad_where", [("imagenet", "top-right"), ("0-1", "bottom-right")])
def test_the_pad_band_is_zero_in_the_networks_input(normalize, pad_where):
    """--fit pad pads after the normalisation, as Fast-ACVNet's loaders do: the band is 0 in the network's input
    (ImageNet's mean colour under its normalisation); padded before it, a black band became -2.1/-2.0/-1.8."""
    from gtforge.predictors import InputConvention, _network_input

    img = np.random.default_rng(1).integers(0, 256, (45, 70, 3), np.uint8)
    conv = InputConvention(normalize=normalize, pad_where=pad_where)
    x, info = _network_input(conv, img)
    assert x.shape == (1, 3, 64, 96) and x.dtype == np.float32
    assert info == ("pad", 45, 70, 19 * (pad_where == "top-right"))
    top = info[3]
    np.testing.assert_array_equal(x[:, :, top:top + 45, :70], conv.prepare(img))
    band = np.ones(x.shape, bool)
    band[:, :, top:top + 45, :70] = False
    assert band.sum() == 3 * (64 * 96 - 45 * 70) and not x[band].any()


def test_a_torchscript_models_output_is_a_tensor_or_names_what_it_is():
    """A TorchScript model returning a dict crashed evaluate with a traceback ('dict' object has no attribute
    'float'; a run-through): a dict's one tensor is the disparity, a list's or tuple's last; two tensors in a dict,
    or no tensor at all, are one line naming what came out."""
    from gtforge.predictors import _torch_disparity

    class FakeTensor:  # the four calls the conversion makes (torch is an optional extra, not installed in CI)
        def __init__(self, a):
            self.a = a

        def detach(self):
            return self

        def float(self):
            return FakeTensor(self.a.astype(np.float32))

        def cpu(self):
            return self

        def numpy(self):
            return self.a

    a, b = np.full((2, 3), 25.0), np.zeros((2, 3))
    for out in (FakeTensor(a), [FakeTensor(b), FakeTensor(a)], (FakeTensor(a),), {"disp": FakeTensor(a), "n": 3}):
        got = _torch_disparity(Path("m.pt"), out)
        assert got.dtype == np.float32 and np.array_equal(got, a)
    with pytest.raises(InputError, match=r"m.pt \[output\]: .* got a dict with 2 tensors \(disp, conf\)"):
        _torch_disparity(Path("m.pt"), {"disp": FakeTensor(a), "conf": FakeTensor(b)})
    with pytest.raises(InputError, match=r"got str \(hint: wrap the model"):
        _torch_disparity(Path("m.pt"), "disparity")


@pytest.mark.slow
def test_onnx_model_mistakes_stop_before_scoring(dataset, tmp_path):
    """A model onnxruntime cannot run on the scenes (a fixed input size, a channels-last or integer input, a
    1/4-size output) is refused in one line naming the model and what to do, before any scene is scored: not once
    per scene, not an onnxruntime traceback. A float16 model is fed float16 and scores as the float32 one."""
    from onnx import TensorProto

    from gtforge.predictors import InputConvention

    ds, _ = dataset
    fixed = constant_onnx(tmp_path / "fixed.onnx", 35.0, dims=(1, 3, 256, 512))
    # (each message starts with the model: one error, not the per-scene errors' summary, which names the dataset)
    with pytest.raises(InputError, match=rf"^{re.escape(str(fixed))} \[inputs\]: expected 512x256 px \(its fixed "
                                         r"input size\), got 896x512 px after --fit pad.*"
                                         r"--fit resize --resize 512x256"):
        evaluate(ds, OnnxModel(fixed), tmp_path / "ev")
    assert not (tmp_path / "ev").exists()  # nothing written
    rep = evaluate(ds, OnnxModel(fixed, InputConvention(fit="resize", resize_wh=(512, 256))), tmp_path / "ev")
    assert rep.pooled["all"].coverage_pct == 100.0 and not rep.missing
    quarter = constant_onnx(tmp_path / "quarter.onnx", 35.0, step=4)
    with pytest.raises(InputError, match=rf"^{re.escape(str(quarter))} \[output\]: expected a disparity map of the "
                                         r"input's size, 896x512 px, got 224x128 px"):
        evaluate(ds, OnnxModel(quarter), tmp_path / "ev2")
    with pytest.raises(InputError, match=r"\[inputs\]: expected two NCHW inputs.*\(channels last, NHWC\)"):
        OnnxModel(constant_onnx(tmp_path / "nhwc.onnx", 1.0, dims=("N", "H", "W", 3)))
    with pytest.raises(InputError, match=r"\[inputs\]: expected float image inputs.*left tensor\(uint8\)"):
        OnnxModel(constant_onnx(tmp_path / "u8.onnx", 1.0, elem_type=TensorProto.UINT8))
    half = OnnxModel(constant_onnx(tmp_path / "half.onnx", 35.0, elem_type=TensorProto.FLOAT16))
    assert half.dtype == np.float16
    rep = evaluate(ds, half, tmp_path / "ev3")
    assert rep.pooled["all"].epe_px == pytest.approx(_expected_epe(ds, 35.0), rel=1e-5)
    with pytest.raises(InputError, match=rf"^{re.escape(str(tmp_path))}: expected an ONNX model file, got a folder"):
        OnnxModel(tmp_path)


def test_a_rewrite_leaves_no_empty_map_folder(tmp_path):
    """An evaluation written again without --clouds removed the earlier one's clouds but left clouds/ empty (the docs
    run-through, session 18); a folder holding a user's file, or this run's maps, stays."""
    from gtforge.evaluate import _remove_earlier_outputs

    ev = tmp_path / "ev"
    for name in ("clouds/000_depth_error.ply", "heatmaps/000_disp_error.png", "heatmaps/preview/000_disp_error.jpg",
                 "heatmaps/001_disp_error.png", "heatmaps/preview/001_disp_error.jpg", "fruit_size.csv"):
        (ev / name).parent.mkdir(parents=True, exist_ok=True)
        (ev / name).write_bytes(b"x")
    kept = [ev / "heatmaps" / "000_disp_error.png", ev / "heatmaps" / "preview" / "000_disp_error.jpg"]
    _remove_earlier_outputs(ev, kept)
    assert sorted(p.relative_to(ev).as_posix() for p in ev.rglob("*")) == [
        "heatmaps", "heatmaps/000_disp_error.png", "heatmaps/preview", "heatmaps/preview/000_disp_error.jpg"]
    (ev / "clouds").mkdir()
    (ev / "clouds" / "mine.txt").write_text("a user's")
    _remove_earlier_outputs(ev, [])  # what evaluate does before its first map: every map goes, the user's file stays
    assert sorted(p.relative_to(ev).as_posix() for p in ev.rglob("*")) == ["clouds", "clouds/mine.txt"]


def test_network_input_options_are_checked_by_name(tmp_path):
    """--resize without --fit resize was ignored, --fit resize without --resize failed once per scene, and a bad
    --fit printed pydantic's 'validation error for InputConvention': each is now one line naming the option."""
    cases = [(["--resize", "512x256"], "--resize: expected --fit resize with it, got --fit pad"),
             (["--fit", "resize"], "--resize: expected the network's input size WxH with --fit resize, got none"),
             (["--fit", "crop"], "--fit: expected pad or resize, got 'crop'"),
             (["--channels", "GBR"], "--channels: expected RGB or BGR, got 'GBR'"),
             (["--fit", "resize", "--resize", "0x256"], "--resize: expected a width and height of at least 1 px")]
    for extra, message in cases:
        r = gtforge("evaluate", tmp_path, "--sgbm", "-o", tmp_path / "ev", *extra)
        assert r.returncode == 2 and one_line_error(r) and message in r.stderr, (extra, r.stderr)


@pytest.mark.slow
def test_evaluation_folder_of_its_own_and_rewritten_whole(dataset, tmp_path):
    """evaluate wrote its results among the predictions it scored (-o PREDICTIONS), and a folder reused from an
    earlier evaluation kept that one's maps of scenes not scored now; compare wrote into any folder."""
    ds, _ = dataset
    preds = _constant_offset_predictions(ds, tmp_path / "p", 0.5)
    for out in (preds, preds / "ev"):
        with pytest.raises(InputError, match=r"\[--output\]: expected a folder of its own, outside the predictions"):
            evaluate(ds, PredictionFolder(preds), out)
    other = tmp_path / "notes"
    other.mkdir()
    (other / "mine.txt").write_text("a user's file")
    with pytest.raises(InputError, match=r"notes \[--output\]: expected a new or empty folder \(or one with "
                                         r"results\.json\), got a folder with 1 entry"):
        evaluate(ds, PredictionFolder(preds), other)
    (other / "results.json").write_text('{"mine": 1}')  # a results.json, but no evaluation's: not taken as one
    with pytest.raises(InputError, match=r"notes \[--output\]: expected a new or empty folder, or an earlier "
                                         r"evaluation's, got a folder whose results\.json is not gtforge evaluate's"):
        evaluate(ds, PredictionFolder(preds), other)
    assert sorted(p.name for p in other.iterdir()) == ["mine.txt", "results.json"]
    ev = tmp_path / "ev"
    evaluate(ds, PredictionFolder(preds), ev, write_clouds=True)
    assert len(list((ev / "heatmaps").glob("*.png"))) == 6 and len(list((ev / "clouds").glob("*.ply"))) == 3
    (ev / "notes.txt").write_text("mine")  # a user's files in the folder stay
    (ev / "heatmaps" / "mine.png").write_bytes(b"x")
    (preds / "002.pfm").unlink()
    rep = evaluate(ds, PredictionFolder(preds), ev, fruit_size=False)
    assert rep.scenes == ["000", "001"]
    assert sorted(p.name for p in (ev / "heatmaps").glob("*.png")) == [
        "000_depth_error.png", "000_disp_error.png", "001_depth_error.png", "001_disp_error.png", "mine.png"]
    assert (ev / "notes.txt").read_text() == "mine"
    assert len(list((ev / "heatmaps" / "preview").glob("*.jpg"))) == 4
    assert not (ev / "clouds").exists() or not list((ev / "clouds").iterdir())
    assert not (ev / "fruit_size.csv").exists()
    with pytest.raises(InputError, match=r"\[--output\]: expected a new or empty folder \(or one with "
                                         r"comparison\.md\)"):
        compare([ev / "results.json"], ev)
    # an evaluation's folder stands for its results.json (a run-through: the folder evaluate's -o named was refused)
    table, _ = compare([ev], tmp_path / "cmp")
    assert table == compare([ev / "results.json"], tmp_path / "cmp")[0]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match=r"expected an evaluation result \(results\.json"):
        compare([tmp_path / "empty"], tmp_path / "cmp2")


@pytest.mark.slow
def test_sgbm_baseline_is_plausible(dataset, tmp_path):
    ds, _ = dataset
    rep = evaluate(ds, SGBM(), tmp_path, write_clouds=True)
    allm = rep.pooled["all"]
    assert allm.coverage_pct > 80 and 0 < allm.epe_px < 1.0
    assert rep.pooled["fruit"].depth_mae_mm is not None and 0 < rep.pooled["fruit"].depth_mae_mm < 20
    assert len(list((tmp_path / "clouds").glob("*.ply"))) == 3
    html = (tmp_path / "results.html").read_text()
    assert "Per scene, worst EPE first" in html and html.count("data:image/jpeg;base64") == 6
    # the same model name twice: compare says so, labels the rows with the folder, and writes an HTML table
    (tmp_path / "b").mkdir()
    shutil.copy(tmp_path / "results.json", tmp_path / "b" / "results.json")
    table, warnings = compare([tmp_path / "results.json", tmp_path / "b" / "results.json"], tmp_path / "cmp")
    assert len(warnings) == 1 and "model name 'SGBM' is used by 2 results" in warnings[0]
    assert table.count("| SGBM [b] | all |") == 1 and table.count(f"| SGBM [{tmp_path.name}] | all |") == 1
    chtml = (tmp_path / "cmp" / "comparison.html").read_text()
    # 4 region rows, the fruit size row, the sources table
    assert "model name &#x27;SGBM&#x27; is used by 2 results" in chtml and chtml.count("<td>SGBM [b]</td>") == 6


@pytest.mark.slow
def test_results_html_is_small_with_colour_bars_and_header(dataset, tmp_path):
    """Issue 11 item 10: previews (JPEG, with colour bars) link full-size maps; header; depth-MAE note; no clouds."""
    ds, _ = dataset
    rep = evaluate(ds, SGBM(), tmp_path)
    assert not (tmp_path / "clouds").exists()  # point clouds only with write_clouds / --clouds
    html = (tmp_path / "results.html").read_text()
    assert len(html.encode()) < 400_000, len(html.encode())  # 883x497 maps inlined would be > 1.5 MB
    assert "data:image/png" not in html
    for sid in rep.scenes:
        for kind in ("disp_error", "depth_error"):
            assert f'href="heatmaps/{sid}_{kind}.png"' in html
    import gtforge

    assert f"<th>gtforge version</th><td>{gtforge.__version__}</td>" in html
    assert f"<th>dataset</th><td>{ds.resolve()}</td>" in html and "StereoSGBM" in html
    assert "Depth MAE is computed on the fruit regions only" in html
    # the full-size map: pixel-aligned turbo colours on top, a colour bar strip below
    from gtforge.reports.evaluation import heatmap_rgb

    s = ds / "scenes" / rep.scenes[0]
    gt = read_pfm(s / "disp0GT.pfm")
    full = read_image(tmp_path / "heatmaps" / f"{rep.scenes[0]}_disp_error.png")
    H, W = gt.shape
    assert full.shape[0] > H + 40 and full.shape[1] == W
    from gtforge.io.middlebury import SceneCalib

    cal = SceneCalib(s / "calib.txt")
    pred = SGBM().predict(rep.scenes[0], read_image(s / "im0.png"), read_image(s / "im1.png"), cal.ndisp, cal.vmin)
    err = np.where((read_image(s / "mask0nocc.png") > 0) & np.isfinite(gt), np.abs(pred - gt), np.nan)
    np.testing.assert_array_equal(full[:H], heatmap_rgb(err, 2.0))
    strip = full[H:]
    assert (strip == 255).all(axis=2).mean() > 0.5 and strip.std() > 20  # white background with the bar and ticks


def _constant_offset_predictions(ds, folder, offset_px, scenes=None):
    folder.mkdir()
    for s in sorted((ds / "scenes").iterdir()):
        if scenes is None or s.name in scenes:
            write_pfm(folder / f"{s.name}.pfm", read_pfm(s / "disp0GT.pfm") + offset_px)
    return folder


@pytest.mark.slow
def test_depth_error_map_is_scaled_to_the_data(dataset, tmp_path):
    """Issue 11 item 10: the fruit depth-error map's scale follows the errors (not a fixed 0-1 mm, solid red)."""
    from gtforge.io.middlebury import SceneCalib
    from gtforge.reports.html import nice_ceil

    ds, _ = dataset
    preds = _constant_offset_predictions(ds, tmp_path / "p", 0.5)
    rep = evaluate(ds, PredictionFolder(preds), tmp_path / "ev")
    for sr in rep.per_scene:
        s = ds / "scenes" / sr.scene
        gt = read_pfm(s / "disp0GT.pfm")
        cal = SceneCalib(s / "calib.txt")
        fruit = (read_image(s / "region.png") >= 2) & (read_image(s / "mask0nocc.png") > 0) & np.isfinite(gt)
        zerr = np.abs(cal.depth(gt[fruit] + 0.5) - cal.depth(gt[fruit]))
        assert sr.depth_error_map_max_mm == nice_ceil(float(np.percentile(zerr, 95)))
        assert sr.depth_error_map_max_mm >= float(np.percentile(zerr, 95))
        assert sr.metrics["fruit"].depth_mae_mm == pytest.approx(float(zerr.mean()), rel=1e-5)
        # at most ~5 % of the fruit saturates the colour scale
        assert np.mean(zerr > sr.depth_error_map_max_mm) <= 0.05
    html = (tmp_path / "ev" / "results.html").read_text()
    top = rep.per_scene[0].depth_error_map_max_mm
    assert f"fruit depth error, scale 0\u2013{top:g} mm" in html


@pytest.mark.slow
def test_prediction_folder_with_missing_and_wrong_size(dataset, tmp_path):
    ds, _ = dataset
    preds = tmp_path / "preds"
    preds.mkdir()
    gt0 = read_pfm(ds / "scenes" / "000" / "disp0GT.pfm")
    write_pfm(preds / "000.pfm", gt0 + 0.25)
    write_kitti_disparity(preds / "001_10.png", np.ones((10, 10), np.float32))  # wrong size
    rep = evaluate(ds, PredictionFolder(preds), tmp_path / "ev")
    assert rep.scenes == ["000"] and set(rep.missing) == {"001", "002"}
    assert "883x497" in rep.missing["001"] and "no prediction file (002.pfm" in rep.missing["002"]
    assert rep.pooled["all"].epe_px == pytest.approx(0.25, abs=1e-5)
    assert "2 scene(s) excluded" in (tmp_path / "ev" / "results.html").read_text()
    # none left to score: the line counts the scenes without a file apart from those refused (it called all refused)
    (preds / "000.pfm").unlink()
    with pytest.raises(InputError) as err:
        evaluate(ds, PredictionFolder(preds), tmp_path / "ev")
    assert "got none of 3 (2 without a prediction file, 1 refused, each said above)" in str(err.value), err.value


@pytest.mark.slow
def test_partial_predictions_are_reported_first_and_exit_nonzero(dataset, tmp_path):
    """Issue 11 item 9: predictions for only some scenes -> said before any table, exit code 1."""
    ds, _ = dataset
    preds = _constant_offset_predictions(ds, tmp_path / "preds", 0.25, scenes={"000"})
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    r = subprocess.run([sys.executable, "-m", "gtforge.cli", "evaluate", str(ds), "--predictions", str(preds),
                        "-o", str(tmp_path / "ev")], capture_output=False, stdout=subprocess.PIPE,
                       stderr=subprocess.STDOUT, text=True, env=env)
    assert r.returncode == 1, r.stdout
    first = r.stdout.index("no prediction for 2 of 3 scene(s)")
    assert first < r.stdout.index("| model | region |")
    assert "001, 002" in r.stdout[first:first + 400] and "exit with code 1" in r.stdout[first:first + 400]
    assert "2 scene(s) excluded" in r.stdout and "Traceback" not in r.stdout
    # none at all: a one-line input error naming the expected files
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match=r"a prediction per scene named <id>\.pfm.*none for the 3 scene\(s\)"):
        evaluate(ds, PredictionFolder(empty), tmp_path / "ev2")


@pytest.mark.slow
def test_empty_split_says_why(dataset, tmp_path):
    """Issue 11 item 9: `evaluate --split val` on a split that came out empty says why (exit 2, one line)."""
    ds, summary = dataset
    empty = [k for k, v in summary.splits.items() if not v]
    assert empty, summary.splits  # 3 scenes of 2 fruit at 0.8/0.1: one split gets nothing
    r = CliRunner().invoke(app, ["evaluate", str(ds), "--sgbm", "--split", empty[0], "-o", str(tmp_path / "ev")])
    assert r.exit_code != 0
    with pytest.raises(InputError) as exc:
        evaluate(ds, SGBM(), tmp_path / "ev", split=empty[0])
    msg = str(exc.value)
    assert "\n" not in msg and f"at least one scene in the '{empty[0]}' split, got an empty list" in msg
    counts = ", ".join(f"{k} {len(v)}" for k, v in summary.splits.items())
    assert f"into {counts}" in msg and "evaluate without --split" in msg


def _dataset_copy_with_sigma(ds, dst):
    """The test dataset plus a sigma map per scene: 0.1 px on the left half, 1.0 px on the right, +inf without GT."""
    shutil.copytree(ds, dst)  # files, not links: the sigma maps written below stay in the copy
    for s in sorted((dst / "scenes").iterdir()):
        gt = read_pfm(s / "disp0GT.pfm")
        sigma = np.full(gt.shape, 0.1, np.float32)
        sigma[:, gt.shape[1] // 2:] = 1.0
        sigma[~np.isfinite(gt)] = np.inf
        write_pfm(s / "disp0GT_sigma.pfm", sigma)
    return dst


@pytest.mark.slow
def test_max_gt_sigma_scores_only_certain_pixels(dataset, tmp_path):
    """Issue 10 consumer: --max-gt-sigma PX leaves out GT pixels whose sigma is not below PX and counts them."""
    ds0, _ = dataset
    old = tmp_path / "old"  # a dataset from before build-dataset wrote sigma maps
    shutil.copytree(ds0, old)
    for f in old.glob("scenes/*/disp0GT_sigma.pfm"):
        f.unlink()
    with pytest.raises(InputError, match=r"disp0GT_sigma\.pfm.*none in 3 of 3 scene\(s\).*hint: rebuild"):
        evaluate(old, SGBM(), None, max_gt_sigma_px=0.5)
    ds = _dataset_copy_with_sigma(ds0, tmp_path / "ds")
    preds = tmp_path / "preds"
    preds.mkdir()
    expect = {r: [0, 0] for r in ("all", "fruit")}  # scored, left out
    for s in sorted((ds / "scenes").iterdir()):
        gt = read_pfm(s / "disp0GT.pfm")
        half = gt.shape[1] // 2
        pred = gt + 0.25
        pred[:, half:] = gt[:, half:] + 3.0  # uncertain half: badly predicted, must not count
        write_pfm(preds / f"{s.name}.pfm", pred)
        ok = (read_image(s / "mask0nocc.png") > 0) & np.isfinite(gt)
        fruit = ok & (read_image(s / "region.png") >= 2)
        for r, m in (("all", ok), ("fruit", fruit)):
            expect[r][0] += int(m[:, :half].sum())
            expect[r][1] += int(m[:, half:].sum())
    r = CliRunner().invoke(app, ["evaluate", str(ds), "--predictions", str(preds), "--max-gt-sigma", "0.5",
                                 "-o", str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output
    rep = EvalResult.read(tmp_path / "ev" / "results.json")
    assert rep.max_gt_sigma_px == 0.5
    for reg in ("all", "fruit"):
        m = rep.pooled[reg]
        assert (m.n_gt, m.n_gt_sigma_left_out) == tuple(expect[reg])
        assert m.epe_px == pytest.approx(0.25, abs=1e-5) and m.bad_1_0_pct == 0.0
    assert sum(s.metrics["all"].n_gt_sigma_left_out for s in rep.per_scene) == expect["all"][1]
    md = (tmp_path / "ev" / "results.md").read_text()
    share = 100.0 * expect["all"][1] / sum(expect["all"])
    assert "GT left out by sigma" in md and f"| {expect['all'][1]} ({share:.1f} %) |" in md
    csv_rows = (tmp_path / "ev" / "results.csv").read_text().splitlines()
    assert csv_rows[0].split(",")[3] == "GT left out by sigma (pixels)"
    assert csv_rows[1].split(",")[3] == str(expect["all"][1])
    # without the limit every GT pixel counts, and nothing is left out
    rep_all = evaluate(ds, PredictionFolder(preds), None)
    assert rep_all.pooled["all"].n_gt == sum(expect["all"]) and rep_all.pooled["all"].n_gt_sigma_left_out == 0
    # compare: the same predictions scored with and without the limit are not comparable
    rep_all.model = "unlimited"
    rep_all.write(tmp_path / "all.json")
    _, warnings = compare([tmp_path / "ev" / "results.json", tmp_path / "all.json"], tmp_path / "cmp")
    assert len(warnings) == 1 and "different scoring limits" in warnings[0]


@pytest.mark.slow
def test_compare_warns_about_different_datasets(dataset, tmp_path):
    """Issue 11 item 9: compare warns when results come from different datasets (and prints it on the CLI)."""
    ds0, _ = dataset
    ds = tmp_path / "ds"
    shutil.copytree(ds0, ds)
    man = json.loads((ds / "manifest.json").read_text())
    man["params"]["erosion_px"] = 9  # as if rebuilt with other parameters
    (ds / "manifest.json").write_text(json.dumps(man))
    preds = _constant_offset_predictions(ds0, tmp_path / "p", 0.25)
    evaluate(ds0, PredictionFolder(preds, "a"), tmp_path / "a")
    evaluate(ds, PredictionFolder(preds, "b"), tmp_path / "b")
    r = CliRunner().invoke(app, ["compare", str(tmp_path / "a" / "results.json"), str(tmp_path / "b" / "results.json"),
                                 "-o", str(tmp_path / "cmp")])
    assert r.exit_code == 0, r.output
    assert "the results come from different datasets (manifest.json differs, beyond where and when" in r.output
    assert (tmp_path / "cmp" / "comparison.html").is_file() and (tmp_path / "cmp" / "comparison.csv").is_file()
    assert "> warning: the results come from different datasets" in (tmp_path / "cmp" / "comparison.md").read_text()
    # the same labels built again elsewhere (a rebuild, a Dask build, a copy): other times, stamps and paths only,
    # which compare called a different dataset (a run-through)
    same = tmp_path / "same"
    shutil.copytree(ds0, same)
    man = json.loads((same / "manifest.json").read_text())
    man["session_dir"] = "/elsewhere/session"
    for meta in man["scenes"].values():
        meta["time_s"] += 1.0
        for st in meta["input_stamps"].values():
            st["hashed_at_ns"] += 5
    (same / "manifest.json").write_text(json.dumps(man))
    evaluate(same, PredictionFolder(preds, "c"), tmp_path / "c")
    _, warnings = compare([tmp_path / "a" / "results.json", tmp_path / "c" / "results.json"], tmp_path / "cmp2")
    assert not any("different datasets" in w for w in warnings), warnings


@pytest.mark.slow
def test_loader_yields_training_arrays(dataset):
    ds, _ = dataset
    items = list(StereoDataset(ds, split=None))
    assert len(items) == 3
    it = items[0]
    assert it["left"].shape == (497, 883, 3) and it["disparity"].dtype == np.float32
    np.testing.assert_array_equal(it["valid"], np.isfinite(it["disparity"]))
    assert set(np.unique(it["weight"][it["valid"]])) <= {np.float32(0.8), np.float32(1.0), np.float32(1.4)}


def test_an_evaluation_stopped_over_an_earlier_one_leaves_no_tables_of_the_other_model(dataset, tmp_path):
    """Ctrl-C while an evaluation rewrote an earlier one's folder left the earlier model's results.* beside the new
    model's maps (a newcomer's run-through). The earlier tables go before the first new map is written."""
    ds, _ = dataset
    out = tmp_path / "ev"
    evaluate(ds, SGBM(), out)
    assert (out / "results.json").is_file() and (out / "fruit_size.csv").is_file()

    class StopsAtTheSecondScene(SGBM):
        def __init__(self):
            super().__init__(block_size=7, name="SGBM-7")
            self.calls = 0

        def predict(self, *args, **kwargs):
            self.calls += 1
            if self.calls == 3:  # (the first scene's are a warm-up and the timed call)
                raise KeyboardInterrupt
            return super().predict(*args, **kwargs)

    with pytest.raises(KeyboardInterrupt):
        evaluate(ds, StopsAtTheSecondScene(), out)
    assert not [p.name for p in out.iterdir() if p.name.startswith("results.")]
    assert not (out / "fruit_size.csv").exists()  # one model's table too (a second run-through)
    # the new model's first scene, whole, and no map of the earlier model beside it (the other scenes' stayed: a
    # second run-through)
    assert sorted(p.name for p in (out / "heatmaps").glob("*_disp_error.png")) == ["000_disp_error.png"]
    assert (out / ".evaluation-incomplete").is_file()  # the folder stays one evaluate may write again
    with pytest.raises(InputError, match=r"evaluate was stopped before it wrote its tables\) \(hint: run that"):
        compare([out, out.parent / "other"], tmp_path / "cmp")  # (said of the folder, not "give the file's path")
    rep = evaluate(ds, SGBM(block_size=7, name="SGBM-7"), out)  # the same command again: a whole evaluation
    assert rep.model == "SGBM-7" and (out / "results.html").is_file()
    assert not (out / ".evaluation-incomplete").exists()


def test_quarantined_scenes_scored_are_named(dataset, tmp_path, caplog):
    """Scenes verify --quarantine took out of the split lists, or verification flagged, were scored without a word
    when every scene was asked for (newcomers' run-throughs): a warning names them."""
    import json
    import logging

    ds = tmp_path / "ds"
    shutil.copytree(dataset[0], ds)
    man = json.loads((ds / "manifest.json").read_text())
    man["quarantined"] = ["001"]
    (ds / "manifest.json").write_text(json.dumps(man))
    with caplog.at_level(logging.WARNING, logger="gtforge"):
        evaluate(ds, SGBM(), None)
    assert any("quarantined" in r.getMessage() and "001" in r.getMessage() for r in caplog.records)
    assert not any("verification flagged" in r.getMessage() for r in caplog.records)
    # flagged, not quarantined (build-dataset without --quarantine): named as well (a run-through)
    man["flagged"] = {"000": ["texture shift 0.4 px"], "001": ["texture shift 0.3 px"]}
    (ds / "manifest.json").write_text(json.dumps(man))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="gtforge"):
        rep = evaluate(ds, SGBM(), tmp_path / "eval")
    # and the results say which of the scored scenes they were, with verify's reasons (a run-through)
    assert rep.suspect_scenes == {"000": "flagged: texture shift 0.4 px", "001": "quarantined: texture shift 0.3 px"}
    assert EvalResult.read(tmp_path / "eval" / "results.json").suspect_scenes == rep.suspect_scenes
    assert "2 scored scene(s) with suspect ground truth" in (tmp_path / "eval" / "results.html").read_text()
    assert [r.getMessage()[:78] for r in caplog.records if "verification flagged" in r.getMessage()] == [
        "scoring 1 scene(s) that verification flagged (their ground truth may not match"]
    assert any("flagged" in r.getMessage() and ": 000;" in r.getMessage() for r in caplog.records)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="gtforge"):
        rep = evaluate(dataset[0], SGBM(), None)
    assert not any("quarantined" in r.getMessage() or "flagged" in r.getMessage() for r in caplog.records)
    assert rep.suspect_scenes == {}


def test_compare_refuses_the_same_evaluation_twice(tmp_path):
    """compare A/results.json A/results.json gave two identical rows and only the name-clash warning (a run-through);
    the same file twice, under any spelling, is refused before anything is written."""
    from gtforge.evaluate import compare

    (tmp_path / "a").mkdir()
    f = tmp_path / "a" / "results.json"
    f.write_text("{}")
    with pytest.raises(InputError, match=r"each evaluation once, got the same file as"):
        compare([f, tmp_path / "a" / ".." / "a" / "results.json"], tmp_path / "cmp")
    assert not (tmp_path / "cmp").exists()


def test_a_file_that_is_no_model_is_one_line_with_a_hint(dataset, tmp_path):
    """A file that is not an ONNX model: onnxruntime's message was cut mid-word at 100 characters ("Protobuf parsing
    f") with no hint (a run-through); its first line whole up to 160 characters, cut at a word, and a hint."""
    pytest.importorskip("onnxruntime")
    bad = tmp_path / "notamodel.onnx"
    bad.write_text("not a model")
    r = gtforge("evaluate", dataset[0], "--onnx", bad, "-o", tmp_path / "e")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "expected a loadable ONNX model" in r.stderr and "(hint: export the network with torch.onnx.export" in \
        r.stderr, r.stderr
    from gtforge.predictors import _first_words

    assert _first_words(ValueError("word " * 60)).endswith("word ...") and len(_first_words(ValueError("x " * 90))) \
        <= 164
    assert _first_words(ValueError("short\nsecond line")) == "short"


def test_prediction_arrays_that_are_not_float_are_said_so(dataset, tmp_path, caplog):
    """An .npy of strings said only "got ValueError"; one of integers was scored without a word (a run-through)."""
    import logging

    from gtforge.predictors import PredictionFolder

    ds = dataset[0]
    ids = sorted(d.name for d in (ds / "scenes").iterdir() if d.is_dir())
    gt = read_pfm(ds / "scenes" / ids[0] / "disp0GT.pfm")
    p = tmp_path / "p"
    p.mkdir()
    np.save(p / f"{ids[0]}.npy", np.nan_to_num(gt).round().astype(np.int32))
    np.save(p / f"{ids[1]}.npy", np.array(["a", "b"]))
    folder = PredictionFolder(p)
    with caplog.at_level(logging.WARNING, logger="gtforge"):
        d = folder.predict(ids[0], np.zeros(gt.shape + (3,), np.uint8), None)
    assert d.dtype == np.float32 and any("integer disparities" in r.getMessage() for r in caplog.records)
    with pytest.raises(InputError, match=r"\[dtype\]: expected an array of real disparities \(float32, px\), got <U1 "
                       r".*np\.save"):
        folder.predict(ids[1], np.zeros(gt.shape + (3,), np.uint8), None)


def test_complex_and_bool_prediction_arrays_are_refused(tmp_path):
    """A complex .npy was cast to its real part with numpy's ComplexWarning on the terminal, said to hold "integer
    disparities", and scored (exit 0); a bool one was scored as 0/1 px. Both are one line naming the dtype."""
    d = np.full((30, 40), 12.5, np.float32)
    for sid, a in (("c", d.astype(np.complex64)), ("b", d > 0)):
        np.save(tmp_path / f"{sid}.npy", a)
        with pytest.raises(InputError) as e:
            PredictionFolder(tmp_path).predict(sid, np.zeros((30, 40, 3), np.uint8), None)
        assert e.value.field == "dtype" and e.value.actual == str(a.dtype) and e.value.hint


@pytest.mark.parametrize("suffix", [".npy", ".pfm"])
def test_predictions_in_another_unit_are_refused(tmp_path, suffix):
    """A .npy or .pfm of KITTI's round(d * 256) (or of depth in mm) was scored as it was: EPE 7165 px, exit 0, not a
    word (a run-through on a 662 px wide dataset). Disparities mostly as large as the image is wide match nothing:
    the scene is refused with the unit's hint; right-unit disparities (up to just under the width) are read."""
    gt = np.linspace(20.0, 39.0, 30 * 40, dtype=np.float32).reshape(30, 40)
    img = np.zeros((30, 40, 3), np.uint8)
    write = (lambda f, a: np.save(f, a)) if suffix == ".npy" else write_pfm
    write(tmp_path / f"a{suffix}", gt * 256)
    with pytest.raises(InputError) as e:
        PredictionFolder(tmp_path).predict("a", img, None)
    assert e.value.field == "disparity" and e.value.actual == f"median {float(np.median(gt * 256)):.4g} px"
    assert "below its width, 40 px" in e.value.expected and "256" in e.value.hint
    write(tmp_path / f"b{suffix}", gt)
    np.testing.assert_array_equal(PredictionFolder(tmp_path).predict("b", img, None), gt)


def test_predictions_of_minus_the_disparity_are_said_once(dataset, tmp_path, caplog):
    """-disparity saved (RAFT-Stereo's flow_x): as .pfm it was scored as a 100-px EPE, as .npy not at all ("no pixel
    was scored"), neither with a word on the sign. Both now warn, once a model; a mostly positive map does not."""
    import logging

    from gtforge.io.formats import write_pfm
    from gtforge.predictors import PredictionFolder

    ds = dataset[0]
    ids = sorted(d.name for d in (ds / "scenes").iterdir() if d.is_dir())
    gt = read_pfm(ds / "scenes" / ids[0] / "disp0GT.pfm")
    img = np.zeros(gt.shape + (3,), np.uint8)
    for suffix in (".pfm", ".npy"):
        p = tmp_path / suffix[1:]
        p.mkdir()
        for sid in ids[:2]:
            neg = -np.nan_to_num(read_pfm(ds / "scenes" / sid / "disp0GT.pfm"), nan=50.0)
            write_pfm(p / f"{sid}.pfm", neg) if suffix == ".pfm" else np.save(p / f"{sid}.npy", neg)
        folder = PredictionFolder(p)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="gtforge"):
            d0 = folder.predict(ids[0], img, None)
            folder.predict(ids[1], img, None)
        said = [r.getMessage() for r in caplog.records if "of its disparities are negative" in r.getMessage()]
        assert len(said) == 1 and said[0].startswith(f"{p / (ids[0] + suffix)}: 100 % of its disparities are "
                                                     "negative (median -")
        assert ("not scored" in said[0]) == (suffix == ".npy") and np.isnan(d0).all() == (suffix == ".npy")
    caplog.clear()
    mostly = np.nan_to_num(gt, nan=50.0)
    mostly[:, : gt.shape[1] // 3] *= -1  # a third negative: a bad prediction, not a sign convention
    np.save(tmp_path / "npy" / f"{ids[2]}.npy", mostly)
    with caplog.at_level(logging.WARNING, logger="gtforge"):
        PredictionFolder(tmp_path / "npy").predict(ids[2], img, None)
    assert "negative" not in caplog.text
