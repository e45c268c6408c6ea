"""Scenarios on routes through real networks (issue 19): the on-ramp merge and the curved highway,
from the scenario file through placements, SUMO, twins, lane changes, datasets and the predictor."""

import numpy as np
import pandas as pd
import pytest

from scenario_files import REFUSED_DEPARTURE, REPO, SCENARIOS, write_scenario
from vcfusion.prediction.dataset import build_samples
from vcfusion.prediction.features import features_from_twins_table, lane_end_ahead_m
from vcfusion.prediction.model import load_model
from vcfusion.run import build_cosimulation
from vcfusion.scenario import load_scenario
from vcfusion.traffic.network import Road, read_road, read_vehicle_types
from vcfusion.traffic.session import RunError, plan_placements

ONRAMP = SCENARIOS / "onramp.yaml"
CURVED = SCENARIOS / "curved.yaml"
RAMP_ROUTE = ("ramp", "accel", "main_out")


def test_shipped_route_scenarios_load():
    onramp, curved = load_scenario(ONRAMP), load_scenario(CURVED)
    main = read_road(onramp.network, onramp.route)
    assert main.route == ("main_in", "accel", "main_out") and main.num_tracks == 4
    # the acceleration lane is track 0 of the main route, present only along `accel`
    np.testing.assert_allclose(main.lane_spans(0), [[main.edge_start_s[":merge_0"], main.edge_start_s["main_out"] - 8.0]],
                               atol=1e-9)
    assert [tuple(f.route) for f in onramp.flows if f.route] == [RAMP_ROUTE]
    frame = read_road(curved.network, curved.route)
    assert len(frame.route) == 5 and not frame.is_straight and curved.accident.edge == "c34"


def test_placements_follow_each_route():
    """Placements in tracks of their own route, converted to SUMO's edge, lane index and position;
    a track absent at the drawn position is drawn again; on the straight road nothing changes."""
    scenario = load_scenario(ONRAMP)
    road = read_road(scenario.network, scenario.route)
    vtypes = read_vehicle_types(scenario.vehicle_types)
    placements = plan_placements(scenario, road, vtypes, np.random.default_rng(3))
    ramp = read_road(scenario.network, RAMP_ROUTE)
    for p in placements:
        frame = ramp if p.group in ("ramp_cars", "flow2") else road
        lane_id = f"{p.edges[0]}_{p.sumo_lane}"
        assert frame.track_of[lane_id] == p.lane, p
        assert frame.route_position(lane_id, p.sumo_pos_m) == pytest.approx(p.pos_m, abs=1e-9)
        assert frame.route[frame.route.index(p.edges[0]):] == p.edges
    assert {p.edges[0] for p in placements if p.group == "ramp_cars"} == {"ramp"}
    assert {p.edges[0] for p in placements if p.group == "main"} >= {"main_in", "accel", "main_out"}
    # spacing holds along each lane of the route across its edges (fronts 45 m + a length apart)
    at_start = [p for p in placements if p.depart_s == 0.0 and p.group == "main"]
    for lane in (1, 2, 3):
        fronts = np.sort([p.pos_m for p in at_start if p.lane == lane])
        assert (np.diff(fronts) >= 45.0 + 4.6 - 1e-9).all()

    # a group in the acceleration lane (track 0) drawn over a range mostly without it
    group = scenario.vehicles[0].model_copy(update={"lanes": [0], "count": 3, "pos_m": (100.0, 1500.0)})
    only = scenario.model_copy(update={"vehicles": [group], "flows": []})
    placed = plan_placements(only, road, vtypes, np.random.default_rng(0))
    assert len(placed) == 3 and all(p.edges[0] == "accel" and p.sumo_lane == 0 for p in placed)
    assert all(road.lane_exists(0, p.pos_m) for p in placed)

    straight = load_scenario(SCENARIOS / "accident.yaml")
    for p in plan_placements(straight, read_road(straight.network), read_vehicle_types(straight.vehicle_types),
                             np.random.default_rng(0)):
        assert (p.edges, p.sumo_lane, p.sumo_pos_m) == (("hw",), p.lane, p.pos_m)


def test_no_vehicle_departs_where_its_lane_ends_before_it_can_stop(tmp_path):
    """SUMO refuses a departure on a lane that ends closer than the vehicle can stop ("will not be
    able to depart ... junction too close"): such draws are drawn again, and the run goes."""
    scenario = load_scenario(ONRAMP)
    road = read_road(scenario.network, scenario.route)
    vtypes = read_vehicle_types(scenario.vehicle_types)
    lane_end = float(road.lane_spans(0)[0, 1])
    group = scenario.vehicles[0].model_copy(update={"lanes": [0], "count": 1, "speed_mps": 18.0,
                                                    "pos_m": (lane_end - 60.0, lane_end - 1.0), "min_spacing_m": 5.0})
    only = scenario.model_copy(update={"vehicles": [group], "flows": [], "ego": None})
    stopping = 18.0 ** 2 / (2 * float(vtypes[group.vtype].get("decel", 4.5)))
    for seed in range(10):
        placed = plan_placements(only, road, vtypes, np.random.default_rng(seed))
        assert all(lane_end - p.pos_m >= stopping for p in placed)
    short = only.model_copy(update={"simulation": only.simulation.model_copy(update={"max_time_s": 1.0}),
                                    "metrics": only.metrics.model_copy(update={"enabled": False})})
    for seed in range(4):  # before, some of these seeds ended with "SUMO could not insert"
        result = build_cosimulation(short, seed).run()
        assert set(result.tables["vehicles"]["vehicle_id"]) == {"main0"}


def test_a_refused_departure_names_the_vehicle_its_neighbour_and_the_group_to_change(tmp_path):
    scenario = write_scenario(tmp_path, REFUSED_DEPARTURE)
    with pytest.raises(RunError) as err:
        build_cosimulation(load_scenario(scenario), 0).run()
    msg = str(err.value)
    assert msg.startswith("SUMO could not insert 'b0' (vehicles.b, lane 0 at 115.0 m, 10 m/s): ")
    assert "10.4 m ahead of 'a0' (vehicles.a, 30 m/s)." in msg
    assert "raise vehicles.b.min_spacing_m" in msg and "Also not inserted: ['c0']" in msg
    assert "line above" not in msg


def test_lane_end_ahead_feature():
    """Distance to the end of the own lane: the acceleration lane ends at `accel`'s end; the main
    line's lanes do not end (the cap); off the road 0."""
    road = read_road(REPO / "sumo_net" / "onramp.net.xml", ["main_in", "accel", "main_out"])
    end = road.edge_start_s["main_out"] - 8.0  # the acceleration lane ends where the junction lane does
    s = np.array([800.0, 800.0, 900.0, 800.0])
    got = lane_end_ahead_m(road, s, np.array([0, 1, 0, -1]))
    np.testing.assert_allclose(got, [end - 800.0, 400.0, end - 900.0, 0.0])
    straight = Road("hw", (0.0, 0.0), (2000.0, 0.0), 3, 3.5, 25.0)
    assert lane_end_ahead_m(straight, np.array([100.0]), np.array([2])).tolist() == [400.0]


@pytest.fixture(scope="module")
def onramp_run():
    scenario = load_scenario(ONRAMP)
    scenario = scenario.model_copy(update={
        "simulation": scenario.simulation.model_copy(update={"max_time_s": 60.0}),
        "prediction": scenario.prediction.model_copy(update={"enabled": True})})
    return scenario, build_cosimulation(scenario, 0).run(progress=False)


@pytest.mark.slow
def test_onramp_merges_detected_labelled_and_predicted(onramp_run):
    scenario, result = onramp_run
    tables = result.tables
    road = read_road(scenario.network, scenario.route)
    vehicles = tables["vehicles"]
    ramp_ids = set(vehicles.loc[vehicles["group"].isin(["ramp_cars", "flow2"]), "vehicle_id"])
    changes = tables["lane_changes"]
    merges = changes[changes["vehicle_id"].isin(ramp_ids) & (changes["from_lane"] == 0)]
    # every ramp vehicle leaves the acceleration lane (track 0) for the main line's right lane
    # (track 1), with SUMO's reason: it must (strategic)
    assert len(merges) >= 10
    assert (merges["to_lane"] == 1).all() and merges["reason"].str.contains("strategic").all()
    assert merges["vehicle_id"].is_unique
    # independently of SUMO's lanechange-output: the trajectory's lane (the track of SUMO's lane
    # id) is 0 before the change's midpoint and 1 after it, and its d (the frame of the twins)
    # finds the manoeuvre's start and end
    traj = tables["trajectories"][["time", "vehicle_id", "lane", "s", "d"]]
    for ev in merges.itertuples():
        own = traj[traj["vehicle_id"] == ev.vehicle_id]
        before = own[own["time"] < ev.mid_time - 0.15]["lane"].to_numpy()
        after = own[own["time"] > ev.mid_time + 0.15]["lane"].to_numpy()
        assert before[-1] == 0 and after[0] == 1, ev
        assert ev.start_time < ev.mid_time < ev.end_time, ev
    # on the acceleration lane (pos_m along the route), before it ends
    assert merges["pos_m"].between(road.edge_start_s["accel"], road.edge_start_s["main_out"]).all()

    # the dataset labels them
    samples = build_samples(tables, road, scenario.v2c.period_s, 0, 4.0, 2.0,
                            scenario.simulation.lanechange_duration_s / 2)
    for ev in merges.itertuples():
        own = samples[samples["event_id"] == ev.event_id]
        assert (own["window_label"] == 1).sum() > 0 and (own["lc_reason"] == ev.reason).all()
    in_accel = samples[samples["vehicle_id"].isin(ramp_ids) & (samples["lane"] == 0)]
    assert len(in_accel) and (in_accel["right_lane_exists"] == 0).all() and (in_accel["left_lane_exists"] == 1).all()
    twin_s = road.to_frame(*(tables["twins"].set_index(["time", "vehicle_id"]).loc[
        list(zip(in_accel["time"], in_accel["vehicle_id"])), ["x", "y"]].to_numpy().T))[0]
    assert (lane_end_ahead_m(road, twin_s, in_accel["lane"].to_numpy()) < 260.0).all()

    # the predictor ran on them at run time (lc_prob in the twins table) and gives what the
    # model gives on the features rebuilt from that table
    twins = tables["twins"]
    theirs = twins[twins["vehicle_id"].isin(ramp_ids) & (twins["lane"] == 0)]
    assert len(theirs) and theirs["lc_prob"].between(0.0, 1.0).all()
    feats = features_from_twins_table(twins, vehicles, road, scenario.v2c.period_s)
    model = load_model()  # the shipped default, MLP or GRU: run offline along each twin's whole track
    stream = twins[["time", "vehicle_id", "lc_prob"]].merge(feats, on=["time", "vehicle_id"], validate="one_to_one")
    stream = stream.assign(seed=0).sort_values(["vehicle_id", "time"], kind="stable").reset_index(drop=True)
    stream["offline"] = model.stream_proba(stream, list(model.feature_names))
    merged = theirs[["time", "vehicle_id"]].merge(stream, on=["time", "vehicle_id"], validate="one_to_one")
    np.testing.assert_allclose(merged["offline"].to_numpy(), merged["lc_prob"].to_numpy(), atol=1e-5)


@pytest.mark.slow
def test_curved_run_end_to_end():
    """The curved five-edge highway with an accident on its right curve, the ego and the driver
    model: the trip completes; trajectories' (s, d) agree with SUMO's own lane and lateral
    position; the twins map-match the lanes SUMO reports."""
    scenario = load_scenario(CURVED)
    result = build_cosimulation(scenario, 0).run(progress=False)
    assert result.summary["end_reason"] == "trip_complete"
    road = read_road(scenario.network, scenario.route)
    tables = result.tables
    traj = tables["trajectories"]
    lengths = dict(zip(tables["vehicles"]["vehicle_id"], tables["vehicles"]["length"]))
    on = traj[traj["lane"] >= 0]
    assert len(on) > 0.95 * len(traj)  # vehicles are on the route's lanes (junctions included)
    # SUMO's lateral lane position is that of the front bumper: d of the front bumper minus the
    # centre of SUMO's lane there, at every sample of every vehicle (lane changes included)
    half = on["vehicle_id"].map(lengths).to_numpy() / 2
    heading = on["heading"].to_numpy()
    s_front, d_front = road.to_frame(on["x"].to_numpy() + half * np.cos(heading),
                                     on["y"].to_numpy() + half * np.sin(heading))
    lateral = d_front - road.lane_centre_d(on["lane"].to_numpy(), s_front)
    np.testing.assert_allclose(lateral, on["lateral_offset"].to_numpy(), atol=0.05)
    # the centre's lane from (s, d) is SUMO's lane wherever the vehicle is not straddling two
    # (slow lane changers turn so far that their centre is still in the old lane: not those)
    along = np.angle(np.exp(1j * (heading - road.heading(on["s"].to_numpy(), on["d"].to_numpy()))))
    centred = (np.abs(on["lateral_offset"].to_numpy()) < 1.0) & (np.abs(along) < 0.03)
    assert centred.mean() > 0.9
    assert (road.lane_of(on["s"].to_numpy(), on["d"].to_numpy())[centred] == on["lane"].to_numpy()[centred]).all()
    # lane changes were found on the curves, with their manoeuvre from the lateral trajectory
    changes = tables["lane_changes"]
    assert len(changes) > 10 and changes["start_time"].notna().mean() > 0.9
    assert (changes["from_lane"] >= 0).all() and (changes["to_lane"] >= 0).all()
    # the ego's s (SUMO's route position of its front) and its trajectory's frame s agree
    ego = pd.merge_asof(traj[traj["vehicle_id"] == "ego"][["time", "s"]].sort_values("time"),
                        tables["ego"][["time", "s"]].rename(columns={"s": "front"}).sort_values("time"), on="time")
    np.testing.assert_allclose(ego["front"] - ego["s"], lengths["ego"] / 2, atol=0.3)
    # the twins (GNSS noise 0.3 m) map-match SUMO's lanes almost always
    twins = tables["twins"][["time", "vehicle_id", "lane"]].merge(
        traj[["time", "vehicle_id", "lane"]], on=["time", "vehicle_id"], suffixes=("_twin", "_sumo"))
    assert (twins["lane_twin"] == twins["lane_sumo"]).mean() > 0.93


def test_lane_features_count_the_lanes_present():
    """On the on-ramp's main route: before the merge the main line's right lane (track 1) is lane 0
    with no lane to its right; beside the acceleration lane it is lane 1, whose right neighbour
    (track 0) is seen; on the straight road the same numbers as the lane count gives."""
    from vcfusion.prediction.features import tick_features

    road = read_road(REPO / "sumo_net" / "onramp.net.xml", ["main_in", "accel", "main_out"])
    s = np.array([300.0, 800.0, 850.0])
    f = tick_features(s, np.array([1, 1, 0]), np.full(3, 20.0), np.zeros(3), np.full(3, 4.6), road)
    assert f["lane"].tolist() == [0, 1, 0] and f["lanes_to_left"].tolist() == [2, 2, 3]
    assert f["right_lane_exists"].tolist() == [0, 1, 0] and f["left_lane_exists"].tolist() == [1, 1, 1]
    assert f["gap_lead_right"][0] == 0.0  # no right lane: the sentinel
    assert f["gap_lead_right"][1] == pytest.approx(850.0 - 2.3 - (800.0 + 2.3))
    straight = Road("hw", (0.0, 0.0), (2000.0, 0.0), 3, 3.5, 25.0)
    a = tick_features(s, np.array([0, 1, 2]), np.full(3, 20.0), np.zeros(3), np.full(3, 4.6), straight)
    b = tick_features(s, np.array([0, 1, 2]), np.full(3, 20.0), np.zeros(3), np.full(3, 4.6), 3)
    assert all(np.array_equal(a[k], b[k]) for k in b)


def test_an_ego_on_its_own_route_is_placed_along_that_route(tmp_path):
    # the ego's route is the scenario's from `accel` on: a position along it is not one along the
    # scenario's route (placed with the scenario's frame, it jumped 700 m back onto main_in)
    import libsumo

    from vcfusion.traffic.session import SumoSession

    path = write_scenario(tmp_path, f"""
extends: {ONRAMP.as_posix()}
ego: {{vtype: ego, route: [accel, main_out], lane: 2, depart_pos_m: 50.0, speed_mps: 20.0, trip_distance_m: 300.0}}
vehicles: []
flows: []
""")
    session = SumoSession(load_scenario(path), 0, tmp_path / "lc.xml", np.random.default_rng(0))
    try:
        s_front, *_ = session.ego_state()
        session.place_ego(s_front + 2.0, float(session.ego_frame.lane_centre_d(2, s_front + 2.0)), 0.0)
        session.step()
        assert libsumo.vehicle.getRoadID("ego") == "accel"
        assert session.ego_state()[0] == pytest.approx(s_front + 2.0, abs=0.5)
    finally:
        session.close()


def test_vehicles_off_a_one_edge_route_of_a_larger_network_are_off_the_route(tmp_path):
    # the route is `accel` alone: vehicles on main_in and on the ramp are on no lane of it (SUMO's
    # lane index made them lanes 2 and 0 of `accel`)
    from vcfusion.traffic.session import SumoSession

    path = write_scenario(tmp_path, f"""
name: one_edge
network: {(REPO / "sumo_net" / "onramp.net.xml").as_posix()}
vehicle_types: NET_DIR/vtypes.add.xml
route: [accel]
simulation: {{step_s: 0.1, max_time_s: 5.0}}
prediction: {{enabled: false}}
vehicles:
  - {{name: on, count: 1, lanes: [1], pos_m: [100, 100], speed_mps: 20.0}}
  - {{name: main, count: 1, route: [main_in, accel], lanes: [2], pos_m: [300, 300], speed_mps: 20.0}}
  - {{name: ramp, count: 1, route: [ramp, accel], lanes: [0], pos_m: [100, 100], speed_mps: 20.0}}
""")
    session = SumoSession(load_scenario(path), 0, tmp_path / "lc.xml", np.random.default_rng(0))
    try:
        lanes = dict(zip(*(lambda st: (st.ids, st.lane.tolist()))(session.states())))
    finally:
        session.close()
    assert lanes == {"on0": 1, "main0": -1, "ramp0": -1}


def test_a_lane_closed_to_the_vehicles_class_is_refused_or_drawn_around(tmp_path):
    # lane 0 of e1 is a bus lane, open to all on e2: SUMO refuses a car's departure on the bus lane
    # ("Invalid departLane"), which a scenario that loads must never meet
    from vcfusion.scenario import ScenarioError
    from vcfusion.traffic.network import build_network

    (tmp_path / "n.nod.xml").write_text('<nodes><node id="a" x="0" y="0"/><node id="b" x="500" y="0"/>'
                                        '<node id="c" x="1000" y="0"/></nodes>')
    (tmp_path / "n.edg.xml").write_text('<edges><edge id="e1" from="a" to="b" numLanes="3" speed="25" width="3.5">'
                                        '<lane index="0" allow="bus"/></edge>'
                                        '<edge id="e2" from="b" to="c" numLanes="3" speed="25" width="3.5"/></edges>')
    net = build_network(tmp_path, "n")

    def scenario(block):
        return write_scenario(tmp_path, f"""
name: shoulder
network: {net.as_posix()}
vehicle_types: NET_DIR/vtypes.add.xml
route: [e1, e2]
simulation: {{step_s: 0.1, max_time_s: 1.0}}
prediction: {{enabled: false}}
{block}
""")
    with pytest.raises(ScenarioError, match=r"vehicles\[0\]\.lanes: lane 0 is closed to passenger vehicles"):
        load_scenario(scenario("vehicles: [{name: a, count: 1, lanes: [0], pos_m: [50, 400]}]"))
    with pytest.raises(ScenarioError, match=r"flows\[0\]\.lanes: lane 0 is closed to passenger vehicles"):
        load_scenario(scenario("flows: [{vehs_per_hour: 600, lanes: [0]}]"))
    # a range reaching the open part: the vehicles are drawn there, and the run goes
    sc = load_scenario(scenario("vehicles: [{name: a, count: 3, lanes: [0], pos_m: [50, 900], min_spacing_m: 5}]"))
    road = read_road(sc.network, sc.route)
    for seed in range(5):
        placed = plan_placements(sc, road, read_vehicle_types(sc.vehicle_types), np.random.default_rng(seed))
        assert all(p.edges[0] == "e2" for p in placed)
    result = build_cosimulation(sc.model_copy(update={"metrics": sc.metrics.model_copy(update={"enabled": False})}),
                                0).run()
    assert set(result.tables["vehicles"]["vehicle_id"]) == {"a0", "a1", "a2"}


def test_a_departure_refused_before_a_lane_end_names_the_lane_end(tmp_path):
    # a lane that only the middle edge has (2 -> 3 -> 4 -> 3 -> 2 lanes): SUMO refuses a car 85 m
    # before its end, two lane changes from a lane that goes on ("too many lane changes required");
    # the message blamed the spacing, with no other vehicle on the road
    import subprocess

    from vcfusion.traffic.network import netconvert_binary

    (tmp_path / "n.nod.xml").write_text(
        "<nodes>" + "".join(f'<node id="n{k}" x="{x}" y="0" type="priority"/>'
                            for k, x in enumerate((0, 500, 1000, 1500, 2000, 2600))) + "</nodes>")
    (tmp_path / "n.edg.xml").write_text(
        "<edges>" + "".join(f'<edge id="e{k}" from="n{k}" to="n{k + 1}" numLanes="{lanes}" speed="33" width="3.5"/>'
                            for k, lanes in enumerate((2, 3, 4, 3, 2))) + "</edges>")
    subprocess.run([netconvert_binary(), "-n", "n.nod.xml", "-e", "n.edg.xml", "-o", "n.net.xml"], cwd=tmp_path,
                   check=True, capture_output=True)
    path = write_scenario(tmp_path, """
name: lane_end
network: n.net.xml
vehicle_types: NET_DIR/vtypes.add.xml
route: [e0, e1, e2, e3, e4]
simulation: {step_s: 0.1, max_time_s: 1.0, lanechange_duration_s: 3.0}
metrics: {enabled: false}
prediction: {enabled: false}
vehicles:
  - {name: late, count: 1, lanes: [0], pos_m: [1412, 1412], speed_mps: 20.0}
""")
    with pytest.raises(RunError) as err:
        build_cosimulation(load_scenario(path), 0).run()
    msg = str(err.value)
    assert msg.startswith("SUMO could not insert 'late0' (vehicles.late, lane 0 at 1412.0 m, 20 m/s): no other "
                          "vehicle in its lane; its lane ends 85 m ahead. SUMO refuses a departure that leaves too "
                          "little road for the lane changes it needs before the end of its lane")
