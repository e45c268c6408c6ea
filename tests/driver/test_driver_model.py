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

ROAD = read_road(Path(__file__).resolve().parents[2] / "sumo_net" / "highway.net.xml")
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


def _states(t, rows):
    """VehicleStates from (id, s, lane, speed, length, height) rows; the first is the ego."""
    ids = tuple(r[0] for r in rows)
    s = np.array([r[1] for r in rows])
    d = np.array([ROAD.lane_centre_d(r[2]) for r in rows])
    x, y = ROAD.to_world(s, d)
    n = len(rows)
    return VehicleStates(time=t, ids=ids, vtype=("car",) * n, vclass=("passenger",) * n, x=x, y=y, z=np.zeros(n),
                         heading=np.zeros(n), speed=np.array([r[3] for r in rows]), accel=np.zeros(n),
                         lane=np.array([r[2] for r in rows], dtype=np.int16), lateral_offset=np.zeros(n),
                         length=np.array([r[4] for r in rows]), width=np.full(n, 1.8),
                         height=np.array([r[5] for r in rows]))


def test_a_car_fully_behind_a_truck_is_not_seen_until_it_emerges():
    from vcfusion.driver.perception import DriverView, visible_vehicles

    view = DriverView()
    seen_with, seen_without = [], []
    for k in range(60):
        # a truck in lane 1 25 m ahead; a car in lane 0 behind it (from the ego in lane 2) drives away
        car_s = 150.0 + 2.0 * k
        for trucks, out in ((True, seen_with), (False, seen_without)):
            rows = [("ego", 100.0, 2, 19.0, 4.6, 1.5), ("car", car_s, 0, 20.0, 4.6, 1.5)]
            rows += [("truck", 131.0, 1, 19.0, 12.0, 3.8)] if trucks else []
            truth = _states(0.1 * k, rows)
            s, d = truth.road_frame(ROAD)
            mask = visible_vehicles(s, d, truth.length, truth.width, truth.height, 0, POLICY, view)
            out.append(bool(mask[1]))
            if trucks:
                assert mask[2]  # the truck itself is seen
    assert not seen_with[0] and seen_with[-1]  # hidden at first, seen once it emerges
    first = seen_with.index(True)
    assert not any(seen_with[:first]) and all(seen_with[first:])  # and it stays seen
    assert all(seen_without)  # without the truck it is seen all along
    # the driver model sees through the same test: it does not see the hidden car
    drv = _driver(False)
    tick = Tick(0.0, _states(0.0, [("ego", 100.0, 2, 19.0, 4.6, 1.5), ("car", 150.0, 0, 20.0, 4.6, 1.5),
                                   ("truck", 131.0, 1, 19.0, 12.0, 3.8)]), None, None, None)
    drv.acceleration(tick)
    assert drv.log_rows[-1]["vehicles_seen"] == 1


def test_field_of_view_and_left_mirror():
    from vcfusion.driver.perception import DriverView, visible_vehicles

    # ego in lane 1: beside it (outside the 70 deg forward view), left lane 20 m behind (mirror),
    # right lane 20 m behind (no right mirror), 40 m ahead in the right lane (forward view)
    truth = _states(0.0, [("ego", 100.0, 1, 19.0, 4.6, 1.5), ("beside", 101.0, 2, 19.0, 4.6, 1.5),
                          ("left_behind", 80.0, 2, 19.0, 4.6, 1.5), ("right_behind", 80.0, 0, 19.0, 4.6, 1.5),
                          ("ahead", 140.0, 0, 19.0, 4.6, 1.5)])
    policy = GuidancePolicy.on_road(ROAD, ego_lane=1, medium=0.3, high=0.6, view_range_m=150.0)
    s, d = truth.road_frame(ROAD)
    mask = visible_vehicles(s, d, truth.length, truth.width, truth.height, 0, policy, DriverView())
    assert dict(zip(truth.ids, mask.tolist())) == {"ego": False, "beside": False, "left_behind": True,
                                                   "right_behind": False, "ahead": True}
    wide = visible_vehicles(s, d, truth.length, truth.width, truth.height, 0, policy, DriverView(hfov_deg=178.0))
    assert wide[1]  # a wider field of view sees the car beside


def _warned_drive(shown_at, until=4.0):
    """The cutter stays in its lane 20 m ahead at the ego's speed (the gap does not close); the
    warning is shown at the ticks in `shown_at`."""
    drv = _driver(True, guidance_reaction_s=0.75, pedal_time_constant_s=0.3, cover_decel_mps2=0.5)
    accs = []
    ego_s, ego_v, cut_s = 100.0, 19.0, 124.6
    for k in range(int(until / 0.1) + 1):
        t = round(k * 0.1, 6)
        truth = _truth(t, ego_s - 2.3, ego_v, cut_s - 2.3, ROAD.lane_centre_d(1), 19.0)
        items = (Guidance(t, "cutter", 0.9, "high", None),) if k in shown_at else ()
        accs.append(drv.acceleration(Tick(t, truth, None, None, None, guidance=GuidanceSet(items, "cloud"))))
        ego_s += ego_v * 0.1
        ego_v = max(0.0, ego_v + accs[-1] * 0.1)
        cut_s += 19.0 * 0.1
    return drv, np.array(accs)


def test_a_one_tick_warning_flicker_does_not_move_the_pedal():
    steady = set(range(5, 41))
    _, a_none = _warned_drive(set())
    drv, a_steady = _warned_drive(steady)
    # the warning response: throttle released, a small deceleration, sustained while shown
    assert a_steady.min() < -0.3 and a_steady.min() >= -drv.p.cover_decel_mps2 - 1e-9
    assert np.all(a_steady[:13] == a_none[:13])  # nothing before the reaction time (0.5 + 0.75 s)
    # one tick missing amid a steady warning: held by the hysteresis, the pedal does not move
    _, a_gap = _warned_drive(steady - {20})
    assert np.array_equal(a_gap, a_steady)
    # a warning shown for one tick only ends (0.3 s hold) before the response would start
    _, a_blip = _warned_drive({10})
    assert np.array_equal(a_blip, a_none)
    # a gap longer than the hold ends the response: the pedal comes back up
    _, a_long_gap = _warned_drive(set(range(5, 21)))
    assert a_long_gap[-1] > a_steady[-1] + 0.2


def test_brakes_toward_a_gap_only_when_the_highlighted_car_moves_over_or_the_gap_closes():
    # highlighted, staying in its lane, slower but far enough: only the cover deceleration
    drv = _driver(True, guidance_reaction_s=0.75, pedal_time_constant_s=0.2, cover_decel_mps2=0.5,
                  comfort_decel_mps2=2.0)
    accs = _drive(drv, guidance_at=0.5, until=2.0, gap=40.0)
    assert accs.min() >= -0.5 - 1e-9 and accs.min() < -0.4
    # once the gap to it closes (nearer than s0 + v T, closing in) it brakes toward a gap
    drv = _driver(True, guidance_reaction_s=0.75, pedal_time_constant_s=0.2, cover_decel_mps2=0.5,
                  comfort_decel_mps2=2.0)
    accs = _drive(drv, guidance_at=0.5, until=5.0, gap=40.0)
    assert accs.min() < -1.0 and accs.min() >= -2.0 - 1e-9
    assert [r["leader_kind"] for r in drv.log_rows][-1] == "prospective"
    # the same with the car moving over: it becomes a prospective leader, braking up to b
    drv = _driver(True, guidance_reaction_s=0.75, pedal_time_constant_s=0.2, cover_decel_mps2=0.5,
                  comfort_decel_mps2=2.0)
    accs = _drive(drv, guidance_at=0.5, drift_at=1.0, until=4.0, gap=12.0)
    assert accs.min() < -1.0
    lateral = [e for e in drv.events if e["cue"] == "lateral"]
    # the driver was warned, so the move-over is an expected event: the shorter reaction time
    assert lateral and lateral[0]["response_time"] - lateral[0]["time"] == pytest.approx(0.75)


def _reference_visible(s, d, length, width, height, ego, policy, view):
    """Plain-Python transcription of driver/perception.py's rules (the reference for the kernel)."""
    import math

    n = len(s)
    eye_s, eye_d, half = s[ego] + view.eye_forward_m, d[ego], math.radians(view.hfov_deg) / 2
    w = policy.lane_width_m
    out, box = [False] * n, {}
    for i in range(n):
        if i == ego:
            continue
        near, far = s[i] - length[i] / 2 - eye_s, s[i] + length[i] / 2 - eye_s
        lo_d, hi_d = d[i] - width[i] / 2 - eye_d, d[i] + width[i] / 2 - eye_d
        side = d[i] - policy.ego_lane_centre_d
        if w / 2 <= side < 1.5 * w and -view.mirror_range_m < far < 0:
            out[i] = True
            continue
        if far <= 0 or near > view.sight_range_m:
            continue
        angles = [math.atan2(y, x) for x in (max(near, 1e-3), far) for y in (lo_d, hi_d)]
        lo, hi = max(min(angles), -half), min(max(angles), half)
        if hi <= lo:
            continue
        r_near = max(math.hypot(min(max(0.0, near), far), min(max(0.0, lo_d), hi_d)), 0.1)
        r_far = math.hypot(far, max(abs(lo_d), abs(hi_d)))
        box[i] = (lo, hi, r_near, (height[i] - view.eye_height_m) / r_near, (height[i] - view.eye_height_m) / r_far)
    for i, (lo, hi, r_near, slope, _) in box.items():
        covers = sorted((a, b) for k, (a, b, r, _, occ) in box.items() if k != i and r < r_near and occ >= slope)
        covered, reach = 0.0, lo
        for a, b in covers:
            a, b = max(a, reach), min(b, hi)
            if b > a:
                covered, reach = covered + b - a, b
        out[i] = 1.0 - covered / (hi - lo) >= view.min_visible_fraction
    return np.array(out)


def test_perception_kernel_equals_the_plain_python_rules():
    from vcfusion.driver.perception import DriverView, visible_vehicles

    rng = np.random.default_rng(0)
    view = DriverView()
    seen_counts = []
    for _ in range(300):
        n = int(rng.integers(2, 25))
        s = rng.uniform(0.0, 400.0, n)
        s[0] = 150.0
        d = np.array([ROAD.lane_centre_d(int(k)) for k in rng.integers(0, 3, n)]) + rng.normal(0, 0.4, n)
        d[0] = ROAD.lane_centre_d(2)
        truck = rng.random(n) < 0.3
        length, height = np.where(truck, 12.0, 4.6), np.where(truck, 3.8, 1.5)
        width = np.full(n, 1.8)
        got = visible_vehicles(s, d, length, width, height, 0, POLICY, view)
        want = _reference_visible(s, d, length, width, height, 0, POLICY, view)
        assert np.array_equal(got, want)
        seen_counts.append(int(got.sum()))
    # the scenes exercise both outcomes: some vehicles seen, some hidden or out of view
    assert 0 < np.mean(seen_counts) < 12


def _lateral_trace(driver, d_of_t, until=8.0, ahead_m=40.0, speed=19.0):
    """Ego at 19 m/s; another car `ahead_m` ahead at `speed`, its lateral position d_of_t(t)."""
    ego_s, other_s = 100.0, 100.0 + ahead_m + 4.6
    for k in range(int(until / 0.1) + 1):
        t = round(k * 0.1, 6)
        tick = Tick(t, _truth(t, ego_s, 19.0, other_s, d_of_t(t), speed), None, None, None,
                    guidance=GuidanceSet((), "none"))
        driver.acceleration(tick)
        ego_s += 1.9
        other_s += speed * 0.1
    return driver


def test_a_car_leaving_the_ego_lane_is_no_cut_in_cue_and_never_a_prospective_leader():
    # the leader moves from the ego lane to the lane on its right at 1.2 m/s: it crosses the band
    # where a cut-in is noticed, moving away
    leave = _lateral_trace(_driver(False, lateral_notice_m=0.4, cutin_reaction_s=1.2),
                           lambda t: ROAD.lane_centre_d(2) - min(W, 1.2 * max(0.0, t - 0.5)))
    assert [e for e in leave.events if e["cue"] == "lateral"] == []
    kinds = {r["leader_kind"] for r in leave.log_rows if r["leader_id"] == "cutter"}
    assert kinds == {"lane"}  # followed while its centre was in the ego lane, then let go
    assert leave.log_rows[-1]["leader_id"] == ""


def test_a_car_that_moves_over_again_after_going_back_is_a_new_cue():
    # drifts 1 m toward the ego lane from t = 1, goes back to its lane centre by t = 3.3, and
    # moves over again from t = 5: two lateral cues, and no prospective leader while it is back
    def d(t):
        toward = 1.2 * (t - 1.0) if 1.0 <= t < 1.9 else max(0.0, 1.08 - 0.8 * (t - 1.9)) if t < 5.0 else 1.2 * (t - 5.0)
        return ROAD.lane_centre_d(1) + min(W, toward)
    drv = _lateral_trace(_driver(False, lateral_notice_m=0.4, cutin_reaction_s=1.2), d)
    cues = [e["time"] for e in drv.events if e["cue"] == "lateral"]
    assert cues == pytest.approx([1.4, 5.4])
    back = [r for r in drv.log_rows if 3.4 <= r["time"] < 5.0]
    assert back and all(r["leader_id"] == "" for r in back)


def test_the_gap_is_not_extrapolated_past_the_age_of_the_first_views():
    # closing in at 5 m/s from 20 m: in the trip's first follow_reaction_s the driver's only view is
    # younger than the delay, and the gap it perceives is the true one (not 5 m short)
    drv = _driver(False, follow_reaction_s=1.0)
    ego_s, lead_s = 100.0, 100.0 + 20.0 + 4.6
    for k in range(4):
        t = round(k * 0.1, 6)
        drv.acceleration(Tick(t, _truth(t, ego_s, 19.0, lead_s, ROAD.lane_centre_d(2), 14.0), None, None, None,
                              guidance=GuidanceSet((), "none")))
        assert drv.log_rows[-1]["perceived_gap_m"] == pytest.approx(20.0 - 0.5 * k)
        ego_s += 1.9
        lead_s += 1.4


_SIZES = {"car": (4.6, 1.8, 1.5), "truck": (12.0, 2.5, 3.6)}


def _scene(t, ego_front, ego_v, others):
    """The ego's truth at time `t`: the ego in lane 2, its front bumper at s = `ego_front`, and
    `others`: (id, lane, d, rear s, speed, vtype "car" or "truck") each."""
    kinds = ("car",) + tuple(o[5] for o in others)
    size = np.array([_SIZES[k] for k in kinds])
    s = np.array([ego_front - size[0, 0] / 2] + [o[3] + _SIZES[o[5]][0] / 2 for o in others])
    x, y = ROAD.to_world(s, np.array([ROAD.lane_centre_d(2)] + [o[2] for o in others]))
    n = len(kinds)
    return VehicleStates(time=t, ids=("ego",) + tuple(o[0] for o in others), vtype=("ego",) + kinds[1:],
                         vclass=tuple("truck" if k == "truck" else "passenger" for k in kinds),
                         x=x, y=y, z=np.zeros(n), heading=np.zeros(n),
                         speed=np.array([ego_v] + [o[4] for o in others], dtype=float), accel=np.zeros(n),
                         lane=np.array([2] + [o[1] for o in others], dtype=np.int16), lateral_offset=np.zeros(n),
                         length=size[:, 0], width=size[:, 1], height=size[:, 2])


def _drive_past(driver, others_at, ego_v, until):
    """Tick the driver every 0.1 s to `until`, the ego from s = 100 m (front) and `ego_v` moving as
    it asks; `others_at(t)` gives the other vehicles (as :func:`_scene`). The (t, ego front) of
    every tick."""
    ego_front, trace = 100.0, []
    for k in range(int(until / 0.1) + 1):
        t = round(k * 0.1, 6)
        a = driver.acceleration(Tick(t, _scene(t, ego_front, ego_v, others_at(t)), None, None, None,
                                     guidance=GuidanceSet((), "none")))
        trace.append((t, ego_front))
        ego_front += ego_v * 0.1 + 0.5 * a * 0.01
        ego_v = max(0.0, ego_v + a * 0.1)
    return trace


def _slide_in(driver, gap_m, kind, from_lane, counted, ego_v, lateral_mps=0.6, until=14.0):
    """A stopped `kind` ("car" or "truck") `gap_m` ahead of the ego's front sliding from lane
    `from_lane`'s centre into the ego lane (lane 2) at `lateral_mps`; the ego from `ego_v` moves as
    the driver asks. The smallest gap (m) between the ego's front and its rear while `counted(d)`
    holds of its centre's d, and the driver."""
    start, d2 = ROAD.lane_centre_d(from_lane), ROAD.lane_centre_d(2)
    rear = 100.0 + gap_m
    slide = lambda t: min(d2, start + lateral_mps * t)  # noqa: E731
    trace = _drive_past(driver, lambda t: [(kind, from_lane, slide(t), rear, 0.0, kind)], ego_v, until)
    gaps = [rear - front for t, front in trace if counted(slide(t))]
    return min(gaps, default=np.inf), driver


def _truck_slide(driver, gap_m):
    """A stopped truck (12 x 2.5 m) sliding from lane 0 over lane 1 into the ego lane, as a truck
    blocked before a closure does (curved.yaml seed 16), the ego from 12 m/s (:func:`_slide_in`):
    the gap counted while the truck's body leaves the ego's less than SUMO's lane-change
    bookkeeping allows (its centre beyond lane 1's: SUMO counts it in the ego lane)."""
    return _slide_in(driver, gap_m, "truck", 0, lambda d: d > ROAD.lane_centre_d(1), ego_v=12.0)


def test_a_stopped_truck_sliding_over_from_two_lanes_across_is_noticed_and_stopped_for():
    # the truck's move toward the ego lane is noticed as it enters the adjacent lane's band, having
    # moved more than lateral_notice_m (not only 0.4 m past lane 1's centre), and the ego, arriving as the truck
    # crosses lane 1, stops behind it: braking beyond the comfortable deceleration where the gap
    # asks for it (v^2 / 2 s)
    kw = dict(lateral_notice_m=0.4, cutin_reaction_s=1.25, comfort_decel_mps2=2.0, pedal_time_constant_s=0.3,
              follow_reaction_s=0.9)
    for gap in (80.0, 95.0, 110.0):
        worst, drv = _truck_slide(_driver(False, **kw), gap)
        cue = next(e for e in drv.events if e["cue"] == "lateral")
        # the adjacent band starts 1.5 lane widths from the ego lane's centre: 0.5 w of slide
        assert cue["time"] == pytest.approx(0.5 * W / 0.6, abs=0.11)
        assert worst > 0.5, gap


def test_a_prospective_leader_asks_beyond_the_comfortable_deceleration_only_when_the_gap_needs_it():
    from vcfusion.driver.model import stopping_decel

    assert stopping_decel(20.0, 10.0) == pytest.approx(2.5)
    assert stopping_decel(20.0, -3.0) == 0.0 and stopping_decel(0.0, 1.0) == pytest.approx(5.0)


def _queue_squeeze(driver, gap_m):
    """A car standing in the adjacent lane (lane 1) squeezing into the ego lane, as cars queued
    before a closure do (curved.yaml seed 1038: a car standing 26 m before the accident, taken as a
    leader 3.2 m ahead at 3.8 m/s), the ego from 4 m/s (:func:`_slide_in`): the gap counted once
    the car's body reaches into the ego lane."""
    d2 = ROAD.lane_centre_d(2)
    return _slide_in(driver, gap_m, "car", 1, lambda d: d2 - d < 1.8, ego_v=4.0, until=10.0)


def test_a_car_squeezing_in_from_a_queue_is_stopped_for_short_of_the_minimum_gap():
    # the driver brakes for a prospective leader to stop s0 (2 m) short of it, not at its bumper:
    # a stop planned at contact ends in contact with the pedal lag (10 m: -0.01 m, 12 m: 0.58 m)
    kw = dict(lateral_notice_m=0.4, guidance_reaction_s=0.75, cutin_reaction_s=1.25, comfort_decel_mps2=2.0,
              pedal_time_constant_s=0.3, follow_reaction_s=0.9, desired_speed_mps=4.0)
    worst, drv = _queue_squeeze(_driver(False, **kw), 10.0)
    assert 0.3 < worst < 1.5  # the emergency stop: the car moved over 2.5 s before the ego got there
    assert min(r["applied_accel"] for r in drv.log_rows) < -8.0
    for gap in (12.0, 16.0, 20.0, 24.0):
        worst, _ = _queue_squeeze(_driver(False, **kw), gap)
        assert worst > 1.9, gap  # s0, less the pedal's overshoot


def test_an_expected_merger_close_ahead_makes_the_driver_cover_the_brake():
    # a car creeping up to a truck stopped in the adjacent lane is expected to merge; while the ego,
    # faster, is nearer to it than its desired gap s0 + v T, the driver releases the throttle and
    # covers the brake, as for a warning; the same car with nothing stopped ahead of it is not
    # expected to merge and changes nothing
    for stopped_ahead in (True, False):
        drv = _driver(False, time_headway_s=1.5, cover_decel_mps2=0.5, pedal_time_constant_s=0.2)
        ego_s, ego_v, merger_rear = 100.0, 6.0, 130.0
        rows = []
        for k in range(70):
            t = round(k * 0.1, 6)
            d1 = ROAD.lane_centre_d(1)
            cars = [("merger", 1, d1, merger_rear, 1.0, "car")]
            if stopped_ahead:
                cars.append(("truck", 1, d1, merger_rear + 4.6 + 3.0, 0.0, "truck"))
            drv.acceleration(Tick(t, _scene(t, ego_s, ego_v, cars), None, None, None,
                                  guidance=GuidanceSet((), "none")))
            rows.append((merger_rear - ego_s, drv.log_rows[-1]))
            ego_s += ego_v * 0.1  # the ego holds 6 m/s: the test reads what the driver asks
            merger_rear += 0.1
        desired_gap = 2.0 + 6.0 * 1.5
        far = [r for gap, r in rows if gap > desired_gap + 0.5]
        near = [r for gap, r in rows if 0.5 < gap < desired_gap - 0.5]
        assert far and near
        assert all(r["desired_accel"] > 0 and r["leader_kind"] != "cover" for r in far)
        cues = [e["cue"] for e in drv.events if e["vehicle_id"] == "merger"]
        if stopped_ahead:
            assert cues == ["anticipation"]
            assert all(r["desired_accel"] == pytest.approx(-0.5) and r["leader_kind"] == "cover" for r in near)
        else:
            assert cues == []
            assert all(r["desired_accel"] > 0 for r in near)
