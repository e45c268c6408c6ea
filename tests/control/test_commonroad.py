"""`vcfusion export-commonroad`: a run folder as a CommonRoad scenario that commonroad-io reads back."""

import json

import numpy as np
import pandas as pd
import pytest
from scenario_files import SCENARIOS

from vcfusion.control.commonroad import commonroad_problem

pytestmark = pytest.mark.skipif(commonroad_problem() is not None, reason=str(commonroad_problem()))

SHORT = """
extends: {accident}
simulation: {{max_time_s: 6.0}}
metrics: {{enabled: false}}
"""


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    from vcfusion.run import execute_run
    from vcfusion.scenario import load_scenario

    tmp = tmp_path_factory.mktemp("cr")
    path = tmp / "short.yaml"
    path.write_text(SHORT.format(accident=(SCENARIOS / "accident.yaml").as_posix()))
    execute_run(load_scenario(path), 3, tmp / "run")
    return tmp / "run", path


def test_positions_survive_the_round_trip_within_a_centimetre(run_folder, tmp_path):
    from commonroad.common.file_reader import CommonRoadFileReader

    from vcfusion.commands import main

    folder, scenario = run_folder
    out = tmp_path / "run.xml"
    assert main(["export-commonroad", str(folder), "--out", str(out), "--scenario", str(scenario)]) == 0
    table = json.loads(out.with_suffix(".ids.json").read_text())
    cr, problems = CommonRoadFileReader(str(out)).open()
    traj = pd.read_parquet(folder / "trajectories.parquet")
    assert len(cr.dynamic_obstacles) == traj["vehicle_id"].nunique() == len(table["obstacle_ids"])
    worst = 0.0
    for vid, rows in traj.groupby("vehicle_id"):
        obstacle = cr.obstacle_by_id(table["obstacle_ids"][vid])
        states = [obstacle.initial_state] + list(obstacle.prediction.trajectory.state_list)
        assert [s.time_step for s in states] == list(np.rint(rows["time"] / 0.1).astype(int))
        xy = np.array([s.position for s in states])
        worst = max(worst, float(np.hypot(*(xy - rows[["x", "y"]].to_numpy()).T).max()))
        assert [s.velocity for s in states] == pytest.approx(rows["speed"].tolist(), abs=1e-4)
    assert worst < 0.01
    # the road: one lanelet per lane, the ego in the lanelet of its lane; the ego is the planning problem
    assert len(cr.lanelet_network.lanelets) == 3
    ego = cr.obstacle_by_id(table["ego_obstacle_id"])
    lanelet = cr.lanelet_network.find_lanelet_by_position([ego.initial_state.position])[0]
    assert lanelet == [300]  # LANELET_ID0 + 100 * lane 2
    right = cr.lanelet_network.find_lanelet_by_id(300).adj_right
    assert right == 200 and problems.planning_problem_dict[1].initial_state.position == pytest.approx(
        ego.initial_state.position)


def test_a_folder_that_is_not_a_run_and_a_bad_output_name_are_refused(run_folder, tmp_path):
    from vcfusion.commands import main

    folder, scenario = run_folder
    assert main(["export-commonroad", str(tmp_path), "--out", str(tmp_path / "x.xml")]) == 2
    assert main(["export-commonroad", str(folder), "--out", str(tmp_path / "x.json"), "--scenario", str(scenario)]) == 2
    assert not list(tmp_path.glob("x*"))
