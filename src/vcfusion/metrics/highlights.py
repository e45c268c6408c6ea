"""What makes a highlight right, wrong or missed: the one definition used by the identification
study, the guidance study (model and person trips alike) and `vcfusion explain-highlights`.

A highlight is judged in one camera frame, for one twin the cloud means (a warning in the guidance
study, a target in the identification study), against the frame's ground truth (scoring only:
nothing here is shown to a driver or given to a detector):

- the twin's vehicle is **visible** when the box around its largest connected patch of pixels in
  the instance map (`vcfusion.render.gt_boxes`: the part of it a person sees; pixels scattered
  between a nearer truck's wheels are not a view of it) is at least `MIN_VISIBLE_PX` pixels and
  covers at least `MIN_VISIBLE_SHARE` of its outline (the box around the part of its 3D box's
  projection inside the image: a sliver of a vehicle behind another is not a vehicle to see);
- **right**: a box is drawn for the twin and its IoU with that vehicle's visible box (the box
  around its largest patch, as above) is at least `RIGHT_IOU`;
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
# fewest pixels of a vehicle's visible box (the box around its largest connected patch) for it to
# be judged (a target of the identification study, a vehicle the driver can be expected to see):
# 100 px, about 10 x 10 px, a car at ~140 m with the shipped 90-degree 640 px camera.
MIN_VISIBLE_PX = 100.0
# least share of a vehicle's outline (the box around its projected 3D box's part inside the image)
# that its visible box covers for it to be judged: 0.2, the visibility floor of the CityPersons
# benchmark's "All" and "Heavy occlusion" settings (visible box area / full box area; Zhang,
# Benenson and Schiele, CVPR 2017), below which an object is neither a target nor a miss.
# Registered before it was written (docs/components/guidance-loop.md), from the development seeds
# curved 307/309/310, where most missed updates were slivers of 112-360 px beside a nearer vehicle
# (15 of the fusion arm's 28 are under 0.2; the other 13 are small far cars showing 0.9 of their
# outlines). The largest patch and the in-image outline were registered the same way, from the
# curved development seeds 300-315 (7 of 10 missed episodes: a strip beside a nearer truck plus
# pixels seen between its wheels).
MIN_VISIBLE_SHARE = 0.2
OUTCOMES = ("right", "wrong", "missed", "unseen")


@dataclass(frozen=True)
class Judgement:
    outcome: str  # one of OUTCOMES
    iou: float  # IoU of the drawn box with the meant vehicle's visible box (0: none drawn or not in the frame)
    visible_px: float  # area of the meant vehicle's visible box, 0 when it has none
    visible_share: float  # that area over its outline's (gt_boxes.visible_shares), 0 when it has none
    box_vehicle_id: str  # the vehicle whose visible box the drawn box overlaps most ("" : none / no box)
    visible: bool  # the meant vehicle is visible (is_visible of its box and share): a target, nothing drawn a miss


def is_visible(area_px: float, share: float, min_visible_px: float = MIN_VISIBLE_PX) -> bool:
    """Whether a vehicle whose visible box is `area_px` pixels, `share` of its outline, is visible."""
    return area_px >= min_visible_px and share >= MIN_VISIBLE_SHARE


def judge_highlight(vehicle_id: str, box, gt_boxes, gt_ids, gt_visible_share=None, right_iou: float = RIGHT_IOU,
                    min_visible_px: float = MIN_VISIBLE_PX) -> Judgement:
    """The outcome of drawing `box` (x1, y1, x2, y2, or None for nothing drawn) for the twin
    `vehicle_id` in a frame whose vehicles `gt_ids` show the visible boxes `gt_boxes` (the boxes
    around their largest patches of pixels, CameraFrame.visible_boxes), covering
    `gt_visible_share` of their outlines (None: frames without outlines, such as a person's display
    judged from its instance map, where only the drawn box's owner is asked for; every share 1)."""
    from vcfusion.fusion.matching import box_iou

    gt = np.asarray(gt_boxes, dtype=float).reshape(-1, 4)
    k = next((j for j, vid in enumerate(gt_ids) if vid == vehicle_id), None)
    own = None if k is None else gt[k]
    area = 0.0 if own is None else float((own[2] - own[0]) * (own[3] - own[1]))
    share = 0.0 if own is None else 1.0 if gt_visible_share is None else float(gt_visible_share[k])
    visible = is_visible(area, share, min_visible_px)
    if box is None:
        return Judgement("missed" if visible else "unseen", 0.0, area, share, "", visible)
    b = np.asarray(box, dtype=float).reshape(1, 4)
    ious = box_iou(b, gt)[0] if len(gt) else np.zeros(0)
    best = str(gt_ids[int(np.argmax(ious))]) if len(ious) and ious.max() > 0 else ""
    iou = float(box_iou(b, own[None])[0, 0]) if own is not None else 0.0
    right = iou >= right_iou - 1e-12  # on the meant vehicle, however small it is
    return Judgement("right" if right else "wrong", iou, area, share, vehicle_id if right else best, visible)


def instance_boxes(instances, vehicle_ids) -> tuple[np.ndarray, tuple[str, ...]]:
    """Each vehicle's visible box in an instance map (-1: no vehicle; k: vehicle_ids[k]): the
    bounding box (x1, y1, x2, y2) px of its largest 8-connected patch of pixels, x2 and y2 one past
    the last pixel, for judging a box drawn on a frame that carries no ground-truth boxes (a
    person's display)."""
    from vcfusion.render.gt_boxes import largest_patch_box

    if instances is None:
        return np.zeros((0, 4)), ()
    inst = np.asarray(instances)
    rows, cols = np.nonzero(inst >= 0)
    if not len(rows):
        return np.zeros((0, 4)), ()
    labels = inst[rows, cols]
    boxes, ids = [], []
    for k in np.unique(labels):
        boxes.append(np.add(largest_patch_box(rows[labels == k], cols[labels == k]), 0.5))
        ids.append(str(vehicle_ids[int(k)]))
    return np.asarray(boxes, dtype=float), tuple(ids)


def warning_hold_s() -> float:
    """How long a highlight gap goes unnoticed: the driver model's warning hold (a warning stays
    active this long after it was last shown, vcfusion.driver.params.DriverParams.warning_hold_s)."""
    from vcfusion.driver.params import DriverParams

    return float(DriverParams.warning_hold_s)


@dataclass(frozen=True)
class Episode:
    """A warning episode of one twin: consecutive AR updates with one outcome and one vehicle in
    the box. `rows`: positions (in the judged table given) of its updates; `bridged`: updates
    without a box inside it that the hold spans (see :func:`warning_episodes`)."""

    twin: str
    outcome: str
    box_vehicle_id: str
    rows: tuple[int, ...]
    bridged: int = 0


def warning_episodes(judged, period_s: float, hold_s: float | None = None) -> list[Episode]:
    """The warning episodes of judged rows (a DataFrame with ``time``, ``vehicle_id``,
    ``outcome``, ``box_vehicle_id``; one row per warned twin and AR update), in order of start.

    An episode is a run of updates of one twin with one outcome and one vehicle in the box, a gap
    of more than 1.5 periods ending it. Where a box drawn on one vehicle is missing for at most
    `hold_s` (default :func:`warning_hold_s`, 0.3 s: three 0.1 s updates) between two right runs
    (the box on the twin's vehicle before and after), the gap is no episode of its own (no missed
    or unseen warning): the warning the driver sees spans it, as the driver model's does (a flicker
    of the box); the two right runs are one episode and the gap's updates are counted as `bridged`.
    Nothing else is bridged: a wrong box that flickers is a wrong episode each time it appears, and
    a gap before the first box or after the last is a missed (or unseen) episode however short."""
    hold_s = warning_hold_s() if hold_s is None else hold_s
    episodes: list[Episode] = []
    if judged is None or not len(judged):
        return episodes
    t_all = judged["time"].to_numpy(dtype=float)
    twins = judged["vehicle_id"].astype(str).to_numpy()
    outcomes = judged["outcome"].astype(str).to_numpy()
    shown = judged["box_vehicle_id"].fillna("").astype(str).to_numpy()
    for twin in dict.fromkeys(twins):
        idx = np.flatnonzero(twins == twin)
        idx = idx[np.argsort(t_all[idx], kind="stable")]
        runs: list[list] = []  # [outcome, shown, positions, bridged]
        for k in idx:
            last = runs[-1] if runs else None
            if (last is not None and last[0] == outcomes[k] and last[1] == shown[k]
                    and t_all[k] - t_all[last[2][-1]] <= 1.5 * period_s + 1e-9):
                last[2].append(int(k))
            else:
                runs.append([outcomes[k], shown[k], [int(k)], 0])
            # a short gap without a box between two right runs on the same vehicle: one episode
            if (len(runs) >= 3 and runs[-1][0] == "right" and runs[-2][0] in ("missed", "unseen")
                    and (runs[-1][0], runs[-1][1]) == (runs[-3][0], runs[-3][1])):
                a, gap, b = runs[-3], runs[-2], runs[-1]
                span = t_all[b[2][0]] - t_all[a[2][-1]] - period_s  # the time without a box
                joined = (t_all[gap[2][0]] - t_all[a[2][-1]] <= 1.5 * period_s + 1e-9
                          and t_all[b[2][0]] - t_all[gap[2][-1]] <= 1.5 * period_s + 1e-9)
                if joined and span <= hold_s + 1e-9:
                    runs[-3:] = [[a[0], a[1], a[2] + b[2], a[3] + gap[3] + len(gap[2])]]
        episodes += [Episode(str(twin), o, s, tuple(p), n) for o, s, p, n in runs]
    episodes.sort(key=lambda e: (t_all[e.rows[0]], e.twin))
    return episodes
