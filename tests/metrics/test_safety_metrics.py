"""TTC, acceleration, jerk and exposure metrics on analytic trajectories."""

import math

import numpy as np
import pandas as pd
import pytest

from vcfusion.metrics.safety import (acceleration_from_speed, exposure, jerk_from_acceleration, trip_metrics,
                                     ttc_series)

DT = 0.01
RANGE = 250.0  # metrics.leader_range_m's default: how far ahead a change into the ego's lane is a cut-in


def _tables(ego_speed, target_s_centre, target_speed, target_lane=2, mid_time=0.0, length=4.0, gap_at_mid=10.0):
    n = len(ego_speed)
    t = np.round(np.arange(n) * DT, 6)
    ego_s = np.concatenate([[0.0], np.cumsum(ego_speed[:-1] * DT)])
    ego = pd.DataFrame({"time": t, "s": ego_s, "speed": ego_speed, "accel": 0.0, "command_accel": 0.0,
                        "leader_id": "", "leader_gap_m": np.nan})
    every = slice(0, n, 10)  # the 0.1 s trajectory table
    traj = pd.DataFrame({"time": t[every], "vehicle_id": "cutter", "s": target_s_centre[every],
                         "speed": target_speed[every], "lane": target_lane})
    lc = pd.DataFrame([{"vehicle_id": "cutter", "mid_time": mid_time, "into_ego_lane": True,
                        "ahead_of_ego": True, "gap_to_ego_m": gap_at_mid}])
    vehicles = pd.DataFrame([{"vehicle_id": "cutter", "length": length}, {"vehicle_id": "ego", "length": length}])
    collisions = pd.DataFrame(columns=["collider", "victim"])
    return {"ego": ego, "trajectories": traj, "lane_changes": lc, "vehicles": vehicles, "collisions": collisions}


def test_constant_speed_closing_ttc_is_gap_over_closing_speed():
    n = 501  # 5 s
    t = np.arange(n) * DT
    ego_v = np.full(n, 20.0)
    # target rear starts 50 m ahead of the ego front; centre = rear + 2 m
    target_s = 50.0 + 15.0 * t + 2.0
    m = trip_metrics(_tables(ego_v, target_s, np.full(n, 15.0)), ego_lane=2, dt=DT, cut_in_range_m=RANGE)
    # gap(t) = 50 - 5 t, TTC = 10 - t on t in [0, 5]: mean 7.5, min 5
    assert m["avg_ttc_s"] == pytest.approx(7.5, abs=1e-6)
    assert m["min_ttc_s"] == pytest.approx(5.0, abs=1e-6)
    assert m["ttc_samples"] == n
    assert m["avg_abs_accel_mps2"] == pytest.approx(0.0)
    assert m["tet_s"] == 0.0


def test_ttc_undefined_when_not_closing_and_interval_starts_at_mid_time():
    n = 301
    t = np.arange(n) * DT
    m = trip_metrics(_tables(np.full(n, 15.0), 30.0 + 20.0 * t, np.full(n, 20.0)), ego_lane=2, dt=DT, cut_in_range_m=RANGE)
    assert m["ttc_samples"] == 0 and math.isnan(m["avg_ttc_s"])
    # closing, but only from t = 2 s on: samples before the mid time do not count
    m = trip_metrics(_tables(np.full(n, 20.0), 52.0 + 15.0 * t, np.full(n, 15.0), mid_time=2.0), ego_lane=2, dt=DT, cut_in_range_m=RANGE)
    assert m["ttc_samples"] == 101
    assert m["min_ttc_s"] == pytest.approx(10 - 3.0, abs=1e-6)
    # not in the ego lane: no TTC
    m = trip_metrics(_tables(np.full(n, 20.0), 52.0 + 15.0 * t, np.full(n, 15.0), target_lane=1), ego_lane=2, dt=DT, cut_in_range_m=RANGE)
    assert m["ttc_samples"] == 0


def test_the_gap_is_measured_while_the_cut_in_vehicle_stays_in_the_ego_lane():
    # it cuts in 50 m ahead and pulls away, leaves the lane at 3 s, and changes back in at 5 s
    # 20 m behind the ego's front (curved seed 4174): the minimum gap is the cut-in's own, 50 m,
    # not -20 m, and no TTC is read after it left
    n = 701
    t = np.arange(n) * DT
    target_s = np.where(t < 4.0, 52.0 + 20.0 * t, 52.0 + 20.0 * 4.0 + 5.0 * (t - 4.0))
    target_s = np.where(t >= 5.0, 20.0 * t - 20.0 + 2.0, target_s)
    tables = _tables(np.full(n, 20.0), target_s, np.full(n, 20.0))
    lane = np.where((tables["trajectories"].time >= 3.0) & (tables["trajectories"].time < 5.0), 1, 2)
    tables["trajectories"]["lane"] = lane
    m = trip_metrics(tables, ego_lane=2, dt=DT, cut_in_range_m=RANGE)
    assert m["min_gap_to_target_m"] == pytest.approx(50.0, abs=1e-6)
    assert m["ttc_samples"] == 0  # it never came closer while it stayed


def test_the_minimum_gap_is_the_response_to_the_cut_in_within_its_window():
    # it cuts in 50 m ahead a little faster than the ego, then at 15 s brakes into a queue and the ego closes
    # to 2 m at 25 s (curved seeds 5042, 5124): the gap of the cut-in's window is 50 m, reached at
    # its start; over the whole stay it is 2 m, at 25 s
    n = 2501
    t = np.arange(n) * DT
    target_v = np.where(t < 15.0, 20.5, np.maximum(20.5 - 4.5 * (t - 15.0), 14.0))
    target_s = 52.0 + np.concatenate([[0.0], np.cumsum(target_v[:-1] * DT)])
    tables = _tables(np.full(n, 20.0), target_s, target_v, mid_time=0.0)
    m = trip_metrics(tables, ego_lane=2, dt=DT, cut_in_range_m=RANGE, cut_in_window_s=10.0)
    assert m["min_gap_to_target_m"] == pytest.approx(50.0, abs=1e-6)
    assert m["min_gap_after_cut_in_s"] == pytest.approx(0.0, abs=1e-9)
    gap_then = 50.0 + np.sum((target_v[:-1] - 20.0) * DT)  # the ego at 20 m/s to the end
    assert m["min_gap_stay_m"] == pytest.approx(gap_then, abs=0.05) and m["min_gap_stay_m"] < 3.0
    # a window as long as the trip reads the whole stay; one from a later cut-in shifts with it
    m = trip_metrics(tables, ego_lane=2, dt=DT, cut_in_range_m=RANGE, cut_in_window_s=30.0)
    assert m["min_gap_to_target_m"] == pytest.approx(m["min_gap_stay_m"])
    assert m["min_gap_after_cut_in_s"] == pytest.approx(25.0, abs=0.01)
    late = _tables(np.full(n, 20.0), target_s, target_v, mid_time=12.0)
    m = trip_metrics(late, ego_lane=2, dt=DT, cut_in_range_m=RANGE, cut_in_window_s=10.0)
    assert m["min_gap_after_cut_in_s"] == pytest.approx(10.0, abs=0.01)
    assert 10.0 < m["min_gap_to_target_m"] < 50.0


def test_a_trip_without_a_cut_in_has_no_exposure_to_measure():
    # TET / TIT are NaN like TTC (0 would pair the trip in the study's TET row only)
    n = 101
    t = np.arange(n) * DT
    tables = _tables(np.full(n, 20.0), 52.0 + 15.0 * t, np.full(n, 15.0))
    tables["lane_changes"] = tables["lane_changes"].iloc[0:0]
    m = trip_metrics(tables, ego_lane=2, dt=DT, cut_in_range_m=RANGE)
    assert m["target_id"] is None and math.isnan(m["tet_s"]) and math.isnan(m["tit_s2"])


def test_a_change_into_the_ego_lane_beyond_the_leader_range_is_no_cut_in():
    # on a long network the first change into the ego's lane was taken 1.4 km ahead, and the study
    # reported TTC and gaps to it ("minimum gap 856 m") as those of the lane-change vehicle
    n = 101
    t = np.arange(n) * DT
    far = _tables(np.full(n, 20.0), 1400.0 + 15.0 * t, np.full(n, 15.0), gap_at_mid=1398.0)
    m = trip_metrics(far, ego_lane=2, dt=DT, cut_in_range_m=RANGE)
    assert m["target_id"] is None and math.isnan(m["min_gap_to_target_m"]) and math.isnan(m["tet_s"])
    near = _tables(np.full(n, 20.0), 52.0 + 15.0 * t, np.full(n, 15.0), gap_at_mid=50.0)
    assert trip_metrics(near, ego_lane=2, dt=DT, cut_in_range_m=RANGE)["target_id"] == "cutter"
    assert trip_metrics(near, ego_lane=2, dt=DT, cut_in_range_m=40.0)["target_id"] is None


def test_tet_tit_below_threshold():
    ttc = np.array([5.0, 2.0, 1.0, np.nan, 4.0])
    tet, tit = exposure(ttc, 0.1, 3.0)
    assert tet == pytest.approx(0.2)
    assert tit == pytest.approx((1.0 + 2.0) * 0.1)


def test_constant_deceleration():
    n = 501
    v = 20.0 - 3.0 * np.arange(n) * DT
    a = acceleration_from_speed(v, DT)
    assert np.allclose(a, -3.0)
    assert np.allclose(jerk_from_acceleration(a, DT), 0.0, atol=1e-9)
    m = trip_metrics(_tables(v, 200.0 + 20.0 * np.arange(n) * DT, np.full(n, 20.0)), 2, DT, RANGE)
    assert m["avg_abs_accel_mps2"] == pytest.approx(3.0)
    assert m["max_decel_mps2"] == pytest.approx(3.0)
    assert m["max_abs_jerk_mps3"] == pytest.approx(0.0, abs=1e-6)


def test_jerk_step_ramp_is_measured_exactly_and_a_step_as_its_rate_over_the_window():
    t = np.arange(0, 3, DT)
    # acceleration ramps from 0 to -4 m/s^2 at -8 m/s^3 (0.5 s), then holds
    a = np.clip(-8.0 * (t - 1.0), -4.0, 0.0)
    j = jerk_from_acceleration(a, DT)
    assert np.max(np.abs(j)) == pytest.approx(8.0, rel=1e-6)
    # a command step of 1 m/s^2 held for a 0.1 s control tick reads 1 / 0.1 = 10 m/s^3
    step = np.where(t >= 1.0, 1.0, 0.0)
    assert np.max(np.abs(jerk_from_acceleration(step, DT))) == pytest.approx(10.0)
    # without the window, the raw 0.01 s difference would be 100 m/s^3
    assert np.max(np.abs(jerk_from_acceleration(step, DT, window_s=DT))) == pytest.approx(100.0)


def test_ttc_series_nan_when_opening():
    out = ttc_series(np.array([10.0, 10.0, -1.0]), np.array([20.0, 15.0, 20.0]), np.array([15.0, 20.0, 15.0]))
    assert out[0] == pytest.approx(2.0) and math.isnan(out[1]) and math.isnan(out[2])
