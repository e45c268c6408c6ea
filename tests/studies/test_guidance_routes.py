"""The guidance study on a network with routes (the on-ramp: the scenario names a route list)."""

from pathlib import Path

import pandas as pd
import pytest

from vcfusion.scenario import load_scenario
from vcfusion.studies.guidance import StudyError, arm_scenario, renderer_key, run_guidance_study

REPO = Path(__file__).resolve().parents[2]
ONRAMP = REPO / "scenarios" / "onramp_camera.yaml"


def short_onramp(tmp_path, seconds: float, extra: str = "") -> Path:
    path = tmp_path / "short_onramp.yaml"
    path.write_text(f"extends: {ONRAMP}\nname: short_onramp\nsimulation: {{max_time_s: {seconds}}}\n{extra}")
    return path


def test_renderer_key_is_hashable_and_names_what_the_renderer_draws():
    sc = load_scenario(ONRAMP)
    assert isinstance(sc.route, (list, tuple)) and len(sc.route) == 3  # the case that failed: a route list
    fusion, oracle = renderer_key(arm_scenario(sc, "fusion")), renderer_key(arm_scenario(sc, "oracle"))
    assert hash(fusion) == hash(oracle) and fusion == oracle  # one renderer for both camera arms
    wider = sc.model_copy(update={"camera": sc.camera.model_copy(update={"width_px": sc.camera.width_px + 2})})
    assert renderer_key(wider) != fusion
    ramp = sc.model_copy(update={"ego": sc.ego.model_copy(update={"route": ["ramp", "accel", "main_out"]})})
    assert renderer_key(ramp) != fusion  # the camera draws the ego's own route


def test_a_scenario_without_a_predictor_is_refused_before_any_trip(tmp_path):
    path = short_onramp(tmp_path, 5.0, "prediction: {enabled: false}\n")
    with pytest.raises(StudyError, match="prediction.enabled is false"):
        run_guidance_study(path, trips=2, workers=1, out=tmp_path / "study", renders=tmp_path / "renders",
                           progress=False, arms=("none", "cloud"))
    assert not (tmp_path / "study").exists()


@pytest.mark.slow
def test_camera_arm_study_on_a_network_with_routes(tmp_path):
    res = run_guidance_study(short_onramp(tmp_path, 12.0), trips=2, workers=1, out=tmp_path / "study",
                             renders=tmp_path / "renders", progress=False, arms=("none", "oracle"))
    assert res["failed"] == []
    trips = pd.read_parquet(tmp_path / "study" / "trips.parquet")
    assert trips["arm"].tolist() == ["none", "oracle", "none", "oracle"]
    oracle = trips[trips["arm"] == "oracle"]
    assert set(oracle["guidance_source"]) == {"fusion"} and (oracle["ticks_without_frame"] == 0).all()
    assert (oracle["process_models"] == "lane_change").all()
    # the camera arm's wrong episodes split by the vehicle in the box, summing to them; none for the unguided arm
    kinds = ["wrong_on_meant_vehicle", "wrong_on_other_vehicle", "wrong_on_no_vehicle"]
    assert oracle[kinds].notna().all().all() and (oracle[kinds].sum(axis=1) == oracle["highlights_wrong"]).all()
    assert trips.loc[trips["arm"] == "none", kinds].isna().all().all()
