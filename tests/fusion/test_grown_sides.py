"""On noisy depth, a snapped box does not grow over a surface that a ramp of intermediate depths
joins to its vehicle (box_refine._grown_sides; synthetic depth images whose answers are known)."""

from dataclasses import replace

import numpy as np

from support.road_depth import flat_road_depth, road_camera_pose
from vcfusion.fusion.box_refine import BoxRefineParams, refine_boxes
from vcfusion.fusion.road import DepthNoise

W, H, F = 320, 240, 460.0
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
# a stereo pair's error after the depth step's 5 x 5 median: 0.3 x sigma_d / (f B), 0.25 px, 0.12 m
STEREO = DepthNoise(c=0.3 * 0.25 / (F * 0.12))


def _scene():
    """A car 15 m ahead (columns 130-189, rows 105-138), and left of its lower half a low surface 13.5 m
    ahead (columns 100-125, a barrier, or a car beside it) joined to the car by four columns whose depth
    steps 0.3-0.4 m from one to the next (what the median and the hole fill leave of a depth jump)."""
    T = road_camera_pose(3.0, 1.4)
    ramp = [(126 + k, 118, 127 + k, 135, d) for k, d in enumerate((13.8, 14.1, 14.4, 14.7))]
    depth = flat_road_depth(T, K, W, H, 400.0, [(130, 105, 190, 139, 15.0), (100, 118, 126, 135, 13.5), *ramp])
    return depth, T


def test_on_noisy_depth_a_side_stops_where_the_depth_leaves_the_detectors_side():
    depth, T = _scene()
    detected = np.array([[129.0, 103.0, 192.0, 141.0]])  # the car's box, its left side on the ramp
    params = BoxRefineParams()
    # the step from the car (15 m) to the barrier (13.5 m) exceeds the jump threshold (1.2 m at 15 m),
    # but no step between neighbouring columns does: the segment runs on over the barrier
    without = refine_boxes(detected, depth, K, T, replace(params, grown_sides=False), STEREO)
    assert without.refined[0] and without.boxes[0, 0] < 105
    exact = refine_boxes(detected, depth, K, T, params, DepthNoise())  # exact depth: the rule does not run
    assert exact.refined[0] and exact.boxes[0, 0] < 105
    out = refine_boxes(detected, depth, K, T, params, STEREO)
    assert out.refined[0] and not out.gated[0]
    # column medians from the detector's side (14.7 m) outward: 14.4, 14.1, 13.8 within the threshold
    # of 14.7 (1.12 m at 13.8 m), 13.5 m beyond it: the side ends left of column 126
    assert out.boxes[0, 0] == 125.5
    # the other sides are the snap's own
    assert np.array_equal(out.boxes[0, 1:], without.boxes[0, 1:])


def test_a_side_grown_over_the_vehicle_s_own_surface_is_kept():
    depth, T = _scene()
    detected = np.array([[145.0, 103.0, 192.0, 141.0]])  # a box that stopped 15 px short of the car's left
    out = refine_boxes(detected, depth, K, T, BoxRefineParams(), STEREO)
    # the car's columns all read 15 m: the side goes on over them, and over the ramp's columns within
    # the threshold of 15 m (14.7-14.1 m; 1.13 m at 14.1 m), and stops before 13.8 m
    assert out.refined[0] and 126.5 <= out.boxes[0, 0] <= 129.5


def test_a_side_stops_at_the_detectors_box_of_a_vehicle_beside_it_at_the_same_depth():
    T = road_camera_pose(3.0, 1.4)
    # two trucks abreast 20 m ahead (columns 100-159 and 160-219): one surface to depth
    depth = flat_road_depth(T, K, W, H, 400.0, [(100, 80, 160, 135, 20.0), (160, 80, 220, 135, 20.0)])
    detected = np.array([[98.0, 78.0, 158.0, 137.0], [165.0, 78.0, 221.0, 137.0]])
    without = refine_boxes(detected, depth, K, T, replace(BoxRefineParams(), grown_sides=False), STEREO)
    assert without.refined[1] and without.boxes[1, 0] < 150  # the right truck's box grows over the left one
    out = refine_boxes(detected, depth, K, T, BoxRefineParams(), STEREO)
    assert out.refined[1] and out.boxes[1, 0] == 158.0  # it stops at the left truck's box
    # a box of something nearer beside it (another depth) does not stop it
    nearer = flat_road_depth(T, K, W, H, 400.0, [(100, 80, 160, 135, 12.0), (160, 80, 220, 135, 20.0)])
    alone = refine_boxes(detected[1:], nearer, K, T, BoxRefineParams(), STEREO)
    beside = refine_boxes(detected, nearer, K, T, BoxRefineParams(), STEREO)
    assert np.array_equal(beside.boxes[1], alone.boxes[0])


def test_a_side_cut_far_inward_where_the_depth_beyond_is_holes_is_the_detectors():
    T = road_camera_pose(3.0, 1.4)
    # a truck 7 m ahead (columns 100-219, rows 40-169) whose upper half is textureless: a hole
    depth = flat_road_depth(T, K, W, H, 400.0, [(100, 40, 220, 170, 7.0)])
    depth[40:100, 100:220] = np.nan
    detected = np.array([[98.0, 38.0, 222.0, 172.0]])
    without = refine_boxes(detected, depth, K, T, replace(BoxRefineParams(), hole_side_share=0.0), STEREO)
    assert without.refined[0] and without.boxes[0, 1] > 95  # the top moved down to the hole's edge
    out = refine_boxes(detected, depth, K, T, BoxRefineParams(), STEREO)
    assert out.refined[0] and out.boxes[0, 1] == detected[0, 1]  # beyond it the depth is holes
    assert np.array_equal(out.boxes[0, [0, 2, 3]], without.boxes[0, [0, 2, 3]])
    # a side moved inward by less than a fifth of the box keeps the snap's side, holes or not (the
    # unmatched sky above a car's roof)
    short = np.array([[98.0, 90.0, 222.0, 172.0]])
    assert refine_boxes(short, depth, K, T, BoxRefineParams(), STEREO).boxes[0, 1] > 95
