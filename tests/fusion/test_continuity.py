"""The drawn box's continuity over AR updates (vcfusion.fusion.continuity), alone and in the fusion hook."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from support.cuboid_frames import CuboidFrameSource
from vcfusion.cosim import Tick
from vcfusion.detection.detectors import Detections
from vcfusion.fusion.continuity import MIN_CONTINUITY_IOU, BoxContinuity, moved_box
from vcfusion.fusion.fuse import VisionFusionHook
from vcfusion.fusion.matching import box_iou
from vcfusion.guidance import GuidancePolicy
from vcfusion.records import TwinStates, VehicleStates
from vcfusion.traffic.network import read_road

W, H = 640, 480
TRUCK = np.array([300.0, 200.0, 330.0, 218.0])  # a far truck's box, 30 x 18 px
OUTLINE = np.array([298.0, 198.0, 332.0, 220.0])


def _iou(a, b):
    return float(box_iou(np.asarray(a, float)[None], np.asarray(b, float)[None])[0, 0])


def test_a_box_covering_half_the_vehicle_for_one_update_is_drawn_as_the_mean_with_the_previous_box():
    """A far truck's box covers its left 14 px for one update while its outline stays: the mean of
    it and the box drawn the update before is drawn; the next update's box (whole again) as given."""
    c = BoxContinuity()
    half = TRUCK.copy()
    half[2] = half[0] + 14.0
    assert _iou(half, TRUCK) < MIN_CONTINUITY_IOU
    out, held = c.update(["truck"], [TRUCK], [OUTLINE], W, H)
    assert held == [False] and np.allclose(out[0], TRUCK)
    out, held = c.update(["truck"], [half], [OUTLINE], W, H)
    assert held == [True] and np.allclose(out[0], (half + TRUCK) / 2)
    assert _iou(out[0], TRUCK) >= 0.5 > _iou(half, TRUCK)
    out, held = c.update(["truck"], [TRUCK], [OUTLINE], W, H)
    assert held == [False] and np.allclose(out[0], TRUCK)
    assert c.held_count == 1


def test_a_change_that_stays_is_drawn_whole_one_update_late():
    """The new box differs from the previous one for good (another box given to the twin): it is
    drawn halfway once, then as given."""
    c = BoxContinuity()
    other = TRUCK + np.array([40.0, 0.0, 40.0, 0.0])
    c.update(["truck"], [TRUCK], [OUTLINE], W, H)
    out, held = c.update(["truck"], [other], [OUTLINE], W, H)
    assert held == [True] and np.allclose(out[0], (TRUCK + other) / 2)
    out, held = c.update(["truck"], [other], [OUTLINE], W, H)
    assert held == [False] and np.allclose(out[0], other)


def test_a_box_that_moves_and_grows_with_its_outline_is_drawn_as_given():
    """A vehicle approached fast: its outline moves 12 px and grows by half in one update, and so
    does its box; the previous box moved as the outline moved agrees with it (kept still, it would not)."""
    c = BoxContinuity()
    grown_outline = np.array([310.0, 195.0, 361.0, 228.0])
    grown = moved_box(TRUCK, OUTLINE, grown_outline, W, H)
    assert _iou(grown, TRUCK) < MIN_CONTINUITY_IOU  # without the outline's motion it would be a jump
    c.update(["truck"], [TRUCK], [OUTLINE], W, H)
    out, held = c.update(["truck"], [grown], [grown_outline], W, H)
    assert held == [False] and np.allclose(out[0], grown)


def test_an_outline_cut_by_the_image_side_moves_no_box():
    cut = np.array([600.0, 150.0, 639.5, 300.0])
    assert np.allclose(moved_box(TRUCK, OUTLINE, cut, W, H), TRUCK)
    assert np.allclose(moved_box(TRUCK, cut, OUTLINE, W, H), TRUCK)


def test_a_car_entering_the_frame_at_its_side_is_drawn_as_given():
    """A car alongside enters at the image's right side: its outline is cut by the side, and its
    box grows from a 14 px strip to 60 px in one update (curved.yaml seed 116, 53.6-53.7 s): drawn
    as given, not as a mean with the box before."""
    c = BoxContinuity()
    outline = np.array([560.0, 120.0, 639.5, 479.5])
    strip, entered = np.array([625.5, 260.5, 639.5, 318.5]), np.array([580.0, 260.0, 639.5, 344.0])
    c.update(["car"], [strip], [outline], W, H)
    out, held = c.update(["car"], [entered], [outline], W, H)
    assert held == [False] and np.allclose(out[0], entered)


def test_a_twin_with_nothing_drawn_or_an_update_without_a_frame_forgets_its_box():
    half = TRUCK.copy()
    half[2] = half[0] + 14.0
    c = BoxContinuity()
    c.update(["truck"], [TRUCK], [OUTLINE], W, H)
    c.update(["truck"], [None], [OUTLINE], W, H)
    out, held = c.update(["truck"], [half], [OUTLINE], W, H)
    assert held == [False] and np.allclose(out[0], half)
    c.update(["truck"], [TRUCK], [OUTLINE], W, H)
    c.forget()
    out, held = c.update(["truck"], [half], [OUTLINE], W, H)
    assert held == [False]


@pytest.mark.parametrize("bad", [{"min_iou": 1.5}, {"max_held": -1}])
def test_bad_parameters_are_refused(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        BoxContinuity(**bad)


ROAD = read_road(Path(__file__).resolve().parents[2] / "sumo_net" / "highway.net.xml")
POLICY = GuidancePolicy.on_road(ROAD, ego_lane=2, medium=0.3, high=0.6, view_range_m=150.0)


def _tick(t):
    """The ego in lane 2 and a warned car 30 m ahead in lane 1, both at 15 m/s."""
    s = np.array([100.0 + 15 * t, 130.0 + 15 * t])
    d = np.array([ROAD.lane_centre_d(2), ROAD.lane_centre_d(1)])
    x, y = ROAD.to_world(s, d)
    truth = VehicleStates(time=t, ids=("ego", "car"), vtype=("ego", "car"), vclass=("passenger",) * 2, x=x, y=y,
                          z=np.zeros(2), heading=np.zeros(2), speed=np.full(2, 15.0), accel=np.zeros(2),
                          lane=np.array([2, 1], dtype=np.int16), lateral_offset=np.zeros(2),
                          length=np.full(2, 4.6), width=np.full(2, 1.8), height=np.full(2, 1.5))
    twins = TwinStates(time=t, ids=("car",), measured_time=np.full(1, t), x=truth.x[1:], y=truth.y[1:],
                       z=truth.height[1:] / 2, heading=truth.heading[1:], speed=truth.speed[1:], accel=truth.accel[1:],
                       lane=truth.lane[1:], length=truth.length[1:], width=truth.width[1:], height=truth.height[1:],
                       outputs={"lc_prob": np.array([0.9]), "lc_decision": np.array([True])})
    return Tick(t, truth, None, None, twins)


class HalfBoxOnce:
    """The car's true box, except at 0.3 s: its middle 40 % of columns only (a detection glitch that
    still holds the twin's anchor)."""

    frame = None
    time = 0.0

    def detect(self, image):
        box = self.frame.gt_boxes[list(self.frame.gt_ids).index("car")].copy()
        if abs(self.time - 0.3) < 1e-6:
            w = box[2] - box[0]
            box[0], box[2] = box[0] + 0.3 * w, box[2] - 0.3 * w
        return Detections.of(np.array([box]), np.array([0.9]), np.array([3]))


@pytest.mark.parametrize("continuity", [True, False])
def test_the_hook_smooths_a_one_update_glitch_with_the_previous_box(continuity):
    frames, detector = CuboidFrameSource(), HalfBoxOnce()

    def source(tick):
        detector.frame, detector.time = frames(tick), tick.time
        return detector.frame

    hook = VisionFusionHook(source, detector, 0, POLICY, method="baseline", continuity=continuity)
    rows = pd.DataFrame([r for k in range(6) for r in hook(_tick(round(0.1 * k, 6))) or []])
    glitch = rows[np.isclose(rows["time"], 0.3)].iloc[0]
    others = rows[~np.isclose(rows["time"], 0.3)]
    assert (others["outcome"] == "right").all() and not others["smoothed"].any()
    if continuity:
        assert glitch["outcome"] == "right" and glitch["smoothed"]
    else:
        assert glitch["outcome"] == "wrong" and not glitch["smoothed"]
