"""The ``gtforge`` command: a thin Typer layer over ``gtforge.<stage>.<function>``.

Bad input (``InputError``) prints one line and exits with code 2; a FAIL verdict of ``validate``
exits with 1; unexpected bugs keep their traceback.
"""
from __future__ import annotations

import logging
import signal
import sys
from pathlib import Path
from typing import List, Optional

import typer
from rich.console import Console

from gtforge.errors import InputError, Interrupted

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Structured-light + ZED stereo rig -> stereo training data with sub-pixel ground truth.")
console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)
out = Console(soft_wrap=True, highlight=False, markup=False)


def _setup_logging(verbose: bool) -> None:
    if console.is_terminal:
        from rich.logging import RichHandler

        handler: logging.Handler = RichHandler(console=console, show_time=False, show_path=False)
        fmt = "%(message)s"
    else:  # logs and pipes: one plain line per message
        handler, fmt = logging.StreamHandler(sys.stderr), "%(levelname)s: %(message)s"
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format=fmt, handlers=[handler], force=True)


def _status(msg: str) -> None:
    """Progress of long work, on an interactive terminal only (logs and pipes stay clean)."""
    if console.is_terminal:
        console.print(msg, style="dim")


def _wh(text: Optional[str], name: str) -> Optional[tuple[int, int]]:
    if not text:
        return None
    try:
        w, h = (int(x) for x in text.lower().split("x"))
        return w, h
    except ValueError:
        raise InputError(None, name, "WIDTHxHEIGHT, e.g. 736x528", repr(text)) from None


@app.callback()
def _main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Show info messages.")) -> None:
    _setup_logging(verbose)


@app.command()
def calibrate(session: Path = typer.Argument(..., help="Capture session folder (docs/capture-layout.md)."),
              output: Path = typer.Option(Path("calibration.yaml"), "--output", "-o", help="Calibration YAML to write."),
              report_dir: Optional[Path] = typer.Option(None, help="Report folder (default: beside the output)."),
              cols: int = typer.Option(12, help="Inner corners along a row."),
              rows: int = typer.Option(9, help="Inner corners along a column."),
              square_mm: float = typer.Option(20.0, help="Square size (mm)."),
              use_depth: bool = typer.Option(False, help="Also solve 3D-2D through the depth camera's board "
                                                         "measurement, use it, and report both methods."),
              captures: Optional[str] = typer.Option(None, help="Comma-separated capture names to use."),
              no_loo: bool = typer.Option(False, help="Skip leave-one-pose-out cross-validation.")) -> None:
    """Solve T_zed_from_mech from checkerboard captures in SESSION/board/."""
    from gtforge.calibrate import BoardModel, CalibrateParams, calibrate as run
    from gtforge.reports.calibration import write_calibration_report

    params = CalibrateParams(board=BoardModel(cols=cols, rows=rows, square_size_mm=square_mm), use_depth=use_depth,
                             leave_one_out=not no_loo)
    res = run(session, None, params, captures.split(",") if captures else None, progress=_status)
    res.write(output)
    rep = write_calibration_report(res, report_dir or output.parent / (output.stem + "_report"))
    n_used = len(res.captures_used)
    n_bad = sum(p.status != "used" for p in res.poses)
    out.print(f"poses used {n_used}, skipped/outliers {n_bad}; RMS {res.rms_px:.3f} px, worst {res.max_px:.3f} px")
    out.print(f"1-sigma rotation {res.sigma_rot_deg:.4f} deg, translation {res.sigma_trans_mm:.3f} mm"
              + (f"; leave-one-out transfer {res.loo_transfer_mean_px:.3f} px mean" if res.loo_transfer_mean_px else ""))
    for m in res.methods[1:]:
        out.print(f"method {m.method}: RMS {m.rms_zed_px:.3f} px, differs by {m.rot_diff_to_primary_deg:.4f} deg / "
                  f"{m.trans_diff_to_primary_mm:.3f} mm")
    out.print(f"wrote {output} and {rep}")


@app.command("build-dataset")
def build_dataset(session: Path = typer.Argument(..., help="Capture session folder."),
                  calibration: Path = typer.Option(..., "--calibration", "-c", help="From gtforge calibrate."),
                  output: Path = typer.Option(..., "--output", "-o", help="Dataset folder."),
                  mode: str = typer.Option("mesh", help="mesh (default) or splat."),
                  workers: Optional[int] = typer.Option(None, help="Parallel scenes (default: all cores)."),
                  overwrite: bool = typer.Option(False, help="Rebuild every scene."),
                  strict: bool = typer.Option(False, help="Stop at the first bad scene."),
                  crop: Optional[str] = typer.Option(None, help="Crop around the fruit, e.g. 736x528."),
                  ply: bool = typer.Option(False, help="Write a PLY point cloud per scene."),
                  erosion_px: int = typer.Option(15, help="Fruit centre = fruit mask eroded by this."),
                  max_slant_deg: float = typer.Option(85.0, help="mesh: reject triangles steeper than this."),
                  split: str = typer.Option("0.8,0.1", help="train,val ratios (test gets the rest)."),
                  seed: int = typer.Option(0, help="Split seed.")) -> None:
    """Build disparity ground truth for SESSION/scenes/ into OUTPUT (docs/dataset-format.md)."""
    from gtforge.build_dataset import BuildParams, build_dataset as run

    try:
        tr, va = (float(x) for x in split.split(","))
    except ValueError:
        raise InputError(None, "--split", "two ratios 'train,val' such as 0.8,0.1", repr(split)) from None
    if mode not in ("mesh", "splat"):
        raise InputError(None, "--mode", "mesh or splat", repr(mode))
    params = BuildParams(mode=mode, crop_wh=_wh(crop, "--crop"), ply=ply, erosion_px=erosion_px,
                         max_slant_deg=max_slant_deg, split_train=tr, split_val=va, split_seed=seed)
    s = run(session, calibration, output, params, workers, overwrite, strict, progress=True)
    failed = f" ({', '.join(s.failures)}; reasons above and in manifest.json)" if s.failures else ""
    out.print(f"built {len(s.built)}, unchanged {len(s.skipped_unchanged)}, failed {len(s.failures)}{failed} "
              f"in {s.time_s:.1f} s -> {s.out_dir}")
    if s.failures:
        raise typer.Exit(1)


@app.command()
def validate(session: Path = typer.Argument(..., help="Capture session folder (board/ captures)."),
             calibration: Optional[Path] = typer.Option(None, "--calibration", "-c",
                                                        help="Calibration YAML (not needed with --holdout)."),
             output: Path = typer.Option(Path("validation"), "--output", "-o", help="Report folder."),
             holdout: int = typer.Option(0, help="Calibrate without the last K board captures (written to "
                                                 "OUTPUT/holdout_calibration.yaml) and validate on them."),
             captures: Optional[str] = typer.Option(None, help="Comma-separated capture names to validate on."),
             cols: int = typer.Option(12), rows: int = typer.Option(9), square_mm: float = typer.Option(20.0),
             xy_threshold_px: float = typer.Option(0.3), z_threshold_pct: float = typer.Option(0.05)) -> None:
    """XY reprojection (px) and Z geometric (%) accuracy; exit code 1 on FAIL."""
    from gtforge.calibrate import BoardModel
    from gtforge.validate import REFERENCE_XY_PX, REFERENCE_Z_PCT, ValidateParams, validate as run

    params = ValidateParams(board=BoardModel(cols=cols, rows=rows, square_size_mm=square_mm),
                            xy_threshold_px=xy_threshold_px, z_threshold_pct=z_threshold_pct)
    rep = run(session, calibration, output, params, captures.split(",") if captures else None, holdout, _status)
    out.print(f"XY reprojection: mean {rep.xy_mean_px:.3f} px (median {rep.xy_median_px:.3f}, max {rep.xy_max_px:.3f}); "
              f"published {REFERENCE_XY_PX} px; threshold {xy_threshold_px} -> {'PASS' if rep.pass_xy else 'FAIL'}")
    out.print(f"Z geometric: mean {rep.z_error_mean_pct:.4f} % (max {rep.z_error_max_pct:.4f}); published "
              f"{REFERENCE_Z_PCT} %; threshold {z_threshold_pct} -> {'PASS' if rep.pass_z else 'FAIL'}")
    out.print(f"report: {output / 'validation.html'}")
    if not rep.passed:
        raise typer.Exit(1)


@app.command()
def evaluate(dataset: Path = typer.Argument(..., help="Dataset folder from build-dataset."),
             output: Path = typer.Option(Path("evaluation"), "--output", "-o"),
             onnx: Optional[Path] = typer.Option(None, help="ONNX model (inputs: left, right NCHW)."),
             torchscript: Optional[Path] = typer.Option(None, help="TorchScript (.pt) or torch.export (.pt2) model (needs torch)."),
             predictions: Optional[Path] = typer.Option(None, help="Folder of predicted disparities."),
             sgbm: bool = typer.Option(False, help="OpenCV SGBM baseline."),
             name: Optional[str] = typer.Option(None, help="Model name in the tables."),
             split: Optional[str] = typer.Option(None, help="train/val/test (default: every scene)."),
             max_disp: Optional[float] = typer.Option(None, help="Only score GT below this disparity."),
             channels: str = typer.Option("RGB", help="RGB or BGR."),
             normalize: str = typer.Option("imagenet", help="imagenet, 0-255 or 0-1."),
             fit: str = typer.Option("pad", help="pad (to a multiple of 32, crop back) or resize."),
             resize: Optional[str] = typer.Option(None, help="Network input WxH with --fit resize."),
             params_count: Optional[int] = typer.Option(None, help="Parameter count for the table."),
             no_clouds: bool = typer.Option(False, help="Skip the per-scene PLY clouds.")) -> None:
    """Score a model's disparities against the built ground truth, per region."""
    from gtforge.evaluate import evaluate as run
    from gtforge.reports.evaluation import tables_markdown
    from gtforge.predictors import SGBM, InputConvention, OnnxModel, PredictionFolder, TorchScriptModel

    chosen = [x for x in (onnx, torchscript, predictions) if x is not None] + ([True] if sgbm else [])
    if len(chosen) != 1:
        raise InputError(None, "model", "exactly one of --onnx, --torchscript, --predictions, --sgbm",
                         f"{len(chosen)} given")
    try:
        conv = InputConvention(channels=channels, normalize=normalize, fit=fit, resize_wh=_wh(resize, "--resize"))
    except Exception as exc:
        raise InputError(None, "input convention", "--channels RGB|BGR, --normalize imagenet|0-255|0-1, --fit pad|resize",
                         f"{channels}/{normalize}/{fit}", str(exc).splitlines()[0]) from None
    if onnx:
        pred = OnnxModel(onnx, conv, name)
    elif torchscript:
        pred = TorchScriptModel(torchscript, conv, name)
    elif predictions:
        pred = PredictionFolder(predictions, name)
    else:
        pred = SGBM(name=name or "SGBM")
    rep = run(dataset, pred, output, split, max_disp, not no_clouds, params_count, _status)
    out.print(tables_markdown([rep]))
    out.print(f"median warm inference {rep.time_ms_median:.1f} ms/frame ({rep.provider}); results in {output}")
    if rep.missing:
        out.print(f"{len(rep.missing)} scene(s) excluded: " + "; ".join(f"{k}: {v}" for k, v in rep.missing.items()))
        raise typer.Exit(1)


@app.command()
def compare(results: List[Path] = typer.Argument(..., help="results.json files from gtforge evaluate."),
            output: Path = typer.Option(Path("comparison"), "--output", "-o")) -> None:
    """Put several evaluated models side by side in one table."""
    from gtforge.evaluate import compare as run

    out.print(run(results, output))


@app.command()
def synth(output: Path = typer.Argument(..., help="Folder for the synthetic session."),
          boards: int = typer.Option(8), scenes: int = typer.Option(3), scale: float = typer.Option(0.5),
          seed: int = typer.Option(0), depth_noise_mm: float = typer.Option(0.03)) -> None:
    """Render a synthetic capture session with exact truth (truth/ beside the captures)."""
    from gtforge.synthetic import generate_session

    generate_session(output, n_board=boards, n_scenes=scenes, scale=scale, seed=seed, depth_noise_mm=depth_noise_mm,
                     progress=_status)
    out.print(f"wrote {output}")


@app.command()
def demo(directory: Path = typer.Argument(Path("demo_out"), help="Where the demo writes everything."),
         scale: float = typer.Option(0.5, help="Resolution factor of the synthetic cameras (1.0 = ZED 2K)."),
         boards: int = typer.Option(8), scenes: int = typer.Option(4), seed: int = typer.Option(0)) -> None:
    """Generate a synthetic session and run calibrate -> build-dataset -> validate -> evaluate."""
    from gtforge.demo import run_demo

    run_demo(directory, scale=scale, n_board=boards, n_scenes=scenes, seed=seed, say=out.print, status=_status)


def _raise_interrupted(signum, frame) -> None:
    raise Interrupted("interrupted")


def main() -> None:
    # Ctrl-C raises Interrupted (not KeyboardInterrupt, which Click turns into "Aborted!" and exit 1):
    # stages clean up, say what is complete, and the command exits with 130 like any interrupted program.
    signal.signal(signal.SIGINT, _raise_interrupted)
    try:
        app(standalone_mode=True)
    except InputError as exc:
        from rich.text import Text

        console.print(Text.assemble(("error: ", "bold red"), str(exc)), highlight=False, soft_wrap=True)
        sys.exit(2)
    except Interrupted as exc:
        console.print(str(exc))
        sys.exit(130)


if __name__ == "__main__":
    main()
