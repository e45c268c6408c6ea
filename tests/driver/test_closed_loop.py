"""The closed loop on hand-made ticks: what the AR draws is what the driver sees and responds to.

Real fusion hook (matcher, overlay items, the judged vehicle in each box), real guidance log, real driver and
the study's highlight counting; the frames come from the test-only cuboid frame source (it has an
instance map), the boxes from a detector that draws them where the test says.
"""

from pathlib import Path

import numpy as np
import pandas as pd

from support.cuboid_frames import CuboidFrameSource, ShiftedOntoNeighbour
from vcfusion.cosim import Tick
from vcfusion.detection.detectors import Detections
from vcfusion.driver.cloud_guidance import CloudGuidanceFallback
from vcfusion.driver.model import DriverModel
from vcfusion.driver.params import draw_driver
from vcfusion.fusion.fuse import VisionFusionHook
from vcfusion.guidance import GuidancePolicy
from vcfusion.records import TwinStates, VehicleStates
from vcfusion.studies.guidance import highlight_counts
from vcfusion.traffic.network import read_road

ROAD = read_road(Path(__file__).resolve().parents[2] / "sumo_net" / "highway.net.xml")
POLICY = GuidancePolicy.on_road(ROAD, ego_lane=2, medium=0.3, high=0.6, view_range_m=150.0)
IDS = ("ego", "cutter", "neighbour")


def _truth(t, ego_s):
    """The ego in lane 2; the cutter 25 m ahead and a neighbour 12 m ahead, both in lane 1."""
    s = np.array([ego_s, ego_s + 25.0 + 0.6 * t, ego_s + 12.0 + 0.6 * t])
    d = np.array([ROAD.lane_centre_d(2), ROAD.lane_centre_d(1), ROAD.lane_centre_d(1)])
    x, y = ROAD.to_world(s, d)
    n = 3
    return VehicleStates(time=t, ids=IDS, vtype=("ego", "car", "car"), vclass=("passenger",) * n, x=x, y=y,
                         z=np.zeros(n), heading=np.zeros(n), speed=np.array([19.0, 15.0, 15.0]), accel=np.zeros(n),
                         lane=np.array([2, 1, 1], dtype=np.int16), lateral_offset=np.zeros(n),
                         length=np.full(n, 4.6), width=np.full(n, 1.8), height=np.full(n, 1.5))


def _twins(truth, warned=True):
    """Perfect twins of the two neighbours; the cloud warns about the cutter only."""
    k = [1, 2]
    return TwinStates(time=truth.time, ids=tuple(truth.ids[i] for i in k), measured_time=np.full(2, truth.time),
                      x=truth.x[k], y=truth.y[k], z=truth.z[k] + truth.height[k] / 2, heading=truth.heading[k],
                      speed=truth.speed[k], accel=truth.accel[k], lane=truth.lane[k], length=truth.length[k],
                      width=truth.width[k], height=truth.height[k],
                      outputs={"lc_prob": np.array([0.9 if warned else 0.05, 0.05]),
                               "lc_decision": np.array([warned, False])})


class NoBoxes:
    def detect(self, image):
        return Detections.empty()


def _closed_loop(detector, guided=True, until=3.0, warned=True):
    frames = CuboidFrameSource()

    def source(tick):
        frame = frames(tick)
        detector.frame = frame
        return frame

    fusion = VisionFusionHook(source, detector, 0, POLICY, method="baseline")
    log = CloudGuidanceFallback(ROAD, POLICY, camera=True)
    driver = DriverModel(draw_driver(3, 19.0), ROAD, POLICY, guidance_enabled=guided)
    fusion_rows, guidance_rows, accs = [], [], []
    ego_s = 100.0
    for k in range(int(round(until / 0.1)) + 1):
        t = round(0.1 * k, 6)
        truth = _truth(t, ego_s)
        tick = Tick(t, truth, None, None, _twins(truth, warned))
        fusion_rows += fusion(tick) or []
        guidance_rows += log(tick)
        accs.append(driver.acceleration(tick))
        ego_s += 19.0 * 0.1
    return driver, pd.DataFrame(fusion_rows), pd.DataFrame(guidance_rows), np.array(accs)


def test_the_overlay_does_not_draw_a_box_spread_onto_the_nearer_neighbour():
    # the box over both cars is many times the cutter's outline: it cannot be the cutter's vehicle
    driver, fusion, guidance, accs = _closed_loop(ShiftedOntoNeighbour())
    assert not (guidance["level"].isin(["medium", "high"])).any() and driver.warnings == {}
    cutter = fusion[fusion["vehicle_id"] == "cutter"]
    assert len(cutter) and not cutter["matched"].any() and set(cutter["outcome"]) <= {"missed", "unseen"}


def test_a_box_shifted_onto_the_neighbour_makes_the_driver_respond_to_the_neighbour(monkeypatch):
    import vcfusion.fusion.fuse as fuse

    # the overlay's plausibility gates off: the box drawn for the cutter shows the neighbour
    monkeypatch.setattr(fuse, "MAX_BOX_TO_OUTLINE_AREA", float("inf"))
    monkeypatch.setattr(fuse, "MAX_HIDDEN_SHARE_DRAWN", 2.0)
    monkeypatch.setattr(fuse, "MIN_BOX_INSIDE_OUTLINE", 0.0)
    driver, fusion, guidance, accs = _closed_loop(ShiftedOntoNeighbour())
    warned = guidance[guidance["level"].isin(["medium", "high"])]
    # the cloud meant the cutter; the box drawn for it holds the neighbour
    assert len(warned) and set(warned["vehicle_id"]) == {"cutter"} and set(warned["box_vehicle_id"]) == {"neighbour"}
    cues = [e for e in driver.events if e["cue"] == "guidance"]
    assert [(e["vehicle_id"], e["twin_id"]) for e in cues] == [("neighbour", "cutter")]
    assert set(driver.warnings) == {"neighbour"}
    counts = highlight_counts(guidance, fusion, 0.1)
    assert counts == {"highlights_right": 0, "highlights_wrong": 1, "missed_warnings": 0, "unseen_warnings": 0}
    # and the driver does respond (releases the throttle), unlike one without guidance
    _, _, _, unguided = _closed_loop(ShiftedOntoNeighbour(), guided=False)
    assert accs.min() < unguided.min() - 0.2


def test_a_twin_without_a_matched_box_gives_no_highlight_and_no_response():
    driver, fusion, guidance, accs = _closed_loop(NoBoxes())
    assert (guidance["vehicle_id"] == "").all() and set(guidance["source"]) == {"fusion"}  # nothing shown
    assert not fusion["matched"].any() and (fusion[fusion["vehicle_id"] == "cutter"]["level"] == "high").all()
    assert driver.warnings == {} and not [e for e in driver.events if e["cue"] == "guidance"]
    assert highlight_counts(guidance, fusion, 0.1) == {"highlights_right": 0, "highlights_wrong": 0,
                                                       "missed_warnings": 1, "unseen_warnings": 0}
    _, _, _, unguided = _closed_loop(NoBoxes(), guided=False)
    assert np.array_equal(accs, unguided)


def test_right_boxes_count_as_right():
    class OwnBoxes:
        frame = None

        def detect(self, image):
            return Detections.of(self.frame.gt_boxes, np.full(len(self.frame.gt_boxes), 0.9),
                                 np.full(len(self.frame.gt_boxes), 3))

    driver, fusion, guidance, _ = _closed_loop(OwnBoxes())
    assert set(driver.warnings) == {"cutter"}
    assert highlight_counts(guidance, fusion, 0.1) == {"highlights_right": 1, "highlights_wrong": 0,
                                                       "missed_warnings": 0, "unseen_warnings": 0}


class TallBoxes:
    """The boxes of the truth with the cutter's grown upward to 2.7 times its height (a car and the
    truck behind it joined into one surface by the depth step): a box of the cutter, mostly not it."""

    frame = None

    def detect(self, image):
        boxes = np.array(self.frame.gt_boxes, float)
        k = self.frame.gt_ids.index("cutter")
        boxes[k, 1] = boxes[k, 3] - 2.7 * (boxes[k, 3] - boxes[k, 1])
        return Detections.of(boxes, np.full(len(boxes), 0.9), np.full(len(boxes), 3))


def test_a_box_mostly_above_the_twins_outline_is_drawn_within_it(monkeypatch):
    import vcfusion.fusion.fuse as fuse

    driver, fusion, guidance, _ = _closed_loop(TallBoxes())
    cutter = fusion[(fusion["vehicle_id"] == "cutter") & fusion["matched"]]
    assert len(cutter) and (cutter["outcome"] == "right").all()
    assert highlight_counts(guidance, fusion, 0.1) == {"highlights_right": 1, "highlights_wrong": 0,
                                                       "missed_warnings": 0, "unseen_warnings": 0}
    # without the rule the tall box is drawn whole and shows the cutter by IoU 0.37: wrong
    monkeypatch.setattr(fuse, "MIN_BOX_INSIDE_OUTLINE", 0.0)
    _, fusion, guidance, _ = _closed_loop(TallBoxes())
    assert highlight_counts(guidance, fusion, 0.1)["highlights_wrong"] == 1
