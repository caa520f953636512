"""Disparity predictors for ``gtforge evaluate``: ONNX (onnxruntime), TorchScript (optional torch),
OpenCV SGBM (baseline) and a folder of predictions. Every predictor maps an RGB uint8 pair
``(H, W, 3)`` to a float32 ``(H, W)`` disparity (px, NaN invalid)."""
from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Literal, Protocol

import cv2
import numpy as np
from pydantic import model_validator

from gtforge.core.schema import GTModel
from gtforge.errors import InputError
from gtforge.io.formats import read_kitti_disparity, read_pfm

# the files PredictionFolder looks for, in this order (docs/metrics.md, "Predictions")
PREDICTION_CANDIDATES = ("<id>.pfm", "<id>.npy", "<id>.png", "<id>_10.png", "<id>/disp0.pfm", "<id>/disp0GT.pfm")
PREDICTION_NAMES = "<id>.pfm, <id>.npy, <id>.png (KITTI uint16), <id>_10.png, <id>/disp0.pfm or <id>/disp0GT.pfm"

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)


class InputConvention(GTModel):
    """How a network wants its input (Fast-ACVNet / MI-ACVNet defaults: RGB, ImageNet, pad to 32)."""

    channels: Literal["RGB", "BGR"] = "RGB"
    normalize: Literal["imagenet", "0-255", "0-1"] = "imagenet"
    fit: Literal["pad", "resize"] = "pad"
    pad_multiple: int = 32
    pad_where: Literal["top-right", "bottom-right"] = "top-right"  # Fast-ACVNet pads top and right
    resize_wh: tuple[int, int] | None = None  # with fit="resize": the network's input size

    @model_validator(mode="after")
    def _resize_with_fit(self) -> "InputConvention":
        if self.fit == "resize" and not self.resize_wh:
            raise ValueError("fit='resize' needs resize_wh, the network's input size (W, H)")
        if self.fit != "resize" and self.resize_wh:
            raise ValueError(f"resize_wh is used only with fit='resize' (fit is {self.fit!r})")
        return self

    def prepare(self, img: np.ndarray) -> np.ndarray:
        x = img.astype(np.float32)
        mean, std = IMAGENET_MEAN, IMAGENET_STD
        if self.channels == "BGR":  # each colour keeps its own statistics, in the order the network takes them
            x, mean, std = x[..., ::-1], mean[::-1], std[::-1]
        if self.normalize == "imagenet":
            x = (x / 255.0 - mean) / std
        elif self.normalize == "0-1":
            x = x / 255.0
        return np.ascontiguousarray(x.transpose(2, 0, 1)[None], dtype=np.float32)


class Predictor(Protocol):
    name: str  # the model's name in tables
    source: str  # where it comes from (a file or folder path), shown in report headers

    def predict(self, scene_id: str, left: np.ndarray, right: np.ndarray, ndisp: int, vmin: int) -> np.ndarray: ...


def _network_input(conv: InputConvention, img: np.ndarray) -> tuple[np.ndarray, tuple]:
    """The network's input for image ``img`` (``1 x 3 x H' x W'``, ``conv.prepare``d, fitted) and what ``_unfit``
    needs to undo the fit. A pad comes after the normalisation: its band is 0 in the network's input, ImageNet's mean
    colour under its normalisation, as Fast-ACVNet's loaders pad (a black band, padded before, was -2.1/-2.0/-1.8)."""
    H, W = img.shape[:2]
    if conv.fit == "resize":  # (resize_wh is set: InputConvention checks it)
        return conv.prepare(cv2.resize(img, conv.resize_wh, interpolation=cv2.INTER_LINEAR)), ("resize", H, W)
    m = conv.pad_multiple
    ph, pw = (-H) % m, (-W) % m
    top = ph if conv.pad_where == "top-right" else 0
    return np.pad(conv.prepare(img), ((0, 0), (0, 0), (top, ph - top), (0, pw))), ("pad", H, W, top)


def _disparity_from_output(path: Path, out: np.ndarray, fitted_hw: tuple[int, int], info: tuple,
                           said: set | None = None) -> np.ndarray:
    """A network's output as the scene's disparity (``_unfit``), after checking it is one map of the right size:
    the same for every scene, so a mistake here is the model's (one error, before any scoring). ``said``: the
    warnings already given for this model (each once)."""
    out = np.squeeze(out)
    if out.ndim != 2:
        raise InputError(path, "output", "a disparity map (1 x 1 x H x W, 1 x H x W or H x W)",
                         f"shape {tuple(np.shape(out))} after dropping its size-1 axes",
                         "export the model's final disparity output first")
    if info[0] == "pad" and out.shape != tuple(fitted_hw):
        raise InputError(path, "output", f"a disparity map of the input's size, {fitted_hw[1]}x{fitted_hw[0]} px",
                         f"{out.shape[1]}x{out.shape[0]} px",
                         "export the model's full-resolution output (a low-resolution disparity upsampled and "
                         "scaled), or evaluate with --fit resize --resize WxH")
    if info[0] == "resize" and out.ndim == 2 and out.shape != tuple(fitted_hw) and said is not None \
            and "size" not in said:
        said.add("size")
        logging.getLogger("gtforge.evaluate").warning(
            "%s: its output is %dx%d px, not its input's %dx%d: read as disparities in the output's own pixels "
            "(resized to the image and scaled by %.4g); a network that gives full-resolution disparities on a "
            "smaller map would be scored wrong", path, out.shape[1], out.shape[0], fitted_hw[1], fitted_hw[0],
            info[2] / out.shape[1])
    d = _unfit(out, info).astype(np.float32)
    say_if_negative(d, path, said)
    return d


def say_if_negative(d: np.ndarray, source, said: set | None, invalid_there: bool = False) -> None:
    """Warn, once a model (``said``), when most of a prediction's finite disparities are negative: a network or a
    script that saved -disparity (RAFT-Stereo's ``flow_x``, for one) is otherwise scored as a 100-px error or, where
    negative values are invalid (``invalid_there``: a .npy), not at all, with nothing to say why."""
    if said is None or "negative" in said:
        return
    v = d[np.isfinite(d)]
    n_negative = int(np.count_nonzero(v < 0))
    if v.size and n_negative > v.size / 2:
        said.add("negative")
        logging.getLogger("gtforge.evaluate").warning(
            "%s: %.0f %% of its disparities are negative (median %.3g px): was -disparity saved (RAFT-Stereo's flow_x, "
            "for one)? gtforge scores disparities as left x minus right x, > 0; %s", source,
            100.0 * n_negative / v.size, float(np.median(v)),
            "a .npy's values <= 0 are invalid, so these are not scored" if invalid_there
            else "these are scored as they are")


def _unfit(disp: np.ndarray, info: tuple) -> np.ndarray:
    if info[0] == "resize":
        _, H, W = info
        scale = W / disp.shape[1]
        return cv2.resize(disp, (W, H), interpolation=cv2.INTER_LINEAR) * scale
    _, H, W, top = info
    return disp[top:top + H, :W]


class OnnxModel:
    """Any stereo network exported to ONNX with inputs (left, right) NCHW float32, or one 6-channel input."""

    def __init__(self, path: str | Path, convention: InputConvention | None = None, name: str | None = None):
        try:
            import onnxruntime as ort
        except ImportError:
            raise InputError(path, "onnxruntime", "onnxruntime installed", "not installed",
                             "pip install 'gtforge[onnx]'") from None
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(self.path, None, "an ONNX model file",
                             "a folder" if self.path.is_dir() else "no such file",
                             "a folder of predicted disparities goes to --predictions" if self.path.is_dir()
                             else "check the path")
        self.conv = convention or InputConvention()
        self.said: set[str] = set()  # the warnings given for this model, each once
        providers = [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in ort.get_available_providers()]
        try:
            self.sess = ort.InferenceSession(str(self.path), providers=providers)
        except Exception as exc:
            raise InputError(self.path, None, "a loadable ONNX model", f"{type(exc).__name__}: {_first_words(exc)}",
                             "export the network with torch.onnx.export (docs/metrics.md, 'Models')") from None
        self.provider = self.sess.get_providers()[0]
        self.inputs = self.sess.get_inputs()
        self.layout = _onnx_layout(self.path, self.inputs)
        # (left, right) in the graph's order, unless its names say the other: "right..." first, "...left..." second
        names = [i.name.lower() for i in self.inputs[:2]]
        self.swapped = self.layout == "two" and "right" in names[0] and "left" in names[1] and \
            "left" not in names[0] and "right" not in names[1]
        self.dtype = _onnx_input_dtype(self.path, self.inputs)
        # the height and width the model was exported with, where they are fixed numbers (None: any)
        dims = self.inputs[0].shape
        self.fixed_hw = tuple(d if isinstance(d, int) and d > 0 else None for d in dims[2:4])
        self.name = name or self.path.stem
        self.source = str(self.path.resolve())

    def predict(self, scene_id, left, right, ndisp=192, vmin=0) -> np.ndarray:
        a, info = _network_input(self.conv, left)
        b, _ = _network_input(self.conv, right)
        fitted_hw = a.shape[2:]
        self._check_size(fitted_hw)
        a, b = a.astype(self.dtype, copy=False), b.astype(self.dtype, copy=False)
        if self.swapped:
            a, b = b, a
        feeds = {self.inputs[0].name: a, self.inputs[1].name: b} if self.layout == "two" else \
            {self.inputs[0].name: np.concatenate([a, b], axis=1)}
        try:
            out = self.sess.run(None, feeds)[0]
        except Exception as exc:  # onnxruntime's own errors (a shape or type the graph cannot take) name no file
            raise _model_error(self.path, exc, "two N x 3 x H x W" if self.layout == "two" else "one N x 6 x H x W")
        return _disparity_from_output(self.path, np.asarray(out, np.float32), fitted_hw, info, self.said)

    def _check_size(self, hw: tuple[int, int]) -> None:
        """A model exported with a fixed height or width takes only that: say so before onnxruntime does."""
        if all(f is None or f == n for f, n in zip(self.fixed_hw, hw)):
            return
        fh, fw = self.fixed_hw
        want = f"{fw or 'any'}x{fh or 'any'} px (its fixed input size)"
        how = (f"evaluate with --fit resize --resize {fw}x{fh}" if fh and fw else
               "export the model with dynamic height and width")
        raise InputError(self.path, "inputs", want, f"{hw[1]}x{hw[0]} px after --fit {self.conv.fit}", how)


# what a runtime's error says when the machine, not the model, ran out (memory on the GPU or the host)
_OUT_OF_MEMORY = ("out of memory", "failed to allocate", "bad_alloc", "cudaerrormemoryallocation")


def _first_words(exc: Exception, limit: int = 160) -> str:
    """A runtime's message, first line only, cut at a word (with "...") where it is longer than ``limit``."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    if len(text) <= limit:
        return text
    return text[:limit].rsplit(" ", 1)[0] + " ..."


def _model_error(path: Path, exc: Exception, inputs: str) -> Exception:
    """A runtime's error on a model's first call as one line naming the model, or ``exc`` itself where it is the
    machine's (out of memory): that is no mistake in the model or its inputs."""
    text = _first_words(exc)
    if isinstance(exc, MemoryError) or any(m in str(exc).lower() for m in _OUT_OF_MEMORY):
        return exc
    return InputError(path, None, f"a model that runs on {inputs} float images", f"{type(exc).__name__}: {text}",
                      "check the model's inputs and output against docs/metrics.md, 'Models'")


# ONNX element types an image input may have, and the array type gtforge feeds it
_ONNX_FLOAT_TYPES = {"tensor(float)": np.float32, "tensor(float16)": np.float16, "tensor(double)": np.float64}


def _onnx_layout(path: Path, inputs) -> str:
    """``"two"`` (left, right: N x 3 x H x W each) or ``"six"`` (one N x 6 x H x W); anything else is refused here,
    where the message can say what the model has (onnxruntime's own says only which axis of which input)."""
    shapes = [list(i.shape) for i in inputs]
    desc = ", ".join(f"{i.name}{list(i.shape)}" for i in inputs)
    want = "two NCHW inputs (left, right: N x 3 x H x W) or one N x 6 x H x W input"
    if len(inputs) == 2 and all(len(s) == 4 for s in shapes):
        if all(s[1] == 3 for s in shapes):
            return "two"
        if all(s[3] == 3 for s in shapes):  # (a width fixed at 3 px is no image)
            raise InputError(path, "inputs", want, f"{desc} (channels last, NHWC)",
                             "export the model with NCHW inputs (a transpose at the graph's start)")
        if all(not isinstance(s[1], int) for s in shapes):  # a channel axis left open: it gets 3
            return "two"
        raise InputError(path, "inputs", want, desc, "the images are RGB (or BGR with --channels BGR): 3 channels")
    if len(inputs) == 1 and len(shapes[0]) == 4 and shapes[0][1] == 6:
        return "six"
    raise InputError(path, "inputs", want, desc, "export the model with left and right image inputs")


def _onnx_input_dtype(path: Path, inputs) -> type:
    types = {i.type for i in inputs}
    if len(types) == 1 and next(iter(types)) in _ONNX_FLOAT_TYPES:
        return _ONNX_FLOAT_TYPES[next(iter(types))]
    desc = ", ".join(f"{i.name} {i.type}" for i in inputs)
    raise InputError(path, "inputs", "float image inputs (tensor(float), or float16 / double)", desc,
                     "export the model with float inputs: gtforge scales the images itself (--normalize)")


class TorchScriptModel:
    """A TorchScript (``.pt``) or ``torch.export`` (``.pt2``) stereo network (needs torch):
    ``model(left, right)`` -> disparity (or a list of them, the last one used)."""

    def __init__(self, path: str | Path, convention: InputConvention | None = None, name: str | None = None):
        try:
            import torch
        except ImportError:
            raise InputError(path, "torch", "torch installed", "not installed",
                             "pip install 'gtforge[torch]'") from None
        self.torch = torch
        self.device = "cuda" if torch.cuda.is_available() else "cpu"
        path = Path(path)
        if not path.is_file():
            raise InputError(path, None, "a TorchScript (.pt) or torch.export (.pt2) file",
                             "a folder" if path.is_dir() else "no such file",
                             "a folder of predicted disparities goes to --predictions" if path.is_dir()
                             else "check the path")
        try:
            if path.suffix == ".pt2":
                self.model = torch.export.load(str(path)).module().to(self.device)
            else:
                self.model = torch.jit.load(str(path), map_location=self.device).eval()
        except Exception as exc:
            raise InputError(path, None, "a loadable TorchScript / torch.export model",
                             f"{type(exc).__name__}: {_first_words(exc)}",
                             "save the network with torch.jit.save or torch.export.save (docs/metrics.md, "
                             "'Models')") from None
        self.conv = convention or InputConvention()
        self.said: set[str] = set()  # the warnings given for this model, each once
        self.path = path
        self.name = name or Path(path).stem
        self.source = str(path.resolve())
        self.provider = self.device

    def predict(self, scene_id, left, right, ndisp=192, vmin=0) -> np.ndarray:
        torch = self.torch
        a, info = _network_input(self.conv, left)
        b, _ = _network_input(self.conv, right)
        try:
            with torch.no_grad():
                out = self.model(torch.from_numpy(a).to(self.device), torch.from_numpy(b).to(self.device))
        except Exception as exc:  # the model's own errors (a shape or type it cannot take) name no file
            raise _model_error(self.path, exc, "two 1 x 3 x H x W float32")
        return _disparity_from_output(self.path, _torch_disparity(self.path, out), a.shape[2:], info, self.said)


def _torch_disparity(path: Path, out) -> np.ndarray:
    """A TorchScript model's output as an array: a tensor, the last of a list or tuple (RAFT-Stereo's iterations), or
    a dict's one tensor; anything else is the model's mistake, one line."""
    if isinstance(out, (list, tuple)) and out:
        out = out[-1]
    if isinstance(out, dict):
        tensors = {k: v for k, v in out.items() if hasattr(v, "detach")}
        if len(tensors) != 1:
            raise InputError(path, "output", "a disparity tensor (or a list, tuple or dict holding one)",
                             f"a dict with {len(tensors)} tensors ({', '.join(map(str, list(out)[:6]))})",
                             "wrap the model so that it returns the final disparity tensor (docs/metrics.md, "
                             "'Output')")
        out = next(iter(tensors.values()))
    if not hasattr(out, "detach"):
        raise InputError(path, "output", "a disparity tensor (or a list, tuple or dict holding one)",
                         f"{type(out).__name__}", "wrap the model so that it returns the final disparity tensor "
                         "(docs/metrics.md, 'Output')")
    return out.detach().float().cpu().numpy()


class SGBM:
    """OpenCV semi-global block matching, a classical baseline (sub-pixel, left-right checked)."""

    provider = "cpu"

    def __init__(self, block_size: int = 5, name: str = "SGBM"):
        self.block_size = block_size
        self.name = name
        self.source = f"OpenCV {cv2.__version__} StereoSGBM (3-way, block size {block_size})"

    def predict(self, scene_id, left, right, ndisp=192, vmin=0) -> np.ndarray:
        bs = self.block_size
        min_disp = max(0, int(vmin) - 8)
        num = int(16 * np.ceil(max(16, ndisp + 8 - min_disp) / 16))
        m = cv2.StereoSGBM_create(minDisparity=min_disp, numDisparities=num, blockSize=bs, P1=8 * 3 * bs * bs,
                                  P2=32 * 3 * bs * bs, disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100,
                                  speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
        d = m.compute(cv2.cvtColor(left, cv2.COLOR_RGB2BGR),
                      cv2.cvtColor(right, cv2.COLOR_RGB2BGR)).astype(np.float32) / 16.0
        d[d < min_disp] = np.nan
        return d


class PredictionFolder:
    """Predicted disparities on disk, one file per scene id (``PREDICTION_CANDIDATES``, first found wins):
    ``<id>.pfm`` (inf/NaN invalid), ``<id>.npy`` (NaN/<=0 invalid), ``<id>.png``/``<id>_10.png`` (KITTI uint16
    x256, 0 invalid), or ``<id>/disp0.pfm`` / ``<id>/disp0GT.pfm`` (Middlebury/ETH3D folders)."""

    provider = "files"

    def __init__(self, folder: str | Path, name: str | None = None):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            layout = ("the folder holds one file per scene id: <id>.pfm, <id>.npy, <id>.png, <id>_10.png (KITTI) or "
                      "<id>/disp0.pfm (docs/metrics.md)")
            is_file = self.folder.is_file()
            raise InputError(self.folder, "--predictions", "a folder of predicted disparities",
                             "a file" if is_file else "no such folder",
                             (f"give the folder that holds it ({self.folder.parent}); " if is_file
                              else "check the path; ") + layout)
        self.name = name or self.folder.name
        self.source = str(self.folder.resolve())
        self.said: set[str] = set()  # the warnings given for these predictions, each once

    def find(self, scene_id: str) -> Path | None:
        for cand in PREDICTION_CANDIDATES:
            p = self.folder / cand.replace("<id>", scene_id)
            if p.is_file():
                return p
        return None

    def predict(self, scene_id, left, right, ndisp=192, vmin=0) -> np.ndarray:
        p = self.find(scene_id)
        if p is None:
            raise InputError(self.folder, scene_id, f"a prediction ({PREDICTION_NAMES.replace('<id>', scene_id)})",
                             "missing", "write one file per scene, named after its scene id (docs/metrics.md "
                             "'Predictions')")
        if p.suffix == ".pfm":
            d = read_pfm(p)
            say_if_negative(d, p, self.said)
        elif p.suffix == ".png":
            d = read_kitti_disparity(p)
        else:
            try:
                d = np.load(p, allow_pickle=False)
            except Exception as exc:
                raise InputError(p, None, "a readable .npy array of disparities (float, px)",
                                 f"{type(exc).__name__}: {_first_words(exc, 80)}",
                                 "save the network's output with np.save(path, disparity.astype(np.float32))") from None
            kind = d.dtype.kind
            if kind not in "fiu":  # complex (cast to its real part with a numpy warning), bool, text, structured
                raise InputError(p, "dtype", "an array of real disparities (float32, px)", f"{d.dtype}",
                                 "save the network's output with np.save(path, disparity.astype(np.float32))")
            d = d.astype(np.float32)
            if kind != "f":  # whole-pixel disparities: scored as they are, their rounding counted as error
                logging.getLogger("gtforge.evaluate").warning(
                    "%s holds integer disparities (no sub-pixel part): scored as whole pixels; a network's output is "
                    "saved as float32", p)
            d = np.squeeze(d)
            say_if_negative(d, p, self.said, invalid_there=True)
            d[~np.isfinite(d) | (d <= 0)] = np.nan
        if d.shape != left.shape[:2]:
            raise InputError(p, "size", f"{left.shape[1]}x{left.shape[0]} px (the scene's image)",
                             f"{d.shape[1]}x{d.shape[0]} px" if d.ndim == 2 else f"shape {d.shape}",
                             "predictions must be at the dataset's resolution (or crop)")
        check_disparity_scale(d, p)
        return d


def check_disparity_scale(d: np.ndarray, source) -> None:
    """Refuse a prediction whose disparities are mostly as large as its image is wide: no pixel matches that far
    away, so they are in another unit (KITTI's ``round(d * 256)`` saved as a .npy or PFM, a depth map in mm at a small
    size). Before, such a file was scored as it was (EPE in the thousands of px, exit 0, nothing said)."""
    v = np.abs(d[np.isfinite(d)])
    width = d.shape[1]
    if v.size and float(np.median(v)) >= width:
        raise InputError(source, "disparity", f"disparities in px at the image's resolution (below its width, "
                         f"{width} px)", f"median {float(np.median(v)):.4g} px",
                         "KITTI's PNG stores round(d * 256): divide by 256 before saving a .npy or .pfm; a depth map "
                         "is no disparity (d = f*B/Z - doffs, calib.txt)")


def timed_predict(pred: Predictor, *args) -> tuple[np.ndarray, float]:
    t = time.perf_counter()
    d = pred.predict(*args)
    return d, (time.perf_counter() - t) * 1000.0
