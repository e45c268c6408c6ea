"""The controller API (vcfusion.control): a scenario names its ego controller by import path."""

import numpy as np
import pandas as pd
import pytest
from scenario_files import SCENARIOS

from vcfusion.control import Command, ControllerStage, Observation
from vcfusion.errors import ScenarioError
from vcfusion.run import build_cosimulation, execute_run
from vcfusion.scenario import load_scenario

# the accident scenario on a shorter trip, without the end-of-run metrics (seconds per run)
SHORT = """
extends: {accident}
simulation: {{max_time_s: 12.0}}
metrics: {{enabled: false}}
ego: {{trip_distance_m: 150.0{more}}}
"""


def short_scenario(tmp_path, more: str = "", name: str = "short.yaml"):
    path = tmp_path / name
    path.write_text(SHORT.format(accident=(SCENARIOS / "accident.yaml").as_posix(), more=more))
    return load_scenario(path)


def test_the_driver_model_behind_the_api_gives_the_same_run_byte_for_byte(tmp_path):
    plain = short_scenario(tmp_path)
    named = short_scenario(tmp_path, ", controller: 'vcfusion.control.builtin:DriverModelController'", "named.yaml")
    execute_run(plain, 5, tmp_path / "plain")
    execute_run(named, 5, tmp_path / "named")
    tables = sorted(p.name for p in (tmp_path / "plain").glob("*.parquet"))
    assert {"ego.parquet", "driver.parquet", "trajectories.parquet"} <= set(tables)
    assert tables == sorted(p.name for p in (tmp_path / "named").glob("*.parquet"))
    for name in tables:
        assert (tmp_path / "plain" / name).read_bytes() == (tmp_path / "named" / name).read_bytes(), name


def test_a_scripted_controller_that_brakes_makes_the_ego_slower_than_the_driver_model(tmp_path):
    driver = build_cosimulation(short_scenario(tmp_path), 2).run()
    braking = short_scenario(tmp_path, ", controller: 'vcfusion.control.builtin:ScriptedController', "
                             "controller_params: {accel_mps2: -2.0, from_s: 1.0, until_s: 4.0}", "brake.yaml")
    scripted = build_cosimulation(braking, 2).run()
    ego_d, ego_s = driver.tables["ego"], scripted.tables["ego"]
    # the command it gave is the one the ego table records, and the ego followed it
    window = (ego_s["time"] >= 1.0) & (ego_s["time"] < 3.95)
    assert (ego_s.loc[window, "command_accel"] == -2.0).all()
    at4 = lambda e: float(e.loc[np.isclose(e["time"], 4.0), "speed"].iloc[0])  # noqa: E731
    assert at4(ego_s) < at4(ego_d) - 5.0
    assert scripted.summary["ego_mean_speed_mps"] < driver.summary["ego_mean_speed_mps"] - 1.0
    assert "driver" not in scripted.summary  # no driver model ran


def test_a_lane_change_request_moves_the_ego_to_the_adjacent_lane_once(tmp_path):
    sc = short_scenario(tmp_path, ", controller: 'vcfusion.control.builtin:ScriptedController', controller_params: "
                        "{accel_mps2: 0.0, lane_change: -1, lane_change_at_s: 0.5}", "change.yaml")
    result = build_cosimulation(sc, 1).run()
    traj = result.tables["trajectories"]
    ego = traj[traj["vehicle_id"] == "ego"]
    assert ego["lane"].iloc[0] == 2 and ego["lane"].iloc[-1] == 1
    changes = result.tables["lane_changes"]
    mine = changes[changes["vehicle_id"] == "ego"]
    assert len(mine) == 1 and (mine["from_lane"].iloc[0], mine["to_lane"].iloc[0]) == (2, 1)


class _Recorder:
    """Keeps every observation; brakes gently."""

    needs = ("guidance",)

    def __init__(self):
        self.seen: list[Observation] = []

    def act(self, obs: Observation) -> Command:
        self.seen.append(obs)
        return Command(-0.5)


def test_the_observation_carries_the_received_twins_with_their_probabilities_and_no_ground_truth(tmp_path):
    sc = short_scenario(tmp_path)
    cosim = build_cosimulation(sc, 4)
    recorder = _Recorder()
    cosim.controller = ControllerStage(recorder)
    cosim.run()
    assert len(recorder.seen) > 50
    obs = recorder.seen[20]
    assert obs.scene is None and obs.guidance is not None
    probs = obs.lane_change_probability()
    assert set(probs) == set(obs.neighbours.ids) and "ego" not in probs and len(probs) >= 3
    assert all(0.0 <= p <= 1.0 for p in probs.values())
    # the ego's speed follows the command: 0.5 m/s^2 less every second
    speeds = [o.ego.speed for o in recorder.seen[:30]]
    assert speeds[10] == pytest.approx(speeds[0] - 0.5, abs=0.02)


@pytest.mark.parametrize("more, expected", [
    (", controller: 'no_such_module_xyz:Brake'", "ego.controller: no_such_module_xyz:Brake: cannot import module"),
    (", controller: 'vcfusion.control.builtin:NoSuchClass'", "has no attribute 'NoSuchClass'"),
    (", controller: 'vcfusion.control.builtin'", "expected an import path 'package.module:Name'"),
    (", controller: 'vcfusion.control.builtin:ScriptedController', controller_params: {brake: 1}",
     "controller_params: vcfusion.control.builtin:ScriptedController: controller_params ['brake'] do not fit"),
    (", controller_params: {accel_mps2: 1}", "given without ego.controller"),
])
def test_a_controller_that_cannot_be_loaded_is_refused_when_the_scenario_loads(tmp_path, more, expected):
    with pytest.raises(ScenarioError) as err:
        short_scenario(tmp_path, more)
    assert expected in str(err.value) and "short.yaml" in str(err.value)


def test_a_command_refuses_a_lane_change_other_than_left_keep_right():
    with pytest.raises(ValueError, match="expected -1, 0 or 1"):
        Command(0.0, lane_change=2)


def test_a_scenario_without_a_controller_records_the_same_scenario_as_before(tmp_path):
    sc = short_scenario(tmp_path)
    record = sc.to_dict()
    assert "controller" not in record["ego"] and "reward" not in record
    named = short_scenario(tmp_path, ", controller: 'vcfusion.control.builtin:ScriptedController', "
                           "controller_params: {accel_mps2: -1.0}", "named.yaml")
    assert named.to_dict()["ego"]["controller_params"] == {"accel_mps2": -1.0}


def test_a_live_run_decided_from_outside_is_the_run_its_controller_would_make(tmp_path):
    sc = short_scenario(tmp_path)
    whole = build_cosimulation(sc, 6).run()
    cosim = build_cosimulation(sc, 6)
    live = cosim.start()
    ticks = 0
    while live.tick is not None:  # the caller asks the same driver model: the same decisions
        live.advance(cosim.controller.acceleration(live.tick))
        ticks += 1
    stepped = live.result()
    assert live.end_reason == whole.summary["end_reason"] == "trip_complete" and ticks > 50
    for name in ("ego", "trajectories", "twins", "driver", "lane_changes"):
        pd.testing.assert_frame_equal(stepped.tables[name], whole.tables[name], check_exact=True)
    with pytest.raises(RuntimeError, match="the run has ended"):
        live.advance(0.0)


def test_the_human_driver_is_a_controller_of_the_api():
    from vcfusion.control import Controller
    from vcfusion.control.builtin import DriverModelController, IdmController
    from vcfusion.hitl.driver import HumanDriver

    for cls in (HumanDriver, DriverModelController, IdmController):
        assert callable(getattr(cls, "act", None)), cls
    # the per-step half of a person at the wheel reaches the loop through the stage
    driver = HumanDriver.__new__(HumanDriver)
    driver.needs = ("ego", "guidance")
    stage = ControllerStage(driver)
    assert isinstance(driver, Controller) and stage.step == driver.step and stage.finish == driver.finish
    assert stage.needs == ("ego", "guidance") and stage.finish_tables == ("inputs", "frames")
