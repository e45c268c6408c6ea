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
