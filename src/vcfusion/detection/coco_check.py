"""`vcfusion coco-check`: does a detector trained on photographs (MS COCO) see our rendered vehicles?

A measuring instrument for the renders' realism (issue 18): the share of *clearly visible*
rendered vehicles (unoccluded, untruncated, at least ``min_width_px`` wide) that a COCO detector
finds as car, bus or truck (IoU >= 0.5 with the ground-truth box, score >= 0.3). The detector is
the user's ONNX file; the project neither ships nor needs one.

The ONNX layout read here is the grid layout of FastestDet-style single-stage detectors:
input (1, 3, S, S) BGR / 255 (plain resize); output (1, 5 + C, Gh, Gw), per cell: objectness
(probability), centre offset x and y within the cell (tanh applied here), box width and height
relative to the image (logistic applied here), then C class probabilities. A cell's score is
objectness^0.6 * class^0.4 for its most likely class (FastestDet's own decoding), then NMS.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from vcfusion.detection.detectors import Detections, batched_nms

# MS COCO's 80-class order, 0-based: car 2, bus 5, truck 7.
COCO_VEHICLE_CLASSES = {2: "car", 5: "bus", 7: "truck"}


class CheckInputError(ValueError):
    """A model or dataset file that cannot be used; the message names the file and what was expected."""


class GridOnnxDetector:
    """An ONNX detector in the grid layout above, run through OpenCV DNN. Classes are 0-based COCO indices."""

    def __init__(self, path, nms_iou: float = 0.45, min_score: float = 0.05):
        path = Path(path)
        if not path.is_file():
            raise CheckInputError(f"{path}: ONNX model not found")
        try:
            self.net = cv2.dnn.readNetFromONNX(str(path))
        except cv2.error as exc:
            raise CheckInputError(f"{path}: OpenCV DNN cannot read this ONNX model: {str(exc).strip()[:200]}") from None
        self.path = path
        self.nms_iou = nms_iou
        self.min_score = min_score
        self.input_size: int | None = None

    def _forward(self, image_bgr: np.ndarray, size: int) -> np.ndarray:
        blob = cv2.resize(image_bgr, (size, size), interpolation=cv2.INTER_LINEAR).astype(np.float32) / 255.0
        self.net.setInput(np.ascontiguousarray(blob.transpose(2, 0, 1)[None]))
        return np.asarray(self.net.forward())

    def _size(self, image_bgr: np.ndarray) -> int:
        """The square input size: from the model's first layer when OpenCV reports it, else tried."""
        if self.input_size is None:
            got = []  # what each tried size gave: the error says what the model is, not only what it is not
            for size in (352, 320, 416, 512, 256, 640):
                try:
                    out = self._forward(image_bgr, size)
                except cv2.error:
                    got.append(f"{size}: no output")
                    continue
                if out.ndim == 4 and out.shape[1] > 5:
                    self.input_size = size
                    break
                got.append(f"{size}: output {tuple(out.shape)}")
            else:
                raise CheckInputError(f"{self.path}: expected a (1, 3, S, S) input and a (1, 5 + C, H, W) grid output; "
                                      f"inputs of S = {'; '.join(got)}")
        return self.input_size

    def detect_rgb(self, rgb: np.ndarray) -> Detections:
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        out = self._forward(bgr, self._size(bgr))
        if out.ndim != 4 or out.shape[0] != 1 or out.shape[1] <= 5:
            raise CheckInputError(f"{self.path}: output: expected (1, 5 + C, H, W), got {out.shape}")
        return decode_grid(out[0], rgb.shape[:2], self.min_score, self.nms_iou)


def decode_grid(grid: np.ndarray, image_hw: tuple[int, int], min_score: float, nms_iou: float) -> Detections:
    """(5 + C, Gh, Gw) grid output -> detections in image pixels (x1, y1, x2, y2; pixel-centre convention)."""
    _, gh, gw = grid.shape
    cells = grid.reshape(grid.shape[0], -1).T.astype(np.float64)  # (Gh * Gw, 5 + C), row-major cells
    cls = np.argmax(cells[:, 5:], axis=1)
    score = np.clip(cells[:, 0], 0, 1) ** 0.6 * np.clip(cells[np.arange(len(cells)), 5 + cls], 0, 1) ** 0.4
    keep = score >= min_score
    rows, cols = np.divmod(np.arange(len(cells)), gw)
    cx = (cols + np.tanh(cells[:, 1])) / gw
    cy = (rows + np.tanh(cells[:, 2])) / gh
    bw, bh = 1.0 / (1.0 + np.exp(-cells[:, 3])), 1.0 / (1.0 + np.exp(-cells[:, 4]))
    h, w = image_hw
    boxes = np.column_stack([(cx - bw / 2) * w, (cy - bh / 2) * h, (cx + bw / 2) * w, (cy + bh / 2) * h]) - 0.5
    boxes, score, cls = boxes[keep], score[keep], cls[keep]
    order = batched_nms(boxes, score, cls, nms_iou)
    return Detections.of(boxes[order], score[order], cls[order])


def iou_one_to_many(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    w = np.clip(np.minimum(box[2], boxes[:, 2]) - np.maximum(box[0], boxes[:, 0]), 0, None)
    h = np.clip(np.minimum(box[3], boxes[:, 3]) - np.maximum(box[1], boxes[:, 1]), 0, None)
    inter = w * h
    union = (box[2] - box[0]) * (box[3] - box[1]) + (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]) - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


@dataclass
class FolderResult:
    folder: str
    images: int = 0
    vehicles: int = 0  # clearly visible vehicles checked
    found: int = 0
    best_scores: list = field(default_factory=list)  # per vehicle: best vehicle-class score at IoU >= iou
    labels: dict = field(default_factory=dict)  # what the best-overlapping detection called it -> count

    @property
    def share(self) -> float:
        return self.found / self.vehicles if self.vehicles else float("nan")


def clearly_visible(ann: dict, min_width_px: float) -> bool:
    """Unoccluded (visible fraction >= 0.99), not cut by the image border, at least min_width_px wide."""
    vis = ann.get("visible_fraction")
    return (vis is not None and vis >= 0.99 and float(ann.get("truncation", 1.0)) <= 0.0
            and float(ann["bbox"][2]) >= min_width_px)


def check_folder(detector: GridOnnxDetector, folder, min_width_px: float = 40.0, iou: float = 0.5,
                 score: float = 0.3, class_names: list[str] | None = None) -> FolderResult:
    folder = Path(folder)
    path = folder / "annotations.json"
    if not path.is_file():
        raise CheckInputError(f"{folder}: expected a `vcfusion render` folder with annotations.json")
    try:
        coco = json.loads(path.read_text())
        images = {img["id"]: img for img in coco["images"]}
        anns = coco["annotations"]
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise CheckInputError(f"{path}: expected COCO JSON with images and annotations ({exc})") from None
    wanted: dict[int, list[dict]] = {}
    for ann in anns:
        if clearly_visible(ann, min_width_px):
            wanted.setdefault(ann["image_id"], []).append(ann)
    result = FolderResult(str(folder), images=len(images))
    for image_id, targets in sorted(wanted.items()):
        file = folder / images[image_id]["file_name"]
        bgr = cv2.imread(str(file), cv2.IMREAD_COLOR)
        if bgr is None:
            raise CheckInputError(f"{path}: images[id={image_id}].file_name: cannot read {file}")
        dets = detector.detect_rgb(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        vehicle = np.isin(dets.classes, list(COCO_VEHICLE_CLASSES))
        for ann in targets:
            x, y, w, h = map(float, ann["bbox"])
            gt = np.array([x - 0.5, y - 0.5, x + w - 0.5, y + h - 0.5])
            overlaps = iou_one_to_many(gt, dets.boxes) if len(dets) else np.zeros(0)
            hit = overlaps >= iou
            best = float(dets.scores[hit & vehicle].max()) if np.any(hit & vehicle) else 0.0
            result.vehicles += 1
            result.found += best >= score
            result.best_scores.append(best)
            if len(dets) and overlaps.max() > 0.3:
                k = int(np.argmax(np.where(overlaps > 0.3, dets.scores, -1)))
                c = int(dets.classes[k])
                name = class_names[c] if class_names and c < len(class_names) else str(c)
                result.labels[name] = result.labels.get(name, 0) + 1
            else:
                result.labels["(nothing)"] = result.labels.get("(nothing)", 0) + 1
    return result
