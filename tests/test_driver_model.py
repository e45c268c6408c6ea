"""The driver model on hand-made ticks (no SUMO): noticing cut-ins with and without guidance."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from vcfusion.cosim import Tick
from vcfusion.driver.model import DriverModel
from vcfusion.driver.params import CarLimits, draw_driver
from vcfusion.guidance import GuidancePolicy
from vcfusion.records import Guidance, GuidanceSet, VehicleStates
from vcfusion.traffic.network import read_road

ROAD = read_road(Path(__file__).resolve().parents[1] / "sumo_net" / "highway.net.xml")
W = ROAD.lane_width_m
POLICY = GuidancePolicy.on_road(ROAD, ego_lane=2, medium=0.3, high=0.6, view_range_m=150.0)


def _truth(t, ego_s, ego_v, other_s, other_d, other_v):
    s = np.array([ego_s, other_s])
    d = np.array([ROAD.lane_centre_d(2), other_d])
    x, y = ROAD.to_world(s, d)
    n = 2
    return VehicleStates(time=t, ids=("ego", "cutter"), vtype=("ego", "car"), vclass=("passenger",) * n,
                         x=x, y=y, z=np.zeros(n), heading=np.zeros(n), speed=np.array([ego_v, other_v]),
                         accel=np.zeros(n), lane=np.array([2, 1], dtype=np.int16), lateral_offset=np.zeros(n),
                         length=np.full(n, 4.6), width=np.full(n, 1.8), height=np.full(n, 1.5))


def _drive(driver, drift_at=None, guidance_at=None, until=4.0, gap=20.0, level="high"):
    """Ego from 19 m/s; a car at 14 m/s in the adjacent lane `gap` m ahead; it starts to drift at drift_at."""
    accs = []
    ego_s, ego_v, cut_s = 100.0, 19.0, 100.0 + gap + 4.6
    for k in range(int(until / 0.1) + 1):
        t = round(k * 0.1, 6)
        d = ROAD.lane_centre_d(1)
        if drift_at is not None and t >= drift_at:
            d += min(W, 1.2 * (t - drift_at))  # 1.2 m/s lateral speed
        truth = _truth(t, ego_s - 2.3, ego_v, cut_s - 2.3, d, 14.0)
        items = []
        if guidance_at is not None and t >= guidance_at:
            items = [Guidance(t, "cutter", 0.9, level, None)]
        tick = Tick(t, truth, None, None, None, guidance=GuidanceSet(tuple(items), "cloud"))
        accs.append(driver.acceleration(tick))
        ego_s += ego_v * 0.1 + 0.5 * accs[-1] * 0.01  # the ego moves as the driver asked
        ego_v = max(0.0, ego_v + accs[-1] * 0.1)
        cut_s += 14.0 * 0.1
    return np.array(accs)


def _driver(guidance, seed=1, **over):
    p = replace(draw_driver(seed, 19.0), **over)
    return DriverModel(p, ROAD, POLICY, guidance_enabled=guidance)


def test_lateral_drift_is_noticed_after_threshold_and_reaction_time():
    drv = _driver(False, lateral_notice_m=0.4, cutin_reaction_s=1.2, pedal_time_constant_s=0.2)
    accs = _drive(drv, drift_at=1.0)
    ev = drv.events[0]
    # 0.4 m at 1.2 m/s lateral speed: first tick at or after 1.0 + 0.333 s
    assert ev["cue"] == "lateral" and ev["time"] == pytest.approx(1.4)
    assert ev["response_time"] == pytest.approx(1.4 + 1.2)
    # before the response (and before the car's centre is in the ego lane at ~2.46 s) nothing happens
    assert np.all(accs[:24] > -0.05)
    assert accs.min() < -1.0


def test_guidance_gives_an_earlier_response_only_when_enabled():
    kwargs = dict(guidance_reaction_s=0.75, cutin_reaction_s=1.25, pedal_time_constant_s=0.2)
    with_g = _driver(True, **kwargs)
    a_with = _drive(with_g, drift_at=2.0, guidance_at=0.5, until=6.0)
    assert with_g.events[0]["cue"] == "guidance"
    assert with_g.events[0]["response_time"] == pytest.approx(0.5 + 0.75)
    # a prospective leader (still in its lane) asks for at most the comfortable deceleration
    before_entry = a_with[:20]
    assert before_entry.min() < -0.2
    assert before_entry.min() >= -with_g.p.comfort_decel_mps2 - 1e-9
    without = _driver(False, **kwargs)
    a_without = _drive(without, drift_at=2.0, guidance_at=0.5, until=6.0)
    assert all(e["cue"] == "lateral" for e in without.events)
    assert np.all(a_without[:20] > -0.05)
    # braking earlier and softer: the hardest braking is milder with guidance
    assert a_with.min() > a_without.min()


def test_applied_acceleration_respects_car_jerk_and_decel_limits():
    drv = _driver(False, pedal_time_constant_s=0.1)
    accs = _drive(drv, drift_at=0.0, gap=2.0, until=3.0)  # a car cutting in 2 m ahead: emergency
    lim = CarLimits()
    assert accs.min() >= -lim.max_decel_mps2
    assert np.min(np.diff(accs)) >= -lim.max_brake_jerk_mps3 * 0.1 - 1e-9


def test_driver_draw_is_seeded_and_within_documented_ranges():
    a, b, c = draw_driver(7, 19.0), draw_driver(7, 19.0), draw_driver(8, 19.0)
    assert a == b and a != c
    for seed in range(50):
        p = draw_driver(seed, 19.0)
        assert 1.0 <= p.time_headway_s <= 1.8 and 0.6 <= p.follow_reaction_s <= 1.2
        assert 0.7 <= p.cutin_reaction_s <= 2.5 and 0.4 <= p.guidance_reaction_s <= 1.5
        assert 0.3 <= p.lateral_notice_m <= 0.5


def test_only_warning_levels_reach_the_driver():
    """An item of level none is shown (a thin outline) but is no warning: the driver does not respond."""
    drv = _driver(True, guidance_reaction_s=0.75)
    _drive(drv, guidance_at=0.5, until=3.0, level="none")
    assert drv.events == []
    drv = _driver(True, guidance_reaction_s=0.75)
    _drive(drv, guidance_at=0.5, until=3.0, level="medium")
    assert [e["cue"] for e in drv.events] == ["guidance"] and drv.events[0]["level"] == "medium"


def test_driver_finishes_with_its_tables_and_summary():
    drv = _driver(True)
    _drive(drv, drift_at=1.0, guidance_at=0.5, until=3.0)
    tables, summary = {}, {}
    drv.finish(tables, summary)
    assert set(tables) == set(drv.finish_tables) and set(summary) == set(drv.finish_summary)
    assert len(tables["driver"]) == 31 and summary["driver"]["guidance_enabled"] is True
    assert tables["driver_events"]["cue"].tolist() == ["guidance", "lateral"]  # both cues are logged
