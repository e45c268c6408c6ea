"""The calibration search's candidates are valid scenario blocks, and its objective is the mean KS
of the lane-change-model quantities only."""

import pandas as pd
import pytest
from scenario_files import SCENARIOS

from vcfusion.prediction.lc_calibration import CANDIDATES, OBJECTIVE, candidate_scenario, score
from vcfusion.scenario import load_scenario


@pytest.mark.parametrize("name", sorted(CANDIDATES))
def test_every_candidate_is_a_valid_scenario(tmp_path, name):
    path = candidate_scenario(SCENARIOS / "dense.yaml", CANDIDATES[name], tmp_path / f"{name}.yaml")
    scenario = load_scenario(path)
    assert scenario.name == "dense"
    if CANDIDATES[name] is None:
        assert scenario.lane_change_model is None
    else:
        assert scenario.lane_change_model.model == CANDIDATES[name]["model"]


def test_score_is_the_mean_ks_of_the_objective_quantities():
    ks = pd.DataFrame({"quantity": [OBJECTIVE[0], OBJECTIVE[1], "gap_target_lead_m"], "ks": [0.2, 0.4, 0.9]})
    assert score(ks) == pytest.approx(0.3)  # gaps follow density: reported, not scored


@pytest.mark.parametrize("name", ["dense_us101", "heavy_us101"])
def test_shipped_calibrated_scenarios_carry_the_searched_best(name):
    from vcfusion.scenario import LaneChangeModelConfig

    scenario = load_scenario(SCENARIOS / "calibrated" / f"{name}.yaml")
    assert scenario.lane_change_model == LaneChangeModelConfig(**CANDIDATES["sl2015-sigma0.9-acc1-logn3.5"])


@pytest.mark.slow
def test_search_of_two_candidates_end_to_end(tmp_path, capsys):
    """Two candidates on a one-minute run of the busy highway, scored against a synthetic
    recording (the one of test_compare_lane_changes): a table row each, the objective finite."""
    from scenario_files import busy_traffic, write_scenario

    from vcfusion.commands import main
    from vcfusion.prediction.sources.trajectories import import_recordings

    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("synthetic", Path(__file__).with_name("test_compare_lane_changes.py"))
    synthetic = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(synthetic)

    real = tmp_path / "real"
    import_recordings([synthetic.recording(5.0, 20.0, 25.0)], real, 5.0, 2.0, progress=False)
    base = write_scenario(tmp_path, busy_traffic(60))
    out = tmp_path / "search"
    assert main(["calibrate-lane-changes", str(base), str(real), "--seeds", "0", "--out", str(out),
                 "--candidates", "lc2013-default,lc2013-fixed5"]) == 0
    table = pd.read_csv(out / "search.csv")
    assert list(table["candidate"]) == ["lc2013-default", "lc2013-fixed5"]
    assert table["objective"].between(0, 1).all() and (table["lane_changes"] > 0).all()
    # the fixed 5 s duration reached SUMO: its changes last longer than the default 3 s ones
    assert table.loc[1, "median_duration_s"] > table.loc[0, "median_duration_s"] + 1.0
    assert "best:" in capsys.readouterr().out
    assert main(["calibrate-lane-changes", str(base), str(real), "--seeds", "0", "--out", str(out),
                 "--candidates", "nosuch"]) == 2
