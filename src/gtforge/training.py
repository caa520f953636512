"""For people who train on the data: a framework-neutral loader and the SGRA loss.

SGRA loss: ``gamma1 * L_init + gamma2 * L_resid`` where each term is the SGRA-weighted smooth-L1
between a disparity estimate and the ground truth over valid pixels:
``L(pred) = sum(w * smoothL1(pred - gt)) / sum(w)``, ``w`` from ``weight.tiff`` (edge 1.4, centre 1.0,
background 0.8 by default), 0 where there is no ground truth.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

import numpy as np
from gtforge.errors import InputError, MissingFileError
from gtforge.io.formats import read_image, read_kitti_disparity, read_pfm


class StereoDataset:
    """Scenes of a built dataset as numpy dicts: left, right (H, W, 3 uint8), disparity (float32, NaN
    invalid), valid (bool), weight (float32 SGRA weights), sigma (float32 1-sigma GT uncertainty in px, +inf where
    there is no ground truth; None for datasets built without it).

    ``split``: a list in ``OUT/filenames/``: ``train``, ``val``, ``test`` (Middlebury layout, PFM disparity) or
    ``kitti_train`` ... (the KITTI view, disparity from its 16-bit PNG, quantised to 1/256 px); None: every scene in
    ``OUT/scenes/``."""

    def __init__(self, root: str | Path, split: str | None = "train"):
        self.root = Path(root)
        # a KITTI list (filenames/kitti_<split>.txt) names files under OUT/kitti, its disparity a KITTI PNG
        self.kitti = bool(split) and split.startswith("kitti_")
        if split:
            lst = self.root / "filenames" / f"{split}.txt"
            if not lst.is_file():
                raise MissingFileError(lst, None, f"a '{split}' list", hint="the dataset folder build-dataset -o "
                                       "wrote, and a split it lists: train, val, test or kitti_train, kitti_val, "
                                       "kitti_test")
            lines = [(k, l.split()) for k, l in enumerate(lst.read_text().splitlines()) if l.strip()]
            self.items = [it for _, it in lines]
            bad = next(((k, it) for k, it in lines if len(it) != 3), None)
            if bad is not None:  # (a bare ValueError, 'not enough values to unpack', when the sample was read)
                raise InputError(lst, f"line {bad[0] + 1}", "three paths: left image, right image, disparity",
                                 f"{len(bad[1])} ({' '.join(bad[1])[:80]!r})", "build-dataset writes the lists so "
                                 "(docs/dataset-format.md); a list of your own needs the disparity's path too")
        else:
            scenes = self.root / "scenes"
            if not scenes.is_dir():
                raise MissingFileError(scenes, None, "a built dataset's scenes folder",
                                       hint="the dataset folder build-dataset -o wrote")
            ids = sorted(p.name for p in scenes.iterdir() if p.is_dir() and not p.name.startswith("."))
            self.items = [[f"scenes/{s}/im0.png", f"scenes/{s}/im1.png", f"scenes/{s}/disp0GT.pfm"] for s in ids]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> dict:
        base = self.root / "kitti" if self.kitti else self.root
        l, r, d = (base / p for p in self.items[i])
        try:
            return self._read(l, r, d)
        except MissingFileError as exc:  # a dataset's file, not a capture's (read_image's hint named those)
            raise MissingFileError(exc.file, exc.field, exc.expected, exc.actual, "the scene is incomplete: run "
                                   "gtforge build-dataset into the dataset again (it rebuilds a scene whose files "
                                   "are missing)") from None

    def _read(self, l: Path, r: Path, d: Path) -> dict:
        if self.kitti:  # training/disp_occ_0/<id>_10.png: the scene's weight and sigma are in scenes/<id>/
            disp = read_kitti_disparity(d)
            scene = self.root / "scenes" / d.stem.removesuffix("_10")
        else:
            disp = read_pfm(d)
            scene = d.parent
        if not (scene / "weight.tiff").is_file():
            raise MissingFileError(scene / "weight.tiff", None, "the scene's SGRA weight map",
                                   hint="rebuild the scene: gtforge build-dataset writes it")
        # read_image: a damaged file is an InputError naming it (tifffile's TiffFileError named none)
        w = read_image(scene / "weight.tiff").astype(np.float32)
        sigma = None
        if (scene / "disp0GT_sigma.pfm").is_file():
            sigma = read_pfm(scene / "disp0GT_sigma.pfm")
            sigma[~np.isfinite(sigma)] = np.inf  # the file's +inf (no GT) reads as NaN: keep it +inf
        return {"left": read_image(l), "right": read_image(r), "disparity": disp, "valid": np.isfinite(disp),
                "weight": w, "sigma": sigma, "scene": scene.name}

    def __iter__(self) -> Iterator[dict]:
        for i in range(len(self)):
            yield self[i]


def smooth_l1(x: np.ndarray, beta: float = 1.0) -> np.ndarray:
    ax = np.abs(x)
    return np.where(ax < beta, 0.5 * ax * ax / beta, ax - 0.5 * beta)


def sigma_confidence(sigma_px: np.ndarray, sigma_ref_px: float = 0.1) -> np.ndarray:
    """Confidence of each GT pixel from its sigma: ``sigma_ref^2 / (sigma_ref^2 + sigma^2)`` (inverse-variance
    weighting with a floor): 1 for a certain label, 0.5 at ``sigma_ref``, 0 where there is no GT (sigma +inf)."""
    s = np.asarray(sigma_px, np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        c = sigma_ref_px ** 2 / (sigma_ref_px ** 2 + s * s)
    return np.where(np.isfinite(s), c, 0.0).astype(np.float32)


def weighted_smooth_l1(pred: np.ndarray, gt: np.ndarray, weight: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Smooth-L1 of ``pred - gt`` averaged with ``weight`` over the pixels with finite ground truth and a positive
    weight (and ``valid``). A non-finite prediction on such a pixel makes it NaN (inf), as ``sgra_loss_torch`` does:
    a diverged network must not look better by its NaN pixels being left out."""
    m = np.isfinite(gt) & (weight > 0)
    if valid is not None:
        m &= valid
    if not m.any():
        return 0.0
    return float(np.sum(weight[m] * smooth_l1(pred[m] - gt[m])) / np.sum(weight[m]))


def sgra_loss(pred_init: np.ndarray, pred_resid: np.ndarray, gt: np.ndarray, weight: np.ndarray,
              gamma1: float = 0.3, gamma2: float = 1.0, valid: np.ndarray | None = None,
              confidence: np.ndarray | None = None) -> float:
    """Numpy reference of the SGRA loss (``gamma1 * L_init + gamma2 * L_resid``). ``confidence`` (e.g.
    ``sigma_confidence(sample["sigma"])``) multiplies the SGRA weights: uncertain labels count less."""
    if confidence is not None:
        weight = weight * confidence
    return (gamma1 * weighted_smooth_l1(pred_init, gt, weight, valid)
            + gamma2 * weighted_smooth_l1(pred_resid, gt, weight, valid))


def sgra_loss_torch(pred_init, pred_resid, gt, weight, gamma1: float = 0.3, gamma2: float = 1.0, valid=None,
                    confidence=None):
    """The same loss for torch tensors (needs torch); NaN ground truth is masked out; ``confidence`` as in
    ``sgra_loss``."""
    import torch
    import torch.nn.functional as F

    if confidence is not None:
        weight = weight * confidence

    def term(pred):
        m = torch.isfinite(gt) & (weight > 0)
        if valid is not None:
            m = m & valid
        if not bool(m.any()):
            return pred.sum() * 0.0
        l = F.smooth_l1_loss(pred[m], gt[m], reduction="none")
        return (weight[m] * l).sum() / weight[m].sum()

    return gamma1 * term(pred_init) + gamma2 * term(pred_resid)
