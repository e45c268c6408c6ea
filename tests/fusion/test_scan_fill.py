"""Depth with gaps made whole enough for the depth step: a LiDAR scan's gaps between returns filled
along the road and along each surface, a stereo pair's holes and occlusion bands filled along the
rows, and the sides of a box the scan cannot see left to the detector (synthetic depth images whose
answers are known)."""

import numpy as np

from support.road_depth import flat_road_depth, road_camera_pose
from vcfusion.detection.detectors import Detections
from vcfusion.fusion.box_refine import BoxRefineParams, _Heights, fill_scan_gaps, refine_boxes
from vcfusion.fusion.fuse import CameraFrame, depth_step, depth_view
from vcfusion.fusion.matching import box_iou
from vcfusion.fusion.road import DepthNoise
from vcfusion.fusion.sensors import SensorModel
from vcfusion.fusion.stage import camera_view

W, H, F, CAM_H = 320, 240, 460.0, 1.4
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])
JUMP = (BoxRefineParams().jump_m, BoxRefineParams().jump_rel)


def _pose(pitch_deg=3.0):
    """Camera 1.4 m above the road at the origin, looking along +x, pitched down."""
    return road_camera_pose(pitch_deg, CAM_H)


def _road_depth(T, cars=()):
    """Depth of a flat road (z = 0) seen from T, with fronto-parallel blocks (x1, y1, x2, y2, depth)."""
    return flat_road_depth(T, K, W, H, 400.0, cars)


def _heights(depth, T):
    return _Heights(K, T).window(np.where(np.isfinite(depth), depth, 0).astype(np.float32), 0, 0)


def test_a_scan_of_the_road_is_filled_along_the_road_and_each_surface():
    T = _pose()
    truth = _road_depth(T, cars=[(140, 105, 190, 139, 15.0)])  # standing on the road 15 m ahead (row 139)
    scan = np.full_like(truth, np.nan)
    scan[2::4] = truth[2::4]  # a return on every fourth row
    on_road = np.isfinite(scan) & (np.abs(_heights(scan, T)) < 0.1)
    filled = fill_scan_gaps(scan, 6, *JUMP, axis=0, on_road=on_road)
    road = np.isfinite(truth) & (truth != 15.0) & (truth < 150)
    road[:, 130:200] = False  # the columns under the car hold its lower edge
    # far down the road two rows' returns lie metres apart (a depth jump), yet the gap is the road's:
    # filled along the plane (inverse depth is linear on a plane), so no road pixel stands above it
    assert np.nanmax(np.abs(_heights(filled, T)[road][np.isfinite(filled[road])])) < 0.01
    without = fill_scan_gaps(scan, 6, *JUMP, axis=0)  # the same, not told which returns are the road's
    assert np.nanmax(np.abs(_heights(without, T)[road])) > 0.1
    # the car's face is whole, and its lower edge lies half-way between its last return and the road's
    assert np.allclose(filled[107:136, 140:190], 15.0)
    lowest = np.flatnonzero(np.abs(filled[:, 165] - 15.0) < 1e-3).max()
    assert abs(lowest - 138) <= 2
    # a gap wider than allowed stays a gap
    sparse = np.full_like(truth, np.nan)
    sparse[::12] = truth[::12]
    assert np.isnan(fill_scan_gaps(sparse, 6, *JUMP, axis=0)[5]).all()


def test_stereo_holes_fill_along_the_rows_and_occlusion_bands_take_the_farther_surface():
    row = np.full((1, 30), np.nan, np.float32)
    row[0, :10], row[0, 15:] = 20.0, 8.0  # a far surface, the band the right camera cannot see, a nearer one
    out = fill_scan_gaps(row, 16, *JUMP, axis=1, occlusion_side="left")
    assert np.all(out[0, 10:15] == 20.0)
    mirrored = np.full((1, 30), np.nan, np.float32)
    mirrored[0, :10], mirrored[0, 15:] = 8.0, 20.0  # nearer on the left: no occlusion, the edge half-way
    out = fill_scan_gaps(mirrored, 16, *JUMP, axis=1, occlusion_side="left")
    assert np.all(out[0, 10:12] == 8.0) and np.all(out[0, 13:15] == 20.0)
    flat = np.full((1, 12), np.nan, np.float32)  # a textureless patch on one surface: interpolated
    flat[0, 0], flat[0, 11] = 10.0, 10.5
    out = fill_scan_gaps(flat, 16, *JUMP, axis=1, occlusion_side="left")
    expected = 1.0 / (1 / 10.0 + np.arange(12) / 11.0 * (1 / 10.5 - 1 / 10.0))
    assert np.allclose(out[0], expected, rtol=1e-5)
    wide = np.full((1, 40), np.nan, np.float32)
    wide[0, 0], wide[0, 39] = 10.0, 10.0
    assert np.isnan(fill_scan_gaps(wide, 16, *JUMP, axis=1)[0, 1:39]).all()


def test_a_side_the_scan_cannot_see_is_the_detectors_and_a_box_between_few_rows_is_gated():
    T = _pose()
    # a truck 9 m ahead (standing on row 167, 127 px high) and a car 40 m ahead (on row 112, 16 px high)
    truth = _road_depth(T, cars=[(100, 40, 220, 167, 9.0), (240, 96, 261, 112, 40.0)])
    scan = np.full_like(truth, np.nan)
    scan[82::4] = truth[82::4]  # no return above row 82 (beyond the top beam): the truck's upper part
    returns = ~np.isnan(scan)
    on_road = returns & (np.abs(_heights(scan, T)) < 0.1)
    filled = fill_scan_gaps(scan, 6, *JUMP, axis=0, on_road=on_road)
    detected = np.array([[97.0, 42.0, 224.0, 170.0]])
    out = refine_boxes(detected, filled, K, T, BoxRefineParams(), DepthNoise(a=0.02), returns)
    assert out.refined[0] and not out.gated[0]
    assert out.boxes[0, 1] == detected[0, 1]  # the top: where the scan sees nothing, the detector's
    assert abs(out.boxes[0, 0] - 99.5) <= 0.5 and abs(out.boxes[0, 2] - 219.5) <= 0.5  # the sides: the truck's
    # without the scan's returns the snapped box stops at the highest beam
    blind = refine_boxes(detected, filled, K, T, BoxRefineParams(), DepthNoise(a=0.02))
    assert blind.boxes[0, 1] > 75
    # a far car crossed by three of the scan's rows: its outline lies between them
    far = np.array([[238.0, 94.0, 263.0, 113.0]])
    assert refine_boxes(far, filled, K, T, BoxRefineParams(), DepthNoise(a=0.02), returns).gated[0]


def test_the_depth_step_snaps_boxes_on_a_lidar_scan():
    T = _pose()
    car = (130, 105, 190, 139)  # a car 15 m ahead on row 139, 34 px high: about ten of the scan's rows
    truth = _road_depth(T, cars=[(*car, 15.0)])
    sensor = SensorModel("lidar", rng=np.random.default_rng(5))
    frame = CameraFrame(0.0, np.zeros((H, W, 3), np.uint8), sensor.depth(truth, K, T), camera_view(K, T, W, H, 0.0),
                        depth_noise=sensor.noise(K))
    assert np.isnan(frame.depth).mean() > 0.7  # a sparse scan
    loose = np.array([[124.0, 100.0, 197.0, 143.0]])  # the detector's box, a few px loose on each side
    true_box = np.array([[car[0] - 0.5, car[1] - 0.5, car[2] - 0.5, car[3] - 0.5]])
    assert box_iou(loose, true_box)[0, 0] < 0.8
    stats = {}
    out = depth_step(frame, Detections.of(loose, np.array([0.9]), np.array([1])), BoxRefineParams(road="from_depth"),
                     stats=stats)
    assert stats["boxes_refined"] == 1 and stats["boxes_gated"] == 0 and "frames_without_proposals" not in stats
    assert box_iou(out.boxes[:1], true_box)[0, 0] > 0.85
    # with the gaps left open, the same scan keeps the detector's box (and says so)
    kept = {}
    out = depth_step(frame, Detections.of(loose, np.array([0.9]), np.array([1])),
                     BoxRefineParams(road="from_depth", scan_fill_px=None), stats=kept)
    assert kept["boxes_gated"] == 1 and np.array_equal(out.boxes, loose)


def test_a_filled_scan_is_not_median_filtered_so_a_far_car_does_not_widen():
    """A 5 x 5 median over a filled scan mixed a far car's depth with the road's beside its lower half
    (the road's depth changes by metres per row there) and stood those pixels above the road."""
    T = _pose(1.0)
    road = _road_depth(T)[:, 160]
    for d, min_iou in ((50.0, 0.75), (70.0, 0.7)):
        row = int(np.argmin(np.abs(np.where(np.isfinite(road), road, 1e9) - d)))  # the car stands on this row
        h_px, w_px = round(1.5 * F / d), round(1.8 * F / d)
        car = (160 - w_px // 2, row - h_px + 1, 160 - w_px // 2 + w_px, row + 1)
        sensor = SensorModel("lidar", rng=np.random.default_rng(5))
        truth = _road_depth(T, cars=[(*car, d)])
        frame = CameraFrame(0.0, np.zeros((H, W, 3), np.uint8), sensor.depth(truth, K, T),
                            camera_view(K, T, W, H, 0.0), depth_noise=sensor.noise(K))
        view = depth_view(frame, BoxRefineParams(road="flat"))
        assert view.returns is not None and not view.sparse  # a scan, its gaps filled
        beside = np.zeros((H, W), bool)  # the columns either side of the car, around its rows
        beside[car[1] - 4:car[3] + 4, car[0] - 6:car[2] + 6] = True
        beside[:, car[0]:car[2]] = False
        at_car = np.isfinite(view.depth) & (np.abs(view.depth - d) < 0.1 * d) & (_heights(view.depth, T) > 0.05)
        assert not (beside & at_car).any()  # with the median: 11 (50 m), 12 (70 m) such pixels
        true_box = np.array([[car[0] - 0.5, car[1] - 0.5, car[2] - 0.5, car[3] - 0.5]])
        loose = true_box + np.array([[-1.0, -1.0, 1.0, 1.0]])
        out = depth_step(frame, Detections.of(loose, np.array([0.9]), np.array([1])),
                         BoxRefineParams(road="from_depth"), stats={})
        assert box_iou(out.boxes[:1], true_box)[0, 0] > min_iou  # with the median: 0.74 (50 m), 0.63 (70 m)


def test_the_depth_step_snaps_a_car_whose_stereo_depth_has_a_textureless_hole_across_it():
    T = _pose()
    car = (130, 105, 190, 139)  # a car 15 m ahead on row 139, 60 px wide
    truth = _road_depth(T, cars=[(*car, 15.0)])
    sensor = SensorModel("stereo", rng=np.random.default_rng(7))
    depth = sensor.depth(truth, K, T)
    depth[:, 155:167] = np.nan  # a flat-coloured band down the car's middle: block matching finds nothing
    frame = CameraFrame(0.0, np.zeros((H, W, 3), np.uint8), depth, camera_view(K, T, W, H, 0.0),
                        depth_noise=sensor.noise(K))
    loose = np.array([[124.0, 100.0, 197.0, 143.0]])
    true_box = np.array([[car[0] - 0.5, car[1] - 0.5, car[2] - 0.5, car[3] - 0.5]])
    dets = Detections.of(loose, np.array([0.9]), np.array([1]))
    stats = {}
    filled = depth_step(frame, dets, BoxRefineParams(road="from_depth"), stats=stats)
    assert stats["boxes_refined"] == 1 and box_iou(filled.boxes[:1], true_box)[0, 0] > 0.85
    # left open, the band cuts the car in two and the box snaps to one half
    frame = CameraFrame(0.0, np.zeros((H, W, 3), np.uint8), depth, camera_view(K, T, W, H, 0.0),
                        depth_noise=sensor.noise(K))
    split = depth_step(frame, dets, BoxRefineParams(road="from_depth", hole_fill_px=0))
    assert box_iou(split.boxes[:1], true_box)[0, 0] < 0.7


def test_fill_settings_out_of_range_say_which():
    import pytest

    with pytest.raises(ValueError, match="scan_fill_px"):
        BoxRefineParams(scan_fill_px=(6, -1))
    with pytest.raises(ValueError, match="hole_fill_px"):
        BoxRefineParams(hole_fill_px=-2)
    with pytest.raises(ValueError, match="occlusion_side"):
        fill_scan_gaps(np.zeros((2, 2), np.float32), 4, *JUMP, axis=1, occlusion_side="right")
