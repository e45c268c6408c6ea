"""The guidance study and a run's metrics report the same ego numbers for the same trip."""

import pytest

from vcfusion.run import build_cosimulation
from vcfusion.scenario import load_scenario
from vcfusion.studies.guidance import arm_metrics, choose_target, simulate_arm


@pytest.mark.slow
def test_study_row_equals_the_runs_ego_metrics(accident_path):
    sc = load_scenario(accident_path)
    sc = sc.model_copy(update={"metrics": sc.metrics.model_copy(update={"jerk_window_s": 0.2,
                                                                        "ttc_threshold_s": 2.5})})
    ego = build_cosimulation(sc, 4, guidance_enabled=True).run().summary["metrics"]["ego"]
    run = simulate_arm(sc, 4, "cloud")  # accident.yaml has no camera: the cloud arm is the same run
    row = arm_metrics(run, choose_target([run]))
    assert row["ttc_threshold_s"] == 2.5  # the study reads the scenario's metrics block
    assert row["avg_abs_accel_mps2"] == ego["mean_abs_accel_mps2"]
    assert row["max_abs_jerk_mps3"] == ego["max_abs_jerk_mps3"]
    assert row["max_decel_mps2"] == ego["max_decel_mps2"]
    assert row["trip_time_s"] == ego["travel_time_s"]
    assert row["fuel_g_per_km"] == ego["movestar_fuel_g_per_km"]
    assert row["co2_g_per_km"] == ego["movestar_co2_g_per_km"]
