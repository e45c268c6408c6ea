"""Our learned single-stage detector (CenterNet-style, anchor-free) and the ONNX loader.

Network (:class:`CenterNetLite`): a small strided CNN (strides 2-16) with a top-down path back to
stride 4, and three heads at stride 4: a per-class centre heatmap, the box size (log of width and
height in stride-4 cells) and the sub-cell centre offset. The input normalisation is inside the
network, so it takes RGB float 0..255 (N, 3, H, W) with H and W multiples of 16.

Dense output (what :func:`export_onnx` writes and :class:`OnnxDetector` expects, "yolo" layout):
one tensor (1, N, 4 + C): per candidate, box centre x, centre y, width, height in network-input
pixels, then the C class scores in [0, 1]. Our export keeps only local heatmap peaks (3x3 max, the
CenterNet decoding) and zeroes the other scores, so a threshold plus NMS finishes the job. A YOLO
export of the usual kind fits the same loader (:func:`decode_yolo_output`): the Ultralytics layout
(1, 4 + C, N) with a letterboxed RGB / 255 input (:meth:`OnnxDetector.ultralytics`, COCO classes
car, bus, truck kept), and with ``objectness=True`` (1, N, 5 + C) with an objectness column before
the class scores (YOLOv5).

Training (:func:`train_detector`, ``vcfusion train-detector DATA --out WEIGHTS``) reads a COCO
dataset folder (RGB PNGs and a COCO JSON with images, annotations (bbox x, y, w, h; category_id)
and categories), with focal loss on the heatmap and L1 on sizes and offsets, seeded.
Weights are a torch file holding the state dict and the metadata needed to rebuild the model.
"""

from __future__ import annotations

import copy
import functools
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from vcfusion.detection.detectors import (COCO80_NAMES, YOLO_DEFAULT_CLASSES, Detections, batched_nms,  # noqa: F401
                                          coco_column_categories)
from vcfusion.errors import InputError
from vcfusion.resources import default_weights_path  # noqa: F401  (the shipped weights; callers import it here)

WEIGHTS_FORMAT = "vcfusion-centernet-v1"
STRIDE = 4
MEAN, STD = 114.0, 58.0  # input normalisation (0..255 RGB)


class DetectorFileError(InputError):
    """A dataset or model file that cannot be used; the message names the file and the problem."""


# ---------------------------------------------------------------------------------------------
# network


def _conv(cin, cout, stride=1):
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class CenterNetLite(nn.Module):
    def __init__(self, num_classes: int, widths: tuple[int, int, int, int] = (16, 32, 64, 128), head: int = 64):
        super().__init__()
        w1, w2, w3, w4 = widths
        self.num_classes = num_classes
        self.s2 = nn.Sequential(_conv(3, w1, 2), _conv(w1, w1))
        self.s4 = nn.Sequential(_conv(w1, w2, 2), _conv(w2, w2))
        self.s8 = nn.Sequential(_conv(w2, w3, 2), _conv(w3, w3))
        self.s16 = nn.Sequential(_conv(w3, w4, 2), _conv(w4, w4), _conv(w4, w4))
        self.lat8 = nn.Conv2d(w3, head, 1)
        self.top16 = nn.Conv2d(w4, head, 1)
        self.lat4 = nn.Conv2d(w2, head, 1)
        self.fuse8 = _conv(head, head)
        self.fuse4 = _conv(head, head)
        self.hm = nn.Sequential(_conv(head, head), nn.Conv2d(head, num_classes, 1))
        self.size = nn.Sequential(_conv(head, head), nn.Conv2d(head, 2, 1))
        self.offset = nn.Sequential(_conv(head, head), nn.Conv2d(head, 2, 1))
        # start the heatmap near the prior of a rare centre (CenterNet's -2.19 = logit(0.1))
        nn.init.constant_(self.hm[-1].bias, -2.19)

    def forward(self, x):
        x = (x - MEAN) / STD
        f4 = self.s4(self.s2(x))
        f8 = self.s8(f4)
        f16 = self.s16(f8)
        p8 = self.fuse8(self.lat8(f8) + F.interpolate(self.top16(f16), scale_factor=2.0, mode="nearest"))
        p4 = self.fuse4(self.lat4(f4) + F.interpolate(p8, scale_factor=2.0, mode="nearest"))
        return self.hm(p4), self.size(p4), self.offset(p4)


def decode_dense(hm_logits, log_size, offset) -> torch.Tensor:
    """(B, N, 4 + C): cx, cy, w, h in input pixels, then peak-only class scores."""
    b, c, h, w = hm_logits.shape
    heat = torch.sigmoid(hm_logits)
    peaks = (F.max_pool2d(heat, 3, 1, 1) == heat).to(heat.dtype)
    scores = heat * peaks
    # the grid on the network's device (CUDA: a CPU grid fails the addition below)
    ys = torch.arange(h, dtype=heat.dtype, device=heat.device).view(1, h, 1).expand(1, h, w)
    xs = torch.arange(w, dtype=heat.dtype, device=heat.device).view(1, 1, w).expand(1, h, w)
    cx = (xs + offset[:, 0]) * STRIDE
    cy = (ys + offset[:, 1]) * STRIDE
    bw = torch.exp(log_size[:, 0]) * STRIDE
    bh = torch.exp(log_size[:, 1]) * STRIDE
    boxes = torch.stack([cx, cy, bw, bh], dim=1)  # (B, 4, h, w)
    dense = torch.cat([boxes, scores], dim=1).reshape(b, 4 + c, h * w)
    return dense.transpose(1, 2)


class _DenseExport(nn.Module):
    def __init__(self, model: CenterNetLite):
        super().__init__()
        self.model = model

    def forward(self, x):
        return decode_dense(*self.model(x))


# ---------------------------------------------------------------------------------------------
# shared pre/post-processing


@dataclass(frozen=True)
class PostParams:
    score_threshold: float = 0.3
    nms_iou: float = 0.7  # high: overlapping vehicles (Fig. 3) must survive; CenterNet peaks do most of it
    max_detections: int = 100


def resize_to_input(image: np.ndarray, input_wh: tuple[int, int]) -> np.ndarray:
    """A frame as the network sees it: stretched to its input size by area interpolation, the same
    in inference, in training and in `vcfusion resize-dataset`."""
    return cv2.resize(image, tuple(input_wh), interpolation=cv2.INTER_AREA)


def preprocess(image: np.ndarray, input_wh: tuple[int, int]) -> np.ndarray:
    """RGB uint8 (H, W, 3) -> float32 (1, 3, h, w), stretched to the network input size."""
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image: expected RGB (H, W, 3), got shape {image.shape}")
    resized = resize_to_input(image, input_wh)
    return np.ascontiguousarray(resized.transpose(2, 0, 1)[None].astype(np.float32))


# Candidates that reach NMS at most (Ultralytics' max_nms): a raw YOLO output has tens of near
# duplicates per object, so a cap near the number of detections kept loses whole objects
MAX_NMS_CANDIDATES = 30_000


def postprocess(dense: np.ndarray, image_hw: tuple[int, int], input_wh: tuple[int, int], class_ids,
                params: PostParams, max_candidates: int | None = None) -> Detections:
    """Dense (N, 4 + C) rows (cx, cy, w, h in input px, class scores) -> detections in image px.
    Before NMS the `max_candidates` best rows are kept (default 4 x max_detections: our network's
    rows are heatmap peaks, one per object, already)."""
    dense = np.asarray(dense, dtype=np.float32)
    cls_scores = dense[:, 4:]
    cls = cls_scores.argmax(axis=1)
    score = cls_scores[np.arange(len(dense)), cls]
    keep = np.flatnonzero(score >= params.score_threshold)
    keep = keep[np.argsort(-score[keep], kind="stable")][: max_candidates or 4 * params.max_detections]
    sx, sy = image_hw[1] / input_wh[0], image_hw[0] / input_wh[1]
    cx, cy, w, h = (dense[keep, k] for k in range(4))
    # the network works in pixel-edge coordinates (pixel c spans [c, c + 1), exact under resizing);
    # detections use the project's pixel-centre convention: minus half a pixel
    boxes = np.stack([(cx - w / 2) * sx, (cy - h / 2) * sy, (cx + w / 2) * sx, (cy + h / 2) * sy], axis=1) - 0.5
    boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(-0.5, image_hw[1] - 0.5)
    boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(-0.5, image_hw[0] - 0.5)
    classes = np.asarray(class_ids, dtype=np.int64)[cls[keep]]
    kept = batched_nms(boxes, score[keep], classes, params.nms_iou)[: params.max_detections]
    return Detections.of(boxes[kept], score[keep][kept], classes[kept])


# ---------------------------------------------------------------------------------------------
# weights files and detectors


@dataclass
class DetectorModel:
    model: CenterNetLite
    input_wh: tuple[int, int]
    class_ids: list[int]
    class_names: list[str]
    widths: tuple[int, ...]
    meta: dict = field(default_factory=dict)

    def save(self, path: Path) -> None:
        """Atomic: written next to the target and renamed when complete."""
        from vcfusion.runio import atomic_write

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().cpu() for k, v in self.model.state_dict().items()}
        blob = {"format": WEIGHTS_FORMAT, "state_dict": state, "input_wh": list(self.input_wh),
                "class_ids": self.class_ids, "class_names": self.class_names, "widths": list(self.widths),
                "meta": self.meta}
        atomic_write(path, lambda tmp: torch.save(blob, tmp))

    @staticmethod
    def load(path) -> "DetectorModel":
        """Read a weights file; DetectorFileError names the file and the key or layer that is wrong."""
        path = Path(path)
        if not path.is_file():
            raise DetectorFileError(f"{path}: detector weights not found")
        try:
            blob = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same message
            raise DetectorFileError(f"{path}: not a vcfusion detector weights file ({exc.__class__.__name__}); "
                                    "expected one written by `vcfusion train-detector`") from None
        if not isinstance(blob, dict) or blob.get("format") != WEIGHTS_FORMAT:
            got = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
            raise DetectorFileError(f"{path}: format: expected {WEIGHTS_FORMAT!r}, got {got!r}")
        missing = [k for k in ("state_dict", "input_wh", "class_ids", "class_names", "widths") if k not in blob]
        if missing:
            raise DetectorFileError(f"{path}: missing keys {missing}; expected a file written by "
                                    "`vcfusion train-detector`")
        class_ids, widths, input_wh = _checked_header(path, blob)
        model = CenterNetLite(len(class_ids), widths[:4], widths[4])
        _check_state_dict(path, blob["state_dict"], model.state_dict())
        model.load_state_dict(blob["state_dict"])
        model.eval()
        return DetectorModel(model, input_wh, class_ids, [str(n) for n in blob["class_names"]],
                             widths, dict(blob.get("meta") or {}))


def _checked_header(path: Path, blob: dict) -> tuple[list[int], tuple[int, ...], tuple[int, int]]:
    def ints(key: str, n: int | None, expected: str) -> list[int]:
        value = blob[key]
        try:
            out = [int(v) for v in value]
        except (TypeError, ValueError):
            out = []
        if not out or (n is not None and len(out) != n) or (key != "class_ids" and min(out) <= 0):
            raise DetectorFileError(f"{path}: {key}: expected {expected}, got {value!r}")
        return out

    class_ids = ints("class_ids", None, "a list of category ids")
    widths = ints("widths", 5, "5 positive layer widths")
    input_wh = ints("input_wh", 2, "[width, height] in pixels")
    if input_wh[0] % 16 or input_wh[1] % 16:  # the network's stride: any other size fails at inference
        raise DetectorFileError(f"{path}: input_wh: expected multiples of 16, got {blob['input_wh']!r}")
    names = blob["class_names"]
    if not isinstance(names, (list, tuple)) or len(names) != len(class_ids):
        raise DetectorFileError(f"{path}: class_names: expected one name per class id ({len(class_ids)}), "
                                f"got {names!r}")
    return class_ids, tuple(widths), (input_wh[0], input_wh[1])


def _check_state_dict(path: Path, state, expected: dict) -> None:
    """Every layer of the network present with the shape the header implies."""
    if not isinstance(state, dict):
        raise DetectorFileError(f"{path}: state_dict: expected a mapping of layer names to tensors")
    missing = [k for k in expected if k not in state]
    unknown = [k for k in state if k not in expected]
    if missing or unknown:
        raise DetectorFileError(f"{path}: state_dict: expected the layers of CenterNetLite; "
                                f"missing {missing[:3]}, unknown {unknown[:3]}")
    for name, tensor in expected.items():
        got = tuple(getattr(state[name], "shape", ()))
        if got != tuple(tensor.shape):
            raise DetectorFileError(f"{path}: state_dict.{name}: expected shape {tuple(tensor.shape)}, got {got}")


@functools.lru_cache(maxsize=4)
def _check_weights_file(name: str, _mtime_ns: int) -> None:
    DetectorModel.load(name)


def check_weights(path) -> None:
    """Raise DetectorFileError if `path` is not a usable weights file (cached by path and modification
    time: a batch loads its scenario once per seed)."""
    path = Path(path)
    if not path.is_file():
        raise DetectorFileError(f"{path}: detector weights not found")
    _check_weights_file(str(path), path.stat().st_mtime_ns)


def inference_copy(model: nn.Module, device: str = "cpu") -> nn.Module:
    """A copy of `model` for inference only: each batch norm folded into the convolution before it
    (eval statistics; outputs equal to float rounding) and the weights in channels-last layout, the
    layout oneDNN's CPU convolutions run fastest in. The two together take the forward pass of the
    shipped network at 320x240 from ~25 to ~16 ms on two CPU threads (``python -m
    vcfusion.fusion.bench``). The model itself is left as it is (training goes on with it)."""
    from torch.nn.utils.fusion import fuse_conv_bn_eval

    folded = copy.deepcopy(model).eval()
    for seq in [m for m in folded.modules() if isinstance(m, nn.Sequential)]:
        for k in range(len(seq) - 1):
            conv, bn = seq[k], seq[k + 1]
            if isinstance(conv, nn.Conv2d) and isinstance(bn, nn.BatchNorm2d):
                seq[k], seq[k + 1] = fuse_conv_bn_eval(conv, bn), nn.Identity()
    return folded.to(device).to(memory_format=torch.channels_last)


class TorchDetector:
    """Our CNN in torch (CPU by default), run from an inference copy (:func:`inference_copy`)."""

    def __init__(self, weights, params: PostParams = PostParams(), device: str = "cpu", threads: int | None = None):
        self.net = weights if isinstance(weights, DetectorModel) else DetectorModel.load(weights)
        self.model = inference_copy(self.net.model, device)
        self.device = device
        self.params = params
        self.threads = threads or torch.get_num_threads()  # CPU threads of the forward pass

    def dense(self, image: np.ndarray) -> np.ndarray:
        # SUMO's steps set the calling thread's OpenMP thread count to 1 (libsumo bundles OpenMP
        # libraries, which bind to torch's OpenMP runtime when torch was loaded first): without
        # this the CNN ran single-threaded in every co-simulation, ~10 ms slower a tick
        if torch.get_num_threads() != self.threads:
            torch.set_num_threads(self.threads)
        x = torch.from_numpy(preprocess(image, self.net.input_wh)).to(self.device)
        with torch.inference_mode():
            return decode_dense(*self.model(x.contiguous(memory_format=torch.channels_last)))[0].cpu().numpy()

    def detect(self, image: np.ndarray) -> Detections:
        return postprocess(self.dense(image), image.shape[:2], self.net.input_wh, self.net.class_ids, self.params)


def export_onnx(net: DetectorModel, path, opset: int = 17) -> Path:
    """Write the model with its dense decoding as ONNX (input 'images' (1, 3, h, w) RGB 0..255,
    output 'detections' (1, N, 4 + C)); atomic. Needs the ``onnx`` package (dev extra)."""
    import warnings

    from vcfusion.runio import atomic_write

    path = Path(path)
    w, h = net.input_wh
    wrapper = _DenseExport(net.model.cpu().eval()).eval()

    def write(tmp: Path) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            # the TorchScript exporter: its graph (Conv, Resize, MaxPool, Exp, Equal) is what OpenCV DNN reads
            torch.onnx.export(wrapper, torch.zeros(1, 3, h, w), str(tmp), dynamo=False, opset_version=opset,
                              input_names=["images"], output_names=["detections"])

    atomic_write(path, write)
    return path


@dataclass(frozen=True)
class Letterbox:
    """Where an image sits in a letterboxed network input: input = image * (sx, sy) + (pad_x, pad_y)
    in pixel-edge coordinates."""

    sx: float
    sy: float
    pad_x: int
    pad_y: int


def letterbox(image: np.ndarray, input_wh: tuple[int, int]) -> tuple[np.ndarray, Letterbox]:
    """Ultralytics' letterbox (``LetterBox(auto=False)``): scale to fit keeping the aspect ratio
    (bilinear), centre, pad with grey 114; the same rounding, so the padding matches theirs."""
    w, h = input_wh
    ih, iw = image.shape[:2]
    r = min(w / iw, h / ih)
    nw, nh = int(round(iw * r)), int(round(ih * r))
    dw, dh = (w - nw) / 2, (h - nh) / 2
    top, left = int(round(dh - 0.1)), int(round(dw - 0.1))
    canvas = np.full((h, w, 3), 114, np.uint8)
    resized = image if (nw, nh) == (iw, ih) else cv2.resize(image, (nw, nh), interpolation=cv2.INTER_LINEAR)
    canvas[top:top + nh, left:left + nw] = resized
    return canvas, Letterbox(nw / iw, nh / ih, left, top)


def decode_yolo_output(out: np.ndarray, columns, image_hw: tuple[int, int], input_wh: tuple[int, int],
                       params: PostParams = PostParams(), objectness: bool = False,
                       box: Letterbox | None = None, source: str = "output") -> Detections:
    """One YOLO-style output -> detections in image pixels.

    ``out``: (1, N, K) or (1, K, N) (or without the batch axis) with K = 4 [+ 1 objectness] + C:
    box centre x, centre y, width, height in network-input pixels, then the C class scores.
    ``columns``: category id per class column, -1 for classes to drop. A candidate's class is its
    best column (as Ultralytics' NMS picks it); candidates whose best class is dropped are dropped.
    ``box``: the letterbox that made the input (None: the image was stretched to ``input_wh``).
    """
    out = np.asarray(out, dtype=np.float32)
    given = out.shape  # as the model gave it, batch axis included (the message named it without)
    if out.ndim == 3 and out.shape[0] == 1:
        out = out[0]
    width = 4 + len(columns) + (1 if objectness else 0)
    if out.ndim != 2 or width not in out.shape:
        raise DetectorFileError(f"{source}: expected (1, N, {width}) or (1, {width}, N) (4 box + "
                                f"{'1 objectness + ' if objectness else ''}{len(columns)} class values per "
                                f"candidate), got shape {given}")
    if out.shape[1] != width:
        out = out.T  # Ultralytics: (4 + C, N)
    columns = np.asarray(columns, dtype=np.int64)
    cls_scores = out[:, 5:] * out[:, 4:5] if objectness else out[:, 4:]
    best = cls_scores.argmax(axis=1) if len(out) else np.zeros(0, np.int64)
    wanted = columns[best] >= 0
    if box is not None:
        # back to the image's pixel-edge coordinates; then postprocess works at scale 1
        out = out.copy()
        out[:, 0] = (out[:, 0] - box.pad_x) / box.sx
        out[:, 1] = (out[:, 1] - box.pad_y) / box.sy
        out[:, 2] /= box.sx
        out[:, 3] /= box.sy
        input_wh = (image_hw[1], image_hw[0])
    rows = np.concatenate([out[wanted, :4], cls_scores[wanted] * (columns >= 0)], axis=1)
    kept = columns.copy()
    kept[kept < 0] = 0  # never chosen: their scores were zeroed above
    return postprocess(rows, image_hw, input_wh, kept, params, MAX_NMS_CANDIDATES)


class OnnxDetector:
    """An ONNX detector run through OpenCV's DNN module, for two layouts:

    - ours (:func:`export_onnx`): input (1, 3, h, w) RGB 0..255, image stretched to (w, h);
      output (1, N, 4 + C); ``class_ids`` maps the score columns to category ids;
    - the common Ultralytics export (:meth:`ultralytics`): input RGB / 255, letterboxed
      (grey 114); output (1, 4 + 80, N) for COCO-trained models; car, bus, truck kept by default.

    Other exports fit through the options: ``scale`` multiplies the 0..255 input, ``letterbox``
    pads instead of stretching, ``objectness`` reads (1, N, 5 + C) (YOLOv5). A ``class_ids``
    entry -1 drops that class. The output's orientation is recognised from its shape.
    """

    def __init__(self, path, input_wh: tuple[int, int], class_ids, params: PostParams = PostParams(),
                 scale: float = 1.0, objectness: bool = False, letterbox: bool = False):
        path = Path(path)
        if not path.is_file():
            raise DetectorFileError(f"{path}: ONNX model not found")
        try:
            self.net = cv2.dnn.readNetFromONNX(str(path))
        except cv2.error as exc:
            raise DetectorFileError(f"{path}: OpenCV DNN cannot read this ONNX model: {str(exc).strip()[:200]}") from None
        self.path = path
        self.input_wh = tuple(input_wh)
        self.class_ids = list(class_ids)
        self.params = params
        self.scale = scale
        self.objectness = objectness
        self.letterbox = letterbox

    @classmethod
    def ultralytics(cls, path, input_wh: tuple[int, int] = (640, 640), keep=YOLO_DEFAULT_CLASSES,
                    names=COCO80_NAMES, params: PostParams = PostParams()) -> "OnnxDetector":
        """A YOLO exported by Ultralytics (``yolo export format=onnx``; v8 and later)."""
        return cls(path, input_wh, coco_column_categories(keep, names), params, scale=1 / 255, letterbox=True)

    def dense(self, image: np.ndarray) -> tuple[np.ndarray, Letterbox | None]:
        """The network's raw output for an image and the letterbox used (None: stretched)."""
        if self.letterbox:
            canvas, geom = letterbox(image, self.input_wh)
            blob = canvas.transpose(2, 0, 1)[None].astype(np.float32)
        else:
            blob, geom = preprocess(image, self.input_wh), None
        self.net.setInput(np.ascontiguousarray(blob * np.float32(self.scale)))
        try:
            out = np.asarray(self.net.forward())
        except cv2.error as exc:
            raise DetectorFileError(f"{self.path}: OpenCV DNN failed on a (1, 3, {self.input_wh[1]}, "
                                    f"{self.input_wh[0]}) input (is that the model's input size?): "
                                    f"{str(exc).strip()[:200]}") from None
        return out, geom

    def detect(self, image: np.ndarray) -> Detections:
        out, geom = self.dense(image)
        return decode_yolo_output(out, self.class_ids, image.shape[:2], self.input_wh, self.params,
                                  self.objectness, geom, source=f"{self.path}: output")


@functools.lru_cache(maxsize=4)
def _check_yolo_file(name: str, _mtime_ns: int, input_wh: tuple[int, int], keep: tuple[str, ...]) -> None:
    # read, then one forward pass and decode on a grey frame: a file OpenCV cannot read, another
    # input size or another output layout fails here as it would on the first camera frame
    OnnxDetector.ultralytics(name, input_wh, keep).detect(np.full((input_wh[1], input_wh[0], 3), 114, np.uint8))


def check_yolo_model(path, input_wh: tuple[int, int], keep) -> None:
    """Raise DetectorFileError unless `path` is an ONNX YOLO that OpenCV runs at `input_wh` with the
    Ultralytics output layout (cached by path and modification time, like :func:`check_weights`)."""
    path = Path(path)
    if not path.is_file():
        raise DetectorFileError(f"{path}: ONNX model not found")
    _check_yolo_file(str(path), path.stat().st_mtime_ns, tuple(input_wh), tuple(keep))


