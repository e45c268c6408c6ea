"""End-to-end runs of the tick loop on real SUMO."""

import xml.etree.ElementTree as ET

import numpy as np
import pandas as pd
import pytest

from scenario_files import REPO, write_scenario
from vcfusion.cosim import CoSimulation
from vcfusion.driver.idm import IdmController
from vcfusion.records import gnss_antenna_points
from vcfusion.scenario import load_scenario
from vcfusion.stages import WiringError

ACCIDENT = """
name: t
network: NET_DIR/highway.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
simulation: {step_s: 0.01, max_time_s: 20}
v2c: {latency_s: LAT, loss_probability: LOSS, gnss_noise_std_m: NOISE}
ego: {lane: 2, depart_pos_m: 50, speed_mps: 19, trip_distance_m: 300}
vehicles:
  - {name: changer, count: 3, lanes: [0, 1], pos_m: [70, 160], speed_mps: 17, desired_speed_mps: 17}
accident: {pos_m: 380, lanes: [0, 1]}
"""


def run(tmp_path, lat=0.0, loss=0.0, noise=0.0, seed=1, **kw):
    text = ACCIDENT.replace("LAT", str(lat)).replace("LOSS", str(loss)).replace("NOISE", str(noise))
    sc = load_scenario(write_scenario(tmp_path, text))
    kw.setdefault("controller", IdmController.for_scenario(sc))
    return CoSimulation(sc, seed, **kw).run()


def run_text(tmp_path, text, seed=1):
    sc = load_scenario(write_scenario(tmp_path, text))
    return CoSimulation(sc, seed, controller=IdmController.for_scenario(sc)).run()


def antenna_truth(result) -> pd.DataFrame:
    traj = result.tables["trajectories"].merge(result.tables["vehicles"][["vehicle_id", "height"]], on="vehicle_id")
    pts = gnss_antenna_points(traj.x.to_numpy(), traj.y.to_numpy(), traj.z.to_numpy(), traj.height.to_numpy())
    return pd.DataFrame({"vehicle_id": traj.vehicle_id, "time": traj.time, "gx": pts[:, 0], "gy": pts[:, 1]})


def test_latency_delivers_state_measured_latency_earlier(tmp_path):
    result = run(tmp_path, lat=0.3)
    twins = result.tables["twins"]
    moving = twins[twins.time >= 1.0]
    np.testing.assert_allclose(moving.time - moving.measured_time, 0.3, atol=1e-9)
    # The twin position at t is the SUMO ground truth (GNSS antenna) at t - 0.3 s.
    truth = antenna_truth(result).rename(columns={"time": "measured_time"})
    joined = moving.merge(truth, on=["vehicle_id", "measured_time"], validate="one_to_one")
    assert len(joined) == len(moving) > 500
    np.testing.assert_allclose(joined.x, joined.gx, atol=1e-9)
    np.testing.assert_allclose(joined.y, joined.gy, atol=1e-9)
    # ... and differs from the truth at t for a moving vehicle (over 10 m/s * 0.3 s).
    now = moving.merge(antenna_truth(result), on=["vehicle_id", "time"])
    assert (np.abs(now.x - now.gx)[now.speed > 10] > 2.5).all()


def test_loss_and_gnss_noise(tmp_path):
    lossy = run(tmp_path, loss=0.5)
    sent, lost = lossy.summary["v2c_reports_sent"], lossy.summary["v2c_reports_lost"]
    assert sent > 800 and abs(lost / sent - 0.5) < 0.05
    twins = lossy.tables["twins"]
    # A lost report leaves the twin at an older measurement: the age is then >= one period.
    stale = (twins.time - twins.measured_time > 0.05).mean()
    assert 0.4 < stale < 0.6

    noisy = run(tmp_path, noise=1.0, seed=2)
    joined = noisy.tables["twins"].merge(antenna_truth(noisy), on=["vehicle_id", "time"])
    err = np.concatenate([joined.x - joined.gx, joined.y - joined.gy])
    assert len(err) > 1500
    assert abs(err.std() - 1.0) < 0.05 and abs(err.mean()) < 0.06


def test_positions_agree_with_sumo_fcd_output(tmp_path):
    fcd = tmp_path / "fcd.xml"
    result = run(tmp_path, extra_sumo_args=["--fcd-output", str(fcd), "--device.fcd.period", "0.1"])
    traj = result.tables["trajectories"].merge(result.tables["vehicles"][["vehicle_id", "length"]], on="vehicle_id")
    rows = [
        {"time": round(float(ts.get("time")), 6), "vehicle_id": v.get("id"), "fx": float(v.get("x")),
         "fy": float(v.get("y")), "fangle": float(v.get("angle")), "fspeed": float(v.get("speed"))}
        for ts in ET.parse(fcd).getroot().iter("timestep") for v in ts.iter("vehicle")
    ]
    joined = traj.merge(pd.DataFrame(rows), on=["time", "vehicle_id"])
    assert len(joined) > 0.9 * len(traj)
    # SUMO reports the front bumper and a compass angle; we store the centre and a yaw.
    front_x = joined.x + np.cos(joined.heading) * joined.length / 2
    front_y = joined.y + np.sin(joined.heading) * joined.length / 2
    np.testing.assert_allclose(front_x, joined.fx, atol=0.01)  # fcd prints 2 decimals
    np.testing.assert_allclose(front_y, joined.fy, atol=0.01)
    np.testing.assert_allclose(np.degrees(np.pi / 2 - joined.heading) % 360, joined.fangle % 360, atol=0.01)
    np.testing.assert_allclose(joined.speed, joined.fspeed, atol=0.01)


def test_lane_change_events_and_ego_control(tmp_path):
    result = run(tmp_path)
    lc = result.tables["lane_changes"]
    assert len(lc) >= 3
    assert (abs(lc.to_lane - lc.from_lane) == 1).all()
    assert (lc.start_time < lc.mid_time).all() and (lc.mid_time < lc.end_time).all()
    # Lane changes are visible in time: about the configured 3 s (--lanechange.duration).
    assert ((lc.end_time - lc.start_time).between(2.0, 4.5)).all()
    traj = result.tables["trajectories"]
    for ev in lc.itertuples():
        track = traj[traj.vehicle_id == ev.vehicle_id].set_index("time")
        assert track.lane.asof(ev.start_time) == ev.from_lane
        assert track.lane.asof(ev.end_time) == ev.to_lane
    assert result.summary["cut_ins_ahead_of_ego"] >= 1
    assert lc[lc.into_ego_lane].to_lane.eq(2).all()
    # The ego's speed is what our controller integrated, not SUMO's car following.
    ego = result.tables["ego"]
    dv = np.diff(ego.speed.to_numpy())
    np.testing.assert_allclose(dv[1:], ego.command_accel.to_numpy()[1:-1] * 0.01, atol=1e-9)
    assert result.summary["end_reason"] == "trip_complete"
    assert 299.0 <= result.summary["ego_distance_m"] <= 301.0


class Reckless:
    """Never brakes."""

    def acceleration(self, tick):
        return 0.0


def test_collisions_are_reported(tmp_path):
    text = ACCIDENT.replace("lane: 2, depart_pos_m: 50", "lane: 1, depart_pos_m: 250")
    text = text.replace("LAT", "0").replace("LOSS", "0").replace("NOISE", "0")
    text = text.replace("pos_m: [70, 160]", "pos_m: [30, 120]")
    sc = load_scenario(write_scenario(tmp_path, text))
    result = CoSimulation(sc, 0, controller=Reckless()).run()
    col = result.tables["collisions"]
    assert len(col) >= 1 and result.summary["collisions"] == len(col[["collider", "victim"]].drop_duplicates())
    assert col.iloc[0].collider == "ego" and col.iloc[0].victim.startswith("accident")
    # one row per contact, from its first to its last step in contact (SUMO repeats the contact's
    # first record every step it lasts: it was a row per step, each with the impact's speeds)
    assert (col.end_time >= col.time).all() and (col.end_time - col.time).max() > 0.5  # 87 steps in contact
    for _, pair in col.groupby(["collider", "victim"]):
        assert (pair.time.to_numpy()[1:] > pair.end_time.to_numpy()[:-1] + 1.5 * sc.simulation.step_s).all()


def test_stopping_short_of_a_stopped_vehicle_is_not_a_collision(tmp_path):
    # every lane closed: the ego's IDM (s0 = 2 m) stops in the queue, closer to its leader than the
    # car type's minGap (2.5 m), which SUMO by default reports as a collision every step
    text = ACCIDENT.replace("LAT", "0").replace("LOSS", "0").replace("NOISE", "0").replace("max_time_s: 20", "max_time_s: 40")
    text = text.replace("accident: {pos_m: 380, lanes: [0, 1]}", "accident: {pos_m: 300, lanes: [0, 1, 2]}")
    result = run_text(tmp_path, text)
    ego = result.tables["ego"]
    stopped = ego[ego.speed < 0.01]
    assert len(stopped) > 100
    assert 0.0 < stopped.leader_gap_m.min() < 2.5
    assert len(result.tables["collisions"]) == 0 and result.summary["collisions"] == 0


def test_lane_change_events_from_tracks_and_without_changes():
    """Start/end times from hand-made lateral tracks; no changes give typed empty columns."""
    from vcfusion.traffic.lanechanges import LANE_CHANGE_COLUMNS, SUMO_CHANGE_DTYPES, lane_change_events
    from vcfusion.traffic.network import read_road

    road = read_road(REPO / "sumo_net" / "highway.net.xml")
    t = np.round(np.arange(0.0, 6.0, 0.1), 6)
    d = np.clip(road.lane_centre_d(1) + (t - 2.0) * road.lane_width_m / 3.0, road.lane_centre_d(1),
                road.lane_centre_d(2))  # lane 1 -> 2 from t = 2 s to t = 5 s
    changes = {name: np.array(v, dtype=dtype) for (name, dtype), v in zip(
        SUMO_CHANGE_DTYPES.items(), [["b", "a"], [3.5, 3.5], [1, 1], [2, 2], [1, 1], ["speedGain"] * 2,
                                     [100.0, 90.0], [20.0, 20.0], [np.nan, 5.0], [7.0, np.nan]])}
    ev = lane_change_events(changes, {"a": {"time": t, "d": d}}, road)
    assert list(ev) == LANE_CHANGE_COLUMNS
    assert ev["vehicle_id"].tolist() == ["a", "b"] and ev["event_id"].tolist() == [0, 1]  # sorted: mid, then id
    assert ev["start_time"][0] == pytest.approx(2.0) and ev["end_time"][0] == pytest.approx(5.0)
    assert np.isnan(ev["start_time"][1]) and np.isnan(ev["end_time"][1])  # no track for b
    assert ev["leader_gap_m"][0] == 5.0
    empty = lane_change_events({k: np.array([], dtype=dt) for k, dt in SUMO_CHANGE_DTYPES.items()}, {}, road)
    frame = pd.DataFrame(empty)
    assert len(frame) == 0 and frame["from_lane"].dtype == np.int64 and frame["start_time"].dtype == np.float64


def test_an_error_in_the_loop_is_not_replaced_by_the_parked_vehicles_rating(tmp_path):
    # the accident's parked trucks are rated when the run ends; a run that fails before they have
    # stopped must report its own error, not "left its stop"
    def fails(twins, store):
        raise ValueError("the process model failed")

    sc = _scenario(tmp_path, seconds=5.0)
    assert sc.metrics.enabled and sc.accident is not None
    with pytest.raises(ValueError, match="the process model failed"):
        CoSimulation(sc, 0, controller=IdmController.for_scenario(sc), process_models=[("fails", fails)]).run()


# -- wiring of the stages (vcfusion.stages) ------------------------------------------------------

def _scenario(tmp_path, seconds=1.0, **blocks):
    sc = load_scenario(REPO / "scenarios" / "accident.yaml")
    update = {"simulation": sc.simulation.model_copy(update={"max_time_s": seconds})}
    for name, values in blocks.items():
        update[name] = values if values is None else getattr(sc, name).model_copy(update=values)
    return sc.model_copy(update=update)


@pytest.mark.slow
def test_normal_wirings_build_and_run(tmp_path):
    """Traffic only (no ego), guidance from the cloud, camera, camera + fusion: each builds and runs,
    and the stages see the tick fields they declare."""
    from vcfusion.run import build_cosimulation

    small = {"width_px": 160, "height_px": 120}
    wirings = {
        "traffic": _scenario(tmp_path, ego=None),
        "guidance": _scenario(tmp_path),
        "vision": _scenario(tmp_path, vision={"enabled": True}, camera=small),
        "vision+fusion": _scenario(tmp_path, vision={"enabled": True}, camera=small,
                                   fusion={"enabled": True, "detector": "oracle"}),
    }
    expected_hooks = {"traffic": [], "guidance": ["CloudGuidanceFallback"],
                      "vision": ["CameraHook", "CloudGuidanceFallback"],
                      "vision+fusion": ["CameraHook", "VisionFusionHook", "CloudGuidanceFallback"]}
    for name, sc in wirings.items():
        seen = []

        class Probe:  # last hook: what the tick carries after the stages ran
            table = f"probe_{name.replace('+', '_')}"

            def __call__(self, tick):
                seen.append((tick.frame is not None, tick.detections is not None,
                             tick.guidance.source if tick.guidance is not None else None))

        cosim = build_cosimulation(sc, 0)
        assert [type(h).__name__ for h in cosim.hooks] == expected_hooks[name]
        cosim.hooks.append(Probe())
        result = cosim.run()
        assert len(seen) == 10 and result.summary["simulated_s"] > 0.8, name
        frames, detections, sources = (set(v) for v in zip(*seen))
        assert frames == {name.startswith("vision")} and detections == {name == "vision+fusion"}
        assert sources == {"traffic": {None}, "guidance": {"cloud"}, "vision": {"cloud"},
                           "vision+fusion": {"fusion"}}[name]
        if name != "traffic":
            assert "driver" in result.summary and "driver" in result.tables
        if name == "vision+fusion":
            wrong_orders(sc, cosim)


def wrong_orders(sc, cosim):
    """The stages of a real vision + fusion run, put in orders that cannot work: refused when built."""
    camera, fusion, cloud, probe = cosim.hooks
    with pytest.raises(WiringError, match=r"VisionFusionHook\) needs 'frame', which no earlier stage provides; "
                                          r"tick hook 1 \(CameraHook\) provides it: put it before"):
        CoSimulation(sc, 0, controller=cosim.controller, hooks=[fusion, camera, cloud])
    # with fusion the guidance log reads the overlay's guidance: it must come after it
    with pytest.raises(WiringError, match=r"tick hook 1 \(CloudGuidanceFallback\) needs 'guidance', which no earlier "
                                          r"stage provides; tick hook 2 \(VisionFusionHook\) provides it"):
        CoSimulation(sc, 0, controller=cosim.controller, hooks=[camera, cloud, fusion])
    # the cloud guidance of a run without fusion fills guidance: a provider after it is refused
    from vcfusion.driver.cloud_guidance import CloudGuidanceFallback

    filler = CloudGuidanceFallback(cloud.road, cloud.policy)
    with pytest.raises(WiringError, match=r"VisionFusionHook\) provides 'guidance' after tick hook 1 "
                                          r"\(CloudGuidanceFallback\), which fills it only where no earlier stage did"):
        CoSimulation(sc, 0, controller=cosim.controller, hooks=[camera, filler, fusion])
    with pytest.raises(WiringError, match="controller DriverModel needs 'guidance', which no earlier stage provides"):
        CoSimulation(sc, 0, controller=cosim.controller, hooks=[camera])
    # a hook list changed after building is checked again when the run starts
    cosim.hooks[:] = [fusion, camera, cloud]
    with pytest.raises(WiringError, match="needs 'frame'"):
        cosim.run()


def test_ego_and_controller_go_together(tmp_path):
    sc = _scenario(tmp_path)
    with pytest.raises(WiringError, match="it has an ego, so the run needs the ego's controller"):
        CoSimulation(sc, 0)
    no_ego = sc.model_copy(update={"ego": None})
    with pytest.raises(WiringError, match="controller IdmController given, but the scenario has no ego block"):
        CoSimulation(no_ego, 0, controller=IdmController.for_scenario(sc))

    class NeedsEgo:
        table = "x"
        needs = ("ego",)

        def __call__(self, tick):
            return None

    with pytest.raises(WiringError, match=r"NeedsEgo\) needs 'ego', which no earlier stage provides; the scenario has no ego"):
        CoSimulation(no_ego, 0, hooks=[NeedsEgo()])

    class Typo(NeedsEgo):
        needs = ("frames",)

    with pytest.raises(WiringError, match="needs 'frames': expected a Tick field"):
        CoSimulation(sc, 0, controller=IdmController.for_scenario(sc), hooks=[Typo()])


def test_end_of_run_steps_keep_to_what_they_declare(tmp_path):
    sc = _scenario(tmp_path, seconds=0.5)

    class Summarises:
        table = "summarises"
        finish_summary = ("my_key",)

        def __init__(self, writes: dict):
            self.writes = writes

        def __call__(self, tick):
            return None

        def finish(self, tables, summary):
            summary.update(self.writes)

    ok = Summarises({"my_key": 1})
    result = CoSimulation(sc, 0, controller=IdmController.for_scenario(sc), hooks=[ok]).run()
    assert result.summary["my_key"] == 1 and result.summary["scenario"] == "accident"
    sneaky = Summarises({"my_key": 1, "undeclared": 2})
    with pytest.raises(WiringError, match="Summarises.finish wrote summary key 'undeclared'"):
        CoSimulation(sc, 0, controller=IdmController.for_scenario(sc), hooks=[sneaky]).run()

    class Twice(Summarises):
        table = "twice"

    with pytest.raises(WiringError, match="summary key 'my_key' is already written by tick hook 0"):
        CoSimulation(sc, 0, controller=IdmController.for_scenario(sc), hooks=[ok, Twice({})])

    class WantsTable(Summarises):
        table = "wants"
        finish_needs = ("driver",)

    with pytest.raises(WiringError, match="needs table 'driver' at the end of the run, which no earlier stage writes"):
        CoSimulation(sc, 0, controller=IdmController.for_scenario(sc), hooks=[WantsTable({})])


def test_a_hook_table_without_rows_keeps_its_columns(tmp_path):
    # camera.parquet and fusion.parquet of a run whose camera never fired had no columns at all
    sc = _scenario(tmp_path, seconds=0.5)

    class Quiet:
        table = "quiet"
        columns = ("time", "value")

        def __call__(self, tick):
            return None

    result = CoSimulation(sc, 0, controller=IdmController.for_scenario(sc), hooks=[Quiet()]).run()
    assert list(result.tables["quiet"].columns) == ["time", "value"] and len(result.tables["quiet"]) == 0


def test_process_models_declare_their_end_of_run_step(tmp_path):
    """The cloud predictor's lane_change_flags come from its own finish, declared like a hook's."""
    from vcfusion.run import build_cosimulation

    sc = _scenario(tmp_path)
    cosim = build_cosimulation(sc, 0)
    (name, predictor), = cosim.process_models
    assert predictor.finish_summary == ("lane_change_flags",)

    class AlsoFlags:
        table = "also"
        finish_summary = ("lane_change_flags",)

        def __call__(self, tick):
            return None

        def finish(self, tables, summary):
            pass

    with pytest.raises(WiringError, match=r"summary key 'lane_change_flags' is already written by "
                                          r"process model lane_change \(LaneChangePredictor\)"):
        CoSimulation(sc, 0, controller=cosim.controller, process_models=cosim.process_models,
                     hooks=cosim.hooks + [AlsoFlags()])


def test_the_ego_lane_of_a_lane_change_is_the_one_the_ego_drives_in_at_its_midpoint():
    from vcfusion.cosim import _ego_lane_at
    from vcfusion.traffic.network import read_road

    road = read_road(REPO / "sumo_net" / "highway.net.xml")  # 3 lanes of 3.5 m
    tracks = {"ego": {"time": np.array([0.0, 0.1, 0.2, 0.3]), "d": np.array([8.75, 6.9, 5.3, 5.25]),
                       "s": np.array([100.0, 102.0, 104.0, 106.0])}}
    assert _ego_lane_at(tracks, np.array([0.0, 0.12, 0.3]), road, 2).tolist() == [2, 1, 1]
    assert _ego_lane_at({}, np.array([1.0]), road, 2).tolist() == [2]


def test_a_persons_lane_change_starts_and_ends_where_the_car_is_wholly_in_a_lane():
    # a person holds a car 0.4-0.8 m off a lane's centre (here pinned to its right edge): the
    # 5 cm "centred" rule of SUMO's vehicles left the start and end NaN, and the ego's own change
    # had a gap "to the ego" of minus its length
    from vcfusion.traffic.lanechanges import ego_lane_changes, lane_change_events, relate_to_ego
    from vcfusion.traffic.network import read_road

    road = read_road(REPO / "sumo_net" / "highway.net.xml")  # 3 lanes of 3.5 m: lane 1 centre 5.25 m
    t = np.round(np.arange(0.0, 3.01, 0.1), 6)
    d = np.interp(t, [0.0, 0.5, 2.5, 3.0], [8.75 - 0.4, 8.75 - 0.4, 5.25 - 0.8, 5.25 - 0.8])  # lane 2 -> 1
    tracks = {"ego": {"time": t, "d": d, "s": 100.0 + 20.0 * t}}
    changes = ego_lane_changes(tracks["ego"], road, 4.6)
    events = lane_change_events(changes, tracks, road)
    assert events["from_lane"].tolist() == [2] and events["to_lane"].tolist() == [1]
    start, end = events["start_time"][0], events["end_time"][0]
    # wholly in lane 2 while |d - 8.75| <= 0.85 (until d = 7.9), wholly in lane 1 from |d - 5.25| <= 0.85
    assert start == pytest.approx(t[d >= 7.9][-1] if (d >= 7.9).any() else np.nan)
    assert end == pytest.approx(t[(np.abs(d - 5.25) <= 0.85) & (t >= events["mid_time"][0])][0])
    assert start < events["mid_time"][0] < end
    related = relate_to_ego(events, tracks, {"ego": 4.6}, 2)
    assert np.isnan(related["gap_to_ego_m"][0]) and not related["into_ego_lane"][0]


@pytest.mark.slow
def test_a_vision_run_of_one_seed_writes_the_same_tables_twice(tmp_path):
    # the camera table carried each frame's render time (wall clock): two runs of one seed differed
    from vcfusion.run import execute_run

    sc = load_scenario(REPO / "scenarios" / "accident_ar.yaml")
    sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": 2.0}),
                               "ar": sc.ar.model_copy(update={"video": False})})
    for out in ("a", "b"):
        execute_run(sc, 3, tmp_path / out)
    tables = sorted(p.name for p in (tmp_path / "a").glob("*.parquet"))
    assert {"camera.parquet", "fusion.parquet"} <= set(tables)
    for name in tables:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    # the columns a hook names for its table when it has no rows are those of its rows
    from vcfusion.driver.cloud_guidance import CloudGuidanceFallback
    from vcfusion.fusion.fuse import VisionFusionHook
    from vcfusion.render.hook import CameraHook

    for hook in (CameraHook, VisionFusionHook, CloudGuidanceFallback):
        table = pd.read_parquet(tmp_path / "a" / f"{hook.table}.parquet")
        assert len(table) and tuple(table.columns) == hook.columns, hook.table


def test_the_ego_views_leader_speed_is_sumos_speed_of_the_leader_at_that_step():
    """EgoView.leader_speed is read from the tick's ground truth, not asked of SUMO: it must be
    SUMO's own getSpeed of the leader at the tick's step."""
    import libsumo

    from vcfusion.run import build_cosimulation

    scenario = load_scenario("accident")
    scenario = scenario.model_copy(update={"simulation": scenario.simulation.model_copy(update={"max_time_s": 12.0})})
    run = build_cosimulation(scenario, 0).start()
    compared = 0
    try:
        while run.tick is not None:
            ego = run.tick.ego
            if ego.leader_id is not None:
                assert ego.leader_speed == libsumo.vehicle.getSpeed(ego.leader_id)
                compared += 1
            else:
                assert ego.leader_speed is None
            run.advance(-0.5 if ego.speed > 25.0 else 0.5)
    finally:
        run.close()
    assert compared > 20
