"""The dataset's views and splits: KITTI and ETH3D folders of links (or copies) to each scene's files, the split lists
(train/val/test by fruit) every view shares."""
from __future__ import annotations

import os
import shutil
import uuid
from pathlib import Path

import numpy as np

from gtforge.dataset.layout import KITTI_DISPARITY_DIRS
from gtforge.infra.atomic import atomic_write_text
from gtforge.infra.digest import blake3_hex
from gtforge.io.formats import read_image, read_pfm, write_kitti_disparity_pair
from gtforge.records.dataset import BuildParams


def make_splits(scene_ids: list[str], fruit_ids: dict[str, str | None], params: BuildParams) -> dict[str, list[str]]:
    """Split by fruit: all scenes of one fruit land in the same split, chosen by that fruit's own draw
    (``fruit_draw``): train below ``split_train``, val below ``split_train + split_val``, else test. A fruit's split
    depends on its id and ``split_seed`` only, so adding or removing other scenes never moves it (a model trained on
    an earlier build's train split has seen none of a later build's val or test); the shares hold on average over the
    fruit, not exactly in a small session. A scene without a fruit id is its own fruit."""
    out = {"train": [], "val": [], "test": []}
    for s in scene_ids:
        u = fruit_draw(fruit_ids.get(s) or f"scene:{s}", params.split_seed)
        split = "train" if u < params.split_train else "val" if u < params.split_train + params.split_val else "test"
        out[split].append(s)
    return {k: sorted(v) for k, v in out.items()}


def fruit_draw(fruit: str, seed: int) -> float:
    """A fruit's number in [0, 1), uniform over fruit ids: from the BLAKE3 of the seed and the id (the same on every
    machine and Python, unlike ``hash``)."""
    return int(blake3_hex(f"{seed}\x00{fruit}".encode())[:16], 16) / 2.0 ** 64


def _link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(f".{dst.name}.tmp")
    if tmp.exists():
        tmp.unlink()
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copy2(src, tmp)
    os.replace(tmp, dst)
    if tmp.exists():  # dst was already a link to src: POSIX rename of two links to one file does nothing
        tmp.unlink()



def scene_view_sources(out: Path, sid: str, params: BuildParams) -> list[tuple[Path, Path, bool]]:
    """The files ``write_scene_views`` writes for scene ``sid``: ``(view, the scene's file it shows, linked)``; not
    linked: a KITTI disparity PNG made from the labels (the right view's only where the scene has ``disp1GT.pfm``)."""
    s = out / "scenes" / sid
    views = []
    if params.kitti:
        k = out / "kitti" / "training"
        views += [(k / "image_2" / f"{sid}_10.png", s / "im0.png", True),
                  (k / "image_3" / f"{sid}_10.png", s / "im1.png", True)]
        views += [(k / d / f"{sid}_10.png", s / "disp0GT.pfm", False) for d in ("disp_occ_0", "disp_noc_0")]
        if (s / "disp1GT.pfm").exists():
            views += [(k / d / f"{sid}_10.png", s / "disp1GT.pfm", False) for d in ("disp_occ_1", "disp_noc_1")]
    if params.eth3d:
        e = out / "eth3d"
        views += [(e / "two_view_training" / sid / f, s / f, True) for f in ("im0.png", "im1.png", "calib.txt")]
        views += [(e / "two_view_training_gt" / sid / f, s / f, True) for f in ("disp0GT.pfm", "mask0nocc.png")]
    return views


def scene_views_current(out: Path, sid: str, params: BuildParams) -> bool:
    """Whether every view ``write_scene_views`` writes for scene ``sid`` is there and is of the scene as it is now: a
    linked file the scene's own (or a copy with its size and time, ``_link``'s fallback), a KITTI disparity written
    after the scene's labels. A scene that landed without its views (a worker stopped between the two) keeps an
    earlier build's views otherwise."""
    views = scene_view_sources(out, sid, params)
    if not all(view.exists() for view, _, _ in views):
        return False
    for view, src, linked in views:
        a, b = src.stat(), view.stat()
        if linked and (a.st_ino, a.st_dev) != (b.st_ino, b.st_dev) and \
                (a.st_size, a.st_mtime_ns) != (b.st_size, b.st_mtime_ns):
            return False
        if not linked and b.st_mtime_ns < a.st_mtime_ns:
            return False
    return True


def write_scene_views(out: Path, sid: str, params: BuildParams, disp: np.ndarray | None = None,
                      noc: np.ndarray | None = None, disp1: np.ndarray | None = None,
                      noc1: np.ndarray | None = None) -> None:
    """KITTI and ETH3D views of one built scene (links where possible). The arrays save re-reading."""

    s = out / "scenes" / sid
    for view, src, linked in scene_view_sources(out, sid, params):
        if linked:
            _link(src, view)
    if params.kitti:
        k = out / "kitti" / "training"
        if disp is None:
            disp = read_pfm(s / "disp0GT.pfm")
            noc = read_image(s / "mask0nocc.png") == 255
        write_kitti_disparity_pair(k / "disp_occ_0" / f"{sid}_10.png", k / "disp_noc_0" / f"{sid}_10.png", disp, noc)
        if disp1 is None and (s / "disp1GT.pfm").exists():
            disp1 = read_pfm(s / "disp1GT.pfm")
            noc1 = read_image(s / "mask1nocc.png") == 255
        if disp1 is not None:  # KITTI's right-view GT, as OpenStereo's RETURN_RIGHT_DISP reads it
            write_kitti_disparity_pair(k / "disp_occ_1" / f"{sid}_10.png", k / "disp_noc_1" / f"{sid}_10.png", disp1,
                                       noc1)
        else:  # built without the right view's GT (--no-right-gt): none from an earlier build stays in the view
            for d in ("disp_occ_1", "disp_noc_1"):
                (k / d / f"{sid}_10.png").unlink(missing_ok=True)



def write_split_views(out: Path, splits: dict[str, list[str]], params: BuildParams) -> Path:
    """``OUT/views/<split>/``: each split in the folder layouts training repositories read from a fixed root, as
    relative symlinks into ``scenes/``, ``kitti/`` and ``eth3d/`` (nothing copied; the dataset stays relocatable):

    * ``Middlebury/MiddEval3/official_train.txt`` + ``training{F,H,Q}/<id>`` (RAFT-Stereo ``middlebury_F/H/Q``;
    IGEV-Stereo
      reads ``trainingH`` for the names; gtforge has one resolution, so F, H and Q are the same scenes);
    * ``Middlebury/2014/<id>/{im0,im1,im1E,im1L}.png, disp0.pfm, calib.txt`` (RAFT-Stereo ``middlebury_2014``; im1E and
      im1L, the 2014 dataset's other exposure and lighting, are im1);
    * ``ETH3D/two_view_training{,_gt}/<id>`` and ``KITTI/training/<kind>/<id>_10.png`` (RAFT-Stereo, IGEV-Stereo).

    A split with no scene gets no folder. The tree is built beside ``views/`` (same depth, so the relative links are the
    same) and swapped in by rename."""
    views = out / "views"
    tmp = out / f".views-{uuid.uuid4().hex[:12]}"
    tmp.mkdir()
    links: list[tuple[str, str]] = []  # (target, link), as absolute paths; made at the end, relative

    def link(target: Path, at: Path) -> None:
        links.append((os.fspath(target), os.fspath(at)))

    for split, ids in splits.items():
        if not ids:
            continue
        root = tmp / split
        midd = root / "Middlebury" / "MiddEval3"
        midd.mkdir(parents=True)
        atomic_write_text(midd / "official_train.txt", "\n".join(ids) + "\n")
        for sid in ids:
            scene = out / "scenes" / sid
            for res in "FHQ":
                link(scene, midd / f"training{res}" / sid)
            for name, src in (("im0.png", "im0.png"), ("im1.png", "im1.png"), ("im1E.png", "im1.png"),
                              ("im1L.png", "im1.png"), ("disp0.pfm", "disp0GT.pfm"), ("calib.txt", "calib.txt")):
                link(scene / src, root / "Middlebury" / "2014" / sid / name)
            if params.eth3d:
                for kind in ("two_view_training", "two_view_training_gt"):
                    link(out / "eth3d" / kind / sid, root / "ETH3D" / kind / sid)
            if params.kitti:
                for kind in ("image_2", "image_3", *KITTI_DISPARITY_DIRS):
                    f = out / "kitti" / "training" / kind / f"{sid}_10.png"
                    if f.exists():
                        link(f, root / "KITTI" / "training" / kind / f"{sid}_10.png")
    _make_symlinks(links)
    old = out / f".views-old-{uuid.uuid4().hex[:12]}"
    if views.exists():
        os.replace(views, old)
    os.replace(tmp, views)
    shutil.rmtree(old, ignore_errors=True)
    return views



def _make_symlinks(links: list[tuple[str, str]]) -> None:
    """Relative symlinks ``link -> target`` (absolute paths given), made folder by folder, each folder made once.
    In that order each link goes in the folder the one before went in; made scene by scene, each link in another
    folder than the one before, the same links took several times the kernel time (benchmarks/RESULTS.md, "Figures
    from code comments")."""
    links = sorted(links, key=lambda ta: ta[1])
    made = set()
    for target, at in links:
        folder = os.path.dirname(at)
        if folder not in made:
            os.makedirs(folder, exist_ok=True)
            made.add(folder)
        os.symlink(os.path.relpath(target, folder), at)



def write_lists(out: Path, splits: dict[str, list[str]]) -> None:
    for split, ids in splits.items():
        lines = [f"scenes/{s}/im0.png scenes/{s}/im1.png scenes/{s}/disp0GT.pfm" for s in ids]
        atomic_write_text(out / "filenames" / f"{split}.txt", "\n".join(lines) + ("\n" if lines else ""))
        klines = [f"training/image_2/{s}_10.png training/image_3/{s}_10.png training/disp_occ_0/{s}_10.png"
                  for s in ids]
        atomic_write_text(out / "filenames" / f"kitti_{split}.txt", "\n".join(klines) + ("\n" if klines else ""))



def moved_between_splits(before: dict[str, list[str]], after: dict[str, list[str]]) -> dict[str, tuple[str, str]]:
    """Scenes in a split in both ``before`` and ``after`` but not the same one: ``{scene: (split before, after)}``."""
    was = {sid: k for k, v in before.items() for sid in v}
    now = {sid: k for k, v in after.items() for sid in v}
    return {sid: (was[sid], now[sid]) for sid in sorted(was.keys() & now.keys()) if was[sid] != now[sid]}


def moved_splits_warning(moved: dict[str, tuple[str, str]]) -> str:
    """build-dataset's warning for ``moved_between_splits``: which scenes moved and what can have moved them. A fruit's
    split is its own draw (``fruit_draw``: --seed and its fruit id), so adding, removing or regrouping other scenes
    never moves a scene; its own fruit id, --split or --seed can, and so can a build over a dataset from before the
    per-fruit draw (round 4, session 14)."""
    from gtforge.errors import first_of

    left_train = [s for s, (a, _) in moved.items() if a == "train"]
    seen = (f"; a model trained on the last build's train split has seen {first_of(left_train)}" if left_train
            else "")
    return (f"{len(moved)} scene(s) changed split since the last build: "
            + first_of(f"{s} {a} -> {b}" for s, (a, b) in moved.items())
            + " (a scene's split is drawn from --seed and its fruit id alone: it moves when its fruit id in "
              f"session.yaml, --split or --seed changed, or when the last build drew the splits before round 4's "
              f"per-fruit draw{seen})")


def final_splits(ok_ids: list[str], fruit_ids: dict[str, str | None], params: BuildParams,
                 quarantined: list[str]) -> dict[str, list[str]]:
    """The split lists: every built scene split by fruit, then quarantined scenes taken out (so a scene's split never
    depends on which other scenes were flagged)."""
    q = set(quarantined)
    return {k: [s for s in v if s not in q] for k, v in make_splits(ok_ids, fruit_ids, params).items()}
