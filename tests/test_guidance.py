"""The one guidance policy of a run (vcfusion.guidance): levels at the scenario's thresholds,
"ahead", the lanes, and the single ego id; and the cloud guidance stage that uses it."""

import math
from pathlib import Path

import numpy as np
import pytest

from vcfusion.cosim import EgoView, Tick
from vcfusion.driver.cloud_guidance import CloudGuidanceFallback
from vcfusion.guidance import GuidancePolicy
from vcfusion.records import EGO_ID, Guidance, GuidanceSet, TwinStates
from vcfusion.scenario import load_scenario
from vcfusion.traffic.network import read_road

REPO = Path(__file__).resolve().parents[1]
ROAD = read_road(REPO / "sumo_net" / "highway.net.xml")
W = ROAD.lane_width_m


def test_levels_follow_the_scenario_thresholds_and_the_cloud_decision():
    sc = load_scenario(REPO / "scenarios" / "accident.yaml")
    policy = GuidancePolicy.from_scenario(sc, ROAD)
    assert (policy.medium, policy.high) == (sc.ar.medium_threshold, sc.ar.high_threshold) == (0.3, 0.6)
    assert [policy.level(p) for p in (0.0, 0.2999, 0.3, 0.5999, 0.6, 1.0, math.nan)] == \
        ["none", "none", "medium", "medium", "high", "high", "none"]
    # nothing is highlighted while the cloud predicts no change, however high the probability
    assert [policy.level(0.95, d) for d in (0, 1)] == ["none", "high"]
    custom = sc.model_copy(update={"ar": sc.ar.model_copy(update={"medium_threshold": 0.1, "high_threshold": 0.2})})
    assert GuidancePolicy.from_scenario(custom, ROAD).level(0.25) == "high"
    assert [policy.warns(level) for level in ("none", "medium", "high")] == [False, True, True]
    with pytest.raises(ValueError, match="medium <= high"):
        GuidancePolicy.on_road(ROAD, 2, 0.7, 0.6, 150.0)


def test_ahead_and_lanes():
    policy = GuidancePolicy.on_road(ROAD, ego_lane=2, medium=0.3, high=0.6, view_range_m=150.0)
    rear = np.array([99.0, 100.0, 100.01, 250.0, 250.01])
    assert policy.ahead(rear, 100.0).tolist() == [False, False, True, True, False]
    assert not policy.ahead(130.0, 100.0, range_m=20.0)
    assert policy.ahead(110.0, 100.0, range_m=20.0)
    centre = ROAD.lane_centre_d(2)
    lateral = policy.lateral_m(np.array([centre, centre - 0.49 * W, centre - 0.5 * W, centre - W,
                                         centre - 1.49 * W, centre - 1.5 * W, centre + W]))
    assert policy.in_ego_lane(lateral).tolist() == [True, True, False, False, False, False, False]
    assert policy.in_adjacent_lane(lateral).tolist() == [False, False, True, True, True, False, True]
    assert policy.ego_id == EGO_ID == "ego"


def _neighbours(s_centres, lc_prob=None, lc_decision=None, length=4.0):
    n = len(s_centres)
    x, y = ROAD.to_world(np.asarray(s_centres, float), np.full(n, ROAD.lane_centre_d(1)))
    z = np.zeros(n)
    return TwinStates(time=1.0, ids=tuple(f"v{k}" for k in range(n)), measured_time=np.ones(n), x=x, y=y, z=z,
                      heading=z, speed=np.full(n, 17.0), accel=z, lane=np.ones(n, np.int16),
                      length=np.full(n, length), width=np.full(n, 1.8), height=np.full(n, 1.5),
                      outputs={} if lc_prob is None else {"lc_prob": np.asarray(lc_prob, float),
                                                          "lc_decision": np.asarray(lc_decision, np.int8)})


def _tick(near):
    ego = EgoView(speed=19.0, accel=0.0, s=100.0, lane=2, leader_id=None, leader_gap_m=None, leader_speed=None)
    return Tick(1.0, None, None, ego, near)


def test_cloud_guidance_shows_neighbours_ahead_with_the_policy_levels():
    policy = GuidancePolicy.on_road(ROAD, ego_lane=2, medium=0.3, high=0.6, view_range_m=150.0)
    stage = CloudGuidanceFallback(ROAD, policy)
    # centres 101 m (alongside: rear at 99 m, behind the ego's front at 100 m), 103 m, 200 m, 260 m (out of range)
    tick = _tick(_neighbours([101.0, 103.0, 200.0, 260.0], [0.9, 0.45, 0.9, 0.9], [1, 1, 0, 1]))
    rows = stage(tick)
    assert tick.guidance.source == "cloud"
    assert [(g.vehicle_id, g.level) for g in tick.guidance.items] == [("v1", "medium"), ("v2", "none")]
    assert [r["vehicle_id"] for r in rows] == ["v1", "v2"] and {r["source"] for r in rows} == {"cloud"}
    # without lc_prob there is nothing to show, and the run says so
    tick = _tick(_neighbours([103.0]))
    assert stage(tick)[0]["source"] == "none" and tick.guidance == GuidanceSet((), "none")
    # guidance an earlier stage (the overlay) provided is kept and logged as such
    tick = _tick(_neighbours([103.0], [0.9], [1]))
    tick.guidance = GuidanceSet((Guidance(1.0, "v0", 0.9, "high", (1.0, 2.0, 3.0, 4.0)),), "fusion")
    tick.guidance = GuidanceSet((Guidance(1.0, "v0", 0.9, "high", (1.0, 2.0, 3.0, 4.0), "v3"),), "fusion")
    assert stage(tick) == [{"time": 1.0, "vehicle_id": "v0", "box_vehicle_id": "v3", "lc_prob": 0.9, "level": "high",
                            "source": "fusion"}]
    # with a camera the overlay is the only source: a tick without a frame is logged, never filled
    camera_stage = CloudGuidanceFallback(ROAD, policy, camera=True)
    assert "guidance" in camera_stage.needs and not getattr(camera_stage, "fills", ())
    tick = _tick(_neighbours([103.0], [0.9], [1]))
    assert camera_stage(tick)[0]["source"] == "no_frame" and tick.guidance is None


def test_one_ego_id():
    """EGO_ID is defined once (records.py); every stage imports that one."""
    import re

    defined = [p for p in (REPO / "src" / "vcfusion").rglob("*.py")
               if re.search(r"^\s*EGO_ID\s*=", p.read_text(), re.M)]
    assert [p.name for p in defined] == ["records.py"]
