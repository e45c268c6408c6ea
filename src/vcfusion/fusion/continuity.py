"""Continuity of the box drawn for a twin from one AR update to the next.

The overlay is a display for a person, refreshed every AR update (0.1 s). Over one update a
vehicle's image moves as its twin's projected outline moves (the twin's own reports, GNSS-smoothed
and moved on by their latency, seen from the ego's camera as it moves): a little. A detector box
that suddenly covers half of the vehicle, or reaches far past it, for one update while the twin's
outline barely changes is a detection glitch, not the vehicle. As a tracker's filter does, the
display then draws the mean of the new box and the previous box moved as the outline moved, for
that one update, and takes the new box as given if it is still there at the next update (a real
change then shows halfway for one update, 0.1 s).

Twin data and detections only: nothing here reads ground truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vcfusion.fusion.matching import box_iou

# The IoU, with the previous update's drawn box moved as the twin's outline moved, below which a
# twin's new box is a jump the twin's motion does not explain: the mean of the two is drawn for
# that one update instead. Chosen on development seeds (curved.yaml 114-117, fusion arm, the
# recorded AR updates re-drawn; docs/components/guidance-loop.md, rule 5): at 0.4 / 0.5 / 0.6 /
# 0.7 / 0.8 the rule draws 13 / 19 / 33 / 75 / 312 of 6,231 drawn boxes as a mean; from 0.7 it
# makes both warned one-update IoU misses right (0.4-0.6: one of them), and at every value it
# makes no warned box wrong (one unwarned); 0.7: the fewest changed boxes that do.
MIN_CONTINUITY_IOU = 0.7
# The most consecutive AR updates drawn as such a mean: one, so that a real change (the matcher
# giving the twin another box that stays) shows whole one update (0.1 s) late.
MAX_HELD_UPDATES = 1


@dataclass(frozen=True)
class _Drawn:
    box: np.ndarray  # (4,) px, the box drawn
    outline: np.ndarray | None  # (4,) px, the twin's projected outline then
    held: int  # consecutive updates this box was a mean with the moved previous box


def _cut(outline: np.ndarray, width: int, height: int) -> bool:
    """Whether the image's side cuts the outline (then its size is not the vehicle's)."""
    e = outline
    return bool(e[0] <= 0.5 or e[1] <= 0.5 or e[2] >= width - 1.5 or e[3] >= height - 1.5)


def _unpredictable(outline, width: int, height: int) -> bool:
    """Whether an outline cannot say how its vehicle's box moves: missing, empty or cut by the image's side."""
    return outline is None or outline[2] <= outline[0] or outline[3] <= outline[1] or _cut(outline, width, height)


def moved_box(box, outline_before, outline_now, width: int, height: int) -> np.ndarray:
    """`box` (x1, y1, x2, y2 px) moved and scaled per axis as the twin's outline moved from
    `outline_before` to `outline_now`; kept where it is when either outline is missing, empty or
    cut by the side of the `width` x `height` image (its size then says nothing of the vehicle's)."""
    b = np.asarray(box, dtype=float)
    if outline_before is None or outline_now is None:
        return b.copy()
    p, e = np.asarray(outline_before, dtype=float), np.asarray(outline_now, dtype=float)
    wp, hp = p[2] - p[0], p[3] - p[1]
    if wp <= 0 or hp <= 0 or e[2] <= e[0] or e[3] <= e[1] or _cut(p, width, height) or _cut(e, width, height):
        return b.copy()
    sx, sy = (e[2] - e[0]) / wp, (e[3] - e[1]) / hp
    return np.array([e[0] + (b[0] - p[0]) * sx, e[1] + (b[1] - p[1]) * sy,
                     e[0] + (b[2] - p[0]) * sx, e[1] + (b[3] - p[1]) * sy])


class BoxContinuity:
    """Per twin, the box drawn at the previous AR update; :meth:`update` gives the boxes to draw now.

    A twin drawn at the previous update whose new box has an IoU under `min_iou` with the previous
    drawn box moved as its outline moved (:func:`moved_box`) gets the mean of the two boxes
    instead, for at most `max_held` consecutive updates; any other box is drawn as given, and so is
    the box of a twin whose outline, then or now, the image's side cuts (a vehicle entering the
    frame: its visible box grows as fast as it enters, which its outline cannot tell). A twin with nothing to
    draw forgets its box (the driver's warning hold bridges a gap), as every twin does at an update
    without a frame (:meth:`forget`)."""

    def __init__(self, min_iou: float = MIN_CONTINUITY_IOU, max_held: int = MAX_HELD_UPDATES):
        if not 0.0 <= min_iou <= 1.0:
            raise ValueError(f"min_iou: expected an IoU in [0, 1], got {min_iou}")
        if max_held < 0:
            raise ValueError(f"max_held: expected a number of updates >= 0, got {max_held}")
        self.min_iou = float(min_iou)
        self.max_held = int(max_held)
        self._drawn: dict[str, _Drawn] = {}
        self.held_count = 0  # boxes drawn as a mean with the moved previous box over the run

    def forget(self) -> None:
        """No box to continue from at the next update (an update without a frame)."""
        self._drawn = {}

    def update(self, twin_ids, boxes, outlines, width: int, height: int) -> tuple[list, list[bool]]:
        """(the box to draw for each twin, whether it is a mean with the previous box moved). `boxes`: each
        twin's box after the overlay's rules (4 values px, or None: nothing drawn); `outlines`: each
        twin's projected outline (4 values px, or None)."""
        out, held = [], []
        drawn: dict[str, _Drawn] = {}
        for vid, box, outline in zip(twin_ids, boxes, outlines):
            e = None if outline is None else np.asarray(outline, dtype=float)
            if box is None:
                out.append(None)
                held.append(False)
                continue
            b = np.asarray(box, dtype=float)
            prev = self._drawn.get(str(vid))
            n = 0
            # an outline the image's side cuts (a vehicle entering or leaving the frame, a car alongside)
            # says nothing of how its box should move: its box is drawn as given
            if (prev is not None and prev.held < self.max_held and not _unpredictable(prev.outline, width, height)
                    and not _unpredictable(e, width, height)):
                moved = moved_box(prev.box, prev.outline, e, width, height)
                if box_iou(b[None], moved[None])[0, 0] < self.min_iou:
                    b, n = (b + moved) / 2, prev.held + 1
            drawn[str(vid)] = _Drawn(b, e, n)
            out.append(b if n else box)
            held.append(n > 0)
        self._drawn = drawn
        self.held_count += sum(held)
        return out, held
