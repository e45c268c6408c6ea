"""The exit scenario (scenarios/exit.yaml, sumo_net/exit): vehicles bound for the exit change
right into the deceleration lane, the main line's vehicles in it leave it; after the gore an
exit vehicle is off the scenario's route (lane -1, d right of the road)."""

import numpy as np
import pytest

from scenario_files import SCENARIOS
from vcfusion.run import build_cosimulation
from vcfusion.scenario import load_scenario
from vcfusion.traffic.network import read_road
from vcfusion.traffic.netgen import failed_properties, frame_properties

EXIT = SCENARIOS / "exit.yaml"
EXIT_ROUTE = ["main_in", "decel", "exit"]


@pytest.fixture(scope="module")
def exit_run():
    scenario = load_scenario(EXIT)
    scenario = scenario.model_copy(update={"simulation": scenario.simulation.model_copy(update={"max_time_s": 60.0})})
    return scenario, build_cosimulation(scenario, 0).run(progress=False)


def test_exit_network_frames():
    scenario = load_scenario(EXIT)
    main, leaving = read_road(scenario.network, scenario.route), read_road(scenario.network, EXIT_ROUTE)
    # the deceleration lane is track 0 along `decel` only, and leaves the main route at the gore
    assert main.track_of["decel_0"] == 0 and [main.track_of[f"main_in_{i}"] for i in range(3)] == [1, 2, 3]
    gore = main.edge_start_s["main_out"]
    assert main.lane_end_ahead(0, main.edge_start_s["decel"] + 10.0) < gore
    assert leaving.track_of["exit_0"] == leaving.track_of["decel_0"] == 0
    for route in (scenario.route, EXIT_ROUTE):
        assert not failed_properties(frame_properties(scenario.network, list(route)))


def test_exit_vehicles_change_right_the_others_leave_the_exit_lane(exit_run):
    scenario, result = exit_run
    tables = result.tables
    road = read_road(scenario.network, scenario.route)
    vehicles, changes, traj = tables["vehicles"], tables["lane_changes"], tables["trajectories"]
    group = dict(zip(vehicles["vehicle_id"], vehicles["group"]))
    leaving = {v for v, g in group.items() if g in ("leaving", "flow2")}
    staying = {v for v, g in group.items() if g == "staying_in_exit_lane"}
    gore = road.edge_start_s["main_out"]
    # every vehicle that took the exit changed right into the deceleration lane (it must: strategic)
    took_exit = set(traj.loc[traj["vehicle_id"].isin(leaving) & (traj["lane"] == -1), "vehicle_id"])
    assert len(took_exit) >= 8
    into = changes[changes["vehicle_id"].isin(took_exit) & (changes["to_lane"] == 0)]
    assert set(into["vehicle_id"]) == took_exit and into["reason"].str.contains("strategic").all()
    assert (into["from_lane"] == 1).all() and into["pos_m"].between(road.edge_start_s["decel"], gore).all()
    # the main line's vehicles placed in the deceleration lane leave it before the gore
    out_of = changes[changes["vehicle_id"].isin(staying) & (changes["from_lane"] == 0)]
    assert set(out_of["vehicle_id"]) == staying and (out_of["to_lane"] == 1).all()
    assert out_of["reason"].str.contains("strategic").all() and (out_of["pos_m"] < gore).all()
    # no main-route vehicle takes the exit; from the gore an exit vehicle is off the route: lane -1,
    # its d right of the main line's lanes and falling as it moves away (s: its footprint centre)
    main_ids = {v for v, g in group.items() if g not in ("leaving", "flow2")}
    assert not (traj["vehicle_id"].isin(main_ids) & (traj["lane"] == -1)).any()
    off = traj[traj["vehicle_id"].isin(took_exit) & (traj["lane"] == -1)]
    right_edge = road.lane_bounds(1, gore + 10.0)[0]
    assert (off["d"] < right_edge).all() and (off["s"] > gore - 10.0).all() and (off["d"] < -10.0).any()
    for _, own in off.groupby("vehicle_id"):
        assert (np.diff(own["d"].to_numpy()) <= 1e-6).all()
