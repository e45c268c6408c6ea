"""The one definition of a right / wrong / missed highlight (vcfusion.metrics.highlights)."""

import numpy as np
import pytest

from vcfusion.metrics.highlights import MIN_VISIBLE_PX, RIGHT_IOU, judge_highlight

GT = np.array([[100, 100, 140, 130],   # "a": 40 x 30 = 1200 px
               [130, 105, 200, 150],   # "b": overlaps a's right side
               [300, 100, 305, 105]])  # "c": 25 px, too small to be judged
IDS = ("a", "b", "c")


def test_a_box_on_the_meant_vehicle_is_right():
    j = judge_highlight("a", (101, 101, 141, 131), GT, IDS)
    assert j.outcome == "right" and j.iou > 0.85 and j.box_vehicle_id == "a" and j.visible_px == 1200


def test_a_box_on_the_neighbouring_vehicle_is_wrong_and_names_it():
    j = judge_highlight("a", (130, 105, 200, 150), GT, IDS)
    assert j.outcome == "wrong" and j.box_vehicle_id == "b" and j.iou < RIGHT_IOU


def test_a_loose_box_below_the_iou_rule_is_wrong_even_around_the_meant_vehicle():
    # twice as wide as a: IoU 0.5 at most on the meant vehicle's side, here below
    j = judge_highlight("a", (80, 95, 165, 135), GT, IDS)
    assert j.outcome == "wrong" and j.box_vehicle_id == "a"
    assert judge_highlight("a", (80, 95, 165, 135), GT, IDS, right_iou=0.3).outcome == "right"


def test_nothing_drawn_for_a_visible_vehicle_is_missed_for_an_unseen_one_unseen():
    assert judge_highlight("a", None, GT, IDS).outcome == "missed"
    assert judge_highlight("c", None, GT, IDS).outcome == "unseen"  # 25 px < MIN_VISIBLE_PX
    assert judge_highlight("hidden", None, GT, IDS).outcome == "unseen"
    assert 25 < MIN_VISIBLE_PX


@pytest.mark.parametrize("twin", ["c", "hidden"])
def test_a_box_drawn_for_a_vehicle_the_frame_does_not_show_is_wrong(twin):
    j = judge_highlight(twin, (101, 101, 141, 131), GT, IDS)
    assert j.outcome == "wrong" and j.box_vehicle_id == "a"


def test_a_frame_without_ground_truth_boxes():
    assert judge_highlight("a", (0, 0, 10, 10), np.zeros((0, 4)), ()).outcome == "wrong"
    assert judge_highlight("a", None, np.zeros((0, 4)), ()).outcome == "unseen"
