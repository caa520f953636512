"""The ``gtforge`` command's commands: one Typer command per stage, each over ``gtforge.<stage>.<function>``; what
it adds is the options' parsing and the console output (help formatting: ``_typer_style``; the entry point, its exit
codes and what starts before this module is imported: ``gtforge.cli.main``).

Bad input (``InputError``) prints one line and exits with code 2; a FAIL verdict of ``validate``
exits with 1; unexpected bugs keep their traceback.

Over 500 lines on purpose: one short command per stage, its options' help beside it.

Each command imports its stage inside its function (the package's only function-local gtforge imports): ``gtforge
--help`` and a mistyped option answer without loading numba, OpenCV and SciPy.
"""
from __future__ import annotations

import functools
import inspect
import logging
import sys
from pathlib import Path
from typing import List, Optional

import typer
from rich.console import Console

from gtforge.cli._typer_style import _Group
from gtforge.errors import InputError
from gtforge.infra import defaults

app = typer.Typer(cls=_Group, add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Structured-light + ZED stereo rig -> stereo training data with sub-pixel ground truth.\n\n"
                       "The whole chain in one command: gtforge run SESSION -o DIR (calibrate -> [align-depth] -> "
                       "validate -> calibrate-scale -> refine -> build-dataset -> verify, then DIR/index.html, the "
                       "dataset's certificate). Each step is also a command of its own, listed below in that order.")
console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)
out = Console(soft_wrap=True, highlight=False, markup=False)


def _setup_logging(verbose: bool) -> None:
    if console.is_terminal:
        from rich.highlighter import NullHighlighter
        from rich.logging import RichHandler

        # (no highlighter: Rich's default coloured digits, parentheses and <id> in the middle of a message)
        handler: logging.Handler = RichHandler(console=console, show_time=False, show_path=False,
                                               highlighter=NullHighlighter())
        fmt = "%(message)s"
    else:  # logs and pipes: one plain line per message
        handler, fmt = logging.StreamHandler(sys.stderr), "%(levelname)s: %(message)s"
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format=fmt, handlers=[handler], force=True)


def _status(msg: str) -> None:
    """Progress of long work, on an interactive terminal only (logs and pipes stay clean)."""
    if console.is_terminal:
        console.print(msg, style="dim")


def _progress_lines(msg: str) -> None:
    """Progress that also goes to logs and pipes (one plain line each, on stderr): for long silent work."""
    console.print(msg, style="dim" if console.is_terminal else None)


CROP_PRESETS = {"kitti": (1242, 375)}  # KITTI 2015's image size: Fast-ACVNet's KITTI loader trains and validates it


def _wh(text: Optional[str], name: str) -> Optional[tuple[int, int]]:
    if not text:
        return None
    if text.lower() in CROP_PRESETS:
        return CROP_PRESETS[text.lower()]
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise InputError(None, name, "WIDTHxHEIGHT (e.g. 1088x376) or a preset (kitti = 1242x375)",
                         repr(text), f"write both sides, e.g. {name} 1088x376") from None
    if w <= 0 or h <= 0:
        raise InputError(None, name, "a width and height of at least 1 px", repr(text),
                         f"the size the network takes, e.g. {name} 1088x376")
    return w, h


# the board model's fields whose command-line option has another name (calibrate, validate, import)
BOARD_OPTIONS = {"kind": "--board", "square_size_mm": "--square-mm", "marker_size_mm": "--marker-mm",
                 "circle_diameter_mm": "--circle-mm"}


def _options(model, **values):
    """Build a parameter model from command-line options; a value the model refuses is a one-line error naming the
    option (``--max-shift-px: expected ... > 0, got -1.0``)."""
    from pydantic import ValidationError

    try:
        return model.model_validate(values)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = [str(p) for p in err.get("loc", ("value",))]
        board = model.__name__ == "BoardModel" or "board" in loc
        name = (BOARD_OPTIONS.get(loc[-1]) if board else None) or "--" + loc[-1].replace("_", "-")
        msg = err.get("msg", "a valid value").removeprefix("Input should be ")
        hint = ("docs/capture-layout.md 'Declaring the board' lists the kinds and what each option counts" if board
                else f"leave {name} out for its default; docs/pipeline.md lists each stage's options")
        raise InputError(None, name, msg if msg.startswith(("a ", "an ")) else f"a value {msg}",
                         repr(err.get("input")), hint) from None


# The board options calibrate, import and synth share (docs/targets.md): each one's type and help text, a command's own
# note after it.
_BOARD_OPTIONS = {
    "board": (str, "checkerboard (default), charuco, circles_symmetric or circles_asymmetric (docs/targets.md)."),
    "cols": (int, "Inner corners along a row (ChArUco: squares; circle grids: circles per row). Default 12."),
    "rows": (int, "Inner corners along a column (ChArUco: squares; circle grids: rows). Default 9."),
    "square_mm": (float, "Square size, or circle spacing (mm). Default 20."),
    "marker_mm": (float, "ChArUco marker side (mm)."),
    "dictionary": (str, "ChArUco ArUco dictionary, e.g. DICT_5X5_100."),
    "legacy_pattern": (bool, "ChArUco board made before OpenCV 4.6 (even rows)."),
    "circle_mm": (float, "Circle diameter (mm; default half the spacing)."),
}


def _board_option(name: str, note: str = "", panel: str | None = None):
    """The typer option of one of the shared board options (``_BOARD_OPTIONS``); ``None`` when not given."""
    decls = ("--legacy-pattern/--no-legacy-pattern",) if name == "legacy_pattern" else ()
    return typer.Option(None, *decls, metavar="KIND" if name == "board" else None, rich_help_panel=panel,
                        help=f"{_BOARD_OPTIONS[name][1]} {note}".strip())


def _board_model(board, cols, rows, square_mm, marker_mm, dictionary, legacy_pattern, circle_mm):
    """The board the options declare, from the options given only; None where none is."""
    from gtforge.core.targets.models import BoardModel

    given = {k: v for k, v in dict(kind=board, cols=cols, rows=rows, square_size_mm=square_mm,
                                   marker_size_mm=marker_mm, dictionary=dictionary, legacy_pattern=legacy_pattern,
                                   circle_diameter_mm=circle_mm).items() if v is not None}
    return _options(BoardModel, **given) if given else None


def _with_board_options(note: str, panel: str | None = None):
    """A command taking the eight board options (``_BOARD_OPTIONS``, ``note`` after --board's text; after the command's
    own options in its help), given to it as ``board_model``: the board they declare (``_board_model``), None where
    none of them is given. One declaration for calibrate, import and synth."""
    def add(fn):
        sig = inspect.signature(fn)
        own = [p for p in sig.parameters.values() if p.name != "board_model"]
        extra = [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=Optional[kind],
                                   default=_board_option(name, note if name == "board" else "", panel))
                 for name, (kind, _) in _BOARD_OPTIONS.items()]

        @functools.wraps(fn)
        def command(*args, **kwargs):
            board_model = _board_model(**{name: kwargs.pop(name) for name in _BOARD_OPTIONS})
            return fn(*args, board_model=board_model, **kwargs)

        command.__signature__ = sig.replace(parameters=own + extra)
        command.__annotations__ = {**{k: v for k, v in fn.__annotations__.items() if k != "board_model"},
                                   **{p.name: p.annotation for p in extra}}
        return command
    return add


def _print_version(value: bool) -> None:
    if value:
        import gtforge

        out.print(f"gtforge {gtforge.__version__}")
        raise typer.Exit()


@app.callback()
def _main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Show info messages."),
          version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                       help="Print the gtforge version and exit.")) -> None:
    _setup_logging(verbose)


@app.command()
def run(session: Path = typer.Argument(..., help="Capture session folder (docs/capture-layout.md)."),
        output: Path = typer.Option(..., "--output", "-o", metavar="DIR",
                                    help="Folder for every stage's output and the certificate (index.html)."),
        calibration: Optional[Path] = typer.Option(None, "--calibration", "-c", metavar="FILE",
                                                   help="Use this calibration instead of calibrating (needed when "
                                                        "the session has no board captures)."),
        use_depth: bool = typer.Option(False, "--use-depth", help="calibrate --use-depth."),
        loo: bool = typer.Option(True, "--loo/--no-loo", help="Leave-one-out cross-validation in calibrate and "
                                 "refine (--no-loo saves time)."),
        holdout: int = typer.Option(0, min=0, metavar="K", help="validate on the last K board captures with a "
                                    "calibration made without them (validate --holdout K; the dataset still uses "
                                    "every capture's). 0: validate the run's calibration on the captures it used "
                                    "(optimistic)."),
        calibration_scenes: Optional[str] = typer.Option(
            None, metavar="IDS", help="Comma-separated scene ids calibrate-scale and refine use (default: up to "
            f"{defaults.MAX_SCENES} and {defaults.REFINE_MAX_SCENES} scenes, evenly spread over the session)."),
        refine_: bool = typer.Option(True, "--refine/--no-refine", help="Refine the extrinsic from the scenes."),
        quarantine: bool = typer.Option(False, "--quarantine", help="Leave flagged scenes out of the split lists "
                                        "(the run then passes with a warning)."),
        workers: Optional[int] = typer.Option(None, min=1, help="Parallel scenes (default: all cores)."),
        scheduler: Optional[str] = typer.Option(
            None, metavar="ADDRESS", help="Build and verify the scenes on a Dask cluster, e.g. tcp://HOST:8786 (needs "
            "gtforge[dask]; session and output on a filesystem the workers share; docs/cluster.md).")) -> None:
    """Run the whole chain: calibrate -> align-depth (a separate depth camera only) -> validate -> calibrate-scale ->
    refine -> build-dataset -> verify, and write the dataset certificate (DIR/index.html, DIR given by --output). A
    rerun redoes only what changed.

    Exit code 0: every check passed; 1: a quality check failed (named); 2: bad input."""
    from gtforge.run import RunOptions, run_session

    opts = _options(RunOptions, calibration=str(calibration) if calibration else None, use_depth=use_depth, loo=loo,
                    holdout=holdout, calibration_scenes=calibration_scenes.split(",") if calibration_scenes else None,
                    refine=refine_, quarantine=quarantine, workers=workers, scheduler=scheduler)
    res = run_session(session, output, opts, say=out.print, progress=_status)
    if res.exit_code:
        raise typer.Exit(res.exit_code)


def _refuse_a_runs_folder(output: str, name: str) -> None:
    """A stage's calibration never goes into ``gtforge run``'s output folder: it would replace the run's own file of a
    stage (calibrate's over scaled.yaml, another session's over calibration.yaml), which the run's certificate cites
    and its later stages read."""
    from gtforge.io.calibrated_session import calibration_output_file
    from gtforge.io.outputs import free_path

    path = calibration_output_file(output, name)
    if (path.parent / "run_state.json").is_file():
        raise InputError(path, "--output", "a path outside gtforge run's output folder",
                         f"a file in {path.parent}, gtforge run's (its files are the run's stages' own)",
                         f"write it beside the run, e.g. {free_path(path.parent.parent, name)}")


@app.command()
@_with_board_options("Where session.yaml declares the board, its values are the defaults of these options.")
def calibrate(session: Path = typer.Argument(..., help="Capture session folder (docs/capture-layout.md)."),
              output: str = typer.Option("calibration.yaml", "--output", "-o", metavar="PATH",
                                         help="Calibration YAML to write (a folder: calibration.yaml inside it)."),
              report_dir: Optional[Path] = typer.Option(None, metavar="DIR",
                                                        help="Report folder (default: OUTPUT's name + _report, "
                                                             "beside it)."),
              use_depth: bool = typer.Option(False, "--use-depth", help="Also solve 3D-2D through the depth camera's "
                                             "board measurement, use it, and report both methods."),
              captures: Optional[str] = typer.Option(None, metavar="NAMES",
                                                     help="Comma-separated capture names to use (default: all)."),
              loo: bool = typer.Option(True, "--loo/--no-loo",
                                       help="Leave-one-pose-out cross-validation (--no-loo saves time)."),
              self_rectify: bool = typer.Option(True, "--self-rectify/--no-self-rectify",
                                                help="Correct the ZED right camera's residual rotation from left-right "
                                                     "matches over the captures (boards and scenes); applied only "
                                                     "where the captures determine it (docs/pipeline.md)."),
              self_rectify_scenes: int = typer.Option(
                  defaults.MAX_SCENES, min=0, metavar="N", help="Scene captures the self-rectification matches at "
                  "most, evenly spread over the session (0: every scene); every board capture is matched."),
              board_model=None) -> None:
    """Solve T_zed_from_mech from board captures in SESSION/board/ (checkerboard, ChArUco or circle grid)."""
    from gtforge.calibrate import calibrate as run
    from gtforge.io.calibrated_session import calibration_output_path
    from gtforge.records.calibration import CalibrateParams
    from gtforge.reports.calibration import write_calibration_report

    # only the board options given: session.yaml's board (if any) fills the rest
    from gtforge.core.zed.selfcal import SelfRectifyParams

    params = _options(CalibrateParams, **({"board": board_model} if board_model else {}),
                      self_rectification=SelfRectifyParams(max_scenes=self_rectify_scenes or None),
                      use_depth=use_depth, leave_one_out=loo, self_rectify=self_rectify)
    from gtforge.io.captures import open_session
    from gtforge.io.outputs import require_output_folder

    opened = open_session(session)
    _refuse_a_runs_folder(output, "calibration.yaml")
    output = calibration_output_path(output, session=opened)
    report_dir = report_dir or output.parent / (output.stem + "_report")
    opened.refuse_output_over_inputs(report_dir, "--report-dir")
    require_output_folder(report_dir, "--report-dir")
    res = run(session, None, params, captures.split(",") if captures else None, progress=_status)
    from gtforge.infra.atomic import atomic_path

    # the calibration, which the next stages read, lands once its report is written: a run stopped (Ctrl-C) or failing
    # in the report leaves the earlier calibration (if any) as it was, never a new one without its report
    with atomic_path(output) as staged:
        res.write(staged)
        rep = write_calibration_report(res, report_dir)
    n_used = len(res.captures_used)
    n_bad = sum(p.status != "used" for p in res.poses)
    out.print(f"poses used {n_used}, skipped/outliers {n_bad}; RMS {res.rms_px:.3f} px, worst {res.max_px:.3f} px")
    out.print(f"1-sigma rotation {res.sigma_rot_deg:.4f} deg, translation {res.sigma_trans_mm:.3f} mm"
              + (f"; leave-one-out transfer {res.loo_transfer_mean_px:.3f} px mean"
                 if res.loo_transfer_mean_px else ""))
    for m in res.methods[1:]:
        out.print(f"method {m.method}: RMS {m.rms_zed_px:.3f} px, differs by {m.rot_diff_to_primary_deg:.4f} deg / "
                  f"{m.trans_diff_to_primary_mm:.3f} mm")
    if res.square_size_measured_mm is not None:
        out.print(f"board {'circle spacing' if res.board.kind.startswith('circles') else 'squares'} measured in the "
                  f"depth: {res.square_size_measured_mm:.2f} mm (declared {res.board.square_size_mm:g} mm)")
    from gtforge.reports.rectification import summary_lines

    if res.zed_self_rectification is not None:
        out.print(res.zed_self_rectification.summary_line())
    for line in summary_lines(res.rectification, res.zed_conf):
        out.print(line)
    if res.coverage is not None and res.coverage.guidance:
        out.print("capture next (docs/targets.md, 'Coverage'):" + "".join(f"\n  - {g}" for g in res.coverage.guidance))
    out.print(f"wrote {output} and {rep}")
    out.print(f"verdict: {res.verdict}" + "".join(f"\n  - {r}" for r in res.verdict_reasons))
    if res.verdict == "FAIL":
        raise typer.Exit(1)


@app.command("build-dataset")
def build_dataset(session: Path = typer.Argument(..., help="Capture session folder."),
                  calibration: Path = typer.Option(..., "--calibration", "-c", metavar="FILE",
                                                   help="Calibration YAML from gtforge calibrate."),
                  output: Path = typer.Option(..., "--output", "-o", metavar="DIR", help="Dataset folder."),
                  mode: str = typer.Option("mesh", help="mesh (default) or splat."),
                  workers: Optional[int] = typer.Option(None, min=1, help="Parallel scenes (default: all cores)."),
                  scheduler: Optional[str] = typer.Option(
                      None, metavar="ADDRESS", help="Run the scenes on a Dask cluster, e.g. tcp://HOST:8786 (needs "
                      "gtforge[dask]; session, calibration and output on a filesystem the workers share; "
                      "docs/cluster.md)."),
                  overwrite: bool = typer.Option(False, "--overwrite", help="Rebuild every scene."),
                  strict: bool = typer.Option(False, "--strict", help="Stop at the first bad scene."),
                  crop: Optional[str] = typer.Option(
                      None, metavar="WxH", help="Crop around the fruit: WIDTHxHEIGHT, or kitti (1242x375, the size "
                      "Fast-ACVNet's KITTI loader trains and validates)."),
                  ply: bool = typer.Option(False, "--ply", help="Write a PLY point cloud per scene."),
                  erosion_px: int = typer.Option(defaults.EROSION_PX, help="Fruit centre = fruit mask eroded by this."),
                  max_slant_deg: float = typer.Option(defaults.MAX_SLANT_DEG,
                                                      help="mesh: reject triangles steeper than this."),
                  split: str = typer.Option(f"{defaults.SPLIT_TRAIN:g},{defaults.SPLIT_VAL:g}", metavar="TRAIN,VAL",
                                            help="train,val ratios (test gets the rest); scenes of one fruit stay "
                                                 "in one split."),
                  seed: int = typer.Option(defaults.SPLIT_SEED, help="Seed of each fruit's split draw."),
                  verification: bool = typer.Option(True, "--verify/--no-verify",
                                                    help="Check every scene's ground truth against its own images "
                                                         "(texture alignment, stereo consistency; verification.html)."),
                  right_gt: bool = typer.Option(True, "--right-gt/--no-right-gt",
                                                help="Write the right view's ground truth (disp1GT.pfm, mask1nocc.png, "
                                                     "KITTI disp_occ_1/disp_noc_1: OpenStereo's RETURN_RIGHT_DISP "
                                                     "configs read it). --no-right-gt builds a scene about 11 % "
                                                     "faster."),
                  quarantine: bool = typer.Option(False, "--quarantine",
                                                  help="Leave scenes that verification flags out of the split lists "
                                                       "(they stay in scenes/)."),
                  motion_compensation: bool = typer.Option(
                      True, "--motion-compensation/--no-motion-compensation",
                      help="A scene verification flags because its fruit moved between the depth and the ZED "
                           "exposure: rebuild its ground truth with each fruit moved by its estimated rigid motion "
                           "when that passes verification (docs/design/motion-compensation.md).")) -> None:
    """Build disparity ground truth for SESSION/scenes/ into OUTPUT (docs/dataset-format.md)."""
    from gtforge.infra.scheduling import prestart_pool

    # the workers' imports and warm-up (build_dataset.warm_worker) overlap this process's own imports
    prestart_pool("gtforge.build_dataset", workers, scheduler,
                  warm_up=("warm_worker", (str(session.resolve()), str(calibration.resolve()))))
    from gtforge.build_dataset import build_dataset as run
    from gtforge.records.dataset import BuildParams

    try:
        tr, va = (float(x) for x in split.split(","))
    except ValueError:
        raise InputError(None, "--split", "two ratios 'train,val' such as 0.8,0.1", repr(split),
                         "give the train and val shares separated by a comma; test gets the rest") from None
    if mode not in ("mesh", "splat"):
        raise InputError(None, "--mode", "mesh or splat", repr(mode),
                         "leave --mode out for mesh, or give --mode splat (docs/pipeline.md 'build-dataset')")
    params = _options(BuildParams, mode=mode, crop_wh=_wh(crop, "--crop"), ply=ply, erosion_px=erosion_px,
                      max_slant_deg=max_slant_deg, split_train=tr, split_val=va, split_seed=seed,
                      verification=verification, right_gt=right_gt, quarantine=quarantine,
                      motion={"compensate": motion_compensation})
    s = run(session, calibration, output, params, workers=workers, overwrite=overwrite, strict=strict, progress=True,
            scheduler=scheduler)
    failed = f" ({', '.join(s.failures)}; reasons above and in manifest.json)" if s.failures else ""
    out.print(f"built {len(s.built)}, unchanged {len(s.skipped_unchanged)}, failed {len(s.failures)}{failed} "
              f"in {s.time_s:.1f} s -> {s.out_dir}")
    if verification:
        q = " (left out of the split lists: --quarantine)" if s.quarantined else ""
        out.print(f"verification: {len(s.flagged)} scene(s) flagged{q}"
                  + (": " + ", ".join(s.flagged) if s.flagged else "") + f"; see {s.out_dir / 'verification.html'}")
        if s.compensated:
            out.print(f"fruit motion compensated in {len(s.compensated)} scene(s): {', '.join(s.compensated)} "
                      "(their ground truth rebuilt with the fruit moved; filenames/compensated.txt)")
    if s.failures:
        raise typer.Exit(1)


@app.command()
def verify(dataset: Path = typer.Argument(..., help="Dataset folder from gtforge build-dataset."),
           session: Optional[Path] = typer.Option(None, metavar="DIR",
                                                  help="The capture session, if it moved since the build "
                                                       "(default: the one manifest.json names)."),
           scenes: Optional[str] = typer.Option(None, metavar="IDS", help="Comma-separated scene ids (default: all)."),
           workers: Optional[int] = typer.Option(None, min=1, help="Parallel scenes (default: all cores)."),
           scheduler: Optional[str] = typer.Option(None, metavar="ADDRESS",
                                                   help="Run on a Dask cluster (docs/cluster.md)."),
           quarantine: bool = typer.Option(False, "--quarantine",
                                           help="Rewrite the split lists without the flagged scenes."),
           max_shift_px: Optional[float] = typer.Option(None, help="Texture shift threshold (px; default 0.25)."),
           max_disparity_bias_px: Optional[float] = typer.Option(None, help="Disparity bias threshold (px; "
                                                                            "default 0.1).")) -> None:
    """Check an existing dataset's ground truth against its captures (verification.json/.html); exit 1 if any
    scene is flagged or could not be verified."""
    from gtforge.infra.scheduling import prestart_pool

    prestart_pool("gtforge.verify", workers, scheduler)  # (verify_one_scene) the workers' imports overlap ours
    from gtforge.records.dataset import Manifest
    from gtforge.verify import verify_dataset

    params = None
    if max_shift_px is not None or max_disparity_bias_px is not None:
        base = Manifest.read(dataset / "manifest.json").params.verify
        params = _options(type(base), **{**base.model_dump(), **{k: v for k, v in (
            ("max_shift_px", max_shift_px), ("max_disparity_bias_px", max_disparity_bias_px)) if v is not None}})
    rep = verify_dataset(dataset, params, scenes.split(",") if scenes else None, session, workers, scheduler,
                         quarantine, _status)
    n_nv = sum(v.status == "not verifiable" for v in rep.scenes.values())
    flagged = rep.flagged
    checked = len(set(scenes.split(","))) if scenes else len(rep.scenes)
    held = f", the report holds {len(rep.scenes)}" if checked != len(rep.scenes) else ""  # (--scenes: merged in)
    out.print(f"verified {checked} scene(s){held}: {len(flagged)} flagged, {n_nv} not verifiable; "
              f"report: {dataset / 'verification.html'}")
    for sid, reasons in flagged.items():
        out.print(f"  {sid}: " + "; ".join(reasons))
    for sid, v in rep.scenes.items():
        if v.status == "not verifiable":
            out.print(f"  {sid}: not verifiable: " + "; ".join(v.reasons))
    if flagged or n_nv:
        raise typer.Exit(1)


def _scenes_option():
    """``--scenes`` of the stages that use a few of the session's scenes (refine, calibrate-scale, align-depth)."""
    return typer.Option(None, metavar="IDS", help="Comma-separated scene ids (default: up to --max-scenes of them, "
                        "evenly spread over the session).")


def _max_scenes_option(default: int):
    """``--max-scenes`` of those stages, with the stage's default (its parameters' ``max_scenes``)."""
    return typer.Option(default, min=0, metavar="N", help="Without --scenes: use at most N scenes, evenly spread over "
                        "the session (0: every scene).")


def _not_selected(n: int) -> str:
    """What a stage's line adds when ``max_scenes`` left scenes of the session out."""
    return f" ({n} more scene(s) of the session not used: --max-scenes, those used evenly spread)" if n else ""


@app.command()
def refine(session: Path = typer.Argument(..., help="Capture session folder (its scenes/ captures are used)."),
           calibration: Path = typer.Option(..., "--calibration", "-c", metavar="FILE",
                                            help="The board calibration to start from (gtforge calibrate)."),
           output: str = typer.Option("refined.yaml", "--output", "-o", metavar="PATH",
                                      help="Refined calibration YAML to write (never the input file)."),
           scenes: Optional[str] = _scenes_option(),
           max_scenes: int = _max_scenes_option(defaults.REFINE_MAX_SCENES),
           loo: bool = typer.Option(True, "--loo/--no-loo",
                                    help="Hold each scene out in turn and measure it (cross-validation).")) -> None:
    """Refine T_zed_from_mech from the scenes' texture alignment; writes a normal calibration file whose
    'refinement' says it was refined and from which scenes."""
    from gtforge.refine import RefineParams
    from gtforge.refine import refine as run

    _refuse_a_runs_folder(output, "refined.yaml")
    params = RefineParams(leave_one_out=loo, max_scenes=max_scenes or None)
    res = run(session, calibration, output, params, scenes.split(",") if scenes else None, progress=_status)
    info = res.refinement
    out.print(f"refined over {len(info.scenes_used)} scene(s); excluded {len(info.scenes_excluded)}"
              + _not_selected(info.scenes_not_selected)
              + "".join(f"\n  {k}: {v}" for k, v in info.scenes_excluded.items()))
    out.print(f"the extrinsic moved by {info.change_rot_deg:.4f} deg / {info.change_trans_mm:.3f} mm; "
              f"1-sigma now {res.sigma_rot_deg:.4f} deg / {res.sigma_trans_mm:.3f} mm")
    for r in info.scenes:
        out.print(f"  scene {r.scene}: |texture shift| "
                  f"{r.shift_before_px if r.shift_before_px is not None else float('nan'):.3f}"
                  f" -> {r.shift_after_px if r.shift_after_px is not None else float('nan'):.3f} px"
                  + (f" (held out: {r.heldout_shift_px:.3f} px)" if r.heldout_shift_px is not None else "")
                  + f" [{r.status}]")
    if info.heldout_shift_after_mean_px is not None:
        out.print(f"cross-validation: held-out scenes {info.heldout_shift_before_mean_px:.3f} -> "
                  f"{info.heldout_shift_after_mean_px:.3f} px mean |texture shift|")
    from gtforge.io.calibrated_session import calibration_output_path

    out.print(f"wrote {calibration_output_path(output, 'refined.yaml')}")


@app.command("calibrate-scale")
def calibrate_scale(session: Path = typer.Argument(..., help="Capture session folder (scenes/ and board/ captures)."),
                    calibration: Path = typer.Option(..., "--calibration", "-c", metavar="FILE",
                                                     help="The calibration to correct (gtforge calibrate)."),
                    output: str = typer.Option("scaled.yaml", "--output", "-o", metavar="PATH",
                                               help="Corrected calibration YAML to write (never the input file)."),
                    scenes: Optional[str] = _scenes_option(),
                    max_scenes: int = _max_scenes_option(defaults.MAX_SCENES),
                    boards: bool = typer.Option(True, "--boards/--no-boards",
                                                help="Use the board captures (they separate baseline from depth "
                                                     "scale).")
                    ) -> None:
    """Estimate the disparity-scale terms (ZED baseline, right-camera yaw, depth scale and offset) from the scenes'
    stereo consistency and the boards; writes a calibration file that applies them (its 'scale_calibration' says
    what was found, each term's sigma and where it came from)."""
    from gtforge.records.calibration import ScaleParams
    from gtforge.scale_calibration import calibrate_scale as run

    _refuse_a_runs_folder(output, "scaled.yaml")
    params = ScaleParams(use_boards=boards, max_scenes=max_scenes or None)
    res = run(session, calibration, output, params, scenes.split(",") if scenes else None, progress=_status)
    from gtforge.reports.calibration import scale_term_lines

    info = res.scale_calibration
    for line in scale_term_lines(info):
        out.print("  " + line)
    by = info.board_poses_by_measurement
    each = [f"{label} {len(by[k])}" for k, label in (("zed_pair", "ZED pair"), ("depth_map", "depth map")) if k in by]
    out.print(f"baseline {info.baseline_file_mm:.4f} -> {res.rig.zed.baseline_mm:.4f} mm; "
              f"scenes {', '.join(info.scenes_used)}{_not_selected(info.scenes_not_selected)}; board poses "
              f"{len(info.board_poses_used)}" + (f" ({', '.join(each)})" if len(each) > 1 else ""))
    from gtforge.io.calibrated_session import calibration_output_path

    out.print(f"wrote {calibration_output_path(output, 'scaled.yaml')}")


@app.command("align-depth")
def align_depth(session: Path = typer.Argument(..., help="Capture session folder (scenes/ and board/ captures)."),
                calibration: Path = typer.Option(..., "--calibration", "-c", metavar="FILE",
                                                 help="The calibration whose depth camera pose to refine "
                                                      "(gtforge calibrate)."),
                output: str = typer.Option("aligned.yaml", "--output", "-o", metavar="PATH",
                                           help="Calibration YAML to write (never the input file)."),
                scenes: Optional[str] = _scenes_option(),
                max_scenes: int = _max_scenes_option(defaults.MAX_SCENES),
                boards: bool = typer.Option(True, "--boards/--no-boards", help="Use the board captures too."),
                search_px: float = typer.Option(defaults.EDGE_SEARCH_PX,
                                                help="First coarse search range (px, at most 48); widened while "
                                                     "the best shift is on its border, up to 48."),
                apply_z: float = typer.Option(defaults.EDGE_APPLY_Z,
                                              help="Apply the correction when it is more than this many sigma "
                                                   "from the factory pose."),
                edges: str = typer.Option("auto", metavar="KIND",
                                          help="Which of the depth camera's edges to put on the texture image's: "
                                               "silhouettes (depth jumps), texture (its own image's edges: IR.png "
                                               "beside each capture, as gtforge import writes an Azure Kinect's "
                                               "infrared image), both, or auto (both where a capture has IR.png)."
                                          )) -> None:
    """Refine a separate depth camera's pose (T_mech_from_depth: Azure Kinect, Orbbec, PrimeSense-class units) by
    putting every capture's depth silhouettes, and its own image's edges where it has one (IR.png), on the texture
    image's edges; writes a calibration file with the
    corrected pose and its covariance (its 'depth_alignment' says what was found, and each capture's pixel offset
    before and after). Run it after calibrate, before calibrate-scale."""
    from gtforge.align_depth import align_depth as run
    from gtforge.align_depth import summary_lines
    from gtforge.core.alignment.edge_alignment import EdgeAlignmentParams
    from gtforge.io.calibrated_session import calibration_output_path
    from gtforge.reports.depth_alignment import write_depth_alignment_report

    params = _options(EdgeAlignmentParams, search_px=search_px, apply_z=apply_z, edges=edges,
                      max_scenes=max_scenes or None)
    _refuse_a_runs_folder(output, "aligned.yaml")
    res = run(session, calibration, output, params, scenes.split(",") if scenes else None, use_boards=boards,
              progress=_status)
    for line in summary_lines(res.depth_alignment):
        out.print(line)
    path = calibration_output_path(output, "aligned.yaml")
    rep = write_depth_alignment_report(res.depth_alignment, path.parent / (path.stem + "_report.html"))
    out.print(f"wrote {path} and {rep}")


@app.command()
def validate(session: Path = typer.Argument(..., help="Capture session folder (board/ captures)."),
             calibration: Optional[Path] = typer.Option(None, "--calibration", "-c",
                                                        metavar="FILE",
                                                        help="Calibration YAML (not needed with --holdout)."),
             output: Path = typer.Option(Path("validation"), "--output", "-o", metavar="DIR", help="Report folder."),
             holdout: int = typer.Option(0, min=0, help="Calibrate without the last K board captures (written to "
                                                 "OUTPUT/holdout_calibration.yaml) and validate on them."),
             captures: Optional[str] = typer.Option(None, metavar="NAMES",
                                                    help="Comma-separated capture names to validate on."),
             cols: Optional[int] = typer.Option(None, help="Inner corners along a row (default: the "
                                                           "calibration's board)."),
             rows: Optional[int] = typer.Option(None, help="Inner corners along a column (default: the "
                                                           "calibration's)."),
             square_mm: Optional[float] = typer.Option(None, help="Square size, mm (default: the calibration's)."),
             xy_threshold_px: float = typer.Option(defaults.XY_THRESHOLD_PX,
                                                   help="PASS when the mean XY error is at most this (px)."),
             z_threshold_pct: float = typer.Option(defaults.Z_THRESHOLD_PCT,
                                                   help="PASS when the mean Z error is at most this (%)."),
             gauges_only: bool = typer.Option(False, "--gauges-only",
                                              help="Only the gauge objects of gauges/gauges.yaml (VDI/VDE 2634-2 "
                                                   "figures; needs --calibration), not the board captures.")) -> None:
    """XY reprojection (px) and Z geometric (%) accuracy, and the gauge objects' VDI/VDE 2634-2 figures when the
    session has gauges/gauges.yaml; exit code 1 on FAIL."""
    from gtforge.core.measure.gauges import summary_lines as gauge_lines
    from gtforge.core.targets.models import BoardModel
    from gtforge.records.validation import REFERENCE_XY_PX, REFERENCE_Z_PCT, ValidateParams
    from gtforge.validate import validate as run
    from gtforge.validate import validate_gauges

    if holdout and calibration is not None:  # (--holdout calibrates anew: the file given would go unused)
        raise InputError(calibration, "--calibration", "no calibration file with --holdout K (it calibrates on the "
                         "other captures and validates that)", "both",
                         "drop -c, or drop --holdout to validate the file")

    if gauges_only:
        if calibration is None:
            raise InputError(None, "--calibration", "a calibration file with --gauges-only", "none",
                             "pass -c with the file gtforge calibrate wrote")
        grep = validate_gauges(session, calibration, output, progress=_status)
        for line in gauge_lines(grep):
            out.print(line)
        out.print(f"report: {output / 'gauges.html'}")
        if grep.status == "FAIL":
            raise typer.Exit(1)
        return

    board = None
    if cols is not None or rows is not None or square_mm is not None:
        if calibration is not None and not holdout:
            from gtforge.records.calibration import CalibrationFile

            base = CalibrationFile.read(calibration).board
        else:
            base = BoardModel()
        board = _options(BoardModel, **{**base.model_dump(), **{k: v for k, v in (
            ("cols", cols), ("rows", rows), ("square_size_mm", square_mm)) if v is not None}})
    params = _options(ValidateParams, board=board, xy_threshold_px=xy_threshold_px, z_threshold_pct=z_threshold_pct)
    names = captures.split(",") if captures else None
    if holdout:
        from gtforge.holdout import validate_holdout

        rep = validate_holdout(session, holdout, output, params, names, _status)
    else:
        rep = run(session, calibration, output, params, names, progress=_status)
    out.print(f"XY reprojection: mean {rep.xy_mean_px:.3f} px (median {rep.xy_median_px:.3f}, "
              f"max {rep.xy_max_px:.3f}); "
              f"published {REFERENCE_XY_PX} px; threshold {xy_threshold_px} -> {'PASS' if rep.pass_xy else 'FAIL'}")
    out.print(f"  corner detectors' noise floor {rep.xy_noise_floor_px:.3f} px; with it removed (board models): "
              f"{rep.xy_model_mean_px:.3f} px")
    out.print(f"Z geometric: mean {rep.z_error_mean_pct:.4f} % (max {rep.z_error_max_pct:.4f}); published "
              f"{REFERENCE_Z_PCT} %; threshold {z_threshold_pct} -> {'PASS' if rep.pass_z else 'FAIL'}")
    from gtforge.reports.rectification import summary_lines

    for line in summary_lines(rep.rectification):
        out.print(line)
    if rep.gauges is not None:
        for line in gauge_lines(rep.gauges):
            out.print(line)
    out.print(f"report: {output / 'validation.html'}")
    if not rep.passed or (rep.gauges is not None and rep.gauges.status == "FAIL"):
        raise typer.Exit(1)


_MODEL = "Model (exactly one is required)"
_NET = "Network input (--onnx, --torchscript)"
_TARGET = "Calibration target (as calibrate takes it)"


@app.command()
def evaluate(dataset: Path = typer.Argument(..., help="Dataset folder from build-dataset."),
             output: Path = typer.Option(Path("evaluation"), "--output", "-o", metavar="DIR",
                                         help="Folder for results.json/.md/.csv/.html and heatmaps/."),
             onnx: Optional[Path] = typer.Option(None, metavar="FILE", rich_help_panel=_MODEL,
                                                 help="ONNX model (inputs: left, right NCHW, or one N x 6 x H x W)."),
             torchscript: Optional[Path] = typer.Option(None, metavar="FILE", rich_help_panel=_MODEL,
                                                        help="TorchScript (.pt) or torch.export (.pt2) model "
                                                             "(needs torch)."),
             predictions: Optional[Path] = typer.Option(None, metavar="DIR", rich_help_panel=_MODEL,
                                                        help="Folder of predicted disparities, one file per scene id: "
                                                             "<id>.pfm, <id>.npy, <id>.png or <id>_10.png (KITTI), "
                                                             "<id>/disp0.pfm (docs/metrics.md)."),
             sgbm: bool = typer.Option(False, "--sgbm", rich_help_panel=_MODEL, help="OpenCV SGBM baseline."),
             name: Optional[str] = typer.Option(None, help="Model name in the tables (default: the file's name)."),
             split: Optional[str] = typer.Option(None, metavar="train|val|test",
                                                 help="Score one split list (default: every scene)."),
             max_disp: Optional[float] = typer.Option(None, metavar="PX",
                                                      help="Only score GT below this disparity (px)."),
             max_gt_sigma: Optional[float] = typer.Option(
                 None, metavar="PX", help="Only score GT pixels whose ground-truth sigma (disp0GT_sigma.pfm) is below "
                 "this (px); the tables count the pixels left out."),
             channels: str = typer.Option("RGB", metavar="RGB|BGR", rich_help_panel=_NET, help="Channel order."),
             normalize: str = typer.Option("imagenet", metavar="imagenet|0-255|0-1", rich_help_panel=_NET,
                                           help="Input scaling."),
             fit: str = typer.Option("pad", metavar="pad|resize", rich_help_panel=_NET,
                                     help="pad (to a multiple of 32, crop back) or resize."),
             resize: Optional[str] = typer.Option(None, metavar="WxH", rich_help_panel=_NET,
                                                  help="Network input size with --fit resize."),
             params_count: Optional[int] = typer.Option(None, metavar="N", min=0,
                                                        help="Parameter count for the table."),
             clouds: bool = typer.Option(False, "--clouds/--no-clouds",
                                         help="Also write a PLY point cloud per scene, coloured by depth error."),
             fruit_size: bool = typer.Option(True, "--fruit-size/--no-fruit-size",
                                             help="Measure each fruit's diameter, height and volume (GT and model)."),
             grades: Optional[str] = typer.Option(
                 None, metavar="QUANTITY:EDGES", help="Grade bins for the fruit, e.g. diameter_mm:180,200,220 or "
                 "volume_ml:2500,4000: grade confusion of model vs GT.")) -> None:
    """Score a model's disparities against the built ground truth, per region.

    Exactly one model option is required: --onnx, --torchscript, --predictions or --sgbm.
    Exit code 1 when some scenes could not be scored (listed first and last), 2 on bad input."""
    from gtforge.evaluate import evaluate as run
    from gtforge.predictors import SGBM, OnnxModel, PredictionFolder, TorchScriptModel
    from gtforge.reports.evaluation import tables_markdown

    chosen = [x for x in (onnx, torchscript, predictions) if x is not None] + ([True] if sgbm else [])
    if len(chosen) != 1:
        raise InputError(None, "model", "exactly one of --onnx, --torchscript, --predictions, --sgbm",
                         f"{len(chosen)} given", "evaluate scores one model a run; gtforge compare puts several "
                         "side by side" if chosen else "name the model to score, e.g. --sgbm for the baseline")
    conv = _input_convention(channels, normalize, fit, resize)
    if grades is not None and not fruit_size:
        raise InputError(None, "--grades", "the fruit measured (the grades are of their sizes)", "--no-fruit-size",
                         "drop one of the two")
    net_options = [o for o, v, d in (("--channels", channels, "RGB"), ("--normalize", normalize, "imagenet"),
                                     ("--fit", fit, "pad"), ("--resize", resize, None)) if v != d]
    if net_options and not (onnx or torchscript):
        logging.getLogger("gtforge.evaluate").warning(
            "%s shape%s a network's input (--onnx, --torchscript): ignored for %s", ", ".join(net_options),
            "" if len(net_options) > 1 else "s", "--predictions" if predictions else "--sgbm")
    if onnx:
        pred = OnnxModel(onnx, conv, name)
    elif torchscript:
        pred = TorchScriptModel(torchscript, conv, name)
    elif predictions:
        pred = PredictionFolder(predictions, name)
    else:
        pred = SGBM(name=name or "SGBM")
    from gtforge.core.measure.fruit_size import parse_grades

    bins = parse_grades(grades) if grades is not None else None
    rep = run(dataset, pred, output, split, max_disp, clouds, params_count, _status, max_gt_sigma_px=max_gt_sigma,
              grades=bins, fruit_size=fruit_size)
    out.print(tables_markdown([rep]))
    if rep.fruit_size is not None and rep.fruit_size.time_ms_per_scene is not None:
        out.print(f"fruit size measured in {rep.fruit_size.time_ms_per_scene:.0f} ms per scene (median)")
    if predictions:
        out.print(f"median {rep.time_ms_median:.1f} ms/frame to read a prediction; results in {output}")
    else:
        out.print(f"median warm inference {rep.time_ms_median:.1f} ms/frame ({rep.provider}); results in {output}")
    allm = rep.pooled["all"]
    if allm.n_valid == 0:  # nothing measured: the tables' dashes are no result (a newcomer's run-through)
        console.print(f"warning: no pixel was scored ({allm.n_gt} ground-truth pixels"
                      + (f", {allm.n_gt_sigma_left_out} left out by --max-gt-sigma" if allm.n_gt_sigma_left_out else "")
                      + ", no valid prediction on them)" + ("" if allm.n_gt else ": check --max-gt-sigma, --max-disp "
                                                          "and --split") + "; exit code 1")
    if rep.missing:
        out.print(f"{len(rep.missing)} scene(s) excluded: " + "; ".join(f"{k}: {v}" for k, v in rep.missing.items()))
    if rep.missing or allm.n_valid == 0:
        raise typer.Exit(1)


def _input_convention(channels: str, normalize: str, fit: str, resize: Optional[str]):
    """evaluate's network options as an ``InputConvention``, each mistake named by its option."""
    from typing import get_args

    from gtforge.predictors import InputConvention

    for field, value in (("channels", channels), ("normalize", normalize), ("fit", fit)):
        allowed = get_args(InputConvention.model_fields[field].annotation)  # (the model's Literal: one list)
        if value not in allowed:
            raise InputError(None, f"--{field}", " or ".join(allowed), repr(value), "gtforge evaluate --help")
    wh = _wh(resize, "--resize")
    if fit == "resize" and wh is None:
        raise InputError(None, "--resize", "the network's input size WxH with --fit resize", "none",
                         "e.g. --fit resize --resize 1248x384")
    if fit != "resize" and wh is not None:
        raise InputError(None, "--resize", "--fit resize with it", f"--fit {fit}",
                         "add --fit resize, or drop --resize (--fit pad pads each image to a multiple of 32)")
    return InputConvention(channels=channels, normalize=normalize, fit=fit, resize_wh=wh)


@app.command()
def compare(results: List[Path] = typer.Argument(..., help="results.json files from gtforge evaluate (or the "
                                                         "folders holding them)."),
            output: Path = typer.Option(Path("comparison"), "--output", "-o", metavar="DIR",
                                        help="Folder for comparison.md/.csv/.html.")) -> None:
    """Put several evaluated models side by side in one table (warns when they are not comparable)."""
    from gtforge.evaluate import compare as run

    table, _ = run(results, output)
    out.print(table)
    out.print(f"wrote {output / 'comparison.html'} (and .md, .csv)")


def _progress_bar():
    """A rich progress bar fed by a stage's ``progress("what: i/n")`` messages (interactive terminals only)."""
    import contextlib
    import re

    from rich.markup import escape
    from rich.progress import Progress

    if not console.is_terminal:
        return contextlib.nullcontext(), lambda msg: None
    bar, tasks = Progress(console=console, transient=True), {}

    def tick(msg: str) -> None:
        m = re.match(r"(.*?)(\d+)/(\d+)$", msg)
        if m:
            key = m.group(1).split(":")[0].strip()
            if key not in tasks:
                tasks[key] = bar.add_task(escape(key), total=int(m.group(3)))  # (rich reads it as markup)
            bar.update(tasks[key], completed=int(m.group(2)))
    return bar, tick


@app.command("import")
@_with_board_options("The target the board captures show.")
def import_(recordings: List[Path] = typer.Argument(..., help="The depth camera's recording (RealSense .bag, Azure "
                                                   "Kinect .mkv, ROS 1/2 bag: .bag, .db3, .mcap or a rosbag2 folder) "
                                                   "and, optionally, the stereo camera's (a ROS bag, a ZED .svo2 "
                                                   "or a ZED SDK export folder)."),
            output: Path = typer.Option(..., "--output", "-o", metavar="SESSION", help="Session folder to write."),
            add: bool = typer.Option(False, "--add", help="Add the captures to an existing session."),
            max_skew_ms: float = typer.Option(20.0, help="Largest time difference between the frames of a capture."),
            still_threshold: float = typer.Option(2.0, help="A frame is still when its mean grey difference to its "
                                                  "neighbours is below this (0-255 levels)."),
            clock_offset_ms: Optional[str] = typer.Option(None, metavar="MS|auto", help="Stereo clock minus depth "
                                                          "clock (default: 0 where the clocks overlap, else "
                                                          "estimated from motion events); auto: always estimate."),
            every: int = typer.Option(1, min=1, help="Keep every N-th still capture."),
            max_captures: Optional[int] = typer.Option(None, min=1, help="Keep at most this many captures."),
            depth_topic: Optional[str] = typer.Option(None, help="Depth image topic (default: realsense-ros names)."),
            color_topic: Optional[str] = typer.Option(None, help="Colour image topic beside the depth."),
            left_topic: Optional[str] = typer.Option(None, help="Rectified left image topic (default: "
                                                     "zed-ros2-wrapper names)."),
            right_topic: Optional[str] = typer.Option(None, help="Rectified right image topic."),
            depth_unit: Optional[str] = typer.Option(None, metavar="mm|m", help="Depth unit (default: by encoding: "
                                                     "16-bit mm, 32FC1 m)."),
            fps: Optional[float] = typer.Option(None, help="Frame rate of a ZED SDK export folder (left%06d.png)."),
            zed_calibration: Optional[Path] = typer.Option(None, metavar="FILE", help="The calibration of a ZED .svo2 "
                                                           "(SN<serial>.conf) or ZED SDK export folder (SN<serial>.conf"
                                                           " or rectified YAML)."),
            classify: bool = typer.Option(True, "--classify/--no-classify",
                                          help="Put captures showing the board into board/ (else all in scenes/)."),
            board_model=None) -> None:
    """Write a capture session (docs/capture-layout.md, "From recordings") from sensor recordings."""
    from rich.table import Table

    from gtforge.importer import import_recordings
    from gtforge.io.ros_recordings import Topics
    from gtforge.records.imports import ImportParams

    if depth_unit not in (None, "mm", "m"):
        raise InputError(None, "--depth-unit", "mm or m", repr(depth_unit),
                         "leave --depth-unit out to take the unit the depth image's encoding implies")
    offset, estimate = None, False
    if clock_offset_ms is not None:
        if clock_offset_ms == "auto":
            estimate = True
        else:
            try:
                offset = float(clock_offset_ms)
            except ValueError:
                raise InputError(None, "--clock-offset-ms", "a number of ms or auto", repr(clock_offset_ms),
                                 "give the stereo clock minus the depth clock in ms (e.g. 12.5), or auto to estimate "
                                 "it (docs/capture-layout.md 'From recordings')") from None
    params = _options(ImportParams, max_skew_ms=max_skew_ms, still_threshold=still_threshold, clock_offset_ms=offset,
                      estimate_clock_offset=estimate, every=every, max_captures=max_captures, classify=classify,
                      board=board_model)
    bar, tick = _progress_bar()
    topics = Topics(depth_topic, color_topic, left_topic, right_topic, depth_unit, fps, zed_calibration)
    with bar:
        s = import_recordings(recordings, output, params, topics, add=add, progress=tick)
    t = Table(title=f"imported into {s.session}")
    for c in ("captures", "boards", "scenes", *(f"dropped: {k}" for k in s.dropped)):
        t.add_column(c, justify="right")
    t.add_row(str(len(s.captures)), str(s.boards), str(s.scenes), *map(str, s.dropped.values()))
    out.print(t)
    out.print(f"clock offset {s.clock_offset_ms:.1f} ms ({s.clock_offset_source}); provenance in "
              f"{s.session / 'import.json'}")
    for w in s.warnings:
        console.print(f"warning: {w}")


@app.command()
@_with_board_options("Written into session.yaml.", _TARGET)
def synth(output: Path = typer.Argument(..., help="Folder for the synthetic session."),
          boards: int = typer.Option(8, metavar="N", min=0, help="Checkerboard captures."),
          scenes: int = typer.Option(3, metavar="N", min=0, help="Fruit scene captures."),
          scale: float = typer.Option(0.5, min=0.1, max=2.0,
                                      help="Resolution factor of the synthetic cameras (1.0 = ZED 2K)."),
          seed: int = typer.Option(0, min=0, help="Random seed (the same seed renders the same session)."),
          depth_noise_mm: float = typer.Option(0.03, metavar="MM", min=0.0,
                                               help="Gaussian noise added to the structured-light depth (mm)."),
          gauges: bool = typer.Option(False, "--gauges", help="Also capture gauge objects (a sphere, a sphere pair, "
                                      "a plate) into gauges/ with gauges.yaml, for validate."),
          baseline_error_pct: float = typer.Option(0.0, metavar="PCT",
                                                   help="The ZED's true baseline is this much longer than its file "
                                                        "says (%; calibrate-scale's test)."),
          right_yaw_deg: float = typer.Option(0.0, metavar="DEG",
                                              help="The right ZED camera is turned by this about its vertical axis."),
          depth_scale_error_pct: float = typer.Option(0.0, metavar="PCT",
                                                      help="The depth map reads this much long (%)."),
          depth_offset_mm: float = typer.Option(0.0, metavar="MM", help="The depth map reads this much far (mm)."),
          separate_depth_camera: bool = typer.Option(False, "--separate-depth-camera",
                                                     help="The structured-light unit's depth map comes from its own "
                                                          "camera, 45 mm beside the texture camera (session.yaml "
                                                          "names it)."),
          depth_pose_error_deg: Optional[str] = typer.Option(
              None, metavar="X,Y,Z", help="With --separate-depth-camera: session.yaml's depth camera pose is the true "
                                          "one turned by this rotation vector (deg; calibrate-scale's test)."),
          moved_fruit_mm: float = typer.Option(
              0.0, metavar="MM", min=0.0,
              help="The last scene: four melons, three moved between the structured-light and the ZED exposure by "
                   "this (mm, turned by 2/3 of it in deg, at most 2), one of them partly out of the depth camera's "
                   "view, and one still; truth at the ZED's exposure (build-dataset's motion compensation)."),
          raw_zed: bool = typer.Option(False, "--raw-zed",
                                       help="The ZED's images raw, straight off the sensor (a VGA ZED Mini with "
                                            "barrel distortion), with its factory SN12345.conf: calibrate rectifies "
                                            "them. Takes --boards, --scenes, --seed, --depth-noise-mm and the board "
                                            "options only."),
          board_model=None) -> None:
    """Render a synthetic capture session with exact truth (truth/ beside the captures).

    A ChArUco session, for instance: gtforge synth S --board charuco --cols 9 --rows 7 --square-mm 30 --marker-mm
    22 --dictionary DICT_5X5_100 --scale 0.6 (its markers must span a dozen pixels or more to be found)."""
    import math

    from gtforge.io.outputs import require_new_or_empty_folder
    from gtforge.synthetic import generate_raw_zed_session, generate_session

    for option, value in (("--depth-noise-mm", depth_noise_mm), ("--baseline-error-pct", baseline_error_pct),
                          ("--right-yaw-deg", right_yaw_deg), ("--depth-scale-error-pct", depth_scale_error_pct),
                          ("--depth-offset-mm", depth_offset_mm), ("--moved-fruit-mm", moved_fruit_mm)):
        if not math.isfinite(value):  # (rendered as given: a NaN rig, an infinite noise)
            raise InputError(None, option, "a finite number", str(value), f"leave {option} out for its default")
    for option, value in (("--baseline-error-pct", baseline_error_pct), ("--depth-scale-error-pct",
                                                                         depth_scale_error_pct)):
        if not -100 < value <= 100:  # (-100 %: a baseline, a depth of zero; 1000 %: no board pose fits both cameras)
            raise InputError(None, option, "a share above -100 % and at most 100 %", f"{value:g}",
                             "give the error in percent of the true length, e.g. 0.5 or -0.3")
    spec = board_model.spec() if board_model is not None else None
    if board_model is not None:
        from gtforge.core.targets.models import check_board_model

        check_board_model(board_model)  # as calibrate will (a ChArUco without its dictionary ...)
    if raw_zed:
        unused = [o for o, v, d in (("--scale", scale, 0.5), ("--gauges", gauges, False),
                                    ("--baseline-error-pct", baseline_error_pct, 0.0),
                                    ("--right-yaw-deg", right_yaw_deg, 0.0),
                                    ("--depth-scale-error-pct", depth_scale_error_pct, 0.0),
                                    ("--depth-offset-mm", depth_offset_mm, 0.0),
                                    ("--separate-depth-camera", separate_depth_camera, False),
                                    ("--depth-pose-error-deg", depth_pose_error_deg, None),
                                    ("--moved-fruit-mm", moved_fruit_mm, 0.0)) if v != d]
        if unused:
            raise InputError(None, "--raw-zed", "only --boards, --scenes, --seed, --depth-noise-mm and the board "
                             "options with it", ", ".join(unused), "render the raw-ZED session without them")
        require_new_or_empty_folder(output, "OUTPUT", "synth writes a whole new session; choose a new folder "
                                    "(it never writes into existing captures)")
        generate_raw_zed_session(output, n_board=boards, n_scenes=scenes, seed=seed, depth_noise_mm=depth_noise_mm,
                                 **({"board": spec} if spec is not None else {}), progress=_progress_lines)
        out.print(f"wrote {output}")
        return

    pose_error = None
    if depth_pose_error_deg is not None:
        try:
            pose_error = tuple(float(x) for x in depth_pose_error_deg.split(","))
        except ValueError:
            pose_error = ()
        if len(pose_error) != 3 or not all(math.isfinite(a) for a in pose_error):
            raise InputError(None, "--depth-pose-error-deg", "three angles 'X,Y,Z' in deg such as 0.1,-0.15,0.1",
                             repr(depth_pose_error_deg), "give three finite numbers separated by commas")
        if not separate_depth_camera:
            raise InputError(None, "--depth-pose-error-deg", "--separate-depth-camera with it",
                             "a rig with one camera", "add --separate-depth-camera")
    rigid = None
    if moved_fruit_mm > 0:
        if scenes < 1:
            raise InputError(None, "--moved-fruit-mm", "at least one scene to move the fruit in", "--scenes 0",
                             "give --scenes 1 or more, or drop --moved-fruit-mm")
        m, r = moved_fruit_mm, min(2.0, 2.0 / 3.0 * moved_fruit_mm)
        rigid = {scenes - 1: [((0.8 * m, -0.6 * m, 0.0), (0.6 * r, 0.0, -0.8 * r)), ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
                              ((-0.6 * m, -0.8 * m, 0.0), (0.0, 0.8 * r, 0.6 * r)), ((0.0, m, 0.0), (0.0, 0.0, r))]}
    require_new_or_empty_folder(output, "OUTPUT", "synth writes a whole new session; choose a new folder "
                                "(it never writes into existing captures)")
    generate_session(output, n_board=boards, n_scenes=scenes, scale=scale, seed=seed, depth_noise_mm=depth_noise_mm,
                     zed_baseline_error_frac=baseline_error_pct / 100.0, right_yaw_deg=right_yaw_deg,
                     depth_scale_error_frac=depth_scale_error_pct / 100.0, depth_offset_mm=depth_offset_mm,
                     two_camera=separate_depth_camera, depth_pose_error_deg=pose_error, progress=_progress_lines,
                     fruit_rigid_motion=rigid, **({"board": spec} if spec is not None else {}))
    if gauges:
        from gtforge.synthetic import generate_gauges

        generate_gauges(output, scale=scale, seed=seed, depth_noise_mm=depth_noise_mm)
        _progress_lines("gauges")
    out.print(f"wrote {output}")


@app.command()
def demo(directory: Path = typer.Argument(Path("demo_out"), help="Where the demo writes everything."),
         scale: float = typer.Option(0.5, min=0.1, max=2.0,
                                     help="Resolution factor of the synthetic cameras (1.0 = ZED 2K)."),
         boards: int = typer.Option(8, metavar="N", min=5,
                                    help="Checkerboard captures (the last 2 are held out for validate)."),
         scenes: int = typer.Option(5, metavar="N", min=1,
                                    help="Fruit scene captures (in the last, the fruit rolls 0.6 mm between the two "
                                         "captures; 4 or more also run refine)."),
         seed: int = typer.Option(0, min=0, help="Random seed.")) -> None:
    """Generate a synthetic session and run calibrate -> validate -> calibrate-scale -> refine -> build-dataset (with
    verification and sigma maps) -> evaluate, each checked against the exact truth; then the same chain as one command
    (gtforge run), which writes the dataset certificate (DIRECTORY/run/index.html)."""
    from gtforge.demo import run_demo

    run_demo(directory, scale=scale, n_board=boards, n_scenes=scenes, seed=seed, say=out.print, status=_status)
