"""The depth of the part of a twin a box shows (matching.outline_depth_in_columns,
JointMatch.shown_depth_sigmas) and the overlay's hidden-twin rule that reads it (fuse.undrawn_reason)."""

import numpy as np
import pytest

from support.fusion_helpers import make_twins, pinhole_camera
from vcfusion.fusion.fuse import HIDDEN_DEPTH_CONFIRM_SIGMAS, undrawn_reason
from vcfusion.fusion.matching import JointMatcher, JointMatcherParams, outline_depth_in_columns, project_twins

NAN_BOX = [np.nan] * 4


def test_outline_depth_in_columns_is_the_nearest_outline_point_the_box_columns_hold():
    cam = pinhole_camera()
    # a car driving straight away, footprint centre 20 m ahead (on the road: the helper's z is the roof)
    car = make_twins(["a"], [20.0], [0.0], length=4.5, width=1.8, height=1.5, z_ground=-0.75)
    whole = project_twins(car, cam).expected_box
    # its whole box: the rear face, 20 - 2.25 m
    assert outline_depth_in_columns(car, cam, whole)[0] == pytest.approx(17.75, abs=1e-6)
    # a box beside it holds none of its outline
    assert np.isnan(outline_depth_in_columns(car, cam, [[0.0, 0.0, 50.0, 50.0]])[0])
    assert np.isnan(outline_depth_in_columns(car, cam, [NAN_BOX])[0])
    with pytest.raises(ValueError, match="one box"):
        outline_depth_in_columns(car, cam, np.zeros((2, 4)))


def oblique_scene():
    """A van seen at an angle (heading 55 deg, moving left across the view), 18 m ahead, that a
    nearer truck's outline hides whole; the camera shows its front end beside the truck (the
    box over the leftmost fifth of its outline), metres deeper than its rear face."""
    cam = pinhole_camera()
    twins = make_twins(["truck", "van"], [9.0, 18.0], [0.0, 0.0], heading=[0.0, np.deg2rad(55)],
                       length=[6.0, 7.5], width=[3.6, 1.8], height=[4.0, 1.5], z_ground=[-2.0, -0.75])
    proj = project_twins(twins, cam)
    e = proj.expected_box[1]
    front = np.array([e[0] + 0.5, e[1] + 1.0, e[0] + 0.2 * (e[2] - e[0]), e[3] - 1.0])
    return cam, twins, proj, np.stack([proj.expected_box[0], front])


def _match(cam, twins, boxes, van_depth):
    samples = np.stack([np.full(20, 6.0), np.full(20, van_depth)])
    params = JointMatcherParams(smoothing_alpha=None, latency_compensation=False)
    matcher = JointMatcher(params)
    surface = np.array([6.0, van_depth])[:len(boxes)]  # the depth step's surfaces drawing the boxes
    details = matcher.match_details(twins, boxes, samples, cam, surface)
    # the matcher's choice is what match returns, and it does not depend on the new figure
    assert np.array_equal(JointMatcher(params).match(twins, boxes, samples, cam, surface), details.choice)
    return details


def test_a_hidden_van_seen_at_an_angle_is_drawn_where_its_box_has_the_depth_of_its_shown_part():
    cam, twins, proj, boxes = oblique_scene()
    sigma = 0.05 * proj.face_z[1] + 1.0
    shown_z = outline_depth_in_columns(twins, cam, np.stack([[np.nan] * 4, boxes[1]]))[1]
    assert shown_z - proj.face_z[1] > 1.2 * sigma  # the part shown lies well behind the rear face
    m = _match(cam, twins, boxes, shown_z + 0.3)
    assert list(m.choice) == [0, 1] and m.hidden_share[1] == 1.0
    # against the rear face the box's depth is over one sigma off: the rule before left it undrawn
    assert m.depth_sigmas[1] > HIDDEN_DEPTH_CONFIRM_SIGMAS
    assert m.shown_depth_sigmas[1] == pytest.approx(0.3 / sigma, abs=1e-6)
    args = (boxes[1], proj.expected_box[1], m.hidden_share[1])
    assert m.depth_on_surface[1]
    assert undrawn_reason(*args, depth_sigmas=m.depth_sigmas[1], depth_on_surface=True) == "hidden"
    assert undrawn_reason(*args, depth_sigmas=m.depth_sigmas[1], shown_depth_sigmas=m.shown_depth_sigmas[1],
                          depth_on_surface=True) == ""
    # the lower-quarter samples alone (no surface drawing the box) do not confirm a twin hidden whole
    assert undrawn_reason(*args, depth_sigmas=m.depth_sigmas[1], shown_depth_sigmas=m.shown_depth_sigmas[1]) == "hidden"


def test_a_box_deeper_than_the_shown_part_of_a_hidden_twin_stays_undrawn():
    """A box 4 m behind the van's front end (the car behind it, say) is allowed to the van by the
    matcher's gate but confirms nothing: it stays hidden."""
    cam, twins, proj, boxes = oblique_scene()
    shown_z = outline_depth_in_columns(twins, cam, np.stack([[np.nan] * 4, boxes[1]]))[1]
    m = _match(cam, twins, boxes, shown_z + 4.0)
    assert m.choice[1] == 1
    assert m.shown_depth_sigmas[1] > HIDDEN_DEPTH_CONFIRM_SIGMAS and m.depth_sigmas[1] > HIDDEN_DEPTH_CONFIRM_SIGMAS
    assert undrawn_reason(boxes[1], proj.expected_box[1], m.hidden_share[1], depth_sigmas=m.depth_sigmas[1],
                          shown_depth_sigmas=m.shown_depth_sigmas[1], depth_on_surface=True) == "hidden"
    # a twin without a box has no figure
    alone = JointMatcher(JointMatcherParams(smoothing_alpha=None, latency_compensation=False)).match_details(
        twins, boxes[:1], np.full((1, 20), 6.0), cam)
    assert alone.choice[1] == -1 and np.isinf(alone.shown_depth_sigmas[1])


def test_a_box_mostly_outside_the_twins_outline_is_drawn_within_it():
    """curved.yaml seed 95 (development), cars12 at 15 m: the depth step joined the car and the truck
    behind it, and the car's twin took the truck-high box (26 % of it within the car's outline);
    what lies within the outline is the car. A box mostly within the outline, an outline the image's
    side cuts (a car alongside) and a box beside the outline are left to the other rules."""
    from vcfusion.fusion.fuse import MIN_BOX_INSIDE_OUTLINE, box_within_outline, undrawn_reason

    outline = np.array([294.0, 212.0, 402.0, 258.0])
    truck_high = np.array([326.0, 160.0, 444.0, 250.0])
    assert np.array_equal(box_within_outline(truck_high, outline, 640, 480), [326.0, 212.0, 402.0, 250.0])
    own = np.array([308.0, 205.0, 418.0, 256.0])  # 75 % of it within the outline
    assert box_within_outline(own, outline, 640, 480) is own
    # the rule's share: just over MIN_BOX_INSIDE_OUTLINE of it inside is kept whole, just under is cut
    over = np.array([294.0, 258.0 - 46.0 / (MIN_BOX_INSIDE_OUTLINE + 0.01), 402.0, 258.0])
    under = np.array([294.0, 258.0 - 46.0 / (MIN_BOX_INSIDE_OUTLINE - 0.01), 402.0, 258.0])
    assert box_within_outline(over, outline, 640, 480) is over
    assert np.array_equal(box_within_outline(under, outline, 640, 480), outline)
    # a car alongside: its outline 3 px wide at the image's right side, its box wider
    alongside = np.array([637.0, 124.0, 639.5, 479.5])
    box = np.array([612.0, 260.0, 640.0, 328.0])
    assert box_within_outline(box, alongside, 640, 480) is box
    # no overlap, or a part within the outline under MIN_DRAWN_VISIBLE_PX: nothing to draw
    assert box_within_outline(np.array([10.0, 10.0, 60.0, 60.0]), outline, 640, 480) is None
    assert box_within_outline(np.array([401.0, 150.0, 470.0, 262.0]), outline, 640, 480) is None  # 46 px
    assert box_within_outline(None, outline, 640, 480) is None
    sliver = box_within_outline(np.array([396.0, 150.0, 470.0, 262.0]), outline, 640, 480)  # 276 px
    assert np.array_equal(sliver, [396.0, 212.0, 402.0, 258.0])


def test_a_mostly_hidden_twin_is_judged_by_its_box_where_the_boxs_surface_lies_at_it():
    """accident_heavy.yaml seed 96 (development), changer4 at 33 m: nearer outlines leave 6 % of its
    outline (42 px, under MIN_DRAWN_VISIBLE_PX), but its box, 108 px within the outline, is drawn by
    a surface 0.01 sigma from the twin: it shows the twin. The samples' depth alone (no surface) or
    a surface more than a sigma off leave it "small"."""
    from vcfusion.fusion.fuse import MIN_DRAWN_VISIBLE_PX

    outline = (307.0, 214.0, 340.0, 235.0)
    box = (334.0, 214.0, 340.0, 232.0)
    assert (outline[2] - outline[0]) * (outline[3] - outline[1]) * (1 - 0.94) < MIN_DRAWN_VISIBLE_PX
    assert undrawn_reason(box, outline, 0.94) == "small"
    assert undrawn_reason(box, outline, 0.94, depth_sigmas=0.01, depth_on_surface=True) == ""
    assert undrawn_reason(box, outline, 0.94, depth_sigmas=0.01) == "small"
    assert undrawn_reason(box, outline, 0.94, depth_sigmas=1.5, depth_on_surface=True) == "small"
    assert undrawn_reason(box, outline, 0.94, depth_sigmas=1.5, shown_depth_sigmas=0.2, depth_on_surface=True) == ""
    # a box whose part within the outline is itself under MIN_DRAWN_VISIBLE_PX stays small
    assert undrawn_reason((338.0, 214.0, 344.0, 232.0), outline, 0.94, depth_sigmas=0.01, depth_on_surface=True) == "small"


def test_a_mostly_hidden_twin_is_drawn_only_where_depth_puts_its_box_at_it():
    """curved.yaml seed 125 (development), trucks1 at 103 m: nearer outlines hide 0.83 of its
    outline, and the matcher gave it the box of trucks2, 15 m nearer, on the lower-quarter samples'
    depth (no surface drew the box's outline; 1.0 sigma). Mostly hidden (MOSTLY_HIDDEN_SHARE) the
    twin needs what a twin hidden whole needs: the surface drawing its box at the twin. Under the
    share the outlines decide as before."""
    from vcfusion.fusion.fuse import MOSTLY_HIDDEN_SHARE

    outline = (363.0, 206.0, 394.0, 222.0)  # 31 x 16 px: 84 px left at 0.83 hidden, over MIN_DRAWN_VISIBLE_PX
    box = (356.0, 204.0, 378.0, 218.0)  # trucks2's box
    assert MOSTLY_HIDDEN_SHARE <= 0.83 < 1.0
    assert undrawn_reason(box, outline, 0.83, depth_sigmas=1.0) == "hidden"
    assert undrawn_reason(box, outline, 0.83, depth_sigmas=0.9, shown_depth_sigmas=1.5) == "hidden"  # samples only
    assert undrawn_reason(box, outline, 0.83, depth_sigmas=1.3, depth_on_surface=True) == "hidden"  # surface off
    # the surface drawing the box lies at the twin (its face or the part the box's columns show): drawn
    assert undrawn_reason(box, outline, 0.83, depth_sigmas=0.2, depth_on_surface=True) == ""
    assert undrawn_reason(box, outline, 0.83, depth_sigmas=1.3, shown_depth_sigmas=0.4, depth_on_surface=True) == ""
    # less hidden than the share: drawn on the outlines' estimate whatever the depth
    below = MOSTLY_HIDDEN_SHARE - 1.0 / 256  # one cell of visible_boxes' 16 x 16 raster
    assert undrawn_reason(box, outline, below, depth_sigmas=3.0) == ""
