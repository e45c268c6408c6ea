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


def test_the_outline_is_the_box_around_the_projections_part_inside_the_image():
    from vcfusion.render.gt_boxes import outline_in_image, visible_shares

    square = np.array([[10.0, 20.0], [50.0, 20.0], [50.0, 60.0], [10.0, 60.0]])  # 40 x 40, inside
    cut = np.array([[600.0, 100.0], [700.0, 100.0], [700.0, 150.0]])  # cut by the right side of a 640 px image
    # a car beside the camera: its near end projects far above, below and beside the image
    beside = np.array([[620.0, 200.0], [2000.0, -3000.0], [2000.0, 4000.0], [620.0, 260.0]])
    trunc, outline = zip(*(outline_in_image(h, 640, 480) for h in (square, cut, beside, None)))
    np.testing.assert_allclose(outline[0], [10, 20, 50, 60])
    # the triangle's part left of x = 639.5 ends at y = 100 + 50 * 39.5 / 100, not at its corner's 150
    np.testing.assert_allclose(outline[1], [600, 100, 639.5, 119.75], atol=1e-3)
    # at x = 639.5 the upper and lower edges are at 200 - 19.5 * 3200 / 1380 and 260 + 19.5 * 3740 / 1380,
    # where the box around the whole projection, clipped, spans the image's height (-0.5 .. 479.5)
    np.testing.assert_allclose(outline[2], [620, 200 - 19.5 * 3200 / 1380, 639.5, 260 + 19.5 * 3740 / 1380],
                               atol=1e-3)
    assert np.isnan(outline[3]).all()
    assert trunc[0] == 0.0 and trunc[3] == 1.0
    assert trunc[1] == pytest.approx(1 - (39.5 * 19.75 / 2) / (100 * 50 / 2), abs=1e-5)
    visible = np.array([[10.0, 20.0, 30.0, 28.0],  # 20 x 8 of 40 x 40
                        [590.0, 100.0, 639.5, 150.0],  # past the outline: 1, not more
                        [0.0, 0.0, 10.0, 10.0]])
    np.testing.assert_allclose(visible_shares(visible, np.array([outline[0], outline[1], outline[3]])),
                               [160 / 1600, 1.0, 1.0])


def test_the_visible_box_is_the_largest_patch_of_pixels_as_scipy_labels_them():
    from scipy import ndimage

    from vcfusion.render.gt_boxes import largest_patch_box

    # a car as the curve showed one: a 3 px wide strip beside a nearer truck, and stray pixels seen
    # between the truck's wheels 10 px away; the box around all of them is 4x the strip's
    mask = np.zeros((9, 15), bool)
    mask[0:8, 11:14] = True
    mask[8, [0, 1, 4, 5, 12]] = True  # the strays, and a pixel touching the strip diagonally
    rows, cols = np.nonzero(mask)
    labels, n = ndimage.label(mask, structure=np.ones((3, 3)))
    biggest = np.argmax(np.bincount(labels.ravel())[1:]) + 1
    r, c = np.nonzero(labels == biggest)
    reference = (c.min() - 0.5, r.min() - 0.5, c.max() + 0.5, r.max() + 0.5)
    assert n == 3 and largest_patch_box(rows + 200, cols + 300) == pytest.approx(
        (reference[0] + 300, reference[1] + 200, reference[2] + 300, reference[3] + 200))
    assert largest_patch_box(rows, cols) == pytest.approx((10.5, -0.5, 13.5, 8.5))
    # one patch (a filled rectangle, or pixels joined at corners) is the box around all of it
    rr, cc = np.mgrid[3:7, 5:9]
    assert largest_patch_box(rr.ravel(), cc.ravel()) == (4.5, 2.5, 8.5, 6.5)
    assert largest_patch_box(np.array([0, 1, 2]), np.array([0, 1, 2])) == (-0.5, -0.5, 2.5, 2.5)
    # equal patches: the first in scan order
    assert largest_patch_box(np.array([0, 0, 5, 5]), np.array([4, 5, 0, 1])) == (3.5, -0.5, 5.5, 0.5)


def test_the_frame_judges_highlights_against_its_visible_boxes_not_the_boxes_around_all_pixels():
    from vcfusion.fusion.fuse import CameraFrame

    # "a": its pixels spread over a 40 x 30 px box, its largest patch a 7 x 10 px strip at the box's right
    patches = GT.copy()
    patches[0] = (133, 100, 140, 110)
    frame = CameraFrame(time=0.0, image=np.zeros((4, 4, 3), np.uint8), depth=np.zeros((4, 4), np.float32),
                        camera=None, gt_boxes=GT, gt_ids=IDS, gt_patches=patches)
    assert judge_highlight("a", None, frame.visible_boxes, IDS).outcome == "unseen"  # 70 px
    assert judge_highlight("a", None, frame.gt_boxes, IDS).outcome == "missed"  # 1200 px
    # a box on the strip is right against it (IoU 0.7), wrong against the box around all pixels
    on_strip = (133, 100, 140, 107)
    assert judge_highlight("a", on_strip, frame.visible_boxes, IDS).outcome == "right"
    assert judge_highlight("a", on_strip, frame.gt_boxes, IDS).outcome == "wrong"
    # without patches (a scene folder) the ground-truth boxes are the visible boxes
    no_patches = CameraFrame(time=0.0, image=frame.image, depth=frame.depth, camera=None, gt_boxes=GT, gt_ids=IDS)
    assert no_patches.visible_boxes is GT


def test_a_persons_display_is_judged_against_the_largest_patch_in_its_instance_map():
    from vcfusion.metrics.highlights import instance_boxes

    inst = np.full((20, 30), -1)
    inst[2:12, 20:23] = 0  # "a": a 3 x 10 px strip ...
    inst[15, [5, 6, 10]] = 0  # ... and stray pixels far from it
    inst[5:9, 2:8] = 1  # "b": one patch
    boxes, ids = instance_boxes(inst, ("a", "b"))
    assert ids == ("a", "b")
    np.testing.assert_array_equal(boxes, [[20, 2, 23, 12], [2, 5, 8, 9]])
    assert judge_highlight("a", (20, 2, 23, 11), boxes, ids).outcome == "right"
