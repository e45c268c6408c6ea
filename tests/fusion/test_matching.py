from types import SimpleNamespace

import numpy as np
import pytest

from support.fusion_helpers import CX, FX, make_twins, pinhole_camera, vehicle_box
from vcfusion.fusion.depth_eval import DepthEvalParams, evaluate_box_depths
from vcfusion.fusion.matching import (
    NO_MATCH, JointMatcher, JointMatcherParams, box_iou, extrapolate_twins, match_all_paper,
    gnss_distances, match_all_baseline, match_baseline, match_baseline_centre, match_paper, project_twins)


def fig3_scene():
    """Fig. 3: a near vehicle (8.46 m) partly hides a farther one (18.69 m) in the next lane; their
    boxes overlap and an anchor in the overlap lies in both."""
    near = np.array([150.0, 200.0, 430.0, 420.0])
    far = np.array([420.0, 150.0, 560.0, 260.0])
    depth = np.full((480, 640), 80.0, np.float32)
    depth[:240] = np.inf  # sky
    depth[150:260, 420:560] = 18.69
    depth[200:420, 150:430] = 8.46  # the near vehicle is painted last: it occludes the far one
    return near, far, depth


def test_fig3_overlapping_boxes_depth_decides():
    near, far, depth = fig3_scene()
    boxes = np.stack([near, far])
    d = evaluate_box_depths(depth, boxes, np.random.default_rng(0), DepthEvalParams(th=0.8, n=30))
    assert d[0] == pytest.approx(8.46, abs=1e-5)
    assert d[1] == pytest.approx(18.69, abs=1e-5)
    overlap_anchor = (425.0, 215.0)
    # the near vehicle's twin (GNSS 9 m): depth picks its box; the nearest-centre RGB rule takes the
    # far box, whose centre is nearer the anchor: the corner case of Fig. 3
    assert match_paper(overlap_anchor, boxes, d, gnss_distance=9.0) == 0
    assert match_baseline_centre(overlap_anchor, boxes) == 1
    # the paper's RGB-only baseline "cannot identify" the target: with equal scores no box, else the
    # detector's most confident box whichever twin is asked for
    assert match_baseline(overlap_anchor, boxes, scores=[0.9, 0.9]) is None
    assert match_baseline(overlap_anchor, boxes) is None
    assert match_baseline(overlap_anchor, boxes, scores=[0.95, 0.6]) == 0
    assert match_baseline(overlap_anchor, boxes, scores=[0.6, 0.95]) == 1
    # the far vehicle's twin (GNSS 19.5 m) at the same anchor: depth picks the far box
    assert match_paper(overlap_anchor, boxes, d, gnss_distance=19.5) == 1
    # order of the boxes does not matter
    assert match_paper(overlap_anchor, boxes[::-1], d[::-1], gnss_distance=9.0) == 1
    # outside the overlap there is one candidate and depth is not consulted
    assert match_paper((500.0, 160.0), boxes, d, gnss_distance=9.0) == 1


def test_single_containing_box_is_taken_whatever_its_depth():
    boxes = np.array([[0, 0, 100, 100], [200, 200, 300, 300]], float)
    assert match_paper((50, 50), boxes, [500.0, 1.0], gnss_distance=1.0) == 0
    assert match_baseline((250, 250), boxes) == 1
    assert match_baseline((250, 250), boxes, scores=[0.99, 0.1]) == 1  # scores only break ties
    assert match_baseline_centre((250, 250), boxes) == 1


def test_no_containing_box_gives_no_match_unless_fallback_radius():
    boxes = np.array([[0, 0, 100, 100], [200, 200, 300, 300]], float)
    assert match_paper((150, 150), boxes, [10.0, 20.0], 15.0) is None
    assert match_baseline((150, 150), boxes) is None
    assert match_paper((150, 150), np.zeros((0, 4)), np.zeros(0), 15.0) is None
    # (105, 50) is 5 px right of the first box
    assert match_paper((105, 50), boxes, [10.0, 20.0], 15.0, fallback_radius_px=10) == 0
    assert match_paper((105, 50), boxes, [10.0, 20.0], 15.0, fallback_radius_px=4) is None
    # (150, 150) is 70.7 px from both boxes' corners
    assert match_baseline((150, 150), boxes, fallback_radius_px=60) is None


def test_paper_matcher_skips_boxes_without_depth():
    boxes = np.array([[0, 0, 100, 100], [20, 20, 80, 80]], float)
    assert match_paper((50, 50), boxes, [np.nan, 40.0], gnss_distance=10.0) == 1
    # no candidate with depth: the baseline rule (most confident; a tie -> no match)
    assert match_paper((60, 50), boxes, [np.nan, np.nan], gnss_distance=10.0, scores=[0.3, 0.8]) == 1
    assert match_paper((60, 50), boxes, [np.nan, np.nan], gnss_distance=10.0, scores=[0.5, 0.5]) is None


def test_baseline_scores_must_align_with_boxes():
    boxes = np.array([[0, 0, 100, 100], [20, 20, 80, 80]], float)
    with pytest.raises(ValueError, match="one detector score per box"):
        match_baseline((50, 50), boxes, scores=[0.5])


def test_paper_compares_depth_with_the_distance_of_the_face_the_camera_sees():
    """A car 30 m ahead with a truck right in front of it (Fig. 3 kind, same lane): the car hides the
    truck's lower part, so Algorithm 1 on the truck's box measures mostly the car's rear. Compared
    with the raw distance of the car's GNSS point (its body centre, 2.3 m behind its rear face) the
    truck box wins; compared with the distance of the car's rear face (from its GNSS position,
    heading and length, D_g 'face') the car's box wins."""
    cam = pinhole_camera()
    # GNSS point = body centre (z_ground = -height / 2 puts make_twins' z at half the height)
    twins = make_twins(["car", "truck"], [30.0 + 2.3, 36.0 + 6.0], [0.0, 0.0], length=[4.6, 12.0],
                       height=[1.5, 3.6], width=[1.8, 2.5], z_ground=[-0.75, -1.8])
    proj = project_twins(twins, cam)
    np.testing.assert_allclose(gnss_distances(proj, "face")[0], 30.0 - cam.position[0], atol=0.05)
    car_box, truck_box = proj.expected_box
    boxes = np.stack([car_box, truck_box])
    assert match_baseline(proj.anchor[0], boxes, scores=[0.9, 0.9]) is None  # ambiguous
    depths = np.array([30.0, 32.0]) - cam.position[0]  # truck box: mostly the car's rear, some road
    assert match_all_paper(proj, boxes, depths, gnss_distance="face")[0] == 0
    assert match_all_paper(proj, boxes, depths, gnss_distance="range")[0] == 1
    assert match_all_paper(proj, boxes, depths)[0] == 0  # 'face' is the default
    with pytest.raises(ValueError, match="gnss_distance"):
        gnss_distances(proj, "rear")


def test_all_twins_baseline_rules():
    """The two RGB-only rules over all twins of a frame: 'score' (paper) and 'centre' (ours)."""
    cam = pinhole_camera()
    twins = make_twins(["near", "far"], [15.0, 27.0], [0.0, 1.8])
    proj = project_twins(twins, cam)
    boxes = proj.expected_box
    n_in = [int(((boxes[:, 0] <= a[0]) & (a[0] <= boxes[:, 2]) & (boxes[:, 1] <= a[1]) & (a[1] <= boxes[:, 3])).sum())
            for a in proj.anchor]
    assert n_in == [1, 2]  # the far car's anchor also lies in the near car's box
    assert list(match_all_baseline(proj, boxes, scores=[0.9, 0.9])) == [0, NO_MATCH]
    assert list(match_all_baseline(proj, boxes, scores=[0.9, 0.7])) == [0, 0]
    assert list(match_all_baseline(proj, boxes, rule="centre")) == [0, 1]
    with pytest.raises(ValueError, match="rule"):
        match_all_baseline(proj, boxes, rule="nearest")


def test_box_iou_against_hand_values():
    iou = box_iou([[0, 0, 10, 10]], [[0, 0, 10, 10], [5, 0, 15, 10], [20, 20, 30, 30]])
    np.testing.assert_allclose(iou, [[1.0, 50 / 150, 0.0]])


def test_box_inside_share_against_hand_values():
    from vcfusion.fusion.matching import box_inside_share

    share = box_inside_share([[0, 0, 10, 10], [2, 2, 4, 4], [5, 5, 5, 9]],
                             [[0, 0, 20, 20], [5, 0, 15, 10], [20, 20, 30, 30]])
    # a box inside a larger one: all of it; half of it across an edge: half; an empty box: 0
    np.testing.assert_allclose(share, [[1.0, 0.5, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert box_inside_share(np.zeros((0, 4)), [[0, 0, 1, 1]]).shape == (0, 1)


def two_in_a_lane(order=(0, 1)):
    """Two cars ahead in the camera's lane (15 m and 27 m), the far one offset 0.9 m to the left so
    its box sticks out of the near one's; boxes and rear-face depths given by the test's own camera."""
    cam = pinhole_camera()
    xs, ys = np.array([15.0, 27.0]), np.array([0.0, 0.9])
    boxes = np.stack([vehicle_box(cam, x, y) for x, y in zip(xs, ys)])
    depths = xs - 4.5 / 2  # depth sees the rear face
    ids = np.array(["near", "far"])[list(order)]
    twins = make_twins(ids, xs[list(order)], ys[list(order)])
    return cam, twins, boxes, depths


@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_joint_matcher_assigns_two_overlapping_vehicles(order):
    cam, twins, boxes, depths = two_in_a_lane(order)
    assert box_iou(boxes[:1], boxes[1:])[0, 0] > 0  # the boxes overlap
    proj = project_twins(twins, cam)
    assert proj.in_view.all()
    # the far car's antenna lies inside both boxes: the Fig. 3 situation
    i_far = twins.ids.index("far")
    inside = [(b[0] <= proj.anchor[i_far, 0] <= b[2]) and (b[1] <= proj.anchor[i_far, 1] <= b[3]) for b in boxes]
    assert all(inside)
    got = JointMatcher().match(twins, boxes, depths, cam)
    expect = {"near": 0, "far": 1}
    assert [int(g) for g in got] == [expect[i] for i in twins.ids]
    # shuffled boxes follow
    got_rev = JointMatcher().match(twins, boxes[::-1], depths[::-1], cam)
    assert [int(g) for g in got_rev] == [1 - expect[i] for i in twins.ids]


def test_joint_matcher_leaves_an_occluded_twin_unmatched():
    cam = pinhole_camera()
    # a third car hidden right behind the near one: no box of its own; its expected box overlaps the
    # near car's box, but the depth disagrees (27 m vs 12.75 m), so it is not given that box.
    twins = make_twins(["near", "hidden"], [15.0, 29.0], [0.0, 0.0])
    boxes = vehicle_box(cam, 15.0, 0.0)[None]
    got = JointMatcher().match(twins, boxes, [15.0 - 2.25], cam)
    assert list(got) == [0, NO_MATCH]


class _GivenCosts(JointMatcher):
    """The joint matcher's assignment on hand-set costs (None: the pair is not allowed)."""

    def __init__(self, costs, hidden_whole=None, **params):
        super().__init__(JointMatcherParams(**params))
        self.costs = costs
        self.hidden = np.zeros(len(costs), bool) if hidden_whole is None else np.asarray(hidden_whole, bool)

    def _cost_terms(self, proj, boxes, box_depths, surface_depths=None, depth_noise=None):
        c = np.array([[np.inf if v is None else v for v in row] for row in self.costs])
        return np.where(np.isfinite(c), c, 10.0), np.isfinite(c), self.hidden


def _assign_given(costs, hidden_whole=None, **params):
    """The joint matcher's assignment on hand-set costs (rows: twins), as a list of box indices."""
    m = len(costs[0])
    got = _GivenCosts(costs, hidden_whole, **params).assign(SimpleNamespace(anchor=np.zeros((len(costs), 2))),
                                                            np.zeros((m, 4)), np.zeros(m))
    return [int(g) for g in got]


def test_joint_matcher_lets_boxes_and_twins_go_unmatched_rather_than_shift_a_chain():
    """A jam frame (dev seed 3030, costs rounded): a near car A with its box 0 and a stray partial
    box 2 on it, a partly hidden car B behind with its box 1, and a car H the two hide entirely,
    whose only allowed box is B's. Forced to give every box an owner, the assignment shifts the
    chain: A takes the stray, B takes A's box, H takes B's (10.8 against 7.5 with H left out at the
    default miss cost 6)."""
    costs = [[0.2, 3.3, 1.0],  # A
             [4.9, 1.3, None],  # B
             [None, 4.9, None]]  # H
    assign = _assign_given
    assert assign(costs, miss_cost=None) == [2, 0, 1]
    assert assign(costs) == [0, 1, NO_MATCH]
    # a pair dearer than leaving the twin out is never taken, however few boxes there are
    assert assign([[5.5], [0.5]], miss_cost=5.0) == [NO_MATCH, 0]
    assert assign([[5.5], [None]], miss_cost=5.0) == [NO_MATCH, NO_MATCH]
    assert assign([[4.5], [None]], miss_cost=5.0) == [0, NO_MATCH]
    assert assign([[5.5], [None]], miss_cost=None) == [0, NO_MATCH]


def test_face_offset_expected_depth_is_half_a_length_nearer():
    cam = pinhole_camera()
    ahead = make_twins(["a", "b"], [30.0, 30.0], [0.0, 3.5], heading=[0.0, np.pi], length=[4.5, 12.0])
    proj = project_twins(ahead, cam)
    # a: drives away, depth sees its rear at 30 - 2.25; b: oncoming truck, its front at 30 - 6
    np.testing.assert_allclose(proj.face_z, [27.75, 24.0])
    np.testing.assert_allclose(proj.anchor_z, [30.0, 30.0])
    np.testing.assert_allclose(proj.gnss_range, [30.0, np.hypot(30.0, 3.5)])


def test_a_vehicle_cut_by_the_image_border_is_expected_at_the_depth_of_its_side_in_view():
    """A truck in the next lane 2-14 m ahead: its rear (the usual face) lies outside the image, left
    of the border; what depth sees of it is its side from where the border cuts it: 2.25 m to the
    left at u = 0 with fx = 500, cx = 320, so 2.25 * 500 / 320 = 3.52 m ahead (outline sampled every
    0.75 m)."""
    cam = pinhole_camera()
    truck = make_twins(["truck", "car"], [8.0, 20.0], [3.5, 0.0], length=[12.0, 4.5], width=[2.5, 1.8],
                       height=[3.6, 1.5])
    proj = project_twins(truck, cam)
    assert proj.in_view.all()
    assert 2.25 * 500 / 320 <= proj.face_z[0] <= 2.25 * 500 / 320 + 0.75
    assert proj.face_z[1] == pytest.approx(20.0 - 4.5 / 2)  # a face in view keeps its depth


def test_extrapolation_moves_along_heading_by_speed_times_age():
    twins = make_twins(["a", "b"], [10.0, 0.0], [0.0, 5.0], measured_time=[0.6, 0.9], heading=[0.0, np.pi / 2],
                       speed=[20.0, 10.0])
    moved = extrapolate_twins(twins, 1.0)
    np.testing.assert_allclose(moved.x, [10.0 + 20.0 * 0.4, 0.0], atol=1e-12)
    np.testing.assert_allclose(moved.y, [0.0, 5.0 + 10.0 * 0.1])
    np.testing.assert_allclose(moved.measured_time, [1.0, 1.0])
    braking = make_twins(["c"], [0.0], [0.0], measured_time=0.0, speed=2.0)
    braking = extrapolate_twins(type(braking)(**{**braking.__dict__, "accel": np.array([-4.0])}), 1.0, use_accel=True)
    np.testing.assert_allclose(braking.x, [0.5])  # stops after 0.5 s and 0.5 m


def test_latency_compensation_recovers_the_right_boxes():
    """Cloud states 0.5 s old at 20 m/s lag 10 m behind: uncompensated, the far twin is expected
    where the near car is (its box and depth), and the near twin falls behind the camera's view."""
    cam = pinhole_camera(time=10.5)
    true_x = np.array([14.0, 24.0])
    ys = np.array([0.0, 0.6])
    boxes = np.stack([vehicle_box(cam, x, y) for x, y in zip(true_x, ys)])
    depths = true_x - 2.25
    stale = make_twins(["near", "far"], true_x - 10.0, ys, measured_time=10.0, speed=20.0)
    compensated = JointMatcher().match(stale, boxes, depths, cam)
    assert list(compensated) == [0, 1]
    plain = JointMatcher(JointMatcherParams(latency_compensation=False)).match(stale, boxes, depths, cam)
    assert plain[1] == 0  # the far twin takes the near car's box
    # the paper's matcher with stale anchors also goes wrong for the far twin
    proj = project_twins(stale, cam)
    assert match_all_paper(proj, boxes, depths)[1] != 1


def test_position_filter_shrinks_gnss_noise_and_follows_motion():
    from vcfusion.fusion.matching import TwinPositionFilter

    rng = np.random.default_rng(0)
    filt = TwinPositionFilter(alpha=0.25)
    errors_raw, errors_filtered = [], []
    for k in range(300):
        t = 0.1 * k
        true_x, true_y = 20.0 * t, -5.25 + (1.0 * (t - 15.0) if 15.0 <= t < 18.5 else (3.5 if t >= 18.5 else 0.0))
        heading = np.arctan2(1.0, 20.0) if 15.0 <= t < 18.5 else 0.0  # a lane change to the left
        speed = np.hypot(20.0, 1.0) if 15.0 <= t < 18.5 else 20.0
        noisy = np.array([true_x, true_y]) + rng.normal(0, 2.0, 2)
        tw = make_twins(["a"], [noisy[0]], [noisy[1]], measured_time=t, heading=heading, speed=speed)
        out = filt.update(tw)
        again = filt.update(tw)  # the same report twice (several detectors per frame) changes nothing
        assert out.x[0] == again.x[0]
        if k > 30:
            errors_raw.append(np.hypot(noisy[0] - true_x, noisy[1] - true_y))
            errors_filtered.append(np.hypot(out.x[0] - true_x, out.y[0] - true_y))
    rms_raw, rms_filtered = np.sqrt(np.mean(np.square(errors_raw))), np.sqrt(np.mean(np.square(errors_filtered)))
    assert rms_raw == pytest.approx(2.0 * np.sqrt(2), rel=0.15)
    # theory: sqrt(alpha / (2 - alpha)) = 0.378 of the raw error on a straight road (0.36-0.41 over
    # seeds); the lane change adds a little
    assert rms_filtered < 0.5 * rms_raw


def test_joint_matcher_with_noisy_gnss_is_steadied_by_the_filter():
    """Two cars side by side in adjacent lanes at the same distance: with 2 m GNSS noise the raw
    anchors often sit on the wrong car; over a few seconds of reports the filter keeps them apart."""
    cam = pinhole_camera()
    rng = np.random.default_rng(3)
    xs, ys = np.array([25.0, 25.0]), np.array([0.0, 3.5])
    boxes = np.stack([vehicle_box(cam, x, y) for x, y in zip(xs, ys)])
    depths = xs - 2.25
    smoothed, raw = JointMatcher(), JointMatcher(JointMatcherParams(smoothing_alpha=None))
    right_s = right_r = 0
    for k in range(100):
        # the cars drive at 20 m/s; the camera moves with them, so the scene stays put
        t = 0.1 * k
        noisy_y = ys + rng.normal(0, 2.0, 2)
        noisy_x = xs + 20.0 * t + rng.normal(0, 2.0, 2)
        cam_t = pinhole_camera(position=(20.0 * t, 0.0, 1.5), time=t)
        tw = make_twins(["r", "l"], noisy_x, noisy_y, measured_time=t, speed=20.0)
        if k >= 20:
            right_s += list(smoothed.match(tw, boxes, depths, cam_t)) == [0, 1]
            right_r += list(raw.match(tw, boxes, depths, cam_t)) == [0, 1]
        else:
            smoothed.match(tw, boxes, depths, cam_t)
    assert right_s >= 95 * 0.8 and right_s > right_r + 10


def test_joint_matcher_matches_a_far_vehicle_whose_lower_part_a_nearer_one_hides():
    """A far truck (rear 74 m) seen above and beside a nearer car (rear 37.75 m): Algorithm 1's
    lower quarter of the truck's box lies on the car, so the box's depth is the car's. The nearer
    twin explains that depth: the truck keeps its box (rather than being gated out by the 7.7-sigma
    depth disagreement). Without the nearer twin nothing explains it and the gate holds."""
    cam = pinhole_camera()
    # make_twins puts the GNSS point at z_ground + height; the body centre is half that up
    twins = make_twins(["near", "far"], [40.0, 80.0], [0.0, 0.3], length=[4.5, 12.0], width=[1.8, 2.5],
                       height=[1.5, 3.6], z_ground=[-0.75, -1.8])
    near_box = vehicle_box(cam, 40.0, 0.0)
    far_box = vehicle_box(cam, 80.0, 0.3, length=12.0, width=2.5, height=3.6)
    lower = far_box.copy()
    lower[1] = far_box[3] - 0.25 * (far_box[3] - far_box[1])
    assert near_box[0] <= lower[0] and lower[2] <= near_box[2] and near_box[1] <= lower[1]  # the car covers it
    samples = np.array([np.full(30, 40.0 - 2.25), np.full(30, 40.0 - 2.25)])  # both boxes measure the car
    boxes = np.stack([near_box, far_box])
    assert [int(g) for g in JointMatcher().match(twins, boxes, samples, cam)] == [0, 1]
    alone = twins.select([1])
    assert list(JointMatcher().match(alone, far_box[None], samples[1:], cam)) == [NO_MATCH]
    # the near twin's own box is never explained away: with only that box the far twin gets nothing
    assert [int(g) for g in JointMatcher().match(twins, near_box[None], samples[:1], cam)] == [0, NO_MATCH]


def test_joint_matcher_matches_the_visible_sliver_of_a_car_a_nearer_truck_hides():
    """A car 40 m ahead in the next lane, all but its left edge hidden behind a truck 20 m ahead:
    its box is the visible sliver (under 5 % of its expected box; its anchor, the body centre,
    lies behind the truck). Compared with the whole expected box the sliver is gated out (the
    matcher before the visible-cuboid term left the car unmatched); compared with the part of the
    expected box that the truck's leaves visible, it is the car's."""
    from vcfusion.fusion.matching import visible_boxes

    cam = pinhole_camera()
    twins = make_twins(["truck", "car"], [20.0, 40.0], [0.0, 2.56], length=[12.0, 4.5], width=[2.5, 1.8],
                       height=[3.6, 1.5], z_ground=[-1.8, -0.75])
    truck_box = vehicle_box(cam, 20.0, 0.0, length=12.0, width=2.5, height=3.6)
    car_full = vehicle_box(cam, 40.0, 2.56)
    sliver = np.array([car_full[0], car_full[1], truck_box[0], car_full[3]])  # left of the truck
    assert 0 < sliver[2] - sliver[0] < 0.05 * (car_full[2] - car_full[0])
    boxes = np.stack([truck_box, sliver])
    proj = project_twins(twins, cam)
    assert box_iou(proj.expected_box[1:], sliver[None])[0, 0] < JointMatcherParams().overlap_gate
    assert not (sliver[0] <= proj.anchor[1, 0] <= sliver[2])  # the anchor is outside its box
    visible, anchor_hidden, hidden_share = visible_boxes(proj)
    assert list(anchor_hidden) == [False, True]
    assert hidden_share[0] == 0 and 0.9 < hidden_share[1] < 1
    np.testing.assert_allclose(visible[0], proj.expected_box[0])  # nothing hides the truck
    assert box_iou(visible[1:], sliver[None])[0, 0] > 0.5
    samples = np.array([np.full(30, 14.0), np.full(30, 37.75)])  # rear faces
    assert [int(g) for g in JointMatcher().match(twins, boxes, samples, cam)] == [0, 1]
    # the mostly hidden car pays for its hidden share (a box wanted by it and a visible twin goes to
    # the visible one); the truck, hidden by nothing, does not
    cost, _ = JointMatcher().cost_matrix(proj, boxes, samples)
    cost0, _ = JointMatcher(JointMatcherParams(w_hidden=0.0)).cost_matrix(proj, boxes, samples)
    np.testing.assert_allclose(cost - cost0, np.repeat(hidden_share[:, None], 2, axis=1))
    # the sliver is not given to the car when the truck's box is the only box
    assert [int(g) for g in JointMatcher().match(twins, truck_box[None], samples[:1], cam)] == [0, NO_MATCH]


def test_an_anchor_off_the_image_is_replaced_by_the_centre_of_the_twins_part_in_view():
    """A car close by in the next lane is cut by the image border: its box is what is in view, its
    expected box is clipped to the image, its anchor (the body centre) is not. Like a hidden anchor,
    it is replaced by the centre of the part in view, so the car's own box pays no anchor distance."""
    cam = pinhole_camera()
    twins = make_twins(["cut"], [4.0], [3.5])
    proj = project_twins(twins, cam)
    assert proj.in_view[0] and proj.anchor[0, 0] < 0  # in view, anchor off the image
    box = vehicle_box(cam, 4.0, 3.5)
    box[[0, 2]] = np.clip(box[[0, 2]], 0, cam.width)
    box[[1, 3]] = np.clip(box[[1, 3]], 0, cam.height)
    samples = np.full((1, 30), 4.0 - 2.25)
    cost, allowed = JointMatcher().cost_matrix(proj, box[None], samples)
    no_anchor, _ = JointMatcher(JointMatcherParams(w_anchor=0.0)).cost_matrix(proj, box[None], samples)
    assert allowed[0, 0]
    np.testing.assert_allclose(cost, no_anchor)  # the anchor term is zero: the anchor used lies in the box
    assert [int(g) for g in JointMatcher().match(twins, box[None], samples, cam)] == [0]


def test_a_twin_hidden_whole_by_the_expected_boxes_takes_a_box_within_its_own_at_its_depth():
    """A car 27 m ahead right behind one 15 m ahead: by the expected boxes the near one hides all of
    it, yet its roof line shows (the expected boxes are coarser than the vehicles: a roof rack, a
    GNSS report's height a little low).
    The roof box is under 5 % of the far car's expected box and its anchor lies below it: no visible
    part to overlap, so only the rule for twins hidden whole lets the far car have it. A box at the
    near car's depth, or one sticking out of the far car's expected box, is not the far car's."""
    from vcfusion.fusion.matching import visible_boxes

    cam = pinhole_camera()
    twins = make_twins(["car", "far"], [15.0, 27.0], [0.0, 0.0])  # both 1.5 m high, at the camera's height
    proj = project_twins(twins, cam)
    _, _, hidden_share = visible_boxes(proj)
    assert list(hidden_share) == [0.0, 1.0]
    car_box, far = proj.expected_box[0].copy(), proj.expected_box[1]
    roof = far + [2, 0, -2, -(1 - 0.04) * (far[3] - far[1])]  # its top rows
    assert box_iou(far[None], roof[None])[0, 0] < JointMatcherParams().overlap_gate
    assert not (roof[1] <= proj.anchor[1, 1] <= roof[3])
    rear = {"car": 15.0 - 2.25, "far": 27.0 - 2.25}
    boxes = np.stack([car_box, roof])
    got = JointMatcher(JointMatcherParams(smoothing_alpha=None)).match(
        twins, boxes, np.array([np.full(30, rear["car"]), np.full(30, rear["far"])]), cam)
    assert [int(g) for g in got] == [0, 1]
    # at the near car's depth the roof box measured the near car: not the far one's
    got = JointMatcher(JointMatcherParams(smoothing_alpha=None)).match(
        twins, boxes, np.array([np.full(30, rear["car"]), np.full(30, rear["car"])]), cam)
    assert int(got[1]) == NO_MATCH
    # half of it above the far car's expected box: not within it
    high = roof - [0, roof[3] - roof[1], 0, 0]
    got = JointMatcher(JointMatcherParams(smoothing_alpha=None)).match(
        twins, np.stack([car_box, high]), np.array([np.full(30, rear["car"]), np.full(30, rear["far"])]), cam)
    assert int(got[1]) == NO_MATCH


def test_a_twin_hidden_whole_is_assigned_from_the_boxes_the_visible_twins_leave():
    """Jam dev seed 3078 (costs rounded): a visible car's own box (cost 0.18) was wanted by a car
    hidden whole behind it (3.69), and one joint assignment gave it to the hidden car, pushing the
    visible one onto a worse box (1.76): 3.69 + 1.76 < 0.18 + 6 (the hidden car without a box).
    Assigned in two rounds, the visible car keeps its box and the hidden one gets what is left."""
    from vcfusion.fusion.matching import visible_boxes
    assign = _assign_given
    swap = [[0.18, 1.76], [3.69, None]]
    assert assign(swap, [False, False]) == [1, 0]  # one round: the swap
    assert assign(swap, [False, True]) == [0, NO_MATCH]
    # a box the visible car does not take still goes to the hidden one, at its own cost
    assert assign([[0.18, None], [3.69, 2.5]], [False, True]) == [0, 1]
    assert assign([[0.18, None], [3.69, 6.5]], [False, True]) == [0, NO_MATCH]
    # which twins are hidden whole: by the expected boxes of nearer twins (a car right behind another)
    cam = pinhole_camera()
    proj = project_twins(make_twins(["car", "far"], [15.0, 27.0], [0.0, 0.0]), cam)
    assert list(visible_boxes(proj)[2]) == [0.0, 1.0]
    assert list(JointMatcher()._cost_terms(proj, np.zeros((0, 4)), np.zeros(0))[2]) == [False, True]


def test_a_weak_first_round_pair_is_decided_again_with_the_hidden_twins():
    """Jam dev seed 3170 (costs rounded): a far car visible by a corner kept, in the first round, the
    box of the car in front of it at 5.97 (just under the miss cost), which that car, hidden whole
    but for its roof, fits at 2.03: decided together, the hidden car gets it (2.03 + 6 < 5.97 + 6)."""
    assign = _assign_given
    steal = [[5.97, None], [2.03, None]]
    assert assign(steal, [False, True]) == [NO_MATCH, 0]
    # the far car keeps another box it can take, and a pair under weak_cost is never reopened
    assert assign([[5.97, 5.5], [2.03, None]], [False, True]) == [1, 0]
    assert assign([[2.4, None], [0.5, None]], [False, True]) == [0, NO_MATCH]
    # a weak pair that no hidden twin may take stays; without the rule the first round would stand
    assert assign([[5.97, None], [None, 2.03]], [False, True]) == [0, 1]
    assert assign(steal, [False, True], weak_cost=6.0) == [0, NO_MATCH]


def test_a_twin_all_but_beyond_the_image_side_does_not_take_the_box_beside_it():
    """Jam dev seed 3194: a car beside the camera, nearer than the car cut by the image's left side,
    shows less than a pixel column (its expected box 0.8 px wide at the border). Its anchor lies off
    the image, so its stand-in is its visible part's centre, which lay inside the box of the car
    beside it: that pair was allowed at 1.84, and it pushed the car onto a box over half of it."""
    cam = pinhole_camera()
    ahead = 6.0
    front_right = (CX - 0.3) * (ahead + 2.25) / FX  # lateral offset of its front right corner at u = 0.3
    proj = project_twins(make_twins(["beside", "edge"], [7.0, ahead], [3.0, front_right + 0.9]), cam)
    assert proj.in_view.all() and proj.expected_box[1, 2] - proj.expected_box[1, 0] < 1.0
    own = proj.expected_box[0]
    half = own.copy()
    half[0] = (own[0] + own[2]) / 2
    boxes = np.array([own, half])
    depths = np.full(2, proj.face_z[0])
    matcher = JointMatcher(JointMatcherParams(smoothing_alpha=None))
    assert not matcher.cost_matrix(proj, boxes, depths)[1][1].any()
    assert list(matcher.assign(proj, boxes, depths)) == [0, NO_MATCH]


def test_a_twin_the_joint_matcher_matched_after_latency_compensation_is_in_view():
    """A car 8 m ahead in the next lane; its report is 0.3 s old at 30 m/s, so as received it lies
    behind the camera. The joint matcher moves it on and matches its box: the twin is in view (the
    fusion stage dropped it: no guidance, no fusion row, not even a missed warning)."""
    from vcfusion.detection.detectors import OracleDetector
    from vcfusion.fusion.fuse import CameraFrame, fuse_frame

    cam = pinhole_camera(time=10.3)
    box = vehicle_box(cam, 8.0, 2.0)
    depth = np.full((480, 640), np.inf, np.float32)
    x1, y1, x2, y2 = np.round(box).astype(int)
    depth[y1:y2, max(x1, 0):x2] = 8.0 - 4.5 / 2
    frame = CameraFrame(10.3, np.zeros((480, 640, 3), np.uint8), depth, cam, gt_boxes=box[None], gt_ids=("car",),
                        gt_classes=np.array([3]))
    stale = make_twins(["car"], [8.0 - 30.0 * 0.3], [2.0], measured_time=10.0, speed=30.0)
    assert not project_twins(stale, cam).in_view[0]
    result = fuse_frame(frame, stale, OracleDetector(), np.random.default_rng(0), methods=("joint",))
    assert result.choice["joint"][0] == 0 and result.in_view[0]


def test_a_truck_alongside_reaching_behind_the_camera_is_in_view_with_its_part_in_front():
    """A 12 m truck in the next lane, its rear 2 m behind the camera, its cab 10 m ahead: most of
    the image's left side. With every corner required in front of the near plane it was out of
    view (no box, no guidance, no fusion row); clipped at the plane, its box runs from the image's
    left border to its front's far corner."""
    cam = pinhole_camera()
    truck = make_twins(["truck"], [4.0], [3.5], length=12.0, width=2.5, height=3.6, z_ground=-1.8)  # antenna 1.8 m up
    proj = project_twins(truck, cam)
    assert proj.in_view[0]
    front = vehicle_box(cam, 10.0 - 0.01, 3.5, length=0.02, width=2.5, height=3.6)  # the front face alone
    x1, y1, x2, y2 = proj.expected_box[0]
    assert x1 == -0.5 and y1 == -0.5 and y2 == 479.5  # cut by the image's borders
    assert x2 == pytest.approx(front[2], abs=0.5)  # the front's inner edge: the box's right side
    assert 0.5 < proj.face_z[0] < 10.0  # depth sees the side in view, not the rear behind the camera


def test_the_surface_drawing_a_box_decides_between_the_vehicle_and_the_one_behind_it():
    """Jam dev seed 3295: a car 7.2 m ahead and, behind it in the next lane, a truck (face 8.9 m) whose
    lower part the car hides. The truck's box samples the car in its lower part, the car's box
    samples the truck above its roof, and the best of the samples' quantiles fits either twin to
    either box: the two swapped boxes on a 0.02 difference in cost. The depth of the surface that
    draws each box's outline (box_refine.box_surface_depths) tells them apart; where it is unknown
    (nan) the samples decide as before, and it never changes which pairs are allowed."""
    cam = pinhole_camera()
    twins = make_twins(["car", "truck"], [9.45, 13.0], [0.6, -1.2], length=[4.5, 8.2], width=[1.8, 2.5],
                       height=[1.5, 3.6], z_ground=[-0.75, -1.8])
    proj = project_twins(twins, cam)
    face = {"car": 9.45 - 2.25, "truck": 13.0 - 4.1}
    car_box = vehicle_box(cam, 9.45, 0.6)
    truck_box = vehicle_box(cam, 13.0, -1.2, length=8.2, width=2.5, height=3.6)
    boxes = np.stack([car_box, truck_box])
    # the car's box: the car, and the truck above its roof; the truck's box: mostly the car in front
    samples = np.array([np.r_[np.full(25, face["car"]), np.full(5, face["truck"])],
                        np.r_[np.full(20, face["car"]), np.full(10, face["truck"])]])
    matcher = JointMatcher(JointMatcherParams(smoothing_alpha=None))
    cost, allowed = matcher.cost_matrix(proj, boxes, samples)
    surface = np.array([face["car"], face["truck"]])
    cost_s, allowed_s = matcher.cost_matrix(proj, boxes, samples, surface)
    sigma = 0.05 * np.array([face["car"], face["truck"]]) + 1.0
    disagree = abs(face["truck"] - face["car"]) / sigma
    # each twin's own box: no depth disagreement either way; the other's box now pays it, less the
    # tolerance the matcher grants any measured depth, scaled to reach the gate's penalty at the gate
    tol, gate = matcher.params.depth_tolerance_sigmas, matcher.params.depth_gate
    np.testing.assert_allclose(np.diag(cost_s), np.diag(cost))
    np.testing.assert_allclose([cost_s[0, 1] - cost[0, 1], cost_s[1, 0] - cost[1, 0]],
                               np.minimum((disagree - tol) * gate / (gate - tol), gate))
    np.testing.assert_array_equal(allowed_s, allowed)
    assert [int(g) for g in matcher.assign(proj, boxes, samples, surface)] == [0, 1]
    # unknown surfaces: the samples' cost, box by box
    half = matcher.cost_matrix(proj, boxes, samples, np.array([face["car"], np.nan]))[0]
    np.testing.assert_allclose(half[:, 1], cost[:, 1])
    np.testing.assert_allclose(half[:, 0], cost_s[:, 0])
    with pytest.raises(ValueError, match="surface_depths"):
        matcher.cost_matrix(proj, boxes, samples, surface[:1])


def test_match_details_report_the_chosen_boxes_depth_agreement_and_the_projection_used():
    """`match_details` gives `match`'s choice with the twins as the matcher projected them and, per
    chosen box, its depth disagreement in sigmas and whether that depth is a nearer twin's: a car
    hidden whole behind another whose roof box measures its own depth agrees (0 sigmas, its own); a
    far truck whose box's lower quarter measures the car in front is matched on the car's depth."""
    from vcfusion.fusion.matching import visible_boxes

    cam = pinhole_camera()
    twins = make_twins(["car", "far"], [15.0, 27.0], [0.0, 0.0])
    proj = project_twins(twins, cam)
    far = proj.expected_box[1]
    roof = far + [2, 0, -2, -(1 - 0.04) * (far[3] - far[1])]
    boxes = np.stack([proj.expected_box[0], roof])
    samples = np.array([np.full(30, 15.0 - 2.25), np.full(30, 27.0 - 2.25)])
    got = JointMatcher(JointMatcherParams(smoothing_alpha=None)).match_details(twins, boxes, samples, cam)
    assert [int(g) for g in got.choice] == [0, 1]
    np.testing.assert_allclose(got.depth_sigmas, [0.0, 0.0], atol=1e-9)
    assert list(got.depth_of_nearer) == [False, False]
    assert list(got.hidden_share) == list(visible_boxes(got.projection)[2]) == [0.0, 1.0]
    # 2 m off for the far car: 2 / (0.05 * 24.75 + 1) = 0.9 sigmas
    off = np.array([np.full(30, 15.0 - 2.25), np.full(30, 27.0 - 2.25 + 2.0)])
    got = JointMatcher(JointMatcherParams(smoothing_alpha=None)).match_details(twins, boxes, off, cam)
    assert got.depth_sigmas[1] == pytest.approx(2.0 / (0.05 * 24.75 + 1.0), rel=1e-6)

    twins = make_twins(["near", "far"], [40.0, 80.0], [0.0, 0.3], length=[4.5, 12.0], width=[1.8, 2.5],
                       height=[1.5, 3.6], z_ground=[-0.75, -1.8])
    boxes = np.stack([vehicle_box(cam, 40.0, 0.0), vehicle_box(cam, 80.0, 0.3, length=12.0, width=2.5, height=3.6)])
    samples = np.array([np.full(30, 40.0 - 2.25), np.full(30, 40.0 - 2.25)])  # both boxes measure the car
    got = JointMatcher().match_details(twins, boxes, samples, cam)
    assert [int(g) for g in got.choice] == [0, 1] and list(got.depth_of_nearer) == [False, True]
    assert got.depth_sigmas[1] > JointMatcherParams().depth_gate
    # an unmatched twin: no depth agreement
    got = JointMatcher().match_details(twins, boxes[:1], samples[:1], cam)
    assert got.choice[1] == NO_MATCH and got.depth_sigmas[1] == np.inf


def test_the_fusion_result_judges_outlines_where_the_matcher_put_the_twins():
    """The overlay's rules read each twin's outline and hidden share from the fusion result. A car
    10 m ahead whose report is 0.3 s old at 20 m/s is, as received, 4 m ahead: its outline then
    covers the whole of a stopped car 25 m ahead and 2.5 m to the left, of which in fact the left
    third shows. The joint matcher moves the report on by its age and matches both boxes; the result's
    outlines are the matcher's, so the far car is not hidden whole and its box is drawn (as
    received it was "hidden": a visible, matched car that got no box)."""
    from vcfusion.detection.detectors import OracleDetector
    from vcfusion.fusion.fuse import CameraFrame, fuse_frame, undrawn_reason
    from vcfusion.fusion.matching import visible_boxes

    cam = pinhole_camera(time=10.3)
    near, far = vehicle_box(cam, 10.0, 0.0), vehicle_box(cam, 25.0, 2.5)
    depth = np.full((480, 640), np.inf, np.float32)
    for (x1, y1, x2, y2), z in ((far, 25.0 - 2.25), (near, 10.0 - 2.25)):  # the near car painted last
        depth[int(y1):int(np.ceil(y2)), max(int(x1), 0):int(np.ceil(x2))] = z
    seen_far = np.array([far[0], far[1], near[0], far[3]])  # the part of the far car left of the near one
    assert seen_far[2] - seen_far[0] > 0.3 * (far[2] - far[0])
    frame = CameraFrame(10.3, np.zeros((480, 640, 3), np.uint8), depth, cam, gt_boxes=np.stack([near, seen_far]),
                        gt_ids=("near", "far"), gt_classes=np.array([3, 3]))
    twins = make_twins(["near", "far"], [10.0 - 20.0 * 0.3, 25.0], [0.0, 2.5], measured_time=[10.0, 10.3],
                       speed=[20.0, 0.0])
    assert visible_boxes(project_twins(twins, cam))[2][1] == 1.0  # as received: hidden whole
    result = fuse_frame(frame, twins, OracleDetector(), np.random.default_rng(0), methods=("joint",))
    assert [int(c) for c in result.choice["joint"]] == [0, 1]
    assert result.hidden_share[1] < 0.9
    moved = project_twins(extrapolate_twins(twins, 10.3), cam)
    np.testing.assert_allclose(result.expected_boxes, moved.expected_box)
    box = result.box_of("joint", 1)
    assert undrawn_reason(box, result.expected_boxes[1], result.hidden_share[1],
                          depth_sigmas=result.depth_sigmas[1]) == ""


def test_a_far_twins_noisy_depth_counts_for_less_under_the_sensors_own_noise():
    """A far car (rear 97.75 m) whose box reads 30 m too deep, as a stereo pair's far depth does
    (sigma_z = z^2 sigma_d / (f B): 40 m at 98 m with B = 0.12 m, 0.25 px), and a box of an
    unconnected car 20 m nearer in the next lane that holds the twin's anchor. With the matcher's
    sigma alone (5.9 m) the right box is 5.1 sigma off and gated, and the wrong one is taken; with
    the sensor's sigma combined the right box wins on its overlap. Exact depth changes nothing."""
    from vcfusion.fusion.road import DepthNoise

    cam = pinhole_camera()
    twins = make_twins(["far"], [100.0], [0.0], z_ground=-0.75)
    boxes = np.stack([vehicle_box(cam, 100.0, 0.0), vehicle_box(cam, 80.0, 0.8)])
    depths = np.array([100.0 - 2.25 + 30.0, 80.0 - 2.25])
    stereo = DepthNoise(c=0.25 / (FX * 0.12))
    assert list(JointMatcher().match(twins, boxes, depths, cam)) == [1]
    assert list(JointMatcher().match(twins, boxes, depths, cam, depth_noise=stereo)) == [0]
    proj = project_twins(twins, cam)
    plain = JointMatcher().cost_matrix(proj, boxes, depths)
    exact = JointMatcher().cost_matrix(proj, boxes, depths, depth_noise=DepthNoise())
    assert all(np.array_equal(a, b) for a, b in zip(plain, exact))


def test_a_box_whose_lower_quarter_a_nearer_car_hides_is_read_on_the_twins_own_samples():
    """Curved seed 2045: a truck turned across its lane 30 m ahead, a car 8 m ahead hiding the lower
    half of the truck's box. That box's lower quarter samples the car (7.2 m) and the truck's side
    receding from its face (24-31 m): over all samples the best quantile reads 26.7 m, 1.2 sigma off
    the face, and a box on the truck's upper part alone (24-27 m) took the twin. Samples nearer
    than the twin's depth gate are the car in front of it: read on the rest, the whole box is the
    truck's. A box whose lower quarter is mostly the car is read as it is."""
    from vcfusion.fusion.matching import DEPTH_QUANTILES, MIN_UNOCCLUDED_SAMPLE_SHARE, _unoccluded_depth_err

    cam = pinhole_camera()
    twins = make_twins(["car", "truck"], [9.45, 30.0], [-1.0, -3.0], length=[4.5, 12.0], width=[1.8, 2.5],
                       height=[1.5, 3.6], z_ground=[-0.75, -1.8])
    face = np.array([9.45 - 2.25, 30.0 - 6.0])
    car = vehicle_box(cam, 9.45, -1.0)
    whole = vehicle_box(cam, 30.0, -3.0, length=12.0, width=2.5, height=3.6)
    w, h = whole[2] - whole[0], whole[3] - whole[1]
    upper = np.array([whole[0] + 0.45 * w, whole[1], whole[2], whole[1] + 0.6 * h])
    truck_side = np.linspace(24.0, 31.0, 15)
    samples = np.array([np.full(30, face[0]), np.r_[np.full(15, face[0]), truck_side], np.linspace(24.0, 27.0, 30)])
    matcher = JointMatcher(JointMatcherParams(smoothing_alpha=None))
    proj = project_twins(twins, cam)
    assert [int(g) for g in matcher.assign(proj, np.stack([car, whole, upper]), samples)] == [0, 1]

    sigma = 0.05 * face + 1.0
    err = _unoccluded_depth_err(samples, face, sigma, JointMatcherParams().depth_gate)
    # the truck against its whole box: the truck's samples alone (np.quantile as reference)
    assert err[1, 1] == pytest.approx(np.min(np.abs(np.quantile(truck_side, DEPTH_QUANTILES) - face[1])) / sigma[1])
    mixed = np.min(np.abs(np.quantile(samples[1], DEPTH_QUANTILES) - face[1])) / sigma[1]
    assert mixed > 1.0 > 3 * err[1, 1]
    # nothing dropped (the car's own box, the upper box, the car against any box): no second reading
    assert np.isinf(err[1, [0, 2]]).all() and np.isinf(err[0]).all()
    # a lower quarter mostly the car: under MIN_UNOCCLUDED_SAMPLE_SHARE left, read as it is
    few = int(MIN_UNOCCLUDED_SAMPLE_SHARE * 30) - 1
    mostly_car = np.r_[np.full(30 - few, face[0]), np.full(few, face[1])][None]
    assert np.isinf(_unoccluded_depth_err(mostly_car, face, sigma, 4.0)).all()
    enough = np.r_[np.full(30 - few - 2, face[0]), np.full(few + 2, face[1])][None]
    assert _unoccluded_depth_err(enough, face, sigma, 4.0)[1, 0] == pytest.approx(0.0)


def test_depths_within_the_tolerance_leave_the_choice_between_two_boxes_to_the_overlap():
    """Curve seed 3104: a turned truck gets two boxes, its whole body and its upper part, both of
    whose depths agree with its face within its own error. Without a tolerance the box whose depth
    happens to read nearer the face wins on noise; within it the overlap decides. A box without
    depth keeps the neutral one-sigma penalty, and a disagreement at the gate still costs the gate."""
    cam = pinhole_camera()
    twin = make_twins(["truck"], [20.0], [0.0], length=8.2, width=2.5, height=3.6, z_ground=-1.8)
    proj = project_twins(twin, cam)
    whole = vehicle_box(cam, 20.0, 0.0, length=8.2, width=2.5, height=3.6)
    upper = whole.copy()
    upper[3] = whole[1] + 0.8 * (whole[3] - whole[1])
    boxes = np.stack([whole, upper])
    face = proj.face_z[0]
    sigma = 0.05 * face + 1.0
    depths = np.array([face + 0.45 * sigma, face + 0.02 * sigma])  # both well within the twin's error

    strict = JointMatcher(JointMatcherParams(smoothing_alpha=None, depth_tolerance_sigmas=0.0))
    tolerant = JointMatcher(JointMatcherParams(smoothing_alpha=None, depth_tolerance_sigmas=0.5))
    assert [int(g) for g in strict.assign(proj, boxes, depths)] == [1]  # the noise decides
    assert [int(g) for g in tolerant.assign(proj, boxes, depths)] == [0]  # the overlap decides
    cost_strict = strict.cost_matrix(proj, boxes, depths)[0]
    cost_tolerant = tolerant.cost_matrix(proj, boxes, depths)[0]
    np.testing.assert_allclose(cost_strict - cost_tolerant, [[0.45, 0.02]], atol=1e-9)
    # no depth: the same neutral penalty with and without the tolerance
    no_depth = np.array([np.nan, np.nan])
    np.testing.assert_allclose(tolerant.cost_matrix(proj, boxes, no_depth)[0],
                               strict.cost_matrix(proj, boxes, no_depth)[0])
    # at the gate the penalty is the gate's either way
    at_gate = np.array([face + 4.0 * sigma, face + 4.0 * sigma])
    np.testing.assert_allclose(tolerant.cost_matrix(proj, boxes, at_gate)[0],
                               strict.cost_matrix(proj, boxes, at_gate)[0])
    with pytest.raises(ValueError, match="depth_tolerance_sigmas"):
        JointMatcherParams(depth_tolerance_sigmas=4.0)
