"""The depth step without a perfect world: the road plane fitted to the depth image, the gates that
keep the detector's box where depth cannot decide (counted), and the noise-aware thresholds."""

import numpy as np

from vcfusion.detection.detectors import Detections
from vcfusion.fusion.box_refine import BoxRefineParams, _Heights, refine_boxes
from vcfusion.fusion.fuse import CameraFrame, depth_step
from vcfusion.fusion.road import DepthNoise, fit_road_plane
from vcfusion.fusion.stage import camera_view
from support.road_depth import flat_road_depth, road_camera_pose

W, H, F, CAM_H = 320, 240, 250.0, 1.4
K = np.array([[F, 0.0, W / 2], [0.0, F, H / 2], [0.0, 0.0, 1.0]])


def _pose(pitch_deg=3.0):
    """Camera 1.4 m above the road at the origin, looking along +x, pitched down."""
    return road_camera_pose(pitch_deg, CAM_H)


def _road_depth(T, car=None):
    """Depth of a flat road (z = 0) seen from T; `car`: (x1, y1, x2, y2, depth) a fronto-parallel block."""
    return flat_road_depth(T, K, W, H, 400.0, [car] if car is not None else ())


def test_the_road_fit_finds_the_road_the_pose_got_wrong():
    true, believed = _pose(3.5), _pose(3.0)  # the camera pitched 0.5 deg more than the fusion believes
    depth = _road_depth(true, car=(140, 100, 180, 135, 15.0))
    fit = fit_road_plane(depth, K, believed)
    assert fit.ok and abs(fit.tilt_deg - 0.5) < 0.02 and abs(fit.height_m - CAM_H) < 0.01
    z = np.where(np.isfinite(depth), depth, 0).astype(np.float32)
    road = np.isfinite(depth) & (depth < 60) & (depth != 15.0)
    prior = _Heights(K, believed).window(z, 0, 0)[road]
    fitted = _Heights(K, fit.T).window(z, 0, 0)[road]
    assert np.abs(prior).max() > 0.3  # 0.5 deg: a road point 40-60 m ahead seems 0.35-0.5 m off the road
    assert np.abs(fitted).max() < 0.02
    # the car's pixels stand up to its top above the fitted road
    car = _Heights(K, fit.T).window(z, 0, 0)[100:135, 140:180]
    assert car.max() > 1.0


def test_a_fit_without_enough_road_says_so_and_keeps_the_nominal_pose():
    depth = np.full((H, W), np.nan, np.float32)
    fit = fit_road_plane(depth, K, _pose())
    assert not fit.ok and np.array_equal(fit.T, _pose())


def test_boxes_depth_cannot_support_keep_the_detectors_box_and_are_counted():
    T = _pose()
    depth = _road_depth(T, car=(140, 100, 180, 135, 15.0))
    box = np.array([[138.0, 98.0, 183.0, 137.0]])
    exact = refine_boxes(box, depth, K, T)
    assert exact.refined[0] and not exact.gated[0]
    # a sensor whose sigma at 15 m (0.05 * 225 = 11 m) dwarfs the jump threshold there
    noisy = refine_boxes(box, depth, K, T, noise=DepthNoise(c=0.05))
    assert noisy.gated[0] and not noisy.refined[0] and np.array_equal(noisy.boxes, box)
    holes = depth.copy()
    holes[100:135, 140:180] = np.nan  # the car holds no measurement
    gated = refine_boxes(box, holes, K, T)
    assert gated.gated[0] and np.array_equal(gated.boxes, box)


def test_the_depth_step_counts_what_it_could_not_decide():
    T = _pose()
    depth = _road_depth(T, car=(140, 100, 180, 135, 15.0))
    sparse = np.full_like(depth, np.nan)
    sparse[::12] = depth[::12]  # every twelfth row measured: a sparse scan
    frame = CameraFrame(0.0, np.zeros((H, W, 3), np.uint8), sparse, camera_view(K, T, W, H, 0.0),
                        depth_noise=DepthNoise(a=0.02))
    dets = Detections.of(np.array([[138.0, 98.0, 183.0, 137.0]]), np.array([0.9]), np.array([1]))
    stats = {}
    out = depth_step(frame, dets, BoxRefineParams(road="from_depth"), stats=stats)
    assert np.array_equal(out.boxes, dets.boxes)  # kept as detected, nothing proposed
    assert stats["boxes_gated"] == 1 and stats["boxes_refined"] == 0 and stats["frames_without_proposals"] == 1
    assert stats["frames"] == 1 and "frames_road_fit_failed" in stats


def test_auto_takes_the_flat_road_only_where_depth_and_pose_are_exact():
    from vcfusion.fusion.stage import refine_params, road_model
    from vcfusion.scenario import load_scenario

    assert road_model("auto", "exact", False) == "flat"
    assert road_model("auto", "stereo", False) == "from_depth"
    assert road_model("auto", "exact", True) == "from_depth"
    assert road_model("flat", "lidar", True) == "flat" and road_model("from_depth", "exact", False) == "from_depth"
    sc = load_scenario("accident_ar")
    assert sc.fusion.road == "auto" and refine_params(sc).road == "flat"
    stereo = sc.model_copy(update={"camera": sc.camera.model_copy(update={"depth": "stereo"})})
    assert refine_params(stereo).road == "from_depth"
    tilted = sc.model_copy(update={"camera": sc.camera.model_copy(update={
        "pose_noise": sc.camera.pose_noise.model_copy(update={"mount_std_deg": 0.3})})})
    assert refine_params(tilted).road == "from_depth"
