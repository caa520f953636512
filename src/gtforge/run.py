"""``gtforge run``: the whole chain in one command, in the documented order (calibrate -> align-depth -> validate ->
calibrate-scale -> refine -> build-dataset -> verify), each stage's output under OUT/ with the step-by-step commands'
file names, then the dataset certificate (``OUT/index.html`` + ``certificate.json``, ``reports.certificate``).

Each stage records in ``OUT/run_state.json`` (``records.run.RunState``) its inputs' BLAKE3 (session files and the
earlier stages' outputs), its options and its outputs; the next run skips a stage whose inputs, options and outputs
are unchanged, and says what it redoes and why. build-dataset rebuilds only the scenes whose inputs changed (its own
resume), and verify re-checks only the scenes rebuilt: with the figures the build's own checks gave them, which are
the ones verify computes from their files (this run's records vouch for the files), and computed again only for a
scene whose fruit moved. A stage's record is written only once the stage is complete, and every stage writes its
files whole, so Ctrl-C at any point leaves a run that the same command resumes.

What each stage reads (its inputs here): calibrate the session's camera files, the board captures and the ZED images
of up to 24 scenes, evenly spread (its self-rectification matches left and right in those; it reads no scene depth);
align-depth (a unit whose depth map lies on a separate depth camera only) every board capture and up to 24 scenes,
evenly spread, and their IR.png, with the calibration; validate the board captures (and gauges/) with the
calibration; calibrate-scale the boards and up to 24 scenes, evenly spread (or ``calibration_scenes``), with the
calibration; refine up to 48 scenes, evenly spread (or those), with the scaled calibration; build-dataset every
scene with the last calibration; verify each built scene. Stages that do not apply are skipped with the reason: no
board captures (the calibration must then be given), no gauges, no scenes, too few scenes for refine.
"""
from __future__ import annotations

import json
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from pydantic import Field

import gtforge
from gtforge.align_depth import align_depth
from gtforge.build_dataset import build_dataset
from gtforge.calibrate import calibrate
from gtforge.core.alignment.edge_alignment import EdgeAlignmentParams
from gtforge.core.schema import GTModel, load_yaml
from gtforge.core.zed.selfcal import SelfRectifyParams
from gtforge.dataset.layout import STAMP_MARGIN_NS
from gtforge.errors import InputError, Interrupted, first_of
from gtforge.holdout import HOLDOUT_CALIBRATION, validate_holdout
from gtforge.infra.atomic import atomic_write_bytes
from gtforge.infra.digest import blake3_file, blake3_hex
from gtforge.infra.scheduling import check_scheduler_address
from gtforge.io.calibrated_session import check_rig_matches_session, open_with_calibration
from gtforge.io.captures import evenly_spread, open_session
from gtforge.io.outputs import free_path, new_folders, remove_if_empty, require_new_or_empty_folder
from gtforge.records.calibration import CalibrateParams, CalibrationFile, ScaleParams
from gtforge.records.certificate import Certificate
from gtforge.records.dataset import BuildParams
from gtforge.records.run import STAGES, FileHash, RunState, StageRecord
from gtforge.refine import RefineParams, refine
from gtforge.reports.calibration import scale_term_lines, write_calibration_report
from gtforge.reports.certificate import write_certificate
from gtforge.reports.depth_alignment import write_depth_alignment_report
from gtforge.scale_calibration import calibrate_scale
from gtforge.validate import validate, validate_gauges
from gtforge.verify import build_checks, verify_dataset

# OUT's files: the names the README's step-by-step commands use
CALIBRATION, CALIBRATION_REPORT, VALIDATION = "calibration.yaml", "calibration_report", "validation"
SCALED, REFINED, DATASET, STATE = "scaled.yaml", "refined.yaml", "dataset", "run_state.json"
ALIGNED, ALIGNED_REPORT = "aligned.yaml", "aligned_report.html"
GAUGES_DIR = "gauges"


class RunOptions(GTModel):
    """The options of ``gtforge run`` that change a stage's result (``workers`` and ``scheduler``, where the scenes are
    built and verified, do not)."""
    calibration: str | None = None  # a calibration file to use instead of calibrating (sessions without boards)
    use_depth: bool = False  # calibrate --use-depth
    loo: bool = True  # calibrate and refine: leave-one-out cross-validation
    # validate: the last K board captures, with a calibration made without them (``holdout.validate_holdout``); 0: the
    # run's calibration on the captures it was made from (optimistic, and said so)
    holdout: int = Field(0, ge=0)
    calibration_scenes: list[str] | None = None  # the scenes calibrate-scale and refine use (default: max_scenes)
    refine: bool = True
    quarantine: bool = False  # build-dataset / verify --quarantine
    workers: int | None = None
    scheduler: str | None = None  # a Dask scheduler's address: build-dataset's and verify's scenes run on its workers


@dataclass
class RunResult:
    state: RunState
    certificate: Certificate
    redone: list[str]  # stages run this time
    skipped: list[str]  # stages unchanged since the last run

    @property
    def exit_code(self) -> int:
        return 1 if self.certificate.verdict == "FAIL" else 0


def _captures_of(state: RunState, root: Path) -> bool:
    """Whether the run ``state`` records is one of the session at ``root`` that has moved or been copied there: at
    least half of the session files its hash cache holds are at the same place under ``root``, with the same sizes (a
    stat each: a resume hashes them again and redoes what differs). Two sessions' PNG captures do not agree in size
    file for file."""
    old = Path(state.session_dir)
    files = []
    for key, h in state.hashes.items():
        try:
            files.append((Path(key).relative_to(old), h.size_bytes))
        except ValueError:  # an output or a file given from elsewhere
            continue
    same = 0
    for rel, size in files:
        p = root / rel
        same += p.is_file() and p.stat().st_size == size
    return bool(files) and 2 * same >= len(files)


def _picked_note(picked: int, not_selected: int) -> str:
    """What a calibration stage's line adds where its ``max_scenes`` left ``not_selected`` of the session's scenes out
    (``picked``: the scenes it read)."""
    return f" ({picked} of the session's {picked + not_selected} picked, evenly spread)" if not_selected else ""


def _moved_key(key: str, old: Path, here: Path) -> str:
    try:
        return str(here / Path(key).relative_to(old))
    except ValueError:
        return key


class _Hasher:
    """BLAKE3 of files, trusting a cached hash while the file's size and mtime are unchanged (``dataset.layout``'s
    rule: not when the file was modified within ``STAMP_MARGIN_NS`` of being hashed)."""

    def __init__(self, cache: dict[str, FileHash]):
        self.cache = cache

    def __call__(self, p: Path) -> str:
        key = str(p.resolve())
        st = p.stat()
        c = self.cache.get(key)
        if c is not None and c.size_bytes == st.st_size and c.mtime_ns == st.st_mtime_ns \
                and c.mtime_ns < c.hashed_at_ns - STAMP_MARGIN_NS:
            return c.blake3
        now = time.time_ns()
        h = blake3_file(p)
        self.cache[key] = FileHash(blake3=h, size_bytes=st.st_size, mtime_ns=st.st_mtime_ns, hashed_at_ns=now)
        return h


SESSION_YAML = "session.yaml"
# the value recorded for session.yaml as an input of the stages that do not read its fruit_ids (``config_hashes``)
WITHOUT_FRUIT_IDS = "without fruit_ids:"

_TIME_LINE = re.compile(rb"^\s*time_s: .*\n", re.M)


def _previous(path: Path) -> bytes | None:
    return path.read_bytes() if path.is_file() else None


def _keep_if_same(path: Path, before: bytes | None) -> None:
    """A stage's calibration file computed again to the same result (only its ``time_s`` differs) is put back as it
    was, byte for byte: the stages after it, which hash it, then see no change and are not redone."""
    if before is not None and path.is_file():
        now = path.read_bytes()
        if now != before and _TIME_LINE.sub(b"", now) == _TIME_LINE.sub(b"", before):
            atomic_write_bytes(path, before)


def _remove_scene_outputs(ds: Path, sid: str) -> None:
    """Every file of scene ``sid`` in the run's dataset ``ds`` (its folder, its KITTI and ETH3D views, its report and
    verification images): a scene the session no longer has must not stay where a loader scanning the views finds
    it. The split lists and the manifest are rewritten by the build that follows."""
    import shutil

    for folder in (ds / "scenes" / sid, ds / "eth3d" / "two_view_training" / sid,
                   ds / "eth3d" / "two_view_training_gt" / sid):
        shutil.rmtree(folder, ignore_errors=True)
    # by their exact names (a glob on the id would also take scene 003_b's for 003)
    kitti = ds / "kitti" / "training"
    files = [kitti / d.name / f"{sid}_10.png" for d in kitti.iterdir() if d.is_dir()] if kitti.is_dir() else []
    files += [ds / "report" / f"{sid}_sigma.jpg"]
    files += [ds / "verification" / f"{sid}_{k}.jpg" for k in ("overlay", "motion_before", "motion_after")]
    for f in files:
        f.unlink(missing_ok=True)


def _plain(x: Any) -> Any:
    return json.loads(json.dumps(x))


def _versioned(options: dict) -> dict:
    """A stage's options as recorded: with the gtforge version that ran it (a new version runs every stage again)."""
    return {**options, "gtforge": gtforge.__version__}


def _option_changes(before: dict, now: dict, prefix: str = "") -> list[str]:
    """``key old -> new`` for each option that differs, a nested model's by its own keys (``params.quarantine``)."""
    out = []
    for k in sorted(set(before) | set(now)):
        a, b = before.get(k), now.get(k)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            out += _option_changes(a, b, f"{prefix}{k}.")
        else:
            out.append(f"{prefix}{k} {a!r} -> {b!r}")
    return out


def _why(rec: StageRecord | None, options: dict, inputs: dict[str, str], outputs_ok: str,
         shown: Callable[[str], str] = str) -> str | None:
    """Why a stage must run again (None: it need not); ``shown``: an input's key as the message names it."""
    if rec is None or rec.status != "done":
        return "not run before" if rec is None else "it did not apply last time"
    if rec.options != options:
        return "options changed: " + ", ".join(_option_changes(rec.options, options))
    changed = [k for k in inputs if k in rec.inputs and rec.inputs[k] != inputs[k]]
    added = [k for k in inputs if k not in rec.inputs]
    removed = [k for k in rec.inputs if k not in inputs]
    parts = []
    for what, keys in (("changed", changed), ("new", added), ("gone", removed)):
        if keys:
            parts.append(f"{first_of(map(shown, keys), 3)} {what}")
    if parts:
        return "; ".join(parts)
    return outputs_ok or None


class _Run:
    def __init__(self, session_dir: Path, out: Path, opts: RunOptions, say, progress):
        self.opts, self.say, self.progress = opts, say, progress
        if opts.scheduler:  # refused now, not once calibrate and the stages before the build have run
            if opts.workers is not None:
                raise InputError(None, "--workers", "no local worker count with --scheduler (the cluster's workers "
                                 "run the scenes)", str(opts.workers), "drop --workers, or drop --scheduler to run "
                                 "locally")
            check_scheduler_address(opts.scheduler)
        self.session = open_session(session_dir)
        self.session.refuse_output_over_inputs(out)  # the run's folder holds every stage's outputs
        if opts.calibration is not None and opts.holdout:
            raise InputError(opts.calibration, "--holdout", "no --holdout with -c (a hold-out validates a calibration "
                             "made from the session's boards without the last K; the run would use the file given)",
                             f"--holdout {opts.holdout} with -c",
                             "drop -c to calibrate from the session's boards, or drop --holdout to validate the file")
        if opts.calibration is not None:
            given = Path(opts.calibration)
            if out.resolve() in given.resolve().parents:
                # the run's folder is the run's: its stages replace (refine: refined.yaml) or remove (align-depth,
                # where it no longer applies: aligned.yaml) the files there, the one given included
                raise InputError(given, "--calibration", "a calibration outside the run's folder (its stages write and "
                                 "remove calibration.yaml, aligned.yaml, scaled.yaml and refined.yaml there)",
                                 f"a file in {out} (the run's own {given.name})",
                                 f"copy it beside the run and give the copy: cp {given} "
                                 f"{free_path(out.resolve().parent, 'given-' + given.name)}")
        # a folder of the user's (not an earlier run's, which holds run_state.json) is never written into: the run's
        # files (calibration.yaml, dataset/ ...) would replace theirs
        require_new_or_empty_folder(out, "--output", "choose a new folder for the run, or an earlier run's folder (a "
                                    "run's folder without run_state.json was cut off before it recorded anything: "
                                    "delete it)", reusable_if=STATE)
        self.root = self.session.root
        self.out = out
        state_path = out / STATE
        self.state = None
        moved = False
        if state_path.is_file():
            try:
                self.state = RunState.read(state_path)
            except InputError as exc:
                say(f"{state_path} unreadable ({exc}): every stage runs again")
        if self.state is not None and self.state.session_dir != str(self.root.resolve()):
            if not _captures_of(self.state, self.root):
                # another session's dataset and calibration: never replaced on a mistyped -o
                raise InputError(out, "--output", f"a new folder or an earlier run of {self.root.resolve()}",
                                 f"the run folder of another session ({self.state.session_dir}, whose captures are "
                                 "not this session's)", "choose another -o; to replace that run, delete the folder "
                                 "first")
            # the session moved (or was copied) with its run: the run resumes here, redoing what differs
            say(f"{out}: the run of {self.state.session_dir}, whose captures are this session's (moved or copied): "
                "resumed here")
            old, here = Path(self.state.session_dir), self.root.resolve()
            # the hash cache's entries follow the files (a move keeps their sizes and times: nothing is read again)
            self.state.hashes = {_moved_key(k, old, here): h for k, h in self.state.hashes.items()}
            self.state.session_dir = str(here)
            moved = True
        if self.state is None:
            self.state = RunState(gtforge_version=gtforge.__version__, session_dir=str(self.root.resolve()))
            if not state_path.exists():
                # the folder is a run's from now on: a run stopped before its first stage resumes in it (an existing
                # state, unreadable or another session's, is replaced only when the first stage records itself)
                out.mkdir(parents=True, exist_ok=True)
                self.save()
        self.hash = _Hasher(self.state.hashes)
        self.redone: list[str] = []
        self.skipped: list[str] = []
        self.changed = False  # a stage ran or its record changed: the certificate is written again
        if moved:
            self.withdraw_certificate()  # it names the session's folder

    # ---- inputs ------------------------------------------------------------------------------------------------
    def key(self, p: Path) -> str:
        p = Path(p).resolve()
        for prefix, base in (("out/", self.out.resolve()), ("session/", self.root.resolve())):
            if base in p.parents:
                return prefix + p.relative_to(base).as_posix()
        return "file:" + str(p)

    def shown(self, key: str) -> str:
        """An input's key (``key``) as a message names it: the path under the session or output folder as given."""
        for prefix, base in (("out/", self.out), ("session/", self.root)):
            if key.startswith(prefix):
                return (base / key[len(prefix):]).as_posix()
        return key.removeprefix("file:")

    def hashes(self, paths) -> dict[str, str]:
        return {self.key(p): self.hash(p) for p in paths}

    def config_hashes(self, cfg: list[Path]) -> dict[str, str]:
        """``hashes`` of the session's own files for the stages before build-dataset, which do not read
        ``session.yaml``'s ``fruit_ids``: that file by its contents without them, so that grouping the scenes by fruit
        again (which moves scenes between splits) rebuilds no calibration."""
        out = self.hashes(cfg)
        sf = self.root / SESSION_YAML
        if sf in cfg:
            content = load_yaml(sf.read_text()) or {}
            content.pop("fruit_ids", None)
            out[self.key(sf)] = WITHOUT_FRUIT_IDS + blake3_hex(json.dumps(content, sort_keys=True).encode())
        return out

    def kind_dirs(self, kind: str) -> list[Path]:
        d = self.root / (self.session.config.board_dir if kind == "board" else self.session.config.scenes_dir)
        if not d.is_dir() or not any(p.is_dir() and not p.name.startswith(".") for p in d.iterdir()):
            return []
        return self.session.capture_dirs(kind)

    def config_files(self) -> list[Path]:
        return sorted(p for p in self.root.iterdir() if p.is_file() and not p.name.startswith("."))

    def capture_files(self, d: Path) -> list[Path]:
        return [p for p in self.session.capture_files(d) if p.exists()]

    def zed_files(self, d: Path) -> list[Path]:
        f = self.session.config.files
        return [p for p in self.capture_files(d) if p.name not in (f.mech_depth, f.mech_texture, f.fruit_mask)]

    def gauge_files(self) -> list[Path]:
        g = self.root / GAUGES_DIR
        return sorted(p for p in g.rglob("*") if p.is_file()) if (g / "gauges.yaml").is_file() else []

    # ---- bookkeeping --------------------------------------------------------------------------------------------
    def outputs_ok(self, rec: StageRecord | None) -> str:
        changed = self.changed_outputs(rec)
        if not changed:
            return ""
        k, why = changed[0]
        return f"its output {self.shown(k)} {why}" + (f" (and {len(changed) - 1} more)" if len(changed) > 1 else "")

    def changed_outputs(self, rec: StageRecord | None) -> list[tuple[str, str]]:
        """``(key, "is missing" or "changed since")`` of each output of ``rec`` that is not as the stage left it: its
        BLAKE3, or for a stamped one (a dataset's scene files, too many to read back) its size and modification
        time."""
        changed = []
        for k, h in (rec.outputs.items() if rec else ()):
            p = self.out / k[len("out/"):]
            if not p.is_file():
                changed.append((k, "is missing"))
            elif h and h != (_stamp(p) if h.startswith(STAMP_PREFIX) else self.hash(p)):
                changed.append((k, "changed since"))
        return changed

    def save(self) -> None:
        self.state.gtforge_version = gtforge.__version__
        self.state.write(self.out / STATE)

    def header(self, k: int, name: str, text: str) -> None:
        self.say(f"[{k}/{len(STAGES)}] {name}: {text}")

    def not_applicable(self, k: int, name: str, reason: str) -> None:
        self.header(k, name, f"skipped, does not apply ({reason})")
        rec = self.state.stages.get(name)
        if rec is None or rec.status != "not applicable" or rec.reason != reason:
            self.withdraw_certificate()  # the stage's part of it changes
        self.state.stages[name] = StageRecord(stage=name, status="not applicable", reason=reason)
        self.save()

    def withdraw_certificate(self) -> None:
        """The certificate describes the files as they were: once a stage writes new ones (or no longer applies) it is
        withdrawn, until this run writes the new one (a run stopped now leaves none rather than one citing figures no
        file holds)."""
        self.changed = True
        for f in ("index.html", "certificate.json"):
            (self.out / f).unlink(missing_ok=True)

    def decide(self, k: int, name: str, options: dict, inputs: dict[str, str]) -> bool:
        """Whether stage ``name`` runs; says so, and why."""
        rec = self.state.stages.get(name)
        why = _why(rec, _versioned(options), inputs, self.outputs_ok(rec), self.shown)
        if why is None:
            self.header(k, name, "unchanged since the last run (inputs, options and outputs): skipped"
                        + (f" [{rec.verdict}]" if rec.verdict else ""))
            self.skipped.append(name)
            return False
        self.header(k, name, f"running ({why})")
        self.redone.append(name)
        self.withdraw_certificate()
        return True

    def done(self, name: str, options: dict, inputs: dict, outputs: list[Path], exist_only: list[Path] = (),
             verdict=None, reasons=(), detail=None, t0=0.0, stamped: list[Path] = ()) -> None:
        outs = {self.key(p): self.hash(p) for p in outputs}
        outs.update({self.key(p): "" for p in exist_only})
        outs.update({self.key(p): _stamp(p) for p in stamped})
        self.state.stages[name] = StageRecord(stage=name, status="done", options=_versioned(options), inputs=inputs,
                                              outputs=outs,
                                              verdict=verdict, verdict_reasons=list(reasons), detail=detail or {},
                                              time_s=time.perf_counter() - t0)
        self.save()

    # ---- the chain ----------------------------------------------------------------------------------------------
    def run(self, after_stage: Callable[[str], None] | None = None) -> RunResult:
        opts, out = self.opts, self.out
        boards, scenes = self.kind_dirs("board"), self.kind_dirs("scenes")
        cfg = self.config_files()
        gauges = self.gauge_files()
        if opts.calibration_scenes:
            # unknown names: one line, exit 2
            self.session.select("scenes", opts.calibration_scenes, option="--calibration-scenes")
        # the scenes calibrate-scale and refine read: those named, else as many as each uses by default (max_scenes,
        # evenly spread: the same ones the stage picks), so that an edit of another scene redoes neither
        if opts.calibration_scenes:
            scale_scenes = refine_scenes = [d for d in scenes if d.name in opts.calibration_scenes]
        else:
            scale_scenes = evenly_spread(scenes, ScaleParams().max_scenes)
            refine_scenes = evenly_spread(scenes, RefineParams().max_scenes)
        steps = [self.stage_calibrate, self.stage_align, self.stage_validate, self.stage_scale, self.stage_refine,
                 self.stage_build, self.stage_verify]
        # the stages before build-dataset record the session's files so (session.yaml read once for all of them)
        ctx = {"boards": boards, "scenes": scenes, "cfg": cfg, "cfg_before_build": self.config_hashes(cfg),
               "gauges": gauges, "scale_scenes": scale_scenes, "refine_scenes": refine_scenes}
        for k, (name, step) in enumerate(zip(STAGES, steps), 1):
            try:
                step(k, ctx)
                if after_stage is not None:
                    after_stage(name)
            except (KeyboardInterrupt, Interrupted) as exc:
                self.save()
                # one message: what the stage said is complete (build-dataset counts its scenes), then how to resume
                detail = getattr(exc, "detail", None)
                message = f"interrupted during or right after {name}" + (f" ({detail})" if detail else "")
                if self.state.stages:
                    message += (f": every stage recorded in {out / STATE} is complete (each writes its files whole); "
                                "run the same command again to resume: it redoes only what is not")
                else:  # (a folder this run made is removed on the way out: no run_state.json to name)
                    message += ": no stage was recorded yet; run the same command again to start the run"
                if isinstance(exc, Interrupted):  # the command prints it
                    raise Interrupted(message) from None
                self.say(message)
                raise
        cert = None
        if not self.changed and (out / "index.html").is_file():
            try:  # nothing redone: the certificate stands as written
                cert = Certificate.read(out / "certificate.json")
            except InputError:
                cert = None
        cert = cert or write_certificate(out, self.state, self.root)
        self.say(f"certificate: {cert.verdict}" + "".join(f"\n  - {r}" for r in cert.verdict_reasons)
                 + f"\n  {out / 'index.html'} (and certificate.json)")
        if not self.redone:
            self.say("nothing to redo: every stage's inputs, options and outputs are unchanged since the last run")
        return RunResult(self.state, cert, self.redone, self.skipped)

    def stage_calibrate(self, k: int, ctx: dict) -> None:
        opts, name = self.opts, "calibrate"
        if opts.calibration is not None:
            given = Path(opts.calibration)
            cal = CalibrationFile.read(given)  # a bad file stops here, with its one line
            # another rig's calibration stops here too, before align-depth decides from its rig whether it applies
            check_rig_matches_session(cal.rig, open_with_calibration(self.root, cal), given)
            ctx["calib"] = given
            reason = f"calibration given: {given}"
            self.header(k, name, f"skipped, does not apply ({reason}; its verdict {cal.verdict})")
            # an earlier run's calibration and its report no longer apply: left, they sat beside a certificate that
            # cites the file given
            (self.out / CALIBRATION).unlink(missing_ok=True)
            shutil.rmtree(self.out / CALIBRATION_REPORT, ignore_errors=True)
            # its verdict and figures are the certificate's (a FAIL calibration given with -c fails the run as one
            # made here would)
            rec = StageRecord(stage=name, status="not applicable", reason=reason, verdict=cal.verdict,
                              verdict_reasons=list(cal.verdict_reasons), detail={"given": str(given.resolve())})
            if self.state.stages.get(name) != rec:
                self.withdraw_certificate()
            self.state.stages[name] = rec
            self.save()
            return
        if not ctx["boards"]:
            raise InputError(self.root / self.session.config.board_dir, None,
                             "board captures to calibrate from, or a calibration file", "no board captures",
                             "give the rig's calibration with -c FILE (e.g. from an earlier gtforge calibrate)")
        ctx["calib"] = self.out / CALIBRATION
        options = _plain({"use_depth": opts.use_depth, "loo": opts.loo})
        inputs = {**ctx["cfg_before_build"],
                  **self.hashes([p for d in ctx["boards"] for p in self.capture_files(d)]
                                + [p for d in evenly_spread(ctx["scenes"], SelfRectifyParams().max_scenes)
                                   for p in self.zed_files(d)])}  # (the scenes its self-rectification matches)
        if not self.decide(k, name, options, inputs):
            return
        t0 = time.perf_counter()
        before = _previous(ctx["calib"])
        cal = calibrate(self.root, ctx["calib"], CalibrateParams(use_depth=opts.use_depth, leave_one_out=opts.loo),
                        progress=self.progress)
        _keep_if_same(ctx["calib"], before)
        rep = write_calibration_report(cal, self.out / CALIBRATION_REPORT)
        self.say(f"      RMS {cal.rms_px:.3f} px over {len(cal.captures_used)} poses; 1-sigma {cal.sigma_rot_deg:.4f} "
                 f"deg / {cal.sigma_trans_mm:.3f} mm; verdict {cal.verdict}")
        report_files = [p for p in (self.out / CALIBRATION_REPORT).rglob("*") if p.is_file()]
        self.done(name, options, inputs, [ctx["calib"]], [rep, *report_files], cal.verdict, cal.verdict_reasons,
                  t0=t0)

    def stage_align(self, k: int, ctx: dict) -> None:
        """align-depth, for a unit whose depth map lies on a separate depth camera: every capture's depth edges (and
        its IR.png's) put on the texture images' edges; the stages after it read the aligned calibration."""
        name = "align-depth"
        cal = CalibrationFile.read(ctx["calib"])
        reason = None
        if not cal.rig.separate_depth_camera:
            reason = "the depth map lies on the texture camera's grid (one camera)"
        elif cal.depth_alignment is not None:
            reason = f"{Path(ctx['calib']).name} is already aligned"
        elif cal.scale_corrected or cal.refinement is not None:
            # align-depth runs before them: they estimated through the depth camera's pose the file holds
            reason = (f"{Path(ctx['calib']).name} is already "
                      f"{'refined' if cal.refinement is not None else 'scale-corrected'}; align-depth runs before "
                      f"calibrate-scale and refine: give -c the calibration calibrate wrote to align it")
        caps = ctx["boards"] + evenly_spread(ctx["scenes"], EdgeAlignmentParams().max_scenes)  # (those it reads)
        if reason is None and not caps:
            reason = "no board or scene captures"
        if reason is not None:
            for f in (ALIGNED, ALIGNED_REPORT):  # an earlier run's, which no longer applies
                (self.out / f).unlink(missing_ok=True)
            self.not_applicable(k, name, reason)
            return
        f = self.session.config.files
        options = _plain({"edges": "auto", "use_boards": True})
        # what it reads of each capture: the depth, the texture image and the depth camera's own image (no ZED image)
        inputs = {**ctx["cfg_before_build"],
                  **self.hashes([ctx["calib"]] + [d / n for d in caps for n in (f.mech_depth, f.mech_texture,
                                                                                f.depth_texture)
                                                  if (d / n).is_file()])}
        aligned = self.out / ALIGNED
        if self.decide(k, name, options, inputs):
            t0 = time.perf_counter()
            before = _previous(aligned)
            res = align_depth(self.root, ctx["calib"], aligned, progress=self.progress)
            _keep_if_same(aligned, before)
            info = res.depth_alignment
            r = info.result
            self.say(f"      {r.decision} ({r.reason}); edges {' and '.join(r.edge_kinds)}; offset before "
                     f"({r.offset_before_px[0]:+.2f}, {r.offset_before_px[1]:+.2f}) px, after "
                     f"({r.offset_after_px[0]:+.2f}, {r.offset_after_px[1]:+.2f}) px")
            rep = write_depth_alignment_report(info, self.out / ALIGNED_REPORT)
            reasons = ([f"the depth camera's pose was not determined: {r.reason}"]
                       if r.decision == "not determined" else []) + list(r.warnings)
            self.done(name, options, inputs, [aligned], [rep], verdict="WARN" if reasons else "PASS",
                      reasons=reasons, t0=t0)
        ctx["calib"] = aligned

    def stage_validate(self, k: int, ctx: dict) -> None:
        name = "validate"
        if not ctx["boards"] and not ctx["gauges"]:
            self.not_applicable(k, name, "no board captures and no gauges/gauges.yaml")
            return
        options = {"gauges_only": not ctx["boards"], **({"holdout": self.opts.holdout} if self.opts.holdout else {})}
        inputs = {**ctx["cfg_before_build"],
                  **self.hashes([ctx["calib"]] + [p for d in ctx["boards"] for p in self.capture_files(d)]
                                + ctx["gauges"])}
        if not self.decide(k, name, options, inputs):
            return
        t0 = time.perf_counter()
        vdir = self.out / VALIDATION
        reasons: list[str] = []
        if ctx["boards"]:
            if self.opts.holdout:  # (a calibration of the other captures, in vdir: the dataset's is the run's own)
                rep = validate_holdout(self.root, self.opts.holdout, vdir, progress=self.progress)
                self.say(f"      on the last {self.opts.holdout} board capture(s), calibrated without them "
                         f"({VALIDATION}/{HOLDOUT_CALIBRATION})")
            else:
                (vdir / HOLDOUT_CALIBRATION).unlink(missing_ok=True)  # (an earlier --holdout run's, no longer cited)
                rep = validate(self.root, ctx["calib"], vdir, progress=self.progress)
            if not rep.pass_xy:
                reasons.append(f"board XY reprojection {rep.xy_mean_px:.3f} px over the threshold "
                               f"{rep.thresholds.get('xy_px', rep.thresholds)}")
            if not rep.pass_z:
                reasons.append(f"board Z geometric error {rep.z_error_mean_pct:.4f} % over the threshold "
                               f"{rep.thresholds.get('z_pct', rep.thresholds)}")
            g = rep.gauges
            self.say(f"      XY {rep.xy_mean_px:.3f} px (noise floor {rep.xy_noise_floor_px:.3f}), Z "
                     f"{rep.z_error_mean_pct:.4f} % -> {'PASS' if rep.passed else 'FAIL'}")
            outputs = [vdir / "validation.json"]
        else:
            g = validate_gauges(self.root, ctx["calib"], vdir, progress=self.progress)
            outputs = [vdir / "gauges.json"]
        if g is not None and g.status == "FAIL":
            reasons += [f"gauge {r.capture}: " + "; ".join(r.reasons) for r in g.gauges if r.status == "FAIL"]
        self.done(name, options, inputs, outputs, [p for p in vdir.rglob("*") if p.is_file() and p not in outputs],
                  verdict="FAIL" if reasons else "PASS", reasons=reasons, t0=t0)

    def stage_scale(self, k: int, ctx: dict) -> None:
        name = "calibrate-scale"
        if not ctx["scale_scenes"]:
            self.not_applicable(k, name, "no scene captures")
            return
        cal = CalibrationFile.read(ctx["calib"])
        if cal.scale_corrected:
            self.not_applicable(k, name, f"{ctx['calib'].name} is already scale-corrected")
            return
        if cal.refinement is not None:  # refine fitted its extrinsic through the uncorrected depth (calibrate_scale)
            self.not_applicable(k, name, f"{ctx['calib'].name} is refined; calibrate-scale runs before refine: give "
                                         f"-c the calibration refine started from ({cal.refinement.refined_from}) to "
                                         f"correct the scale")
            return
        options = _plain({"scenes": self.opts.calibration_scenes, "use_boards": True})
        inputs = {**ctx["cfg_before_build"],
                  **self.hashes([ctx["calib"]] + [p for d in ctx["boards"] for p in self.capture_files(d)]
                                + [p for d in ctx["scale_scenes"] for p in self.capture_files(d)])}
        scaled = self.out / SCALED
        if self.decide(k, name, options, inputs):
            t0 = time.perf_counter()
            before = _previous(scaled)
            res = calibrate_scale(self.root, ctx["calib"], scaled, ScaleParams(), self.opts.calibration_scenes,
                                  progress=self.progress)
            _keep_if_same(scaled, before)
            for line in scale_term_lines(res.scale_calibration):
                self.say("      " + line)
            info = res.scale_calibration
            if info.scenes_not_selected:  # (the session's other scenes: --calibration-scenes names those it uses)
                # (info.scenes: every scene it read, used or excluded)
                self.say(f"      over {len(info.scenes_used)} scene(s)"
                         + _picked_note(len(info.scenes), info.scenes_not_selected))
            self.done(name, options, inputs, [scaled], verdict="PASS", t0=t0)
        ctx["calib"] = scaled

    def stage_refine(self, k: int, ctx: dict) -> None:
        name = "refine"
        need = RefineParams().min_scenes
        reason = None
        if not self.opts.refine:
            reason = "--no-refine"
        elif (given := CalibrationFile.read(ctx["calib"])).refinement is not None:
            # (-c a refined file: refine again only from the file it started from)
            reason = (f"{Path(ctx['calib']).name} is already refined; give -c the calibration refine started from "
                      f"({given.refinement.refined_from}) to refine again")
        elif len(ctx["refine_scenes"]) < need:
            reason = (f"refinement needs at least {need} scenes, "
                      f"{'--calibration-scenes names' if self.opts.calibration_scenes else 'the session has'} "
                      f"{len(ctx['refine_scenes'])}")
        if reason is None:
            options = _plain({"scenes": self.opts.calibration_scenes, "loo": self.opts.loo})
            inputs = {**ctx["cfg_before_build"],
                      **self.hashes([ctx["calib"]] + [p for d in ctx["refine_scenes"] for p in self.capture_files(d)])}
            refined = self.out / REFINED
            if not self.decide(k, name, options, inputs):
                ctx["calib"] = refined
                return
            t0 = time.perf_counter()
            before = _previous(refined)
            try:
                res = refine(self.root, ctx["calib"], refined, RefineParams(leave_one_out=self.opts.loo),
                             self.opts.calibration_scenes, progress=self.progress)
                _keep_if_same(refined, before)
            except InputError as exc:
                if "scenes with textured ground truth" not in exc.expected:
                    raise
                self.redone.remove(name)
                reason = str(exc)
            else:
                info = res.refinement
                spread = _picked_note(len(info.scenes_used) + len(info.scenes_excluded), info.scenes_not_selected)
                self.say(f"      over {len(info.scenes_used)} scene(s){spread}; moved {info.change_rot_deg:.4f} deg / "
                         f"{info.change_trans_mm:.3f} mm")
                self.done(name, options, inputs, [refined], verdict="PASS", t0=t0)
                ctx["calib"] = refined
                return
        (self.out / REFINED).unlink(missing_ok=True)  # a refined calibration of an earlier run no longer applies
        self.not_applicable(k, name, reason)

    def stage_build(self, k: int, ctx: dict) -> None:
        name = "build-dataset"
        if not ctx["scenes"]:
            self.not_applicable(k, name, "no scene captures")
            return
        params = BuildParams(quarantine=self.opts.quarantine)
        options = _plain({"params": params.model_dump(mode="json")})
        calib_in = self.hashes([ctx["calib"]])
        per_scene = {d.name: self.hashes(self.capture_files(d)) for d in ctx["scenes"]}
        inputs = {**self.hashes(ctx["cfg"]), **calib_in, **{k2: v for s in per_scene.values() for k2, v in s.items()}}
        ds = self.out / DATASET
        ctx["dataset"] = ds
        rec = self.state.stages.get(name)
        if not self.decide(k, name, options, inputs):
            return
        if rec is not None and rec.status == "done" and rec.options == _versioned(options) and \
                all(rec.inputs.get(k2) == v for k2, v in {**calib_in, **self.hashes(ctx["cfg"])}.items()):
            why = {s: "its inputs changed" if any(rec.inputs.get(k2) != v for k2, v in h.items()) else None
                   for s, h in per_scene.items()}
        else:
            why = {s: "the calibration, the camera files or the options changed" if rec else "first build"
                   for s in per_scene}
        t0 = time.perf_counter()
        if rec is not None:
            # the scenes an earlier build of this run wrote (its record, and any folder with a meta.json: a build
            # stopped before it recorded itself) that the session no longer has
            earlier = set(rec.detail.get("built", []) + rec.detail.get("unchanged", []))
            earlier |= {m.parent.name for m in (ds / "scenes").glob("*/meta.json")}
            gone = sorted(earlier - set(per_scene))
            for sid in gone:  # built by an earlier run from a capture no longer in the session
                _remove_scene_outputs(ds, sid)
            if gone:
                self.say(f"      removed from the dataset (no longer in the session): {', '.join(gone)}")
        # scenes whose dataset files (their folder, KITTI and ETH3D views, sigma maps) changed since this run wrote
        # them: built again (the build's own resume checks that each file is there, not what it holds)
        edited = sorted({sid for key, how in self.changed_outputs(rec) if how == "changed since"
                         and (sid := _scene_of_output(key)) in per_scene})
        for sid in edited:
            why[sid] = why[sid] or "its dataset files changed since the last run"
        summ = build_dataset(self.root, ctx["calib"], ds, params, workers=self.opts.workers, progress=False,
                             rebuild=edited, scheduler=self.opts.scheduler)
        for sid in summ.built:
            self.say(f"      built {sid} ({why.get(sid) or 'its dataset files were missing or stale'})")
        if summ.skipped_unchanged:
            self.say(f"      unchanged: {', '.join(summ.skipped_unchanged)}")
        reasons = [f"scene {s} failed: {r}" for s, r in summ.failures.items()]
        # every file the build wrote for its scenes (their folders, the KITTI and ETH3D views, the sigma maps): one
        # deleted or changed since (its size and time) is noticed by the next run, whose build then writes it again;
        # the files verify rewrites too (the manifest, the split lists) need only be there
        scene_files = [p for sub in ("scenes", "kitti", "eth3d", "report") for p in (ds / sub).rglob("*")
                       if p.is_file() and not p.name.startswith(".")]
        lists = [p for p in (ds / "filenames").rglob("*") if p.is_file() and not p.name.startswith(".")]
        self.done(name, options, inputs, [], [ds / "manifest.json", ds / "build_report.html", *lists],
                  "FAIL" if reasons else "PASS", reasons,
                  detail={"built": summ.built, "unchanged": summ.skipped_unchanged, "failures": summ.failures}, t0=t0,
                  stamped=scene_files)

    def stage_verify(self, k: int, ctx: dict) -> None:
        name = "verify"
        if "dataset" not in ctx:
            self.not_applicable(k, name, "no dataset built")
            return
        ds = ctx["dataset"]
        from gtforge.records.dataset import Manifest

        man = Manifest.read(ds / "manifest.json")
        options = _plain({"quarantine": self.opts.quarantine, "params": man.params.verify.model_dump(mode="json")})
        metas = {s: ds / "scenes" / s / "meta.json" for s in man.scenes}
        inputs = self.hashes([ctx["calib"]] + list(metas.values()))
        rec = self.state.stages.get(name)
        if not self.decide(k, name, options, inputs):
            return
        if rec is not None and rec.status == "done" and rec.options == _versioned(options) and \
                rec.inputs.get(self.key(ctx["calib"])) == inputs[self.key(ctx["calib"])]:
            todo = [s for s, p in metas.items() if rec.inputs.get(self.key(p)) != inputs[self.key(p)]]
        else:
            todo = sorted(metas)
        t0 = time.perf_counter()
        taken = {}
        if todo:
            # the scenes whose meta.json changed: rebuilt, or regrouped by session.yaml's fruit_ids (not rebuilt)
            self.say(f"      checking {', '.join(todo)}" + (" (meta.json changed; the other scenes as verified before)"
                                                            if len(todo) < len(metas) else ""))
            # the build's own checks of the scenes it wrote, whose files this run's records vouch for (a scene whose
            # files changed since is built again first): taken as verify would compute them, not computed twice
            taken = build_checks(ds, todo)
            if taken:
                rest = len(todo) - len(taken)
                self.say(f"      {len(taken)} of them with the figures build-dataset's checks gave (verify computes "
                         "the same from their files)" + (f"; {rest} checked again" if rest else ""))
            verify_dataset(ds, scenes=todo, workers=self.opts.workers, scheduler=self.opts.scheduler,
                           quarantine=self.opts.quarantine, progress=self.progress, build_figures=taken)
        from gtforge.records.verification import VerificationResult

        rep = VerificationResult.read(ds / "verification.json")
        reasons = [f"scene {s} flagged: " + "; ".join(v.reasons) for s, v in rep.scenes.items()
                   if v.status == "flagged" and not self.opts.quarantine]
        reasons += [f"scene {s} not verifiable: " + "; ".join(v.reasons) for s, v in rep.scenes.items()
                    if v.status == "not verifiable"]
        quarantined = [s for s, v in rep.scenes.items() if v.status == "flagged" and self.opts.quarantine]
        verdict = "FAIL" if reasons else ("WARN" if quarantined else "PASS")
        if quarantined:
            reasons.append(f"flagged and quarantined (left out of the split lists): {', '.join(quarantined)}")
        self.say(f"      {len(rep.scenes)} scene(s): {len(rep.flagged)} flagged -> {verdict}")
        pages = [ds / "verification.html", *(p for p in (ds / "verification").glob("*") if p.is_file())]
        self.done(name, options, inputs, [ds / "verification.json"], [p for p in pages if p.is_file()],
                  verdict=verdict, reasons=reasons, detail={"verified": todo, "checked_by_build": sorted(taken)},
                  t0=t0)


STAMP_PREFIX = "stamp:"  # a recorded output's size and modification time, not its BLAKE3


def _stamp(p: Path) -> str:
    st = p.stat()
    return f"{STAMP_PREFIX}{st.st_size}:{st.st_mtime_ns}"


def _scene_of_output(key: str) -> str | None:
    """The scene a dataset output belongs to (``out/dataset/scenes/<id>/...``, ``kitti/training/<kind>/<id>_10.png``,
    ``eth3d/<kind>/<id>/...``, ``report/<id>_sigma.jpg``), None for any other output."""
    parts = key.split("/")
    if parts[:2] != ["out", DATASET] or len(parts) < 4:
        return None
    if parts[2] == "scenes":
        return parts[3]
    if parts[2] == "eth3d" and len(parts) >= 6:
        return parts[4]
    if parts[2] == "kitti" and len(parts) == 6 and parts[5].endswith("_10.png"):
        return parts[5][:-len("_10.png")]
    if parts[2] == "report" and len(parts) == 4 and parts[3].endswith("_sigma.jpg"):
        return parts[3][:-len("_sigma.jpg")]
    return None


def run_session(session_dir: str | Path, out_dir: str | Path, options: RunOptions | None = None,
                say: Callable[[str], None] = print, progress: Callable[[str], None] | None = None,
                after_stage: Callable[[str], None] | None = None) -> RunResult:
    """Run the chain on ``session_dir`` into ``out_dir`` (module docstring); returns the run's state and certificate
    (``RunResult.exit_code``: 0 all PASS, 1 a quality check failed). ``after_stage(name)`` is called after each stage
    has been recorded (tests use it to interrupt a run)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(out, "--output", "a folder for the run's outputs", "a file", "choose a folder")
    session_dir = Path(session_dir)
    if not session_dir.is_dir():
        raise InputError(session_dir, None, "a capture session folder (docs/capture-layout.md)",
                         "a file" if session_dir.exists() else "no such folder", "check the path")
    made = new_folders(out)
    try:
        run = _Run(session_dir, out, options or RunOptions(), say, progress)
        out.mkdir(parents=True, exist_ok=True)
        return run.run(after_stage)
    except BaseException:
        # nothing in the folder this run made but its mark: nothing was done, nothing stays
        if made and out.is_dir() and [e.name for e in out.iterdir()] == [STATE]:
            (out / STATE).unlink()
        remove_if_empty(made)
        raise
