"""What makes a highlight right, wrong or missed: the one definition used by the identification
study, the guidance study (model and person trips alike) and `vcfusion explain-highlights`.

A highlight is judged in one camera frame, for one twin the cloud means (a warning in the guidance
study, a target in the identification study), against the frame's ground truth (scoring only:
nothing here is shown to a driver or given to a detector):

- the twin's vehicle is **visible** when the frame has a ground-truth box for it (its pixels in the
  instance map, `vcfusion.render.gt_boxes`) of at least `MIN_VISIBLE_PX` pixels;
- **right**: a box is drawn for the twin and its IoU with that vehicle's ground-truth box is at
  least `RIGHT_IOU`;
- **wrong**: a box is drawn for the twin and it is not right (on another vehicle, on part of it,
  on none, or drawn for a twin whose vehicle the frame does not show);
- **missed**: the twin's vehicle is visible and no box is drawn for it;
- **unseen**: the twin's vehicle is not visible and no box is drawn (hidden behind another
  vehicle, too small, or outside the image: the driver could not see it either); not counted as
  a miss, counted on its own.

The identification study's accuracy at a threshold is right / (right + wrong + missed) over the
visible targets at that threshold (its curve varies `iou_threshold`); the guidance study counts
episodes (runs of consecutive frames of one twin with one outcome and one vehicle in the box).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# IoU of the drawn box with the meant vehicle's visible box at or above which the highlight shows
# that vehicle: 0.5, the PASCAL VOC / COCO AP50 rule for "this box is that object"; the
# identification study reports its accuracy at 0.5 to 0.95 and names 0.7 in its headline.
RIGHT_IOU = 0.5
# fewest pixels of a vehicle's visible box for it to be judged (a target of the identification
# study, a vehicle the driver can be expected to see): 100 px, about 10 x 10 px, a car at ~140 m
# with the shipped 90-degree 640 px camera.
MIN_VISIBLE_PX = 100.0
OUTCOMES = ("right", "wrong", "missed", "unseen")


@dataclass(frozen=True)
class Judgement:
    outcome: str  # one of OUTCOMES
    iou: float  # IoU of the drawn box with the meant vehicle's ground-truth box (0: none drawn or not visible)
    visible_px: float  # area of the meant vehicle's ground-truth box, 0 when it has none
    box_vehicle_id: str  # the vehicle whose ground-truth box the drawn box overlaps most ("" : none / no box)


def gt_box_of(vehicle_id: str, gt_boxes, gt_ids) -> np.ndarray | None:
    """The ground-truth box (x1, y1, x2, y2) of `vehicle_id` in a frame, or None."""
    for box, vid in zip(np.asarray(gt_boxes, dtype=float).reshape(-1, 4), gt_ids):
        if vid == vehicle_id:
            return box
    return None


def judge_highlight(vehicle_id: str, box, gt_boxes, gt_ids, right_iou: float = RIGHT_IOU,
                    min_visible_px: float = MIN_VISIBLE_PX) -> Judgement:
    """The outcome of drawing `box` (x1, y1, x2, y2, or None for nothing drawn) for the twin
    `vehicle_id` in a frame whose ground-truth boxes are `gt_boxes` of vehicles `gt_ids`."""
    from vcfusion.fusion.matching import box_iou

    gt = np.asarray(gt_boxes, dtype=float).reshape(-1, 4)
    own = gt_box_of(vehicle_id, gt, gt_ids)
    area = 0.0 if own is None else float((own[2] - own[0]) * (own[3] - own[1]))
    visible = area >= min_visible_px
    if box is None:
        return Judgement("missed" if visible else "unseen", 0.0, area, "")
    b = np.asarray(box, dtype=float).reshape(1, 4)
    ious = box_iou(b, gt)[0] if len(gt) else np.zeros(0)
    best = str(gt_ids[int(np.argmax(ious))]) if len(ious) and ious.max() > 0 else ""
    iou = float(box_iou(b, own[None])[0, 0]) if own is not None else 0.0
    right = iou >= right_iou - 1e-12  # on the meant vehicle, however small it is
    return Judgement("right" if right else "wrong", iou, area, vehicle_id if right else best)


def instance_boxes(instances, vehicle_ids) -> tuple[np.ndarray, tuple[str, ...]]:
    """Each vehicle's visible box in an instance map (-1: no vehicle; k: vehicle_ids[k]): the
    bounding box (x1, y1, x2, y2) px of its visible pixels, x2 and y2 one past the last pixel, for
    judging a box drawn on a frame that carries no ground-truth boxes (a person's display)."""
    if instances is None:
        return np.zeros((0, 4)), ()
    inst = np.asarray(instances)
    rows, cols = np.nonzero(inst >= 0)
    if not len(rows):
        return np.zeros((0, 4)), ()
    labels = inst[rows, cols]
    boxes, ids = [], []
    for k in np.unique(labels):
        r, c = rows[labels == k], cols[labels == k]
        boxes.append((c.min(), r.min(), c.max() + 1, r.max() + 1))
        ids.append(str(vehicle_ids[int(k)]))
    return np.asarray(boxes, dtype=float), tuple(ids)
