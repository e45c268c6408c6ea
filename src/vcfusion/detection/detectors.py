"""Object detectors behind one small interface: an RGB image in; boxes, scores, classes out.

Implementations:
- :class:`OracleDetector`: the renderer's ground-truth boxes (for ablations), optionally degraded
  (pixel jitter, missed detections) with a seeded generator;
- :class:`vcfusion.detection.detector_net.TorchDetector`: our learned single-stage CNN;
- :class:`vcfusion.detection.detector_net.OnnxDetector`: a user's ONNX detector through OpenCV DNN.

Images are RGB uint8 (H, W, 3); boxes are float pixels x1, y1, x2, y2 in the image given, in the
project's pixel-centre convention (OpenCV: integer coordinates at pixel centres, so a box around
pixels c0..c1 spans c0 - 0.5 .. c1 + 0.5; a COCO bbox [x, y, w, h] is x - 0.5 .. x + w - 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Detections:
    boxes: np.ndarray  # (N, 4) float32 x1, y1, x2, y2 px
    scores: np.ndarray  # (N,) float32 in [0, 1]
    classes: np.ndarray  # (N,) int64 category ids (the dataset's COCO category ids)

    def __post_init__(self):
        n = len(self.boxes)
        if np.shape(self.boxes) != (n, 4) or len(self.scores) != n or len(self.classes) != n:
            raise ValueError(f"Detections: expected boxes (N, 4), scores (N,), classes (N,); got "
                             f"{np.shape(self.boxes)}, {np.shape(self.scores)}, {np.shape(self.classes)}")

    def __len__(self) -> int:
        return len(self.boxes)

    @staticmethod
    def empty() -> "Detections":
        return Detections(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64))

    @staticmethod
    def of(boxes, scores, classes) -> "Detections":
        return Detections(np.asarray(boxes, np.float32).reshape(-1, 4), np.asarray(scores, np.float32).reshape(-1),
                          np.asarray(classes, np.int64).reshape(-1))

    def select(self, index) -> "Detections":
        return Detections(self.boxes[index], self.scores[index], self.classes[index])


class Detector(Protocol):
    def detect(self, image: np.ndarray) -> Detections: ...


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy non-maximum suppression; indices kept, highest score first."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    order = np.argsort(-np.asarray(scores), kind="stable")
    area = np.clip(boxes[:, 2] - boxes[:, 0], 0, None) * np.clip(boxes[:, 3] - boxes[:, 1], 0, None)
    keep = []
    while len(order):
        i = order[0]
        keep.append(i)
        rest = order[1:]
        w = np.clip(np.minimum(boxes[i, 2], boxes[rest, 2]) - np.maximum(boxes[i, 0], boxes[rest, 0]), 0, None)
        h = np.clip(np.minimum(boxes[i, 3], boxes[rest, 3]) - np.maximum(boxes[i, 1], boxes[rest, 1]), 0, None)
        inter = w * h
        union = area[i] + area[rest] - inter
        iou = np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)


def batched_nms(boxes, scores, classes, iou_threshold: float) -> np.ndarray:
    """NMS within each class (boxes of different classes never suppress each other)."""
    classes = np.asarray(classes)
    keep = [np.flatnonzero(classes == c)[nms(np.asarray(boxes)[classes == c], np.asarray(scores)[classes == c],
                                                iou_threshold)] for c in np.unique(classes)]
    if not keep:
        return np.zeros(0, np.int64)
    keep = np.concatenate(keep)
    return keep[np.argsort(-np.asarray(scores)[keep], kind="stable")]


# The 80 class names of the COCO detection benchmark in the column order of Ultralytics (and
# most YOLO) exports trained on COCO.
COCO80_NAMES = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat", "traffic light",
    "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog", "horse", "sheep", "cow",
    "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella", "handbag", "tie", "suitcase", "frisbee",
    "skis", "snowboard", "sports ball", "kite", "baseball bat", "baseball glove", "skateboard", "surfboard",
    "tennis racket", "bottle", "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple",
    "sandwich", "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch",
    "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard", "cell phone", "microwave",
    "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase", "scissors", "teddy bear", "hair drier",
    "toothbrush")
assert len(COCO80_NAMES) == 80
YOLO_DEFAULT_CLASSES = ("car", "bus", "truck")
# COCO class names whose vcfusion category (vcfusion.records.VEHICLE_CATEGORIES) has another name
_CATEGORY_OF_COCO = {"car": "passenger"}


def coco_column_categories(keep=YOLO_DEFAULT_CLASSES, names=COCO80_NAMES) -> list[int]:
    """Category id per score column of a COCO-trained YOLO: our id for the kept classes, -1 for
    the others (their candidates are dropped)."""
    from vcfusion.records import VEHICLE_CATEGORIES as CATEGORIES  # the datasets' fixed category ids

    keep = list(keep)
    unknown = [k for k in keep if k not in names]
    if unknown or not keep:
        raise ValueError(f"classes: expected COCO class names such as car, bus, truck, got {unknown or keep}")
    columns = []
    for name in names:
        if name not in keep:
            columns.append(-1)
            continue
        ours = _CATEGORY_OF_COCO.get(name, name)
        if ours not in CATEGORIES:
            raise ValueError(f"classes: COCO class {name!r} has no vcfusion category "
                             f"(kept classes must be one of car, {', '.join(c for c in CATEGORIES if c != 'passenger')})")
        columns.append(CATEGORIES.index(ours) + 1)
    return columns


class OracleDetector:
    """Ground-truth boxes as detections (score 1), for ablations of the matchers.

    Call :meth:`set_truth` with the frame's ground-truth boxes before :meth:`detect`. Optional
    degradations (off by default): each box edge jittered by N(0, jitter_px) and each box missed
    with probability ``miss_probability``, drawn from the given generator.
    """

    def __init__(self, jitter_px: float = 0.0, miss_probability: float = 0.0,
                 rng: np.random.Generator | None = None):
        if jitter_px < 0 or not 0.0 <= miss_probability <= 1.0:
            raise ValueError("OracleDetector: expected jitter_px >= 0 and 0 <= miss_probability <= 1")
        self.jitter_px = jitter_px
        self.miss_probability = miss_probability
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self._truth = Detections.empty()

    def set_truth(self, boxes, classes=None) -> None:
        boxes = np.asarray(boxes, np.float32).reshape(-1, 4)
        classes = np.zeros(len(boxes), np.int64) if classes is None else classes
        self._truth = Detections.of(boxes, np.ones(len(boxes)), classes)

    def detect(self, image: np.ndarray) -> Detections:
        det = self._truth
        if self.miss_probability > 0 and len(det):
            det = det.select(self.rng.random(len(det)) >= self.miss_probability)
        if self.jitter_px > 0 and len(det):
            boxes = det.boxes + self.rng.normal(0.0, self.jitter_px, det.boxes.shape).astype(np.float32)
            boxes = np.concatenate([np.minimum(boxes[:, :2], boxes[:, 2:]), np.maximum(boxes[:, :2], boxes[:, 2:])], 1)
            if image is not None:
                h, w = image.shape[:2]
                boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(0, w)
                boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(0, h)
            det = Detections(boxes, det.scores, det.classes)
        return det
