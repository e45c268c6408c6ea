"""The guidance study end to end on real SUMO: two paired trips, tables, summary, figures."""

import math
from pathlib import Path

import pandas as pd
import pytest

from vcfusion.studies.guidance import StudyError, paired_summary, run_guidance_study

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_study_two_trips_end_to_end(tmp_path):
    # The shipped lane-change predictor runs in the cloud (scenario default).
    res = run_guidance_study(REPO / "scenarios" / "accident.yaml", trips=2, workers=1, out=tmp_path / "study",
                             renders=tmp_path / "renders", progress=False)
    trips = pd.read_parquet(tmp_path / "study" / "trips.parquet")
    assert sorted(trips["arm"]) == ["off", "off", "on", "on"]
    assert set(trips["guidance_source"]) == {"cloud"}
    assert (trips["process_models"] == "lane_change").all()
    # the same driver in both arms of a trip
    for _, pair in trips.groupby("seed"):
        assert pair["driver_cutin_reaction_s"].nunique() == 1
    # with guidance the driver responds to the lane-change vehicle earlier
    on, off = (trips[trips["arm"] == a].set_index("seed") for a in ("on", "off"))
    assert (on["response_time_s"] <= off["response_time_s"]).all()
    assert (on["response_cue"] == "guidance").any()
    assert (trips["fuel_g_per_km"] > 20).all() and (trips["fuel_g_per_km"] < 200).all()
    assert "paper" in res["text"] and "fallback" in res["text"]
    for fig in res["figures"]:
        assert fig.stat().st_size > 10_000
    assert (tmp_path / "study" / "summary.csv").is_file() and (tmp_path / "study" / "trips.csv").is_file()


@pytest.mark.slow
def test_study_without_predictor_says_so(tmp_path):
    text = (REPO / "scenarios" / "accident.yaml").read_text().replace("../sumo_net", str(REPO / "sumo_net"))
    scenario = tmp_path / "no_predictor.yaml"
    scenario.write_text(text + "\nprediction: {enabled: false}\n")
    with pytest.raises(StudyError, match="lc_prob"):
        run_guidance_study(scenario, trips=2, workers=1, out=tmp_path / "s", renders=tmp_path / "r", progress=False)
    assert not (tmp_path / "s" / "trips.parquet").exists()


def test_paired_summary_ci_on_known_differences():
    trips = pd.DataFrame({"seed": [0, 0, 1, 1, 2, 2], "arm": ["off", "on"] * 3,
                          "x": [1.0, 2.0, 2.0, 3.5, 3.0, 3.5]})
    s = paired_summary(trips, [("x", "x", "", None, None, None)]).iloc[0]
    # differences 1.0, 1.5, 0.5: mean 1, sd 0.5, t(0.975, 2) = 4.3027
    assert s["mean_diff"] == pytest.approx(1.0)
    half = 4.302652729911275 * 0.5 / math.sqrt(3)
    assert s["ci95_low"] == pytest.approx(1.0 - half) and s["ci95_high"] == pytest.approx(1.0 + half)
    assert s["rel_change_pct"] == pytest.approx(100 * (3.0 - 2.0) / 2.0)
