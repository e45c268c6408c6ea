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


def test_a_box_on_a_small_far_vehicle_is_right():
    assert judge_highlight("c", (300, 100, 305, 105), GT, IDS).outcome == "right"  # 25 px, IoU 1


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


def test_the_overlay_draws_no_box_many_times_the_twins_outline():
    from vcfusion.fusion.fuse import MAX_BOX_TO_OUTLINE_AREA, drawable_box

    outline = (100.0, 100.0, 112.0, 120.0)  # a car at ~70 m: 12 x 20 px
    own = (100.0, 102.0, 112.0, 120.0)
    truck = (94.0, 90.0, 124.0, 128.0)  # 30 x 38 px: 4.75 times the outline
    assert drawable_box(own, outline) == own
    assert drawable_box(truck, outline) is None
    assert drawable_box(truck, outline, max_ratio=6.0) == truck
    assert drawable_box(None, outline) is None and MAX_BOX_TO_OUTLINE_AREA == 3.0
    assert drawable_box(own, outline, hidden_share=1.0) is None  # hidden whole: a sliver shows at most
    assert drawable_box(own, outline, hidden_share=0.5) == own  # 120 px of it left
    from vcfusion.fusion.fuse import undrawn_reason

    assert [undrawn_reason(b, outline, h) for b, h in ((own, 0.0), (None, 0.0), (own, 1.0), (truck, 0.0))] == \
        ["", "no_match", "hidden", "too_large"]


def test_the_overlay_draws_no_box_for_a_twin_it_expects_too_small_to_see():
    from vcfusion.fusion.fuse import drawable_box, undrawn_reason

    far = (100.0, 100.0, 106.0, 104.0)  # a car at ~180 m: 6 x 4 px, under MIN_VISIBLE_PX
    box = (99.0, 98.0, 105.0, 106.0)  # 6 x 8 px: the top of the truck beside it (curved seed 101)
    assert drawable_box(box, far) is None and undrawn_reason(box, far) == "small"
    outline = (100.0, 100.0, 120.0, 120.0)  # 400 px, 15/16 of it behind the car in front: 25 px left
    assert undrawn_reason((100.0, 100.0, 120.0, 120.0), outline, 0.9375) == "small"
    # 80 px left: drawn (mostly hidden, MOSTLY_HIDDEN_SHARE: where the box's surface lies at the twin)
    assert undrawn_reason((100.0, 100.0, 120.0, 120.0), outline, 0.8, depth_sigmas=0.4, depth_on_surface=True) == ""
    from vcfusion.fusion.fuse import MIN_DRAWN_VISIBLE_PX

    assert 6 * 4 < MIN_DRAWN_VISIBLE_PX <= 80 and MIN_DRAWN_VISIBLE_PX <= MIN_VISIBLE_PX


def _judged(twin, sequence, t0=1.0, shown=None):
    """Judged rows of one twin: one outcome letter per 0.1 s update (r right, w wrong on `other`,
    m missed, u unseen)."""
    import pandas as pd

    names = {"r": "right", "w": "wrong", "m": "missed", "u": "unseen"}
    return pd.DataFrame([{"time": round(t0 + 0.1 * k, 6), "vehicle_id": twin, "outcome": names[c],
                          "box_vehicle_id": {"r": twin, "w": shown or "other"}.get(c, "")}
                         for k, c in enumerate(sequence)])


def _episodes(rows, hold_s=0.3):
    from vcfusion.metrics.highlights import warning_episodes

    return [(e.outcome, len(e.rows), e.bridged) for e in warning_episodes(rows, 0.1, hold_s)]


def test_a_right_box_that_flickers_for_up_to_the_drivers_hold_is_one_episode():
    # right, one update without a box, right, three without (0.3 s: the hold), right: one right episode
    assert _episodes(_judged("a", "rrmrrmmmr")) == [("right", 5, 4)]
    assert _episodes(_judged("a", "rrururr")) == [("right", 5, 2)]  # unseen gaps alike
    # four updates without a box (0.4 s) are longer than the hold: a missed episode between two right ones
    assert _episodes(_judged("a", "rrmmmmr")) == [("right", 2, 0), ("missed", 4, 0), ("right", 1, 0)]
    # with no hold every gap is an episode (the rule before the hold)
    assert _episodes(_judged("a", "rmr"), hold_s=0.0) == [("right", 1, 0), ("missed", 1, 0), ("right", 1, 0)]


def test_no_gap_is_bridged_at_the_ends_or_around_a_wrong_box():
    # a gap before the first box or after the last stays a missed episode, however short
    assert _episodes(_judged("a", "mrrm")) == [("missed", 1, 0), ("right", 2, 0), ("missed", 1, 0)]
    # a wrong box that flickers is a wrong episode each time it appears
    assert _episodes(_judged("a", "wmw")) == [("wrong", 1, 0), ("missed", 1, 0), ("wrong", 1, 0)]
    # a gap between a right box and a wrong one is not bridged either
    assert _episodes(_judged("a", "rmw")) == [("right", 1, 0), ("missed", 1, 0), ("wrong", 1, 0)]
    # two twins are episodes of their own; a time gap of more than 1.5 updates ends an episode
    import pandas as pd

    two = pd.concat([_judged("a", "rr"), _judged("b", "rmr"), _judged("a", "rr", t0=2.0)], ignore_index=True)
    assert _episodes(two) == [("right", 2, 0), ("right", 2, 1), ("right", 2, 0)]


def test_a_twin_hidden_whole_is_drawn_where_depth_puts_its_box_at_the_twin():
    """Nearer twins' outlines hide the whole outline (their reports are a few decimetres off, their
    cuboids coarser than the vehicles), but the matched box's depth lies within one of the matcher's
    sigmas of the twin's face: the box shows the twin and is drawn (curved seed 100 cars14: 470 px
    visible, was missed). Depth further off, or the lower-quarter samples alone (not the surface
    drawing the box's outline), keep it undrawn ("hidden"); a confirmed box
    whose part within the outline is under MIN_DRAWN_VISIBLE_PX is "small"."""
    from vcfusion.fusion.fuse import HIDDEN_DEPTH_CONFIRM_SIGMAS, MIN_DRAWN_VISIBLE_PX, drawable_box, undrawn_reason

    outline = (404.0, 214.0, 452.0, 242.0)
    box = (406.0, 213.0, 430.0, 240.0)  # its left half, beside the car in front
    assert HIDDEN_DEPTH_CONFIRM_SIGMAS == 1.0
    assert undrawn_reason(box, outline, 1.0) == "hidden"  # no depth known
    assert undrawn_reason(box, outline, 1.0, depth_sigmas=0.4, depth_on_surface=True) == ""
    assert drawable_box(box, outline, 1.0, depth_sigmas=0.4, depth_on_surface=True) == box
    assert undrawn_reason(box, outline, 1.0, depth_sigmas=1.3, depth_on_surface=True) == "hidden"
    # the lower-quarter samples alone do not confirm it (they read the vehicle in front of it at about
    # its depth); the surface drawing the box's outline does (above)
    assert undrawn_reason(box, outline, 1.0, depth_sigmas=0.4) == "hidden"
    sliver = (404.0, 214.0, 410.0, 222.0)  # 48 px
    assert (sliver[2] - sliver[0]) * (sliver[3] - sliver[1]) < MIN_DRAWN_VISIBLE_PX
    assert undrawn_reason(sliver, outline, 1.0, depth_sigmas=0.4, depth_on_surface=True) == "small"
    # a partly hidden twin is judged by its outline as before, whatever the depth
    assert undrawn_reason(box, outline, 0.5, depth_sigmas=3.0) == ""


def test_a_sliver_under_the_visible_share_is_unseen_above_it_missed():
    from vcfusion.metrics.highlights import MIN_VISIBLE_SHARE

    # "a" shows a 1200 px box: visible by its size, and by its share of its outline only above the floor
    shares = np.array([MIN_VISIBLE_SHARE - 0.01, 1.0, 1.0])
    assert judge_highlight("a", None, GT, IDS, shares).outcome == "unseen"
    assert judge_highlight("a", None, GT, IDS, shares).visible_share == pytest.approx(MIN_VISIBLE_SHARE - 0.01)
    assert judge_highlight("a", None, GT, IDS, np.array([MIN_VISIBLE_SHARE, 1.0, 1.0])).outcome == "missed"
    assert judge_highlight("a", None, GT, IDS).outcome == "missed"  # no outlines: judged by size alone
    # a drawn box is judged by its IoU whatever the share: on the sliver right, elsewhere wrong
    assert judge_highlight("a", (100, 100, 140, 130), GT, IDS, shares).outcome == "right"
    assert judge_highlight("a", (130, 105, 200, 150), GT, IDS, shares).outcome == "wrong"


def test_the_visible_share_is_the_box_over_its_clipped_outline_at_most_one():
    from vcfusion.render.gt_boxes import outline_boxes, visible_shares

    hulls = [np.array([[10.0, 20.0], [50.0, 20.0], [50.0, 60.0], [10.0, 60.0]]),  # 40 x 40
             np.array([[600.0, 100.0], [700.0, 100.0], [700.0, 150.0]]),  # cut by the right side of a 640 px image
             None]
    rects = [None if h is None else (h.min(axis=0), h.max(axis=0)) for h in hulls]  # as ground_truth_boxes has them
    outline = outline_boxes(rects, 640, 480)
    np.testing.assert_allclose(outline[:2], [[10, 20, 50, 60], [600, 100, 639.5, 150]])
    assert np.isnan(outline[2]).all()
    visible = np.array([[10.0, 20.0, 30.0, 28.0],  # 20 x 8 of 40 x 40
                        [590.0, 100.0, 639.5, 150.0],  # a pixel past the outline: 1, not more
                        [0.0, 0.0, 10.0, 10.0]])
    np.testing.assert_allclose(visible_shares(visible, outline), [160 / 1600, 1.0, 1.0])
