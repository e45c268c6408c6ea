"""How well a far-box head places the detector's boxes on rendered scenes: each detector box matched
to a ground-truth box (IoU >= 0.4), grouped by the ground truth's height, with its IoU as detected
and after the head (`vcfusion.fusion.far_boxes.BoxHead.refine`, mirror average included), and the
share at IoU >= 0.7; the pooled row covers ground-truth boxes up to 60 px high (the far boxes the
head is for). The selection check of the model card (`docs/model-cards.md`, far_box_head.pt):

    python tools/box_head_check.py src/vcfusion/assets/far_box_head.pt data/box-val [HEAD2 ...]
"""

from __future__ import annotations

import argparse

import numpy as np

from vcfusion.detection.detector_net import TorchDetector, default_weights_path
from vcfusion.detection.detector_train import load_coco_many, read_rgb
from vcfusion.fusion.far_boxes import BoxHead
from vcfusion.fusion.matching import box_iou

MATCH_IOU = 0.4  # a detector box belongs to the ground-truth box it overlaps most, if at least this much
HEIGHT_BINS_PX = ((0, 15), (15, 30), (30, 60), (60, 120), (120, np.inf))
FAR_PX = 60.0  # the pooled row: ground-truth boxes up to this height


def box_pairs(folders, head: BoxHead) -> np.ndarray:
    """(N, 3): ground-truth height (px), IoU of the detector's box, IoU of the head's box."""
    ds = load_coco_many(folders)
    detector = TorchDetector(default_weights_path())
    rows = []
    for k, path in enumerate(ds.images):
        image = read_rgb(path)
        boxes, truth = detector.detect(image).boxes, ds.boxes[k]
        if not len(boxes) or not len(truth):
            continue
        iou = box_iou(boxes, truth)
        best = iou.max(axis=1)  # each detector box's IoU with the ground-truth box it overlaps most
        matched = best >= MATCH_IOU
        if not matched.any():
            continue
        boxes, truth = boxes[matched], truth[iou.argmax(axis=1)[matched]]
        placed = head.refine(image, boxes)
        rows += zip(truth[:, 3] - truth[:, 1], best[matched], np.diag(box_iou(placed, truth)))
    return np.array(rows, dtype=float).reshape(-1, 3)


def summary_lines(pairs: np.ndarray) -> list[str]:
    lines = []
    groups = [(f"{lo:g}-{hi:g} px", (pairs[:, 0] >= lo) & (pairs[:, 0] < hi)) for lo, hi in HEIGHT_BINS_PX]
    groups.append((f"pooled <= {FAR_PX:g} px", pairs[:, 0] <= FAR_PX))
    for name, sel in groups:
        s = pairs[sel]
        if len(s):
            lines.append(f"{name:>16} n={len(s):4d}: IoU {s[:, 1].mean():.3f} -> {s[:, 2].mean():.3f}; "
                         f">= 0.7 {np.mean(s[:, 1] >= 0.7):.1%} -> {np.mean(s[:, 2] >= 0.7):.1%}")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("heads", nargs="+", help="head weights files, then the COCO folder(s) (the last arguments "
                                             "that are folders)")
    args = ap.parse_args(argv)
    from pathlib import Path

    heads = [a for a in args.heads if not Path(a).is_dir()]
    folders = [a for a in args.heads if Path(a).is_dir()]
    if not heads or not folders:
        ap.error("expected one or more head weights files and one or more rendered COCO folders")
    for weights in heads:
        print(f"{weights}: detector's box -> head's box")
        for line in summary_lines(box_pairs(folders, BoxHead.load(weights))):
            print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
