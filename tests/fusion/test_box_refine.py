"""Depth-guided box refinement (vcfusion.fusion.box_refine) on real renders: boxes a few pixels off,
or swallowing the car behind (the paper's Fig. 3), snap back to the instance-map boxes; the
oracle's boxes and boxes with no vehicle surface in them are left alone."""

from dataclasses import replace

import numpy as np
import pytest

from vcfusion.fusion.box_refine import BoxRefineParams, refine_boxes
from vcfusion.fusion.matching import box_iou


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Camera frames (RGB, depth, K, pose, instance-map boxes) of procedural scenes: a dense jam
    (chains, cars hiding cars) and the training mix."""
    from scenario_files import SCENARIOS
    from vcfusion.detection.detector_train import load_coco, read_rgb
    from vcfusion.detection.family_eval import _camera_frame
    from vcfusion.detection.scenes import render_scenes
    from vcfusion.scenario import load_scenario

    root = tmp_path_factory.mktemp("refine")
    sc = load_scenario(SCENARIOS / "overlap.yaml")
    out = []
    for family, seeds in (("jam", [3, 4, 5, 6]), ("train", [7, 8, 9])):
        render_scenes(sc, family, seeds, root / family, progress=False)
        ds = load_coco(root / family)
        out += [_camera_frame(ds, k, read_rgb(p)) for k, p in enumerate(ds.images)]
    return out


def _inner(frame, min_area=400.0):
    """Ground-truth boxes of at least min_area px^2 that do not touch the image border."""
    g = frame.gt_boxes
    h, w = frame.depth.shape
    area = (g[:, 2] - g[:, 0]) * (g[:, 3] - g[:, 1])
    keep = (area >= min_area) & (g[:, 0] > 2) & (g[:, 1] > 2) & (g[:, 2] < w - 3) & (g[:, 3] < h - 3)
    return g[keep]


def _refine(frame, boxes, params=BoxRefineParams()):
    return refine_boxes(boxes, frame.depth, frame.camera.K, frame.camera.T_world_to_camera, params)


def test_boxes_a_few_pixels_off_snap_back_to_the_vehicle(frames):
    before, after = [], []
    for frame in frames:
        gt = _inner(frame)
        if not len(gt):
            continue
        w, h = gt[:, 2] - gt[:, 0], gt[:, 3] - gt[:, 1]
        # grown by 12 % per side and shifted: the typical error of a detector at a quarter of the resolution
        off = gt + np.stack([-0.12 * w + 2, -0.12 * h - 1, 0.12 * w + 2, 0.12 * h - 1], axis=1)
        res = _refine(frame, off)
        before += list(np.diag(box_iou(gt, off)))
        after += list(np.diag(box_iou(gt, res.boxes)))
    before, after = np.array(before), np.array(after)
    assert len(after) >= 20
    assert np.median(before) < 0.75  # the perturbation matters
    print(f"IoU with the instance-map box: median {np.median(before):.3f} -> {np.median(after):.3f}, "
          f">= 0.8: {(before >= 0.8).mean():.1%} -> {(after >= 0.8).mean():.1%} ({len(after)} boxes)")
    # a few miss: a truck's side is deeper than the band, or a nearer car joins a truck's segment
    # (measured: median 0.650 -> 0.976, >= 0.8: 0 % -> 87 % of 23 boxes; 0.896 / 65 % with the support at 0.15)
    assert np.median(after) >= 0.93
    assert (after >= 0.8).mean() >= 0.8 and after.mean() >= before.mean() + 0.15


def test_a_box_swallowing_the_car_behind_snaps_to_the_car_in_front(frames):
    """Fig. 3: a chain in one lane; a box over both the near car and the far car above it."""
    results = []
    for frame in frames:
        gt = _inner(frame, 100.0)
        for near in gt:
            for far in gt:
                # on a flat road the nearer vehicle's box reaches lower in the image
                if far[3] >= near[3] - 1 or far[1] >= near[1]:
                    continue
                if far[0] < near[0] - 2 or far[2] > near[2] + 2:
                    continue  # the car behind peeks over the one in front, within its width
                union = np.array([near[0], far[1], near[2], near[3]])
                swallowed = box_iou(near[None], union[None])[0, 0]
                if swallowed > 0.9:
                    continue  # the far car barely shows: no real swallowing
                res = _refine(frame, union[None])
                results.append((swallowed, box_iou(near[None], res.boxes)[0, 0]))
    results = np.array(results)
    assert len(results) >= 3, "the jam scenes should hold chains"
    # (measured: 5 chains, IoU with the car in front 0.79-0.88 -> 0.88-1.00)
    assert (results[:, 1] >= 0.85).mean() >= 0.8, results
    assert results[:, 1].mean() >= results[:, 0].mean() + 0.05, results


def test_a_box_without_a_vehicle_surface_is_kept(frames):
    frame = frames[0]
    sky = np.array([[300.0, 5.0, 340.0, 30.0]])  # above the horizon: sky only
    assert not np.isfinite(frame.depth[5:31, 300:341]).any()
    res = _refine(frame, sky)
    assert not res.refined[0] and np.array_equal(res.boxes, sky)
    empty = _refine(frame, np.zeros((0, 4)))
    assert empty.boxes.shape == (0, 4) and empty.refined.shape == (0,)


def test_the_oracle_is_never_refined_and_a_camera_without_pose_is_refused(frames):
    from dataclasses import replace

    from vcfusion.detection.detectors import Detections, OracleDetector
    from vcfusion.fusion.fuse import detect_frame

    frame = frames[0]
    oracle = detect_frame(frame, OracleDetector(), BoxRefineParams())
    assert np.array_equal(oracle.boxes, frame.gt_boxes)

    class Off:
        def detect(self, image):
            g = frame.gt_boxes[:1] + np.array([-4.0, -4.0, 4.0, 4.0])
            return Detections.of(g, np.ones(1), np.full(1, 3))

    snapped = detect_frame(frame, Off(), BoxRefineParams())
    assert box_iou(frame.gt_boxes[:1], snapped.boxes)[0, 0] > box_iou(frame.gt_boxes[:1], Off().detect(None).boxes)[0, 0]
    with pytest.raises(ValueError, match="intrinsics"):
        detect_frame(replace(frame, camera=replace(frame.camera, K=None)), Off(), BoxRefineParams())


def test_bad_parameters_and_inputs_are_refused():
    with pytest.raises(ValueError, match="margin"):
        BoxRefineParams(margin=-0.1)
    with pytest.raises(ValueError, match="min_iou"):
        BoxRefineParams(min_iou=1.5)
    with pytest.raises(ValueError, match="depth"):
        refine_boxes(np.zeros((1, 4)), np.zeros(5), np.eye(3), np.eye(4))
    with pytest.raises(ValueError, match="K"):
        refine_boxes(np.zeros((1, 4)), np.zeros((4, 4)), np.eye(4), np.eye(4))


def test_the_scenario_switches_the_refinement():
    from scenario_files import SCENARIOS
    from vcfusion.fusion.stage import refine_params
    from vcfusion.scenario import load_scenario

    sc = load_scenario(SCENARIOS / "accident_ar.yaml")
    assert refine_params(sc) == BoxRefineParams()
    off = sc.model_copy(update={"fusion": sc.fusion.model_copy(update={"refine_boxes": False})})
    assert refine_params(off) is None


def _propose(frame, boxes):
    from vcfusion.fusion.box_refine import depth_proposals

    return depth_proposals(frame.depth, frame.camera.K, frame.camera.T_world_to_camera, boxes)


def test_a_vehicle_without_a_box_is_proposed_from_depth(frames):
    """Each vehicle's box left out in turn (the others given as detections): the depth segments
    propose it; with every box given, nothing is proposed on top of a vehicle."""
    found, extra = [], 0
    for frame in frames:
        gt = _inner(frame)
        for k in range(len(gt)):
            boxes, _ = _propose(frame, np.delete(frame.gt_boxes, np.flatnonzero((frame.gt_boxes == gt[k]).all(1)), 0))
            found.append(box_iou(gt[k:k + 1], boxes).max() if len(boxes) else 0.0)
        boxes, is_truck = _propose(frame, frame.gt_boxes)
        assert boxes.shape == (len(is_truck), 4)
        extra += int((box_iou(boxes, frame.gt_boxes).max(axis=1) >= 0.5).sum()) if len(boxes) else 0
    found = np.array(found)
    print(f"left-out vehicles proposed at IoU >= 0.7: {(found >= 0.7).mean():.1%} of {len(found)}; "
          f"proposals on a given box: {extra}")
    assert len(found) >= 20
    # (measured: 91 % of 23; without the 'behind the box's surface' rule 74 %: a car peeking over or
    # beside a nearer one lies inside the nearer one's box; with that rule at 3 m instead of
    # behind_m = 1 m, 87 %: a car 1-3 m behind a nearer one's surface counted as part of it)
    assert (found >= 0.7).mean() >= 0.9 and np.median(found) >= 0.85
    assert extra == 0


def test_detect_frame_adds_proposals_to_the_detectors_boxes(frames):
    from dataclasses import replace

    from vcfusion.detection.detectors import Detections
    from vcfusion.fusion.fuse import detect_frame

    class Blind:
        def detect(self, image):
            return Detections.empty()

    frame = frames[0]
    seen = detect_frame(frame, Blind(), BoxRefineParams())
    assert len(seen) >= 1 and np.all(seen.scores == BoxRefineParams().proposals.score)
    assert set(seen.classes.tolist()) <= {1, 2}  # passenger, truck
    assert box_iou(_inner(frame, 400.0), seen.boxes).max(axis=1).mean() >= 0.7
    assert len(detect_frame(frame, Blind(), replace(BoxRefineParams(), proposals=None))) == 0
    sky = replace(frame, depth=np.full_like(frame.depth, np.inf))
    assert len(detect_frame(sky, Blind(), BoxRefineParams())) == 0


def _mask_box(mask):
    """The pixel-centre box (x1, y1, x2, y2) around a mask's pixels."""
    ys, xs = np.nonzero(mask)
    return np.array([xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5])


def _image_labels(seg, shape):
    """object_segments' labels placed in an image of `shape` (they start at row seg.y_lo)."""
    labels = np.zeros(shape, seg.labels.dtype)
    labels[seg.y_lo:seg.y_lo + len(seg.labels)] = seg.labels
    return labels


def _plate(depth, K, T, x, y0, y1, top, bottom=0.0):
    """A flat upright rectangle facing the camera, x metres ahead, across y0..y1, from `bottom` (the
    road) up to `top`, drawn into the camera-Z depth image by exact ray-plane intersection."""
    R, t = T[:3, :3], T[:3, 3]
    centre = -R.T @ t
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = R.T @ (np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))  # camera-Z = 1 per ray
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (x - centre[0]) / rays[0]
    p = centre[:, None] + s * rays
    hit = (s > 0) & (p[1] >= y0) & (p[1] <= y1) & (p[2] >= bottom) & (p[2] <= top)
    z = depth.ravel().copy()
    z[hit & (s < z)] = s[hit & (s < z)]
    return z.reshape(h, w).astype(np.float32)


def test_a_narrow_car_sliver_is_proposed_but_not_a_post_or_a_tree_trunk():
    """What is left of a car mostly hidden behind another is as narrow as 0.27 m (jam development
    seed 3122: 0.28 m at 13 m), and narrower still: 6 px at 19 m, 0.249 m, and 4 px at 17 m, 0.15 m
    (seeds 3444, 3327; a 0.25 m limit misses them); reflector posts
    (0.12 m) are narrower, and a segment standing higher than a truck's roof line must be as wide as a
    vehicle (tree trunks)."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import ProposalParams, depth_proposals

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    cases = {"car sliver": (2.0, 2.27, 1.5), "narrower sliver": (2.0, 2.2, 1.5), "post": (5.0, 5.12, 1.4),
             "trunk": (-6.0, -5.55, 4.0)}
    proposed, before = {}, {}
    for name, (y0, y1, top) in cases.items():
        depth = _plate(road, K, T, 20.0, y0, y1, top)
        assert (depth < road).sum() > 60, name  # the object is in view
        boxes, _ = depth_proposals(depth, K, T, np.zeros((0, 4)), BoxRefineParams())
        proposed[name] = len(boxes)
        old = BoxRefineParams(proposals=ProposalParams(min_width_m=0.25))
        before[name] = len(depth_proposals(depth, K, T, np.zeros((0, 4)), old)[0])
    assert proposed == {"car sliver": 1, "narrower sliver": 1, "post": 0, "trunk": 0}
    assert before["narrower sliver"] == 0
    # the same sliver 0.8 m wide stands for any vehicle; the trunk that wide is a (truck-high) vehicle
    wide = _plate(road, K, T, 20.0, -6.0, -5.1, 4.0)
    assert len(depth_proposals(wide, K, T, np.zeros((0, 4)), BoxRefineParams())[0]) == 1


def test_a_far_sliver_of_30_to_40_object_pixels_is_proposed():
    """The roof line of a car behind the next one in a jam shows as 20 x 5 px at 30 m (jam development
    seed 3207): a 0.5 m strip at 60 m holds about as few object pixels, and is a vehicle."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import depth_proposals, object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    depth = _plate(road, K, T, 60.0, 2.0, 2.5, 1.4)
    segments = object_segments(depth, K, T)
    assert 30 <= segments.areas[1:].max() < 40
    boxes, _ = depth_proposals(depth, K, T, np.zeros((0, 4)), BoxRefineParams(), segments)
    assert len(boxes) == 1 and box_iou(boxes, _mask_box(depth < road)[None])[0, 0] > 0.6


def test_a_truck_cut_by_the_image_side_is_proposed_however_narrow_it_shows():
    """Beside the camera in a jam, a truck in the next lane shows a strip at the image's side as
    narrow as a tree trunk (jam development seed 3233: 0.73 m of a truck's side): its width is what the
    image cuts, not the vehicle's. The same strip inside the image is still a trunk."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import depth_proposals

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    camera = -T[:3, :3].T @ T[:3, 3]
    for ahead in (8.0, 12.0):
        side = camera[1] + K[0, 2] * (ahead - camera[0]) / K[0, 0]  # the left image side's lateral offset
        cut = _plate(road, K, T, ahead, side - 0.3, side + 3.0, 3.8)
        boxes, is_truck = depth_proposals(cut, K, T, np.zeros((0, 4)), BoxRefineParams())
        assert len(boxes) == 1 and is_truck[0] and boxes[0, 0] == -0.5
        assert box_iou(boxes, _mask_box(cut < road)[None])[0, 0] > 0.85
        inside = _plate(road, K, T, ahead, 1.0, 1.3, 3.8)
        assert len(depth_proposals(inside, K, T, np.zeros((0, 4)), BoxRefineParams())[0]) == 0


def test_a_car_corner_cut_by_the_image_side_is_proposed_but_not_a_guard_rail_or_the_same_inside():
    """Of a car alongside the camera in the next lane only its front corner shows at the image's side,
    bonnet and wing, lower than the 1 m a proposal's top needs (jam development seeds 3282, 3364: tops
    0.96 and 0.99 m at 8.5 m): cut by the side, no wider and no deeper than a vehicle, 0.8 m does. A
    guard rail as high, cut by the same side, runs tens of metres away from the camera: not
    proposed; nor is the corner's shape inside the image (a kerb-high box, a bollard)."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import ProposalParams, depth_proposals

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    camera = -T[:3, :3].T @ T[:3, 3]
    ahead = 8.5
    side = camera[1] + K[0, 2] * (ahead - camera[0]) / K[0, 0]  # the left image side's lateral offset
    corner = _plate(road, K, T, ahead, side - 0.4, side + 0.5, 0.9)
    shown = corner < road
    assert _mask_box(shown)[0] == -0.5  # the image's side cuts it
    boxes, is_truck = depth_proposals(corner, K, T, np.zeros((0, 4)), BoxRefineParams())
    assert len(boxes) == 1 and not is_truck[0]
    # left, top and right as shown (to a pixel)
    np.testing.assert_allclose(boxes[0, :3], _mask_box(shown)[:3], atol=1.0)
    before = BoxRefineParams(proposals=ProposalParams(min_top_truncated_m=1.0))
    assert len(depth_proposals(corner, K, T, np.zeros((0, 4)), before)[0]) == 0
    rail = _side(road, K, T, side + 0.2, 4.0, 60.0, 0.9)  # along the road, from beside the camera on
    assert (rail < road)[:, 0].any()
    assert len(depth_proposals(rail, K, T, np.zeros((0, 4)), BoxRefineParams())[0]) == 0
    inside = _plate(road, K, T, ahead, 0.0, 0.9, 0.9)
    assert len(depth_proposals(inside, K, T, np.zeros((0, 4)), BoxRefineParams())[0]) == 0


def test_a_sliver_between_two_nearer_cars_is_proposed_with_its_whole_outline():
    """A car 30 m ahead seen only between two cars at 15 m: the cut at the depth jumps removes the
    sliver's pixels next to each near car (the farther pixel of each jumping pair); they are given
    back to it, so its box is exactly what the depth image shows of it (without them it is 2 px
    narrower: IoU about 0.8 for a sliver this narrow)."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import depth_proposals

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    far = _plate(road, K, T, 30.0, -1.0, 1.0, 1.5)
    depth = _plate(_plate(far, K, T, 15.0, 0.3, 2.0, 1.6), K, T, 15.0, -2.0, -0.3, 1.6)
    shown = np.isclose(depth, far, rtol=0, atol=1e-4) & (depth < road)  # the far car's own pixels
    truth = _mask_box(shown)
    assert 8 <= truth[2] - truth[0] <= 20  # a sliver
    boxes, _ = depth_proposals(depth, K, T, np.zeros((0, 4)), BoxRefineParams())
    assert len(boxes) == 3  # the two near cars and the sliver
    sliver = boxes[np.argmax(box_iou(truth[None], boxes)[0])]
    # left, top and right as shown; the bottom goes down the car's surface to where the refinement's
    # object pixels end, 0.05 m above the road (it stopped at the proposals' 0.3 m, 7 px higher here)
    np.testing.assert_allclose(sliver[:3], truth[:3])
    from vcfusion.fusion.box_refine import _Heights
    height = _Heights(K, T).window(depth.astype(np.float32), 0, 0)
    lowest = np.flatnonzero((shown & (height > BoxRefineParams().min_height_m)).any(axis=1))[-1]
    assert sliver[3] == lowest + 0.5
    assert truth[3] - sliver[3] <= 2


def test_a_tree_lower_than_the_cap_is_not_proposed_but_a_truck_seen_between_two_cars_is():
    """A crown 1.6 m wide and 1.5-4 m up on a 0.2 m trunk stands on one narrow stem under its middle:
    a tree (it is lower than the 4.5 m cap and wider than a trunk, so only its shape tells). A truck
    seen over two nearer cars and through the 0.2 m gap between them has the same shape, but nearer
    vehicles stand beside its 'stem': it is proposed."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import depth_proposals

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    tree = _plate(_plate(road, K, T, 40.0, -6.8, -5.2, 4.0, bottom=1.5), K, T, 40.0, -6.1, -5.9, 1.5)
    assert len(depth_proposals(tree, K, T, np.zeros((0, 4)), BoxRefineParams())[0]) == 0
    no_rule = replace(BoxRefineParams(), proposals=replace(BoxRefineParams().proposals, max_stem_share=0.0))
    assert len(depth_proposals(tree, K, T, np.zeros((0, 4)), no_rule)[0]) == 1
    truck = _plate(road, K, T, 30.0, -1.25, 1.25, 3.6)
    scene = _plate(_plate(truck, K, T, 15.0, 0.1, 1.9, 1.6), K, T, 15.0, -1.9, -0.1, 1.6)
    boxes, is_truck = depth_proposals(scene, K, T, np.zeros((0, 4)), BoxRefineParams())
    assert len(boxes) == 3 and is_truck.sum() == 1  # the two cars and the truck


def test_a_stem_is_under_the_middle_of_its_crown():
    """The stem rule on hand-made masks (nothing beside them): a crown on a centred run of two
    pixels is a tree; the same run under one end of the crown (what shows of a car down the side of
    a nearer one, here with the nearer one's depth missing) is not, nor are two runs."""
    from vcfusion.fusion.box_refine import _on_a_stem

    def on_stem(stem_cols):
        sel = np.zeros((12, 20), bool)
        sel[:8, 2:18] = True
        for c in stem_cols:
            sel[8:, c:c + 2] = True
        z = np.full(sel.shape, 50.0, np.float32)
        return _on_a_stem(sel, 0, 0, z, sel.copy(), 50.0, 0.25, 0.5, 0.05)

    assert on_stem([9])
    assert not on_stem([2])
    assert not on_stem([4, 14])


def test_a_near_car_touching_a_farther_truck_in_its_band_snaps_to_the_car_alone():
    """A truck's rear 3 m behind a near car and beside it touches the car in the image and lies
    within the car's depth band: only the cut at the depth jump between them keeps the car's box
    from taking in the truck. A box a few pixels off the car must snap to the car."""
    from vcfusion.fusion.bench import default_camera, road_depth

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    car_only = _plate(road, K, T, 5.0, -0.9, 0.9, 1.5)
    scene = _plate(car_only, K, T, 8.0, 0.9, 3.4, 3.8)
    car = car_only < road
    truck = scene < car_only
    truth = _mask_box(car)
    # the two touch in the image (a car pixel beside a truck pixel)
    assert (car[:, :-1] & truck[:, 1:]).any() or (car[:, 1:] & truck[:, :-1]).any()
    detected = truth + np.array([-6.0, 4.0, 5.0, -3.0])
    out = refine_boxes(detected[None], scene, K, T, BoxRefineParams(proposals=None))
    assert out.refined[0]
    assert box_iou(out.boxes, truth[None])[0, 0] > 0.95
    # on the car alone the same box snaps to the same place: the truck changed nothing
    alone = refine_boxes(detected[None], car_only, K, T, BoxRefineParams(proposals=None)).boxes
    np.testing.assert_allclose(out.boxes, alone, atol=1.0)


def test_a_narrow_truck_top_seen_over_a_nearer_car_is_proposed_but_not_a_trunk_on_the_ground():
    """A truck 10 m behind a car shows only a narrow strip above the car's roof, standing higher than a
    car: as narrow as a tree trunk, but its lower outline rests on the nearer car instead of the road."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import depth_proposals

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    car = _plate(road, K, T, 10.0, -1.0, 1.0, 1.5)
    car_box = _mask_box(car < road)[None]
    for y0, y1, over_car in ((0.2, 0.7, True), (-6.0, -5.5, False)):  # over the car / on the verge
        scene = _plate(car, K, T, 20.0, y0, y1, 3.6)
        strip = scene < car
        assert strip.sum() > 60
        boxes, is_truck = depth_proposals(scene, K, T, car_box, BoxRefineParams())
        if over_car:
            assert len(boxes) == 1 and is_truck[0]
            truth = _mask_box(strip)[None]
            assert box_iou(boxes, truth)[0, 0] > 0.85
        else:
            assert len(boxes) == 0  # the same strip standing on the road: a trunk


def test_a_car_in_front_of_the_surface_its_box_measured_is_proposed():
    """Fig. 3 at range: one box over a car at 60 m and the truck 12 m behind it measures the truck
    (the larger surface in its core). The car stands clearly in front of that surface, so the box does
    not explain it and it is proposed."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import depth_proposals

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    truck = _plate(road, K, T, 72.0, -1.25, 1.25, 3.8)
    scene = _plate(truck, K, T, 60.0, -0.9, 0.9, 1.5)

    def box_of(mask):
        return _mask_box(mask)[None]

    car_box = box_of(scene < truck)  # about 18 x 10 px: one row or column off is IoU 0.83
    union = box_of(scene < road)
    boxes, is_truck = depth_proposals(scene, K, T, union, BoxRefineParams())
    assert len(boxes) == 1 and not is_truck[0]
    assert box_iou(boxes, car_box)[0, 0] > 0.8
    # the truck's box instead: the car in front of it is still proposed, the truck is not
    truck_box = box_of((scene < road) & (scene >= truck))
    boxes, _ = depth_proposals(scene, K, T, truck_box, BoxRefineParams())
    assert len(boxes) == 1 and box_iou(boxes, car_box)[0, 0] > 0.8
    # the car's own box explains the car: nothing is proposed over it (the truck, which no box explains
    # then, is: its box reaches down beside the car to the road, as the truck's visible pixels do)
    boxes, _ = depth_proposals(scene, K, T, car_box, BoxRefineParams())
    assert box_iou(boxes, car_box).max() < 0.5
    assert len(boxes) == 1 and box_iou(boxes, truck_box)[0, 0] > 0.8


def test_what_goes_on_above_any_vehicles_roof_is_not_proposed():
    """A wide surface standing from the road to 7 m (a tree crown, a pillar, a sign) cut at the
    4.5 m height cap leaves a vehicle-sized segment whose top goes on upward: not a vehicle. The same
    surface 3.8 m high, with sky above its top, is a truck."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import depth_proposals

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    proposed = {}
    for top in (7.0, 3.8):
        scene = _plate(road, K, T, 40.0, 5.0, 7.5, top)
        assert (scene < road).sum() > 200
        boxes, is_truck = depth_proposals(scene, K, T, np.zeros((0, 4)), BoxRefineParams())
        proposed[top] = (len(boxes), bool(is_truck.all()))
    assert proposed == {7.0: (0, True), 3.8: (1, True)}


def test_a_proposal_the_detector_saw_below_its_threshold_ranks_above_one_it_did_not_see():
    from vcfusion.fusion.fuse import _proposal_scores

    proposals = np.array([[100, 100, 140, 130], [300, 100, 320, 140]], float)
    weak = np.array([[102, 101, 141, 131], [98, 99, 139, 128], [500, 100, 520, 120]], float)
    scores = _proposal_scores(proposals, weak, np.array([0.12, 0.2, 0.25], np.float32), 0.3)
    np.testing.assert_allclose(scores, [0.5, 0.3], atol=1e-6)  # the best covering one; none for the second
    np.testing.assert_allclose(_proposal_scores(proposals, np.zeros((0, 4)), np.zeros(0, np.float32), 0.3), [0.3, 0.3])


def test_a_car_box_standing_as_high_as_a_truck_is_a_truck_and_stays_one_box():
    """At 80 m a truck seen from behind is a 10 px box, and the detector often calls it a car; depth
    measures how high its surface stands. A car box on a 3.8 m high surface becomes a truck (and a
    weaker truck box the detector put at the same place goes); a car 1.5 m high stays a car, and so
    does a box on a surface higher than any vehicle (a tree)."""
    from vcfusion.detection.detectors import Detections
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.fuse import CameraFrame, detect_frame
    from vcfusion.fusion.stage import camera_view
    from vcfusion.render.coco import category_id

    K, T = default_camera()
    depth = road_depth(K, T, 640, 480)
    plates = {"truck": (80.0, -1.25, 1.25, 3.8), "car": (80.0, 2.6, 4.4, 1.5), "tree": (80.0, -6.0, -4.0, 7.0)}
    for x, y0, y1, top in plates.values():
        depth = _plate(depth, K, T, x, y0, y1, top)
    truth = {}
    road = road_depth(K, T, 640, 480)
    for name, (x, y0, y1, top) in plates.items():
        alone = _plate(road, K, T, x, y0, y1, top)
        truth[name] = _mask_box((alone < road) & np.isclose(depth, alone, rtol=0, atol=1e-4))
    car, truck = category_id("passenger"), category_id("truck")
    # the detector's boxes a pixel off: all three called cars, and the truck a truck too, more weakly;
    # and a weak car box on the truck's upper half (another box to the detector: it snaps onto the
    # truck too, but only the detector's own duplicates go -- at 90 m a car and the truck behind it
    # are one depth surface and both boxes snap to it)
    upper = truth["truck"] + [0, 0, 0, -0.35 * (truth["truck"][3] - truth["truck"][1])]
    boxes = np.array([truth["truck"], truth["car"], truth["tree"], truth["truck"], upper]) + [-1, 1, 1, 1]
    seen = Detections.of(boxes, [0.8, 0.8, 0.8, 0.6, 0.5], [car, car, car, truck, car])

    class Fixed:
        def detect(self, image):
            return seen

    frame = CameraFrame(time=0.0, image=np.zeros((480, 640, 3), np.uint8), depth=depth,
                        camera=camera_view(K, T, 640, 480, 0.0))
    out = detect_frame(frame, Fixed(), replace(BoxRefineParams(), proposals=None))
    assert len(out) == 4  # the weaker truck box at the relabelled one's place is gone
    assert box_iou(out.boxes[out.scores == np.float32(0.5)], truth["truck"][None])[0, 0] > 0.9
    assert out.classes[out.scores == np.float32(0.5)][0] == truck
    owner = {name: int(np.argmax(box_iou(b[None], out.boxes)[0])) for name, b in truth.items()}
    assert {name: int(out.classes[j]) for name, j in owner.items()} == {"truck": truck, "car": car, "tree": car}
    assert out.scores[owner["truck"]] == np.float32(0.8)
    # without the depth step nothing changes class
    assert np.array_equal(detect_frame(frame, Fixed(), None).classes, seen.classes)


def test_the_pieces_of_a_car_a_nearer_one_cuts_in_two_join_its_box_but_not_a_car_in_the_next_lane():
    """A car 30 m ahead with a post 15 m ahead in front of its middle shows in two pieces at one
    depth; a box on one piece grows over the other (the ground truth spans both). A car at the same
    depth one lane over, seen past a nearer car, is not a piece of it (together wider than a
    vehicle), nor is a piece of a car farther away."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import join_fragments, object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)

    def shown(depth, alone):
        return _mask_box((alone < road) & np.isclose(depth, alone, rtol=0, atol=1e-4))

    def joined(depth, box):
        segments = object_segments(depth, K, T, BoxRefineParams())
        out = join_fragments(box[None], np.array([True]), segments, K, BoxRefineParams())[0]
        return out, not np.array_equal(out, box)

    car = _plate(road, K, T, 30.0, -1.0, 1.0, 1.5)
    depth = _plate(car, K, T, 15.0, -0.15, 0.15, 2.5)  # the post
    whole = shown(depth, car)
    right = shown(np.where(np.arange(640)[None, :] < (whole[0] + whole[2]) / 2, np.inf, depth), car)  # the piece right of the post
    assert box_iou(whole[None], right[None])[0, 0] < 0.6
    out, grown = joined(depth, right)
    assert grown and np.allclose(out, whole)
    # a car one lane over at the same depth, its near side hidden by a nearer car: not a piece
    pair = _plate(_plate(road, K, T, 30.0, -1.0, 1.0, 1.5), K, T, 30.0, 1.6, 3.6, 1.5)
    depth = _plate(pair, K, T, 15.0, 0.45, 0.85, 1.6)
    left = shown(depth, _plate(road, K, T, 30.0, -1.0, 1.0, 1.5))
    out, grown = joined(depth, left)
    assert not grown and np.allclose(out, left)
    # the piece right of the post 5 m farther away: another vehicle
    depth = _plate(_plate(_plate(road, K, T, 30.0, -1.0, 0.0, 1.5), K, T, 35.0, 0.0, 1.2, 1.5), K, T, 15.0, -0.15, 0.15, 2.5)
    left = shown(depth, _plate(road, K, T, 30.0, -1.0, 0.0, 1.5))
    assert not joined(depth, left)[1]



def test_a_box_on_part_of_a_car_grows_over_its_whole_segment_but_not_over_two_cars_or_another_box():
    """A detector box that covers only the left part of a car 35 m ahead (the refinement keeps what
    overlaps the detected box most, a part when the box was too small) grows over the car's whole
    depth segment. It does not when that segment is two cars touching at one depth (wider than a
    vehicle), nor when the segment is another box's own."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import join_fragments, object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)

    def joined(depth, boxes, owners):
        segments = object_segments(depth, K, T, BoxRefineParams())
        return join_fragments(boxes, owners, segments, K, BoxRefineParams())

    car = _plate(road, K, T, 35.0, -0.9, 0.9, 1.5)
    whole = _mask_box(car < road)
    # the left 55 %, its top a little low (the segment stands above the proposals' 0.3 m: the box
    # keeps its own bottom, which the refinement found with the tyres)
    part = whole + [0, 2, -0.45 * (whole[2] - whole[0]), 0]
    assert box_iou(part[None], whole[None])[0, 0] < 0.6
    np.testing.assert_allclose(joined(car, part[None], np.array([True]))[0], whole)
    # two cars side by side touching at one depth (3.6 m together): one segment, wider than a vehicle
    pair = _plate(car, K, T, 35.0, 0.9, 2.7, 1.5)
    np.testing.assert_allclose(joined(pair, part[None], np.array([True]))[0], part)
    # another box that the fusion uses owns the car's segment: the part stays a part
    out = joined(car, np.array([part, whole + [0.2, 0, -0.2, 0]]), np.array([True, True]))
    np.testing.assert_allclose(out[0], part)


def _side(depth, K, T, y, x0, x1, top):
    """A vehicle's flat side seen from the lane beside it: the vertical plane at lateral y, from x0 to
    x1 metres ahead and from the road up to `top`, drawn into the depth image."""
    R, t = T[:3, :3], T[:3, 3]
    centre = -R.T @ t
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = R.T @ (np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (y - centre[1]) / rays[1]
    p = centre[:, None] + s * rays
    hit = (s > 0) & (p[0] >= x0) & (p[0] <= x1) & (p[2] >= 0.0) & (p[2] <= top)
    z = depth.ravel().copy()
    z[hit & (s < z)] = s[hit & (s < z)]
    return z.reshape(h, w).astype(np.float32)


def test_the_side_of_a_truck_in_the_next_lane_is_refined_whole_however_deep_it_runs():
    """A truck in the next lane seen along its side spans 6-20 m of depth, far more than the
    one-vehicle band; the refinement also takes each surface whole (no depth jump inside it), so a
    box a few pixels off snaps to all of the side, not to the 4 m of it nearest the box's centre."""
    from vcfusion.fusion.bench import default_camera, road_depth

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    depth = _side(road, K, T, 2.5, 6.0, 20.0, 3.8)
    truth = _mask_box(depth < road)
    assert np.ptp(depth[depth < road]) > 10  # the side runs deep
    w, h = truth[2] - truth[0], truth[3] - truth[1]
    off = truth + [0.06 * w, -0.05 * h, 0.04 * w, 0.05 * h]
    res = refine_boxes(off[None], depth, K, T, BoxRefineParams())
    assert res.refined[0] and box_iou(truth[None], res.boxes)[0, 0] > 0.95
    assert 3.5 < res.top_m[0] <= 3.8  # and it stands as high as a truck


def test_a_box_over_two_trucks_side_by_side_snaps_to_one_and_the_other_is_proposed():
    """Jam dev seed 3102: two trucks in neighbouring lanes 2 m apart in depth, one box over both.
    Both lie inside one depth band and touch in the image, so the band's segment (the pair, 4.4 m
    across) overlaps the box best; a segment no wider than a vehicle that still overlaps it by half
    (the nearer truck, cut from the farther one at the depth jump) takes its place, and the farther
    truck is proposed. A truck's side running away from the camera in the
    next lane is no wider than its rear, so it is refined whole (the test above)."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import _lateral_extent, depth_proposals

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    near_only = _plate(road, K, T, 18.0, -1.25, 1.25, 3.8)
    scene = _plate(near_only, K, T, 20.0, 1.25, 3.2, 3.8)
    near, far = near_only < road, (scene < near_only)
    pair = _mask_box(near | far)
    assert (near[:, 1:] & far[:, :-1]).any() or (near[:, :-1] & far[:, 1:]).any()  # they touch
    out = refine_boxes(pair[None], scene, K, T, BoxRefineParams(proposals=None))
    assert out.refined[0] and box_iou(out.boxes, _mask_box(near)[None])[0, 0] > 0.95
    proposals, is_truck = depth_proposals(scene, K, T, out.boxes)
    assert len(proposals) == 1 and is_truck[0] and box_iou(proposals, _mask_box(far)[None])[0, 0] > 0.9
    # without the rule the box stays over the pair: the nearer truck has no box of its own (IoU 0.6)
    wide = BoxRefineParams(proposals=None, pair_width_m=10.0)
    stays = refine_boxes(pair[None], scene, K, T, wide).boxes
    assert box_iou(stays, pair[None])[0, 0] > 0.95 and box_iou(stays, _mask_box(near)[None])[0, 0] < 0.7
    # nor does a narrower segment that no longer explains the box (here overlapping it by 0.56) replace it
    strict = refine_boxes(pair[None], scene, K, T, BoxRefineParams(proposals=None, pair_min_iou=0.6)).boxes
    np.testing.assert_allclose(strict, stays)
    # the width measured: the pair 4.45 m across, the nearer truck 2.5 m
    z = scene.astype(np.float32)
    assert _lateral_extent(near | far, z, 0, K, 0.05) == pytest.approx(4.45, abs=0.15)
    assert _lateral_extent(near, z, 0, K, 0.05) == pytest.approx(2.5, abs=0.15)
    with pytest.raises(ValueError, match="pair_width_m"):
        BoxRefineParams(pair_width_m=0.0)


def test_a_segment_inside_a_box_that_depth_did_not_confirm_is_proposed():
    """A detected box over two trucks and the car in front of them snaps to no segment (none overlaps
    it by 0.3): depth does not confirm it, so a truck lying inside it is not explained by it and is
    proposed; inside a box that snapped, it is that box's."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import depth_proposals

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    scene = _plate(road, K, T, 20.0, -1.25, 1.25, 3.8)
    truck = _mask_box(scene < road)
    w, h = truck[2] - truck[0], truck[3] - truck[1]
    loose = truck + [-0.3 * w, -0.1 * h, 0.6 * w, 0.4 * h]  # the truck mostly inside, IoU under 0.5
    assert box_iou(loose[None], truck[None])[0, 0] < 0.5
    assert len(depth_proposals(scene, K, T, loose[None])[0]) == 0
    assert len(depth_proposals(scene, K, T, loose[None], snapped=np.array([True]))[0]) == 0
    got, _ = depth_proposals(scene, K, T, loose[None], snapped=np.array([False]))
    assert len(got) == 1 and box_iou(got, truck[None])[0, 0] > 0.9  # from 0.3 m above the road up
    with pytest.raises(ValueError, match="snapped"):
        depth_proposals(scene, K, T, loose[None], snapped=np.array([True, False]))


def test_a_strip_of_a_far_truck_between_two_nearer_cars_goes_back_to_the_truck_whole():
    """Jam dev seed 3002: a truck 40 m ahead shows its lower part as a strip 2 px wide between two
    cars 10 m ahead. Every pixel of the strip is the farther one of a jumping pair (a car beside it),
    so the cut removes all of them; given back pass after pass along their own surface, they join
    the truck's segment down to the road, and the truck's box spans them (one pass gave back only
    the strip's top row)."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    truck = _plate(road, K, T, 40.0, -1.25, 1.25, 3.8)
    gap = 2.0 * 10.0 / K[0, 0]  # 2 px at 10 m
    scene = _plate(_plate(truck, K, T, 10.0, -3.0, -gap / 2, 1.5), K, T, 10.0, gap / 2, 3.0, 1.5)
    seen = (truck < road) & (scene == truck)
    rows = np.flatnonzero(seen.any(axis=1))
    strip = seen[rows[-1]]
    assert strip.sum() == 2 and seen[rows[0]].sum() > 20  # 2 px wide at the bottom, whole at the top
    seg = object_segments(scene, K, T)
    labels = _image_labels(seg, scene.shape)
    truck_label = labels[rows[0] + 5, np.flatnonzero(strip)[0]]  # the truck above the cars
    assert truck_label > 0
    lowest_object_row = max(r for r in rows if (labels[r][strip] > 0).any())
    assert (labels[lowest_object_row][strip] == truck_label).all()
    # all of the strip above the proposals' 0.3 m is the truck's, so its box reaches down there
    mine = labels == truck_label
    assert np.flatnonzero(mine.any(axis=1))[-1] == lowest_object_row
    assert lowest_object_row >= rows[-1] - 3  # 0.3 m at 40 m is 3.4 px


def test_a_segment_overlapping_a_box_of_a_nearer_surface_by_under_0_6_is_proposed():
    """A car 10 m ahead hides the lower right of a truck 22 m ahead, which shows as an L (its top
    above the car and its left side). A box over the truck's L and the top of the car measures the
    car's depth in its core; the truck's segment overlaps it by 0.55-0.6, which under a 0.5 limit
    makes it that box's and leaves the truck without a box of its own."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import ProposalParams, _surface_depth, depth_proposals, object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    truck_only = _plate(road, K, T, 22.0, -1.25, 1.25, 3.8)
    scene = _plate(truck_only, K, T, 10.0, -0.5, 2.5, 1.6)
    truck = _mask_box((truck_only < road) & (scene == truck_only))
    box = truck + [-10.0, 0.0, 10.0, 24.0]
    seg = object_segments(scene, K, T)
    assert _surface_depth(seg.z, seg.obj, box, seg.y_lo) < 11  # the box's core is the car

    def truck_proposed(params):
        got, _ = depth_proposals(scene, K, T, box[None], params, seg)
        return bool(len(got)) and box_iou(got, truck[None]).max() > 0.9, got

    proposed, got = truck_proposed(BoxRefineParams())
    assert proposed
    assert 0.5 < box_iou(got, box[None]).max() <= 0.6
    assert not truck_proposed(BoxRefineParams(proposals=ProposalParams(max_overlap=0.5)))[0]


def test_a_car_mid_lane_change_seen_at_an_angle_is_not_split_for_its_width(tmp_path):
    """A car cutting in 10-20 m ahead shows its rear and its side, 3-4 m across the view: as wide as
    two vehicles side by side, but one surface without a depth jump between its parts (the pair rule
    took its rear alone, or the rear and its wheels, and cut the box to IoU 0.78-0.92 on the
    cut_in development scenes; mAP@0.5:0.95 0.952 -> 0.885)."""
    from scenario_files import SCENARIOS
    from vcfusion.detection.detector_train import load_coco, read_rgb
    from vcfusion.detection.family_eval import _camera_frame
    from vcfusion.detection.scenes import render_scenes
    from vcfusion.fusion.box_refine import _lateral_extent
    from vcfusion.scenario import load_scenario

    render_scenes(load_scenario(SCENARIOS / "overlap.yaml"), "cut_in", [3003], tmp_path / "cut_in", progress=False)
    ds = load_coco(tmp_path / "cut_in")
    frame = _camera_frame(ds, 0, read_rgb(ds.images[0]))
    g = frame.gt_boxes
    car = g[np.argmax((g[:, 2] - g[:, 0]) * (g[:, 3] - g[:, 1]))]  # the car cutting in, nearest
    w, h = car[2] - car[0], car[3] - car[1]
    off = car + [-0.06 * w + 1, -0.05 * h, 0.06 * w + 1, 0.05 * h]
    out = _refine(frame, off[None], BoxRefineParams(proposals=None))
    assert out.refined[0] and box_iou(out.boxes, car[None])[0, 0] > 0.95
    # as wide as a pair: inside its box, the vehicle's depth pixels span more than pair_width_m
    x0, y0, x1, y1 = (int(round(v)) for v in car + [0.5, 0.5, -0.5, -0.5])
    z = frame.depth[y0:y1 + 1, x0:x1 + 1].astype(np.float32)
    near = np.isfinite(z) & (z < np.nanmedian(z) + 3.0)
    assert _lateral_extent(near, np.nan_to_num(z), x0, frame.camera.K, 0.05) > BoxRefineParams().pair_width_m


def test_a_box_s_surface_depth_is_the_face_of_the_segment_drawing_its_outline():
    """A truck's rear 9.5 m ahead, partly hidden by a car 7 m ahead: the truck's box holds much of
    the car, yet its outline is the truck's, so its surface depth is the truck's face, the car's
    box's the car's. Nothing where no segment
    explains a box (the sky, half a car), nor for a segment deeper than one vehicle's band (the side
    of a truck that runs 10-25 m away; a far car and the truck behind it, within one depth jump):
    which depth is the face of the vehicle the box outlines is not known."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import box_surface_depths, object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    truck_only = _plate(road, K, T, 9.5, -0.2, 2.3, 3.8)
    scene = _plate(truck_only, K, T, 7.0, -0.9, 0.9, 1.5)
    car = scene < truck_only - 1.0
    truck = (scene < road) & ~car
    car_box, truck_box = _mask_box(car), _mask_box(truck)
    # the truck's box holds more of the car than of the truck: its samples read the car's depth
    assert box_iou(car_box[None], truck_box[None])[0, 0] > 0.1
    segments = object_segments(scene, K, T)
    half_car = car_box.copy()
    half_car[2] = (car_box[0] + car_box[2]) / 2 - 10
    sky = np.array([300.0, 0.0, 340.0, 20.0])
    got = box_surface_depths(np.stack([car_box, truck_box, half_car, sky]), segments)
    # camera-Z over an upright plate varies with the camera's pitch: the face is its nearer part
    for k, mask in enumerate((car, truck)):
        assert scene[mask].min() - 0.01 <= got[k] <= np.median(scene[mask])
    assert got[1] - got[0] > 2.0
    assert np.isnan(got[2:]).all()
    assert np.isnan(box_surface_depths(car_box[None], None)).all()
    wall = _side(road, K, T, 2.5, 10.0, 25.0, 3.5)
    wall_box = _mask_box(wall < road)
    assert np.isnan(box_surface_depths(wall_box[None], object_segments(wall, K, T))).all()
    # far away a car 4.8 m in front of a truck is within one depth jump of it (5.2 m at 104 m): one
    # segment, whose outline is the truck's and whose face is the car's; deeper than a band: unknown
    far_truck = _plate(road, K, T, 108.8, -1.25, 1.25, 3.8)
    chain = _plate(far_truck, K, T, 104.0, -0.9, 0.9, 1.5)
    far_segments = object_segments(chain, K, T)
    truck_seen = (chain < road) & (chain > 106.0)
    assert len(np.unique(far_segments.labels[far_segments.labels > 0])) == 1
    assert np.isnan(box_surface_depths(_mask_box(truck_seen)[None], far_segments)).all()
    # a shorter wall (the side of a car in the next lane, 4 m) is one vehicle deep: its face is known
    short = _side(road, K, T, 2.5, 10.0, 12.5, 1.5)
    face = box_surface_depths(_mask_box(short < road)[None], object_segments(short, K, T))[0]
    assert short[short < road].min() - 0.01 <= face <= np.median(short[short < road])


def test_a_segment_reaching_well_outside_a_box_is_not_its_surface():
    """A car 7 m ahead and a car entering beside it 6.5 m away touch in the image within one depth
    jump: one segment, overlapping the first car's box at IoU above 0.5, a third of it outside the
    box, whose face is the entering car's. That box's surface is unknown (the matcher reads its
    samples); the first car alone (the entering one drawn farther, a separate segment) has its
    face as its surface."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import MIN_SURFACE_INSIDE_SHARE, box_surface_depths, object_segments
    from vcfusion.fusion.matching import box_inside_share

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    alone = _plate(road, K, T, 7.0, -0.9, 0.9, 1.5)
    car = alone < road
    car_box = _mask_box(car)
    joined = _plate(alone, K, T, 6.5, 0.7, 1.6, 1.5)
    segments = object_segments(joined, K, T)
    label = segments.labels[segments.labels > 0]
    assert len(np.unique(label)) == 1  # the two cars are one surface
    seg_box = segments.present_boxes[0]
    assert box_iou(seg_box[None], car_box[None])[0, 0] >= 0.5  # ... which draws the car's outline
    assert box_inside_share(seg_box[None], car_box[None])[0, 0] < MIN_SURFACE_INSIDE_SHARE
    assert np.isnan(box_surface_depths(car_box[None], segments)).all()
    # the entering car farther than one depth jump: its own segment, and the car's face is known again
    apart = _plate(alone, K, T, 9.0, 0.7, 1.6, 1.5)
    face = box_surface_depths(car_box[None], object_segments(apart, K, T))[0]
    assert alone[car].min() - 0.01 <= face <= np.median(alone[car])


def test_the_fusion_s_depth_step_on_given_segments_equals_its_own(frames):
    """fuse_frame cuts the depth image into segments once for the depth step and the matcher."""
    from vcfusion.fusion.fuse import depth_step, frame_segments

    class Fixed:
        def __init__(self, boxes):
            from vcfusion.detection.detectors import Detections

            self.d = Detections.of(boxes, np.full(len(boxes), 0.9, np.float32), np.ones(len(boxes), np.int64))

    for frame in frames[:3]:
        detections = Fixed(frame.gt_boxes + 3.0).d
        own = depth_step(frame, detections, BoxRefineParams())
        given = depth_step(frame, detections, BoxRefineParams(), frame_segments(frame, BoxRefineParams()))
        np.testing.assert_array_equal(own.boxes, given.boxes)
        np.testing.assert_array_equal(own.classes, given.classes)


def test_a_vehicle_whose_parts_a_strip_between_nearer_ones_links_is_one_segment():
    """Jam dev seed 3471: a car 20 m ahead shows its top, then a strip 2 px wide beside a nearer car,
    then its lower part. Every pixel of the strip is the farther one of a jumping pair, so the cut
    removes all of them and the parts above and below became two segments; each removed pixel went
    back to one of them, which joined nothing, and the car's box lost its lower part. Segments that
    touch as one surface are one. Here: a truck 40 m ahead seen above, between and below two bars
    10 m ahead that leave a 2 px gap."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    truck = _plate(road, K, T, 40.0, -1.25, 1.25, 3.8)
    gap = 2.0 * 10.0 / K[0, 0]  # 2 px at 10 m
    scene = _plate(_plate(truck, K, T, 10.0, -3.0, -gap / 2, 1.6, 1.2), K, T, 10.0, gap / 2, 3.0, 1.6, 1.2)
    seen = (truck < road) & (scene == truck)
    widths = seen.sum(axis=1)
    rows = np.flatnonzero(widths)
    narrow = rows[widths[rows] <= 2]
    assert len(narrow) >= 3 and rows[0] < narrow[0] and narrow[-1] < rows[-1]  # wide above and below
    assert widths[rows[0] + 2] > 20 and widths[narrow[-1] + 3] > 20
    seg = object_segments(scene, K, T)
    labels = _image_labels(seg, scene.shape)
    above = labels[rows[0] + 2][seen[rows[0] + 2]]
    below = labels[narrow[-1] + 3][seen[narrow[-1] + 3]]
    assert above.min() > 0 and len(set(above)) == 1
    assert set(below) == set(above)
    # and the bars are not joined to it (a depth jump apart)
    bar = labels[narrow[0]][(scene[narrow[0]] < truck[narrow[0]] - 1.0)]
    assert bar.size and not (set(bar) & set(above))


def test_a_sliver_s_one_pixel_tail_stays_in_its_box_but_a_stray_pixel_of_a_wide_surface_does_not():
    """Jam dev seed 3305: a car hidden but for its roof (a row 24 px wide) and a strip down the side
    of the nearer car, whose last rows are 1 px wide; the ground truth spans them. A truck 40 px high
    with a rail 1 px high running on from its foot is still trimmed to the truck."""
    from vcfusion.fusion.box_refine import _segment_box

    support = BoxRefineParams().support
    sliver = np.zeros((30, 30), bool)
    sliver[0:3, 2:26] = True  # the roof, 24 px
    sliver[3:20, 22:25] = True  # the strip beside the nearer car
    sliver[20:23, 23] = True  # its last rows, 1 px
    np.testing.assert_array_equal(_segment_box(sliver, support, 0, 0), [1.5, -0.5, 25.5, 22.5])
    wide = np.zeros((45, 80), bool)
    wide[0:40, 5:65] = True
    wide[38, 65:78] = True  # a rail running on from its foot: 1 px per column, 1/40 of the fullest
    np.testing.assert_array_equal(_segment_box(wide, support, 0, 0), [4.5, -0.5, 64.5, 39.5])


def test_a_box_on_a_truck_whose_strip_the_cut_removes_snaps_to_the_truck_whole():
    """Jam dev seed 3305: a far vehicle shows its lower part as a strip 2 px wide between two nearer
    cars, and a car beside it lies within its depth band. The band as it is joins that car to the
    truck; cut at the depth jumps it loses the strip (every pixel of it is the farther one of a jumping
    pair). The cut segments take their removed outlines back (as the proposals' do), so a box a few
    pixels off the truck snaps to the truck with its strip (without that its bottom stopped at the
    cars' roofs: IoU about 0.6)."""
    from vcfusion.fusion.bench import default_camera, road_depth

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    truck = _plate(road, K, T, 40.0, -1.25, 1.25, 3.8)
    beside = _plate(road, K, T, 43.5, 1.3, 3.8, 3.0)  # a van 3.5 m behind: a jump, but inside the band
    gap = 2.0 * 10.0 / K[0, 0]  # 2 px at 10 m
    far = np.minimum(truck, beside)
    scene = _plate(_plate(far, K, T, 10.0, -3.0, -gap / 2, 1.5), K, T, 10.0, gap / 2, 3.0, 1.5)
    shown = (truck < road) & (scene == truck)
    assert (((scene == beside) & (beside < road))[:, :-1] & shown[:, 1:]).any()  # the car beside touches it
    rows = np.flatnonzero(shown.any(axis=1))
    assert shown[rows[-1]].sum() == 2  # the strip, 2 px wide at the bottom
    params = BoxRefineParams(proposals=None)
    truth = _mask_box(shown & (scene < road - 1e-3))
    detected = truth + np.array([-2.0, 3.0, 2.0, -6.0])
    out = refine_boxes(detected[None], scene, K, T, params)
    assert out.refined[0]
    assert box_iou(out.boxes, truth[None])[0, 0] > 0.9
    assert out.boxes[0, 3] >= truth[3] - 2  # down the strip, not stopped at the cars' roofs


def test_a_box_over_two_trucks_snaps_to_the_nearer_one_when_a_car_hides_part_of_it():
    """As above, with a car 10 m ahead hiding the lower part of the nearer truck. The truck's cut
    segment takes back its outline along the car (pixels each the farther one of a jumping pair):
    those are its own edge, not a second surface joined to it, so it still counts as jump-free and
    replaces the box over the pair (counted as spanning a jump, it could not: IoU 0.6 with the truck)."""
    from vcfusion.fusion.bench import default_camera, road_depth

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    trucks = _plate(_plate(road, K, T, 18.0, -1.25, 1.25, 3.8), K, T, 20.0, 1.25, 3.2, 3.8)
    scene = _plate(trucks, K, T, 10.0, -1.5, 0.3, 1.5)
    near = (scene < road) & np.isclose(scene, _plate(road, K, T, 18.0, -1.25, 1.25, 3.8), atol=1e-4, rtol=0)
    far = (scene < road) & (scene > 19.0) & (scene < 30.0)
    car = scene < 12.0
    assert near.any() and far.any() and ((car[1:] & near[:-1]).any() or (car[:, 1:] & near[:, :-1]).any())
    pair = _mask_box(near | far)
    out = refine_boxes(pair[None], scene, K, T, BoxRefineParams(proposals=None))
    assert out.refined[0] and box_iou(out.boxes, _mask_box(near)[None])[0, 0] > 0.9


def _van_behind_a_car_seen_in_two_pieces(hidden_below_m=None):
    """Jam dev seed 3427: a van 14 m ahead shows its roof above a car 6 m ahead and a sliver 1 px wide
    beside it, which a mirror-high object 9 m ahead interrupts: the sliver's lower piece is a
    fragment of the van below that object. ``hidden_below_m``: that object reaches down to the road
    but for a gap from this height up, through which the van shows. Returns the scene, the van's
    two pieces and the car."""
    from vcfusion.fusion.bench import default_camera, road_depth

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    van = _plate(road, K, T, 14.0, -1.255, 0.6, 1.95)
    scene = _plate(_plate(van, K, T, 9.0, -1.6, -0.4, 1.2, bottom=0.95), K, T, 6.0, -0.5, 1.5, 1.5)
    if hidden_below_m is not None:
        scene = _plate(scene, K, T, 9.0, -1.6, -0.4, hidden_below_m)
    shown = (van < road) & np.isclose(scene, van, atol=1e-4, rtol=0)
    rows = np.flatnonzero(shown.any(axis=1))
    hidden_rows = np.setdiff1d(np.arange(rows[0], rows[-1] + 1), rows)
    upper, lower = shown.copy(), shown.copy()
    upper[hidden_rows[0]:] = False
    lower[:hidden_rows[-1] + 1] = False
    car = scene < 7.0
    return K, T, scene, upper, lower, car


def test_a_fragment_whose_every_pixel_the_cut_removes_is_a_segment_of_its_own():
    """The van's lower piece is 1 px wide with nearer things left of it, above and below: every pixel
    is the farther one of a jumping pair and none has a neighbour on its surface that kept its label,
    so giving the outlines back cannot place them. They are a segment of their own (were they no
    segment at all, no box could grow over them)."""
    from vcfusion.fusion.box_refine import object_segments

    K, T, scene, upper, lower, car = _van_behind_a_car_seen_in_two_pieces()
    assert (lower.sum(axis=1) <= 1).all() and lower.sum() >= 10  # a 1-px sliver, 10 rows or more
    seg = object_segments(scene, K, T)
    labels = _image_labels(seg, scene.shape)
    object_rows = lower & (labels > 0)
    assert object_rows.sum() >= 0.5 * lower.sum()  # (the lowest rows stand under the proposals' 0.3 m)
    assert len(np.unique(labels[object_rows])) == 1  # one segment
    assert not (labels[upper] == labels[object_rows][0]).any()  # not the upper piece's: a nearer object lies between


def test_a_box_over_a_sliver_grows_over_its_fragment_measured_on_the_surface_drawing_its_outline():
    """The van's box (its roof above the car and the sliver's upper piece) holds mostly the car in its
    core: measured there, its surface lay 6 m ahead and no fragment of the van, 14 m ahead, could
    join it. Measured on the segment drawing its outline (as the matcher does), it is the van's, and
    the box grows over the lower piece."""
    from vcfusion.fusion.box_refine import _core, join_fragments, object_segments

    K, T, scene, upper, lower, car = _van_behind_a_car_seen_in_two_pieces()
    box = _mask_box(upper)
    core = np.zeros(scene.shape, bool)
    core[_core(box, 0, 0)] = True
    assert (core & car).sum() > (core & upper).sum()  # the core shows mostly the car
    seg = object_segments(scene, K, T)
    boxes = np.stack([box, _mask_box(car)])
    joined = join_fragments(boxes, np.array([True, True]), seg, K)
    assert joined[0, 3] >= box[3] + 10  # down over the lower piece
    np.testing.assert_allclose(joined[0, [0, 1, 2]], box[[0, 1, 2]])
    np.testing.assert_allclose(joined[1], boxes[1])  # the car's box: unchanged


def test_a_box_the_noise_gate_keeps_does_not_grow_over_fragments():
    """Where the depth is too noisy to tell one surface from the next (the gate that keeps the
    detector's box), the box does not grow over a fragment either: the same van's box as above stays
    as it is with a depth whose sigma at 14 m (0.01 z^2 = 2 m) exceeds half the jump threshold."""
    from vcfusion.fusion.box_refine import join_fragments, object_segments
    from vcfusion.fusion.road import DepthNoise

    K, T, scene, upper, lower, car = _van_behind_a_car_seen_in_two_pieces()
    boxes = np.stack([_mask_box(upper), _mask_box(car)])
    seg = object_segments(scene, K, T)
    assert join_fragments(boxes, np.array([True, True]), seg, K)[0, 3] >= boxes[0, 3] + 10
    kept = join_fragments(boxes, np.array([True, True]), seg, K, BoxRefineParams(), DepthNoise(c=0.01))
    np.testing.assert_allclose(kept, boxes)


def test_a_box_grows_over_a_fragment_of_two_pixels_seen_through_a_gap():
    """Jam dev seed 3362: of a truck behind a car, 1-3 px show beside the car's outline rows below
    the rest, and the ground truth spans them, so a fragment of any size joins (a 4-px minimum
    leaves them out); the van's lower piece here is 2 px seen through a gap in a nearer object."""
    from vcfusion.fusion.box_refine import join_fragments, object_segments

    K, T, scene, upper, lower, car = _van_behind_a_car_seen_in_two_pieces(hidden_below_m=0.9)
    assert lower.sum() == 2
    boxes = np.stack([_mask_box(upper), _mask_box(car)])
    joined = join_fragments(boxes, np.array([True, True]), object_segments(scene, K, T), K)
    np.testing.assert_allclose(joined[0], np.r_[boxes[0, :3], _mask_box(lower)[3]])
    np.testing.assert_allclose(joined[1], boxes[1])


def test_a_box_grows_over_the_segment_drawing_its_outline_though_its_core_shows_a_nearer_car():
    """Validation seed 900088: a car 33 m ahead and a nearer one 11 m ahead hiding its lower part but
    for a strip at its side. The far car's box stopped at the top of the nearer car,
    so its core showed mostly that car, and the box grew only over the segment most of its core
    shows (the nearer car's, at another depth: not at all). It grows over the segment drawing its
    outline (box_surface_depths' choice) too, down the strip beside the nearer car."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import _core, join_fragments, object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    car = _plate(road, K, T, 33.0, -0.9, 0.9, 1.6)
    scene = _plate(car, K, T, 11.0, -1.5, 0.7 * 11 / 33, 1.4)  # hides all but a strip at its side
    shown = (car < road) & np.isclose(scene, car, atol=1e-4, rtol=0)
    near = (scene < road - 0.01) & (scene < 12.0)
    seg = object_segments(scene, K, T)
    labels = _image_labels(seg, scene.shape)
    (car_label,) = np.unique(labels[shown & (labels > 0)])
    car_box = seg.boxes([car_label])[0]
    box = car_box.copy()
    box[3] = car_box[1] + 0.6 * (car_box[3] - car_box[1])  # stopped at the nearer car's top
    core = np.zeros(scene.shape, bool)
    core[_core(box, 0, 0)] = True
    assert (core & near).sum() > 3 * (core & shown).sum()
    joined = join_fragments(np.stack([box, _mask_box(near)]), np.array([True, True]), seg, K)
    np.testing.assert_allclose(joined[0], car_box)


def test_a_car_in_front_of_a_box_outlining_the_car_behind_is_proposed():
    """Jam dev seed 3445: a box outlining a car 38 m ahead holds, mostly inside it, a car 32 m ahead
    (itself partly hidden by one 23 m ahead). The box's surface was its core's median, which the
    nearer car holds, so that car counted as explained by the box and got none. Measured on the
    segment drawing the box's outline, the car stands in front of it and is proposed."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import _surface_depth, box_surface_depths, depth_proposals, object_segments
    from vcfusion.fusion.matching import box_inside_share

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    far = _plate(road, K, T, 38.0, -0.9, 0.9, 1.5)
    scene = _plate(_plate(far, K, T, 31.7, -0.2, 0.6, 1.4), K, T, 22.9, -2.0, -0.2, 1.3)
    far_shown = (far < road) & np.isclose(scene, far, atol=1e-4, rtol=0)
    car = (scene < road) & (scene > 31.0) & (scene < 33.0)
    box = _mask_box(far_shown | car)
    seg = object_segments(scene, K, T)
    assert box_inside_share(_mask_box(car)[None], box[None])[0, 0] > 0.9
    assert abs(_surface_depth(seg.z, seg.obj, box, seg.y_lo) - 31.7) < 1.0  # the core: the car in front
    assert abs(box_surface_depths(box[None], seg)[0] - 38.0) < 1.0  # the outline: the car behind
    proposed, _ = depth_proposals(scene, K, T, box[None], BoxRefineParams(), seg)
    assert len(proposed) and box_iou(_mask_box(car)[None], proposed).max() > 0.9


def test_a_small_box_grows_over_a_piece_of_its_vehicle_a_metre_fraction_away():
    """Jam dev seed 3409: of a car 13 m ahead, a nearer truck leaves a strip at its side, and a car's
    body beside it (above the road on its wheels) hides the strip's middle: the roof corner (14 x 20
    px) and a lower piece 17 px below it show. 17 px is more than half the small box's larger side
    (the fragment_gap share alone keeps them apart) but 0.5 m at 13 m, within fragment_gap_m."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import ProposalParams, join_fragments, object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    car = _plate(road, K, T, 13.0, -0.9, 0.9, 1.5)
    truck = _plate(road, K, T, 7.0, -3.0, 0.5 * 7 / 13, 3.5)
    scene = _plate(_plate(car, K, T, 7.0, -3.0, 0.5 * 7 / 13, 3.5), K, T, 9.0, 0.5 * 9 / 13, 2.5, 1.1, bottom=0.8)
    shown = (car < road) & np.isclose(scene, car, atol=1e-4, rtol=0)
    seg = object_segments(scene, K, T)
    labels = _image_labels(seg, scene.shape)
    pieces = [label for label in np.unique(labels[shown]) if label]
    assert len(pieces) == 2
    upper, lower = sorted((_mask_box(labels == label) for label in pieces), key=lambda b: b[1])
    gap = lower[1] - upper[3]
    assert 0.5 * max(upper[2] - upper[0], upper[3] - upper[1]) < gap < 0.75 * K[0, 0] / 13.0
    boxes = np.stack([upper, _mask_box((truck < road) & np.isclose(scene, truck, atol=1e-4, rtol=0))])
    joined = join_fragments(boxes, np.array([True, True]), seg, K)
    np.testing.assert_allclose(joined[0], np.r_[upper[:3], lower[3]])
    np.testing.assert_allclose(joined[1], boxes[1])
    unchanged = join_fragments(boxes, np.array([True, True]), seg, K,
                               BoxRefineParams(proposals=ProposalParams(fragment_gap_m=0.0)))
    np.testing.assert_allclose(unchanged, boxes)


def test_a_side_the_band_cuts_off_a_vehicle_s_own_surface_is_the_detector_s():
    """A truck's rear 10 m ahead with its side running 20 m deep beside it: the rear's one-vehicle
    depth band holds the side's nearest 4-5 m only, and that segment overlaps a detector's box over
    the rear and most of the side better than the whole truck does, so the snap moved the box's
    left side 14 px inward over the truck's own side, where no depth jump ends it (exact depth, seeds
    9200-9209: a car's flank seen over a nearer car's roof, cut off its rear face, lost a fifth of the
    box's width and the target). The side the depth does not end is the detector's."""
    from vcfusion.fusion.bench import default_camera, road_depth

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    rear = _plate(road, K, T, 10.0, -4.0, -2.2, 3.8)
    scene = _side(rear, K, T, -2.2, 10.0, 30.0, 3.8)
    truth, rear_box = _mask_box(scene < road), _mask_box(rear < road)
    assert truth[0] < rear_box[0] - 40  # the side shows left of the rear
    detected = np.array([rear_box[0] - 0.7 * (rear_box[0] - truth[0]), truth[1] + 2, rear_box[2] - 1, truth[3] - 2])
    cut = refine_boxes(detected[None], scene, K, T, BoxRefineParams(proposals=None, surface_sides=False))
    kept = refine_boxes(detected[None], scene, K, T, BoxRefineParams(proposals=None))
    assert cut.refined[0] and kept.refined[0]
    assert cut.boxes[0, 0] > detected[0] + 10  # the band's segment: the box cut off inside the detector's
    assert kept.boxes[0, 0] == pytest.approx(detected[0])  # the side the truck's surface goes on past
    np.testing.assert_allclose(kept.boxes[0, 1:], cut.boxes[0, 1:])  # the other sides as snapped
    assert box_iou(cut.boxes, truth[None])[0, 0] < 0.78 < 0.84 < box_iou(kept.boxes, truth[None])[0, 0]
    # a side the detector drew beyond a depth jump (over the truck beside a car) is still snapped:
    # test_a_near_car_touching_a_farther_truck_in_its_band_snaps_to_the_car_alone


def test_a_proposal_of_the_segment_a_snapped_box_outlines_is_that_box_s_vehicle():
    """After the depth step two boxes can describe one car: the detector's box snapped to the car's
    segment but reaching rows below it, and the proposal of that segment (overlapping the box by
    0.52-0.58, under the proposals' 0.6; development seeds 9105, 9108, 9201 of the jam family, 24-29 m,
    where the matcher took the taller box). The box takes the proposal's sides and the proposal goes;
    a proposal of the other class (a truck's L above the car in front) stays its own box."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import merge_same_segment, object_segments

    K, T = default_camera()
    depth = _plate(road_depth(K, T, 640, 480), K, T, 25.0, -0.9, 0.9, 1.5)
    segments = object_segments(depth, K, T)
    car = _mask_box(_image_labels(segments, depth.shape) > 0)
    tall = car + [-2.0, 0.0, 0.0, 0.6 * (car[3] - car[1])]  # reaching far below the car's surface
    assert 0.5 < box_iou(tall[None], car[None])[0, 0] < BoxRefineParams().proposals.max_overlap
    boxes, kept = merge_same_segment(tall[None], np.array([False]), np.array([True]), car[None],
                                     np.array([False]), segments)
    assert not kept[0] and box_iou(boxes, car[None])[0, 0] == pytest.approx(1.0)
    for box_truck, snapped in ((True, True), (False, False)):  # another class, or a box not snapped
        boxes, kept = merge_same_segment(tall[None], np.array([box_truck]), np.array([snapped]), car[None],
                                         np.array([False]), segments)
        assert kept[0] and np.array_equal(boxes[0], tall)
    # a box ending where the proposal ends, reaching above it: the proposal may be a part of another car
    # (a LiDAR scan's lower half of a car, development seed 9407)
    above = car + [-2.0, -0.6 * (car[3] - car[1]), 0.0, 0.0]
    assert 0.5 < box_iou(above[None], car[None])[0, 0]
    boxes, kept = merge_same_segment(above[None], np.array([False]), np.array([True]), car[None],
                                     np.array([False]), segments)
    assert kept[0] and np.array_equal(boxes[0], above)


def test_a_box_on_a_car_s_rear_grows_over_its_flank_seen_at_an_angle_measured_across_the_view():
    """A car 12 m ahead, 4 m to the side, shows its rear face and the flank facing the camera's axis
    as one surface: 2.9 m of image width at the rear's depth, wider than a vehicle (2.7 m), but only
    1.8 m across the view (the flank runs away from the camera). A box on the rear face grows over
    the whole car; two cars side by side at the rear's depth (3.6 m across the view) stay apart."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import _lateral_width, join_fragments, object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)

    def joined(depth, box):
        segments = object_segments(depth, K, T, BoxRefineParams())
        return join_fragments(box[None], np.array([True]), segments, K, BoxRefineParams())[0]

    for side in (1.0, -1.0):
        rear = _plate(road, K, T, 12.0, *sorted((side * 4.0, side * 5.8)), 1.5)
        car = _side(rear, K, T, side * 4.0, 12.0, 16.5, 1.5)
        whole, face = _mask_box(car < road), _mask_box(rear < road)
        assert (whole[2] - whole[0]) * 12.0 / K[0, 0] > BoxRefineParams().proposals.max_width_m
        np.testing.assert_allclose(joined(car, face), whole)
        # one depth at both sides: the image width times depth over the focal length
        assert np.isclose(_lateral_width(face[0], 12.0, face[2], 12.0, K), (face[2] - face[0]) * 12.0 / K[0, 0])
        # a second car beside the first at the same depth, touching it: together wider than a vehicle
        pair = _plate(rear, K, T, 12.0, *sorted((side * 5.8, side * 7.6)), 1.5)
        np.testing.assert_allclose(joined(pair, face), face)


def _roof_line_cut_by_a_post():
    """A car 20 m ahead seen only as its roof line above a car 12 m ahead, cut in two by a post 8 m
    ahead: (K, T, depth, segments, the left and right pieces' labels)."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    far = _plate(road, K, T, 20.0, -1.0, 1.0, 1.6)
    depth = _plate(_plate(far, K, T, 12.0, -1.1, 1.1, 1.25), K, T, 8.0, 0.05, 0.15, 2.5)
    seg = object_segments(depth, K, T)
    pieces = [k for k, b in zip(seg.present, seg.present_boxes)
              if np.isclose(np.median(seg.z[seg.labels == k]), 19.37, atol=0.1)]
    assert len(pieces) == 2
    return K, T, depth, seg, sorted(pieces, key=lambda k: seg.boxes([k])[0, 0])


def test_a_proposal_s_surface_is_its_own_segment_s_though_its_box_reaches_over_a_nearer_car():
    """A proposal's box reaches down over its surface below its segment (bumper and tyres; on a
    staircase outline one pixel column of it goes farther down), so it can overlap its own segment by
    less than IoU 0.5, and its core then shows the nearer car that hides the rest of it. Its surface,
    where the fragments of its vehicle are looked for, is the segment it was proposed from: the roof
    line's box grows over the piece of the roof line beyond the post; by overlap, it does not."""
    from vcfusion.fusion.box_refine import _box_surfaces, depth_proposals, join_fragments

    K, T, depth, seg, (left, right) = _roof_line_cut_by_a_post()
    boxes, _, labels = depth_proposals(depth, K, T, np.zeros((0, 4)), segments=seg, with_labels=True)
    assert {left, right} <= set(labels.tolist())
    for box, label in zip(boxes, labels):
        np.testing.assert_allclose(box[[0, 2]], seg.boxes([label])[0, [0, 2]])
    piece = seg.boxes([left])[0] + [0, 0, 0, 12]  # reaching 12 rows down over the nearer car
    whole = np.r_[piece[:2], seg.boxes([right])[0, 2], piece[3]]
    assert box_iou(piece[None], seg.boxes([left]))[0, 0] < 0.5
    assert _box_surfaces(piece[None], seg, BoxRefineParams())[0][0] < 12.0  # the nearer car's depth
    np.testing.assert_allclose(_box_surfaces(piece[None], seg, BoxRefineParams(), np.array([left]))[0], [19.37],
                               atol=0.05)
    np.testing.assert_allclose(join_fragments(piece[None], np.array([True]), seg, K, outline=np.array([left]))[0],
                               whole)
    # found by overlap, its surface is the nearer car's: it does not reach the piece beyond the post
    assert join_fragments(piece[None], np.array([True]), seg, K)[0, 2] == piece[2]
    with pytest.raises(ValueError, match="outline"):
        join_fragments(piece[None], np.array([True]), seg, K, outline=np.array([left, right]))


def test_a_fragment_showing_a_car_s_flank_is_measured_at_its_nearest_part_as_the_box_is():
    """A car 20 m ahead and 2.5 m to the side, a post 10 m ahead in front of its rear near the corner:
    the piece beyond the post is the corner and the flank running to 24.5 m (its median 1.2 m behind
    the rear). Its nearest part lies at the rear's depth, as the box's surface is measured (the face
    of its segment), and the box on the rear grows over it."""
    from vcfusion.fusion.bench import default_camera, road_depth
    from vcfusion.fusion.box_refine import join_fragments, object_segments

    K, T = default_camera()
    road = road_depth(K, T, 640, 480)
    car = _side(_plate(road, K, T, 20.0, 2.5, 4.3, 1.5), K, T, 2.5, 20.0, 24.5, 1.5)
    depth = _plate(car, K, T, 10.0, 1.30, 1.45, 2.0)
    seg = object_segments(depth, K, T)
    far = [k for k in seg.present if np.median(seg.z[seg.labels == k]) > 15.0]
    rear, flank = sorted(far, key=lambda k: seg.boxes([k])[0, 0])
    assert np.median(seg.z[seg.labels == flank]) - np.median(seg.z[seg.labels == rear]) > 1.1
    box = seg.boxes([rear])[0]
    out = join_fragments(box[None], np.array([True]), seg, K)[0]
    np.testing.assert_allclose(out, np.r_[box[:2], seg.boxes([flank])[0, 2], box[3]])
