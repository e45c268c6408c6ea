"""The scenario's `lane_change_model:` block reaches SUMO: per-vehicle lane-change durations drawn
from the configured distribution are the durations SUMO drives; the sublane model (SL2015) runs
with --lateral-resolution; bad blocks are refused naming the field."""

import numpy as np
import pytest
from scenario_files import busy_traffic, write_scenario

from vcfusion.scenario import ScenarioError, load_scenario
from vcfusion.traffic.session import SumoSession, lane_change_vtypes

BUSY = busy_traffic()


def _run(path, tmp_path, seconds=90.0):
    """Per lane change: (vehicle, measured duration = time its lateral position moves, s)."""
    scenario = load_scenario(path)
    session = SumoSession(scenario, 1, tmp_path / "lc.xml", np.random.default_rng(1))
    w = session.road.lane_width_m
    d = {}
    try:
        for _ in range(int(seconds / 0.1)):
            session.step()
            st = session.states()
            for vid, lane, lat in zip(st.ids, st.lane, st.lateral_offset):
                d.setdefault(vid, []).append(lane * w + lat)
    finally:
        session.close()
    changes = []
    for vid, track in d.items():
        x = np.array(track)
        moving = np.abs(np.diff(x)) > 1e-6
        k = np.flatnonzero(np.diff(np.r_[0, moving.astype(np.int8), 0]))
        for a, b in zip(k[::2], k[1::2]):
            if 0 < a and b < len(moving) and abs(x[b] - x[a]) > w / 2:  # a whole move, seen from start to end
                changes.append((vid, (b - a) * 0.1))
    return session, changes


def test_duration_distribution_reaches_sumo(tmp_path):
    path = write_scenario(tmp_path, BUSY + """
lane_change_model:
  model: LC2013
  duration: {distribution: lognormal, median_s: 5.0, sigma: 0.4, min_s: 2.0, max_s: 10.0}
""")
    session, changes = _run(path, tmp_path)
    assert len(changes) >= 10
    drawn = session.lane_change_durations
    measured = np.array([m for _, m in changes])
    wanted = np.array([drawn[v] for v, _ in changes])
    assert np.all(np.abs(measured - wanted) <= 0.2 + 1e-9)  # each change lasts its vehicle's draw
    assert np.std(wanted) > 0.5 and 2.0 <= wanted.min() and wanted.max() <= 10.0
    # the draws follow the configured lognormal (median 5 s, log-space std 0.4)
    logs = np.log(np.array(list(drawn.values())))
    assert abs(np.median(logs) - np.log(5.0)) < 0.15 and abs(np.std(logs) - 0.4) < 0.12


def test_without_the_block_the_global_duration_holds(tmp_path):
    _, changes = _run(write_scenario(tmp_path, BUSY), tmp_path, 60.0)
    assert len(changes) >= 5
    assert np.allclose([m for _, m in changes], 3.0, atol=0.2)  # simulation.lanechange_duration_s


def test_sublane_model_and_vtype_attributes(tmp_path):
    path = write_scenario(tmp_path, BUSY + """
lane_change_model:
  model: SL2015
  lateral_resolution_m: 0.8
  lc_sigma: 0.3
  lc_accel_lat_mps2: 0.6
  max_speed_lat_mps: 0.9
  lc_speed_gain: 2.0
""")
    scenario = load_scenario(path)
    text = lane_change_vtypes(scenario, tmp_path / "v.add.xml").read_text()
    car = next(line for line in text.splitlines() if 'id="car_mixed"' in line)
    for attr in ('laneChangeModel="SL2015"', 'lcSigma="0.3"', 'lcAccelLat="0.6"', 'maxSpeedLat="0.9"',
                 'lcSpeedGain="2.0"'):
        assert attr in car
    assert "SL2015" not in next(line for line in text.splitlines() if 'id="ego"' in line)
    session, changes = _run(path, tmp_path, 60.0)
    assert "--lateral-resolution" in session.sumo_args and "--lanechange.duration" not in session.sumo_args
    assert len(changes) >= 3
    # bounded lateral speed and acceleration: a 3.5 m change takes longer than at 0.9 m/s throughout
    assert np.median([m for _, m in changes]) > 3.5 / 0.9


@pytest.mark.parametrize("block, needle", [
    ("{model: SL2015}", "lateral_resolution_m exactly with model SL2015"),
    ("{model: LC2013, lc_sigma: 0.2}", "lane_change_model.lc_sigma"),
    ("{vtypes: [nosuchtype]}", "lane_change_model.vtypes"),
    ("{duration: {median_s: 20.0}}", "min_s <= median_s <= max_s"),
])
def test_bad_blocks_are_refused(tmp_path, block, needle):
    path = write_scenario(tmp_path, BUSY + f"lane_change_model: {block}\n")
    with pytest.raises(ScenarioError, match=needle):
        load_scenario(path)


def test_sublane_changes_start_and_end_when_the_lateral_motion_settles():
    """A sublane-model driver keeps an offset of its own (never centred to 5 cm): the settled rule
    times the change by its lateral motion (3 s cosine move from 20 s), the centred one cannot."""
    from vcfusion.traffic.lanechanges import lane_change_events
    from vcfusion.traffic.network import Road

    road = Road("hw", (0.0, 0.0), (2000.0, 0.0), 3, 3.5, 30.0)
    t = np.round(np.arange(0.0, 40.0, 0.1), 6)
    u = np.clip((t - 20.0) / 3.0, 0.0, 1.0)
    d = 1.75 + 0.3 + 3.5 * (1 - np.cos(np.pi * u)) / 2  # 0.3 m left of the lane centres throughout
    changes = {"vehicle_id": np.array(["v"]), "mid_time": np.array([21.5]), "from_lane": np.array([0]),
               "to_lane": np.array([1]), "direction": np.array([1]), "reason": np.array(["speedGain"]),
               "pos_m": np.array([500.0]), "speed_mps": np.array([20.0]), "leader_gap_m": np.array([np.nan]),
               "follower_gap_m": np.array([np.nan])}
    tracks = {"v": {"time": t, "d": d, "s": 20.0 * t}}
    centred = lane_change_events(changes, tracks, road)
    assert np.isnan(centred["start_time"][0])  # never within 5 cm of the old lane's centre
    assert centred["end_time"][0] < 22.7  # only passing the new one's centre, while still moving
    settled = lane_change_events(changes, tracks, road, "settled")
    assert 19.5 <= settled["start_time"][0] <= 20.3 and 22.7 <= settled["end_time"][0] <= 23.5
