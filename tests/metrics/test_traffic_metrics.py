"""Per-vehicle run metrics on hand-made trajectories with known answers (no SUMO)."""

import json

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from vcfusion.metrics import traffic
from vcfusion.metrics.movestar import movestar, resample_to_1hz
from vcfusion.metrics.run_metrics import summary_block
from vcfusion.metrics.traffic import compute_run_metrics, conflict_episodes, histogram_percentile, leaders
from vcfusion.scenario import MetricsConfig

DT = 0.1


def _trajectories(tracks: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]) -> pa.Table:
    """{vehicle: (time, lane, s, speed)} -> a trajectories table in time order, as a run writes it."""
    rows = pd.concat([pd.DataFrame({"time": t, "vehicle_id": vid, "lane": lane, "s": s, "speed": v})
                      for vid, (t, lane, s, v) in tracks.items()])
    rows = rows.sort_values(["time", "vehicle_id"], kind="stable")
    rows["lane"] = rows["lane"].astype(np.int16)
    return pa.Table.from_pandas(rows, preserve_index=False)


def _vehicles(ids, length=4.0, vclass="passenger", vtype="car", group="cars") -> pd.DataFrame:
    return pd.DataFrame({"vehicle_id": list(ids), "vtype": vtype, "vclass": vclass, "length": length,
                         "group": group})


def _metrics(tracks, cfg=None, vehicles=None, **kw):
    table = _trajectories(tracks)
    cfg = cfg or MetricsConfig()
    vehicles = vehicles if vehicles is not None else _vehicles(tracks)
    return compute_run_metrics(cfg, DT, DT, table, vehicles, None, None, None, **kw)


def _times(n):
    return np.round(np.arange(n) * DT, 6)


def test_closing_in_on_a_slower_leader():
    # follower at 20 m/s, leader at 10 m/s, 30 m apart bumper to bumper at t = 0 (lengths 4 m):
    # gap = 30 - 10 t, TTC = 3 - t, DRAC = 10^2 / (2 gap), headway = gap / 20
    t = _times(26)
    tracks = {"F": (t, np.zeros(26), 20.0 * t, np.full(26, 20.0)),
              "L": (t, np.zeros(26), 34.0 + 10.0 * t, np.full(26, 10.0))}
    threshold = 1.55  # clear of the sample values (TTC 1.5 at t = 1.5 is below it)
    result = _metrics(tracks, MetricsConfig(ttc_threshold_s=threshold))
    m = result.vehicles.to_pandas().set_index("vehicle_id")
    f = m.loc["F"]
    assert f["ttc_samples"] == 26
    assert f["min_ttc_s"] == pytest.approx(0.5)
    below = 3.0 - t[t >= 1.5 - 1e-9]
    assert len(below) == 11
    assert f["tet_s"] == pytest.approx(11 * DT)
    assert f["tit_s2"] == pytest.approx(DT * np.sum(threshold - below))  # 0.605 s^2
    assert f["tit_s2"] == pytest.approx(0.605)
    assert f["max_drac_mps2"] == pytest.approx(10.0 ** 2 / (2 * 5.0))
    assert f["min_time_headway_s"] == pytest.approx(5.0 / 20.0)
    assert f["min_gap_m"] == pytest.approx(5.0)
    assert f["conflicts"] == 1
    assert f["distance_m"] == pytest.approx(50.0) and f["travel_time_s"] == pytest.approx(2.6)
    assert f["mean_abs_accel_mps2"] == pytest.approx(0.0) and f["max_abs_jerk_mps3"] == pytest.approx(0.0)
    assert m.loc["L", "ttc_samples"] == 0 and np.isnan(m.loc["L", "min_ttc_s"]) and m.loc["L", "conflicts"] == 0
    c = result.conflicts.to_pandas().iloc[0]
    assert (c["vehicle_id"], c["leader_id"]) == ("F", "L") and len(result.conflicts) == 1
    assert c["start_time"] == pytest.approx(1.5) and c["end_time"] == pytest.approx(2.6)
    assert c["min_ttc_s"] == pytest.approx(0.5) and c["s_start"] == pytest.approx(30.0)


def test_time_headway_at_equal_speeds_and_the_leader_range():
    t = _times(50)
    tracks = {"F": (t, np.ones(50), 20.0 * t, np.full(50, 20.0)),
              "L": (t, np.ones(50), 34.0 + 20.0 * t, np.full(50, 20.0)),
              "far": (t, np.ones(50), 334.0 + 20.0 * t, np.full(50, 20.0)),  # 296 m ahead of L: beyond 250 m
              "other_lane": (t, np.zeros(50), 10.0 + 20.0 * t, np.full(50, 25.0))}
    m = _metrics(tracks).vehicles.to_pandas().set_index("vehicle_id")
    assert m.loc["F", "min_time_headway_s"] == pytest.approx(30.0 / 20.0)
    assert m.loc["F", "ttc_samples"] == 0 and m.loc["F", "tet_s"] == 0.0
    assert np.isnan(m.loc["L", "min_time_headway_s"])  # its next vehicle ahead is out of range
    assert np.isnan(m.loc["other_lane", "min_gap_m"])  # nobody ahead in lane 0


def test_jerk_of_a_constant_jerk_ramp_and_its_filter():
    j = 2.0  # v = 10 + j t^2 / 2: a = j t, jerk = j; a moving average of a ramp keeps its slope
    t = _times(60)
    tracks = {"V": (t, np.zeros(60), 10.0 * t + j * t ** 3 / 6, 10.0 + 0.5 * j * t ** 2)}
    for window in (0.1, 0.3):
        m = _metrics(tracks, MetricsConfig(jerk_window_s=window)).vehicles.to_pandas().iloc[0]
        assert m["max_abs_jerk_mps3"] == pytest.approx(j, rel=1e-9)
        # forward differences: a_i = j (t_i + dt / 2)
        assert m["mean_abs_accel_mps2"] == pytest.approx(np.mean(j * (t[:-1] + DT / 2)), rel=1e-9)
        assert m["max_decel_mps2"] == 0.0


def test_conflict_episodes_split_at_a_new_leader_and_at_a_gap():
    ttc = np.array([1.0, 1.0, 1.0, np.nan, 1.0, 1.0, 2.0, 1.0, 1.0])
    leader = np.array([1, 1, 2, 2, 2, 2, 2, 2, 2])
    assert conflict_episodes(ttc, leader, 1.5) == [(0, 2), (2, 3), (4, 6), (7, 9)]
    assert conflict_episodes(np.full(4, np.nan), np.zeros(4), 1.5) == []


def test_leaders_by_lane_and_position_at_each_time():
    time = np.array([0.0, 0.0, 0.0, 0.0, 0.1, 0.1])
    lane = np.array([0, 0, 1, 0, 0, 0])
    s = np.array([10.0, 30.0, 20.0, 20.0, 5.0, 50.0])
    assert leaders(time, lane, s).tolist() == [3, -1, -1, 1, 5, -1]


def test_vehicles_off_the_routes_lanes_have_no_leader_and_lead_no_one():
    # lane -1 holds every road off the route (an on-ramp, an exit, the other carriageway): two
    # vehicles there are not in one lane, and a route vehicle never follows one
    time = np.zeros(4)
    lane = np.array([-1, -1, 0, 0])
    s = np.array([100.0, 106.0, 90.0, 130.0])
    assert leaders(time, lane, s).tolist() == [-1, -1, 3, -1]


def test_streaming_in_small_pieces_gives_the_same_table(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    tracks = {}
    for k in range(25):  # vehicles entering and leaving at random times, changing lanes
        start = int(rng.integers(0, 200))
        n = int(rng.integers(5, 300))
        t = _times(start + n)[start:]
        v = np.clip(20 + np.cumsum(rng.normal(0, 0.3, n)), 0, None)
        lane = np.repeat(rng.integers(0, 3, 3), int(np.ceil(n / 3)))[:n]
        tracks[f"v{k}"] = (t, lane, rng.uniform(0, 500) + np.cumsum(v) * DT, v)
    cfg = MetricsConfig(ttc_threshold_s=3.0)
    whole = _metrics(tracks, cfg)
    path = tmp_path / "trajectories.parquet"
    pq.write_table(_trajectories(tracks), path, row_group_size=37)
    monkeypatch.setattr(traffic, "BATCH_ROWS", 13)  # time slices cut across many record batches
    pieces = compute_run_metrics(cfg, DT, DT, path, _vehicles(tracks), None, None, None)
    pd.testing.assert_frame_equal(whole.vehicles.to_pandas(), pieces.vehicles.to_pandas())
    pd.testing.assert_frame_equal(whole.conflicts.to_pandas(), pieces.conflicts.to_pandas())
    pd.testing.assert_frame_equal(whole.histograms.to_pandas(), pieces.histograms.to_pandas())
    assert whole.vehicles.to_pandas()["ttc_samples"].sum() > 100 and len(whole.conflicts) > 0


def test_distance_is_the_path_driven_also_off_the_scenarios_route():
    # a vehicle that takes an exit: past the split its s is its position projected back onto the
    # main route, which falls behind the path it drives (the distance came out 26-30 m short on a
    # 1.4 km trip, and every per-km figure with it); one that brakes then speeds up again
    t = _times(101)
    on_route = t <= 6.0
    s_exit = np.where(on_route, 25.0 * t, 150.0 + 0.8 * 25.0 * (t - 6.0))  # the projection lags
    speed = np.where(t < 4.0, 20.0 - 2.0 * t, 12.0 + 3.0 * (t - 4.0)).clip(max=30.0)
    tracks = {"X": (t, np.where(on_route, 0, -1), s_exit, np.full(101, 25.0)),
              "B": (t, np.ones(101), np.cumsum(np.r_[0.0, 0.5 * (speed[1:] + speed[:-1]) * DT]), speed)}
    m = _metrics(tracks).vehicles.to_pandas().set_index("vehicle_id")
    assert m.loc["X", "distance_m"] == pytest.approx(25.0 * 10.0)
    assert m.loc["B", "distance_m"] == pytest.approx(tracks["B"][2][-1])


@pytest.mark.parametrize("batch_rows", [65_536, 50, 1])
def test_a_vehicle_that_comes_back_after_a_long_absence_keeps_one_row(monkeypatch, batch_rows):
    # a SUMO teleport: gone for 100 s, then on the road again (in one record batch or across many)
    monkeypatch.setattr(traffic, "BATCH_ROWS", batch_rows)
    t1, t2 = _times(100), np.round(_times(100) + 110.0, 6)
    tracks = {"V": (np.r_[t1, t2], np.zeros(200), np.r_[15 * t1, 2000 + 15 * (t2 - 110)], np.full(200, 15.0)),
              "W": (np.round(np.arange(1200) * DT, 6), np.ones(1200), np.arange(1200) * 1.0, np.full(1200, 10.0))}
    m = _metrics(tracks).vehicles.to_pandas().set_index("vehicle_id")
    assert m.loc["V", "samples"] == 200
    assert m.loc["V", "travel_time_s"] == pytest.approx(20.0)
    assert m.loc["V", "distance_m"] == pytest.approx(2 * 15 * 9.9)
    assert m.loc["V", "movestar_seconds"] == 20  # ten whole seconds in each stretch


def test_no_acceleration_or_jerk_spans_a_short_absence():
    # a short teleport: 20 m/s for 5 s, gone for 5 s, back at 10 m/s; each stretch is at constant
    # speed (read as one period apart, the two samples around the absence made -100 m/s^2)
    t1, t2 = _times(50), np.round(_times(50) + 10.0, 6)
    tracks = {"A": (np.r_[t1, t2], np.zeros(100), np.r_[20 * t1, 200 + 10 * (t2 - 10)],
                    np.r_[np.full(50, 20.0), np.full(50, 10.0)])}
    a = _metrics(tracks).vehicles.to_pandas().iloc[0]
    assert a["samples"] == 100 and a["travel_time_s"] == pytest.approx(10.0)
    assert a["mean_abs_accel_mps2"] == 0 and a["max_abs_jerk_mps3"] == 0 and abs(a["max_decel_mps2"]) == 0


def test_movestar_and_sumo_model_by_type_and_class():
    t = _times(40)
    tracks = {vid: (t, np.full(40, lane), 100.0 * lane + 20 * t, np.full(40, 20.0))
              for lane, vid in enumerate(["car", "van", "truck"])}
    vehicles = pd.DataFrame({"vehicle_id": ["car", "van", "truck"], "vtype": ["car", "van@van", "truck"],
                             "vclass": ["passenger", "delivery", "truck"], "length": 5.0, "group": "g"})
    cfg = MetricsConfig(movestar={"passenger": 1, "van": 2})  # by vClass, and by vType id (copies 'TYPE@ID' too)
    sumo = pd.DataFrame({"vehicle_id": ["car", "truck"], "emission_class": ["HBEFA4/PC", "HBEFA4/HGV"],
                         "co_g": 1.0, "co2_g": 200.0, "hc_g": 0.1, "nox_g": 0.5, "pmx_g": 0.01, "fuel_g": 60.0,
                         "electricity_wh": 0.0})
    m = compute_run_metrics(cfg, DT, DT, _trajectories(tracks), vehicles, None, None, sumo).vehicles.to_pandas().set_index("vehicle_id")
    assert m["movestar_type"].to_dict() == {"car": 1, "truck": 0, "van": 2}
    assert m.loc["car", "movestar_seconds"] == 4 and np.isnan(m.loc["truck", "movestar_fuel_g"])
    assert m.loc["car", "movestar_fuel_g"] != m.loc["van", "movestar_fuel_g"]
    assert m.loc["truck", "sumo_co2_g_per_km"] == pytest.approx(200.0 / 0.078)  # 78 m travelled
    assert m.loc["truck", "sumo_emission_class"] == "HBEFA4/HGV"
    assert np.isnan(m.loc["van", "sumo_co2_g"]) and m.loc["van", "sumo_emission_class"] == ""


def test_histogram_percentiles_and_a_json_safe_summary():
    edges, counts = np.array([0.0, 1.0, 2.0]), np.array([10, 30, 60])  # the last bin: >= 2
    assert histogram_percentile(edges, counts, 5) == pytest.approx(0.5)
    assert histogram_percentile(edges, counts, 25) == pytest.approx(1.5)
    assert histogram_percentile(edges, counts, 50) is None  # in the open last bin
    assert histogram_percentile(edges, np.zeros(3), 5) is None
    t = _times(30)
    tracks = {"ego": (t, np.zeros(30), 20 * t, np.full(30, 20.0)),
              "accident0": (t, np.zeros(30), np.full(30, 40.0), np.zeros(30)),
              "brief": (t[-5:], np.ones(5), 20 * t[-5:], np.full(5, 20.0))}  # half a second: no MOVESTAR rating
    vehicles = pd.concat([_vehicles(["ego", "brief"], group="ego"),
                          _vehicles(["accident0"], vclass="truck", group="accident")])
    cfg = MetricsConfig()
    result = _metrics(tracks, cfg, vehicles)
    collisions = pd.DataFrame({"collider": ["ego", "ego"], "victim": ["accident0", "accident0"]})
    block = summary_block(cfg, result, collisions, sumo_available=False)
    json.dumps(block, allow_nan=False)
    assert block["traffic"]["vehicles"] == 2  # the accident group is left out of the traffic figures
    ego_row = result.vehicles.to_pandas().set_index("vehicle_id").loc["ego"]
    assert block["traffic"]["fuel_g_per_km"] == pytest.approx(ego_row["movestar_fuel_g_per_km"])
    assert block["traffic"]["collisions"] == 1 and block["ego"]["collisions"] == 1
    assert block["ego"]["conflicts"] == 1 and block["traffic"]["sumo_co2_g_per_km"] is None
    assert block["settings"]["sumo_emissions"].startswith("missing")


def test_movestar_of_many_trips_at_once_is_movestar_of_each():
    from vcfusion.metrics.movestar import OUTPUT_KEYS, movestar, movestar_trips

    rng = np.random.default_rng(5)
    trips = [np.clip(np.cumsum(rng.normal(0, 1.5, n)) + rng.uniform(0, 30), 0, None) for n in (1, 2, 3, 40, 200)]
    types = np.array([1, 2, 1, 2, 1])
    totals, distance = movestar_trips(np.concatenate(trips), np.cumsum([0] + [len(x) for x in trips[:-1]]), types)
    for i, (v, vt) in enumerate(zip(trips, types)):
        one = movestar(v, int(vt))
        assert totals[i].tolist() == [one["totals"][k] for k in OUTPUT_KEYS]  # bitwise: one implementation
        assert distance[i] == one["TD_m"]


def test_a_bad_metrics_block_is_refused_naming_each_field(tmp_path):
    from scenario_files import write_scenario
    from vcfusion.scenario import ScenarioError, load_scenario

    path = write_scenario(tmp_path, """
name: bad
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
vehicles: [{name: a, count: 1, lanes: [0], pos_m: [10, 20]}]
metrics: {ttc_threshold_s: -1, movestar: {passenger: 3}, sumo_emissions: some, colour: red}
""")
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    text = str(err.value)
    for expected in ("metrics.ttc_threshold_s: Input should be greater than 0", "metrics.movestar.passenger: Input "
                     "should be 1 or 2", "metrics.sumo_emissions: Input should be 'others', 'all' or 'none'",
                     "metrics.colour: unknown key"):
        assert expected in text


def test_a_short_stretch_without_a_movestar_rating_adds_nothing_to_its_vehicle():
    # A drives 10 s, is gone 70 s (a new stretch), then is back for 0.5 s: under a whole second,
    # that stretch has no MOVESTAR rating; A keeps the first stretch's totals, and so does the run
    t1 = _times(100)
    t2 = np.round(80 + np.arange(5) * DT, 6)
    t = np.concatenate((t1, t2))
    both = _metrics({"A": (t, np.zeros(len(t)), 20.0 * t, np.full(len(t), 20.0))})
    first = _metrics({"A": (t1, np.zeros(100), 20.0 * t1, np.full(100, 20.0))})
    a, a1 = (r.vehicles.to_pandas().set_index("vehicle_id").loc["A"] for r in (both, first))
    assert a["samples"] == 105 and a["movestar_seconds"] == a1["movestar_seconds"] == 10
    for k in ("movestar_fuel_g", "movestar_co2_g", "movestar_distance_m"):
        assert np.isfinite(a[k]) and a[k] == pytest.approx(a1[k])
    fuel = summary_block(MetricsConfig(), both, None, sumo_available=False)["traffic"]["movestar_fuel_g_per_km"]
    assert fuel == pytest.approx(a1["movestar_fuel_g"] / a1["movestar_distance_m"] * 1000.0)


@pytest.mark.parametrize("dt", [0.15, 0.6])
def test_movestar_rates_every_second_at_a_period_that_does_not_divide_one_second(dt):
    # 60 s at 20 m/s sampled every 0.15 s (6 or 7 samples a second) or 0.6 s (1 or 2): every
    # second is whole (rounding 1 / dt to 7 or 2 dropped the seconds holding one sample fewer)
    n = int(round(60 / dt))
    t = np.round(np.arange(n) * dt, 6)
    table = _trajectories({"A": (t, np.zeros(n), 20.0 * t, np.full(n, 20.0))})
    a = compute_run_metrics(MetricsConfig(), dt, dt, table, _vehicles(["A"]), None, None, None).vehicles
    a = a.to_pandas().iloc[0]
    reference = movestar(np.full(int(a["movestar_seconds"]), 20.0), 1)["totals"]["Fuel"]
    assert a["movestar_seconds"] >= 59
    assert a["movestar_fuel_g"] == pytest.approx(reference)
    assert np.allclose(resample_to_1hz(t, np.full(n, 20.0), dt), 20.0)
    assert len(resample_to_1hz(t, np.full(n, 20.0), dt)) >= 59
