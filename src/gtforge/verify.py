"""``gtforge verify``: re-check an existing dataset's scenes against their own images (the checks themselves:
``gtforge.dataset.scene_verification``), write ``verification.json``/``.html`` and, with ``--quarantine``, leave the
flagged scenes out of the split lists. Nothing here changes the ground truth."""
from __future__ import annotations

import hashlib
import logging
from pathlib import Path
from typing import Callable

import numpy as np

from gtforge.dataset.layout import require_dataset
from gtforge.dataset.motion_compensation import moved_fruit_of
from gtforge.dataset.scene_verification import verify_scene, write_verification_overlay
from gtforge.dataset.views import final_splits, write_lists, write_split_views
from gtforge.dataset.worker_cache import cached_calibration, cached_session, scene_heap_bytes
from gtforge.errors import InputError, Interrupted, first_of
from gtforge.infra.digest import sha256_file
from gtforge.infra.scheduling import prestart_pool, run_tasks
from gtforge.io.calibrated_session import check_rig_matches_session, open_with_calibration
from gtforge.io.captures import read_depth
from gtforge.io.formats import read_image, read_pfm
from gtforge.records.calibration import CalibrationFile
from gtforge.records.dataset import Manifest, SceneMeta
from gtforge.records.verification import (
    SceneVerification,
    VerificationResult,
    VerifyJournal,
    VerifyJournalEntry,
    VerifyParams,
)
from gtforge.reports.verification import write_verification_report

log = logging.getLogger("gtforge.verify")


# ---- image helpers ------------------------------------------------------------------------------


def verify_dataset(dataset_dir: str | Path, params: VerifyParams | None = None, scenes: list[str] | None = None,
                   session_dir: str | Path | None = None, workers: int | None = None, scheduler: str | None = None,
                   quarantine: bool = False, progress: Callable[[str], None] | None = None,
                   build_figures: dict[str, SceneVerification] | None = None) -> VerificationResult:
    """Re-run the checks on an existing dataset (its manifest names the session and calibration); writes
    ``verification.json``/``.html`` and the flagged list into ``manifest.json`` (and, with ``quarantine``, leaves
    flagged scenes out of the split lists).

    ``build_figures``: scenes' figures as build-dataset checked them (``build_checks``), for scenes whose files the
    caller vouches are the ones that build wrote (``gtforge run``, whose records notice a change and build such a scene
    again): taken instead of computed when the thresholds are the build's. verify computes the same figures from those
    files, to the last digit (tests/stages/test_verify.py), in about the time the build took for them."""
    if not build_figures:  # (otherwise most scenes may need no worker: the pool starts only if one does)
        prestart_pool(verify_one_scene.__module__, workers, scheduler)  # its imports overlap the checks of the dataset
    ds = require_dataset(dataset_dir, "point verify at the dataset folder (the -o of build-dataset)")
    man_path = ds / "manifest.json"
    man = Manifest.read(man_path)
    sess = Path(session_dir) if session_dir else Path(man.session_dir)
    if not sess.is_dir():
        raise InputError(man_path, "session_dir", "the capture session the dataset was built from",
                         f"{sess} (no such folder)", "pass --session SESSION if the captures moved")
    calib = Path(man.calibration_path)
    if not calib.is_file():
        raise InputError(man_path, "calibration_path", "the calibration file the dataset was built from",
                         f"{calib} (no such file)", "restore it; verification needs the rig it was built with")

    cal = CalibrationFile.read(calib)
    session = open_with_calibration(sess, cal)
    check_rig_matches_session(cal.rig, session, calib, f"is {sess} the session this dataset was built from?")
    params = params or man.params.verify
    ids = sorted(scenes or man.scenes)
    unknown = [s for s in ids if s not in man.scenes]
    if unknown:
        known = sorted(man.scenes)
        raise InputError(man_path, "--scenes", "scenes of this dataset", ", ".join(repr(s) for s in unknown),
                         f"its scenes: {first_of(known)} (comma-separated, no spaces or empty names)")
    old = {}
    rep_path = ds / "verification.json"
    if rep_path.is_file():
        try:
            old = VerificationResult.read(rep_path).scenes
        except InputError as exc:  # an older schema (figures of a biased sampler, no noise floors): not merged
            if set(ids) != set(man.scenes):
                log.warning("%s cannot be merged (%s): every scene is verified again", rep_path, exc)
                ids = sorted(man.scenes)
    # the calibration's digest: a worker reads the file once for all its scenes (worker_cache.cached_calibration)
    calib_sha = sha256_file(calib)
    captures = session.root / session.config.scenes_dir
    stamps = {sid: inputs_stamp(ds / "scenes" / sid, captures / sid) for sid in ids}
    journal = ds / JOURNAL_FILE
    record = _read_journal(journal)
    # taken over: the record's scenes checked with these thresholds, calibration and session, their files unchanged
    same_setup = record is not None and (record.params, record.calibration_sha256, record.session_dir) == \
        (params, calib_sha, str(sess.resolve()))
    kept = record.scenes if same_setup else {}
    results = {sid: e.verification for sid, e in kept.items() if stamps.get(sid) == e.inputs_stamp}
    if results and progress:
        progress(f"{len(results)} scene(s) verified before an interruption, their files unchanged: kept ({journal})")
    if build_figures and params == man.params.verify:
        results.update({sid: v for sid, v in build_figures.items() if sid in ids and sid not in results})
    args = [(str(sess.resolve()), str(ds.resolve()), sid, str(calib.resolve()), params.model_dump_json(), calib_sha)
            for sid in ids if sid not in results]

    def handle(res):
        sid, ver = res
        results[sid] = SceneVerification.model_validate(ver)
        if progress:
            progress(f"verified {sid} ({len(results)}/{len(ids)}): {results[sid].status}")

    try:
        run_tasks(verify_one_scene, args, handle, workers=workers, scheduler=scheduler,
                  heap_bytes=scene_heap_bytes(cal.rig.zed.left),
                  lost_result=lambda a, reason: (a[2], SceneVerification(status="not verifiable", reasons=[reason])
                                                 .model_dump(mode="json")))
    except BaseException as exc:  # Ctrl-C, a cluster lost, a bug: what was checked is kept for the next verify
        if results:  # (with the record's other scenes: a --scenes run stopped keeps what an earlier one had)
            VerifyJournal(params=params, calibration_sha256=calib_sha, session_dir=str(sess.resolve()),
                          scenes={**{sid: e for sid, e in kept.items() if sid not in stamps},
                                  **{sid: VerifyJournalEntry(inputs_stamp=stamps[sid], verification=v)
                                     for sid, v in results.items()}}).write(journal)
        if isinstance(exc, (KeyboardInterrupt, Interrupted)):
            detail = f"{len(results)} of {len(ids)} scene(s) verified" + (f", kept in {journal}" if results else "")
            raise Interrupted(f"interrupted: {detail}; rerun the same command to resume (it checks only the others)",
                              detail) from None
        raise
    rep = VerificationResult(dataset_dir=str(ds.resolve()), params=params,
                             scenes={**old, **{sid: results[sid] for sid in ids}})
    write_verification_report(rep, ds)  # (and the overlays of scenes it no longer flags go)
    # the scenes this report holds leave the record; a --scenes run keeps the others for a later verify
    rest = {sid: e for sid, e in record.scenes.items() if sid not in stamps} if record is not None else {}
    if rest:
        record.model_copy(update={"scenes": rest}).write(journal)
    else:
        journal.unlink(missing_ok=True)
    man.flagged = rep.flagged
    man.quarantined = sorted(rep.flagged) if quarantine else []
    man.splits = final_splits(sorted(man.scenes), {s: m.fruit_id for s, m in man.scenes.items()}, man.params,
                              man.quarantined)
    write_lists(ds, man.splits)
    write_split_views(ds, man.splits, man.params)
    man.write(man_path)
    return rep


def build_checks(ds: Path, ids: list[str]) -> dict[str, SceneVerification]:
    """The checks build-dataset made of scenes ``ids`` of dataset ``ds`` (each ``meta.json``'s verification), for the
    scenes that have one where the build did not try motion compensation: verify checks a compensated scene on the
    fruit it finds moved in the files (``moved_fruit_of``) and keeps no record of a compensation that was tried and
    not made, so such a scene is checked again."""
    found = {}
    for sid in ids:
        try:
            ver = SceneMeta.read(ds / "scenes" / sid / "meta.json").verification
        except InputError:  # (missing or unreadable: verify_one_scene says so for that scene)
            continue
        if ver is not None and ver.motion_compensation is None:
            found[sid] = ver
    return found


JOURNAL_FILE = ".verify-partial.json"  # an interrupted verify's checked scenes (records.verification.VerifyJournal)


def inputs_stamp(scene_dir: Path, capture_dir: Path) -> str:
    """A digest of the name, size and modification time of every file in a built scene's folder and in the capture
    it was built from: what a scene's check depends on besides the thresholds, calibration and session, which the
    journal records once."""
    entries = []
    for folder in (scene_dir, capture_dir):
        try:
            for p in sorted(folder.iterdir()):
                if p.is_file():
                    st = p.stat()
                    entries.append(f"{folder.name}/{p.name}:{st.st_size}:{st.st_mtime_ns}")
        except FileNotFoundError:
            entries.append(f"{folder}: missing")
    return hashlib.sha256("\n".join(entries).encode()).hexdigest()


def _read_journal(journal: Path) -> VerifyJournal | None:
    """An interrupted verify's record (None: none there, or unreadable, which is set aside with a warning: every
    scene is then checked and the file replaced)."""
    if not journal.is_file():
        return None
    try:
        return VerifyJournal.read(journal)
    except InputError as exc:
        log.warning("%s is set aside (%s): every scene is checked", journal, exc)
        return None


DEPTH_FILE = "depth0.tiff"  # build-dataset's z-depth, float32 mm (docs/dataset-format.md)
# how far depth0.tiff may lie from the depth disp0GT.pfm implies: float32 disparities carry about 1e-7 of it
DEPTH_AGREEMENT_REL = 1e-6


def depth_mismatch(written: np.ndarray, implied: np.ndarray) -> str | None:
    """Why ``written`` (depth0.tiff) is not the depth ``implied`` by disp0GT.pfm, or None when it is (the same
    pixels, each within ``DEPTH_AGREEMENT_REL``)."""
    if written.shape != implied.shape:
        return f"{DEPTH_FILE} is {written.shape[1]}x{written.shape[0]} px, disp0GT.pfm {implied.shape[1]}x" \
               f"{implied.shape[0]} px (checked on the disparity's depth)"
    fw, fi = np.isfinite(written), np.isfinite(implied)
    both = fw & fi
    off = np.count_nonzero(np.abs(written[both] - implied[both]) > DEPTH_AGREEMENT_REL * np.abs(implied[both]))
    n = off + int(np.count_nonzero(fw != fi))
    if n == 0:
        return None
    return (f"{DEPTH_FILE} and disp0GT.pfm disagree at {n} pixel(s) (more than {DEPTH_AGREEMENT_REL:g} apart or one "
            "without a value): was a file changed after the build? (checked on the disparity's depth)")


def verify_one_scene(session_dir: str, dataset_dir: str, sid: str, calib_path: str,
                     params_json: str, calib_sha256: str | None = None) -> tuple[str, dict]:
    """Worker for ``gtforge verify``: re-check a built scene against its captures. Returns (sid, SceneVerification).
    ``calib_sha256``: the calibration file's digest, when the caller took it: the file is then read once per worker
    process for every scene (its YAML took 0.13 s a scene to parse), and again only if it changes."""

    params = VerifyParams.model_validate_json(params_json)
    s = Path(dataset_dir) / "scenes" / sid
    try:
        calib = (cached_calibration(calib_path, calib_sha256) if calib_sha256 is not None
                 else CalibrationFile.read(calib_path))
        session = cached_session(session_dir, calib)
        rig = calib.rig
        if not s.is_dir():
            raise InputError(s, None, "the scene's folder (manifest.json lists it)", "no such folder",
                             "rerun gtforge build-dataset with the same options: it builds the scenes a dataset lacks")
        meta = SceneMeta.read(s / "meta.json")
        folder = session.root / session.config.scenes_dir / sid
        if not folder.is_dir():
            raise InputError(folder, None, "the capture this scene was built from", "no such folder",
                             "verification needs the session's captures (pass --session if they moved)")
        cap = session.load_capture(folder)  # the right image as the dataset's im1 has it (every correction applied)
        disp = read_pfm(s / "disp0GT.pfm")
        mask = read_image(s / "mask0nocc.png")
        region = read_image(s / "region.png")
    except InputError as exc:
        return sid, SceneVerification(status="not verifiable", reasons=[str(exc)]).model_dump(mode="json")
    unreadable = None
    try:
        written = read_depth(s / DEPTH_FILE) if (s / DEPTH_FILE).is_file() else None
    except InputError as exc:  # the labels are still there to check: on the disparity's depth, the scene flagged
        written, unreadable = None, f"{DEPTH_FILE} is unreadable ({exc}): checked on the disparity's depth"
    H, W = cap.zed_left.shape[:2]
    if meta.crop_xywh:  # a cropped dataset: put the crop back where it was cut from
        x0, y0, cw, ch = meta.crop_xywh

        def uncrop(a, fill):
            full = np.full((H, W), fill, a.dtype)
            full[y0:y0 + ch, x0:x0 + cw] = a
            return full

        disp, mask, region = uncrop(disp, np.nan), uncrop(mask, 0), uncrop(region, 0)
        written = uncrop(written, np.nan) if written is not None and written.shape == (ch, cw) else written
    depth = rig.zed.disparity_to_depth(disp)
    mismatch = unreadable
    if written is not None:
        # the depth the build checked (depth0.tiff), where the labels agree with it: the build's own figures to the
        # last digit (the depth disp0GT.pfm implies differs by 1e-7, which can move a pixel across a mask's edge)
        mismatch = depth_mismatch(written, depth)
        if mismatch is None:
            depth = written
    mc = meta.verification.motion_compensation if meta.verification is not None else None
    moved = moved_fruit_of(region, depth, rig, mc) if mc is not None and mc.status == "compensated" else None
    ver, rendered = verify_scene(depth, disp, mask == 255, region, cap.zed_left, cap.zed_right, cap.mech_texture, rig,
                                 params, moved)
    if moved is not None:  # the ground truth's fruit moved between the exposures: still so
        ver = ver.model_copy(update={"motion_compensation": mc})
    if mismatch is not None:  # checked on the labels' own depth; the scene's two files no longer tell one story
        ver = ver.model_copy(update={"status": "flagged", "reasons": [*ver.reasons, mismatch]})
    if ver.status == "flagged" and rendered is not None:
        write_verification_overlay(Path(dataset_dir) / "verification" / f"{sid}_overlay.jpg", cap.zed_left, rendered)
    return sid, ver.model_dump(mode="json")
