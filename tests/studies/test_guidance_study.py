"""The guidance study end to end on real SUMO: paired trips in several arms, tables, summary, figures."""

import io
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vcfusion.studies.guidance import StudyError, paired_summary, parse_arms, run_guidance_study

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_study_two_trips_end_to_end(tmp_path):
    # The shipped lane-change predictor runs in the cloud (scenario default).
    res = run_guidance_study(REPO / "scenarios" / "accident.yaml", trips=2, workers=1, out=tmp_path / "study",
                             renders=tmp_path / "renders", progress=False, arms=("none", "cloud"))
    trips = pd.read_parquet(tmp_path / "study" / "trips.parquet")
    assert trips["arm"].tolist() == ["none", "cloud", "none", "cloud"]
    assert set(trips.loc[trips["arm"] == "cloud", "guidance_source"]) == {"cloud"}
    assert (trips["process_models"] == "lane_change").all()
    # the same driver in both arms of a trip, and TTC against the same vehicle
    for _, pair in trips.groupby("seed"):
        assert pair["driver_cutin_reaction_s"].nunique() == 1 and pair["target_id"].nunique() == 1
    cloud = trips[trips["arm"] == "cloud"]
    assert (cloud["highlights_right"] > 0).all() and (cloud["highlights_wrong"] == 0).all()
    assert trips.loc[trips["arm"] == "none", "highlights_right"].isna().all()
    assert (trips["fuel_g_per_km"] > 20).all() and (trips["fuel_g_per_km"] < 200).all()
    assert "paper" in res["text"] and "cloud vs none" in res["text"]
    assert len(res["figures"]) == 2  # Fig. 8 (safety and comfort) and Fig. 9 (fuel and emissions)
    for fig in res["figures"]:
        assert fig.stat().st_size > 10_000
    assert (tmp_path / "study" / "summary.csv").is_file() and (tmp_path / "study" / "trips.csv").is_file()


@pytest.mark.slow
def test_camera_arm_renders_and_detects_on_a_scenario_without_vision(tmp_path):
    """accident.yaml has no vision/fusion blocks: the oracle arm turns the camera and fusion on."""
    res = run_guidance_study(REPO / "scenarios" / "accident.yaml", trips=2, workers=2, out=tmp_path / "study",
                             renders=tmp_path / "renders", progress=False, arms=("none", "oracle"))
    assert res["failed"] == []
    trips = pd.read_parquet(tmp_path / "study" / "trips.parquet")
    assert trips["arm"].tolist() == ["none", "oracle"] * 2
    oracle = trips[trips["arm"] == "oracle"]
    assert set(oracle["guidance_source"]) <= {"fusion", "fusion+no_frame"}
    assert (oracle["highlights_right"] > 0).all() and (oracle["ticks_without_frame"] == 0).all()


def quiet_predictor(scenario):
    """Every twin gets a probability below the medium threshold: items are shown, none warns."""
    def model(twins, store):
        return {"lc_prob": np.full(len(twins), 0.2), "lc_decision": np.ones(len(twins), dtype=bool)}
    return model


@pytest.mark.slow
def test_guidance_without_warnings_leaves_the_ego_trace_byte_identical(accident_path):
    from vcfusion.run import build_cosimulation
    from vcfusion.scenario import load_scenario

    sc = load_scenario(accident_path)
    sc = sc.model_copy(update={"prediction": sc.prediction.model_copy(update={"enabled": False})})
    ego = {}
    for guided in (False, True):
        result = build_cosimulation(sc, 4, guidance_enabled=guided,
                                    extra_process_models=[("quiet", quiet_predictor(sc))]).run()
        shown = result.tables["guidance"]
        assert (shown["vehicle_id"] != "").any() and set(shown["level"]) <= {"none", ""}
        buf = io.BytesIO()
        result.tables["ego"].to_parquet(buf, index=False)
        ego[guided] = buf.getvalue()
    assert ego[True] == ego[False]


@pytest.mark.slow
def test_study_without_predictor_says_so(tmp_path):
    text = (REPO / "scenarios" / "accident.yaml").read_text().replace("../sumo_net", str(REPO / "sumo_net"))
    scenario = tmp_path / "no_predictor.yaml"
    scenario.write_text(text + "\nprediction: {enabled: false}\n")
    with pytest.raises(StudyError, match="lc_prob"):
        run_guidance_study(scenario, trips=2, workers=1, out=tmp_path / "s", renders=tmp_path / "r", progress=False,
                           arms=("none", "cloud"))
    assert not (tmp_path / "s" / "trips.parquet").exists()


def test_arms_are_checked():
    assert parse_arms("none,fusion") == ("none", "fusion")
    assert parse_arms("none, cloud,fusion,oracle") == ("none", "cloud", "fusion", "oracle")
    for bad, why in (("none,radar", "radar"), ("fusion,oracle", "'none'"), ("none", "besides"),
                     ("none,cloud,cloud", "twice"), ("", "comma")):
        with pytest.raises(ValueError, match=why):
            parse_arms(bad)


def test_paired_summary_ci_on_known_differences():
    trips = pd.DataFrame({"seed": [0, 0, 1, 1, 2, 2, 3, 3], "arm": ["none", "fusion"] * 4,
                          "x": [1.0, 2.0, 2.0, 3.5, 3.0, 3.5, 5.0, np.nan]})
    s = paired_summary(trips, [("x", "x", "", None, None, None)]).iloc[0]
    # seed 3 lacks the metric in one arm: left out of both. Differences 1.0, 1.5, 0.5: mean 1,
    # sd 0.5, t(0.975, 2) = 4.3027
    assert s["arm"] == "fusion" and s["n_pairs"] == 3 and s["mean_diff"] == pytest.approx(1.0)
    half = 4.302652729911275 * 0.5 / math.sqrt(3)
    assert s["ci95_low"] == pytest.approx(1.0 - half) and s["ci95_high"] == pytest.approx(1.0 + half)
    assert s["rel_change_pct"] == pytest.approx(100 * (3.0 - 2.0) / 2.0)
    assert s["mean_ref"] == pytest.approx(2.0) and s["mean_arm"] == pytest.approx(3.0)


def test_paired_summary_of_a_constant_difference_is_certain_unless_it_is_zero():
    # every pair differs by 0.5: no spread, a zero-width interval, and p = 0 (was 1); by 0: p = 1
    trips = pd.DataFrame({"seed": [0, 0, 1, 1, 2, 2], "arm": ["none", "fusion"] * 3,
                          "x": [1.0, 1.5, 2.0, 2.5, 4.0, 4.5], "y": [1.0, 1.0, 2.0, 2.0, 3.0, 3.0]})
    s = paired_summary(trips, [("x", "x", "", None, None, None), ("y", "y", "", None, None, None)])
    x, y = s.iloc[0], s.iloc[1]
    assert (x["mean_diff"], x["ci95_low"], x["ci95_high"], x["p_value"]) == pytest.approx((0.5, 0.5, 0.5, 0.0))
    assert (y["mean_diff"], y["p_value"]) == (0.0, 1.0)


def test_highlight_updates_are_counted_per_warned_twin_and_update_without_episodes():
    from vcfusion.studies.guidance import HIGHLIGHT_UPDATES, highlight_counts, highlight_update_counts

    rows = [("a", "high", "right", "a"), ("a", "high", "missed", ""), ("a", "high", "right", "a"),
            ("b", "medium", "wrong", "c"), ("b", "medium", "unseen", ""), ("c", "none", "missed", "")]
    fusion = pd.DataFrame([{"time": round(1.0 + 0.1 * (k % 3), 6), "vehicle_id": v, "level": lv, "outcome": o,
                            "box_vehicle_id": s} for k, (v, lv, o, s) in enumerate(rows)])
    # the calm twin (level none) is no warning; the one-update gap of a's right box is bridged in episodes only
    assert highlight_update_counts(fusion) == {"updates_right": 2, "updates_wrong": 1, "updates_missed": 1,
                                               "updates_unseen": 1}
    assert highlight_counts(None, fusion, 0.1) == {"highlights_right": 1, "highlights_wrong": 1,
                                                   "missed_warnings": 0, "unseen_warnings": 1}
    assert all(math.isnan(v) for v in highlight_update_counts(None).values()) and len(HIGHLIGHT_UPDATES) == 4


def test_wrong_episodes_are_split_by_the_vehicle_in_the_box():
    from vcfusion.studies.guidance import WRONG_KINDS, highlight_counts, highlight_tallies

    def wrong_episode_kinds(fusion, period_s):
        return {k: highlight_tallies(None, fusion, period_s)[k] for k in WRONG_KINDS}

    # a's box on a itself at too low an IoU for one update, then right; b's box on c for two updates,
    # then on nothing; the calm twin d (level none) is no warning
    rows = [(1.0, "a", "high", "wrong", "a"), (1.1, "a", "high", "right", "a"),
            (1.0, "b", "medium", "wrong", "c"), (1.1, "b", "medium", "wrong", "c"), (1.2, "b", "medium", "wrong", ""),
            (1.0, "d", "none", "wrong", "e")]
    fusion = pd.DataFrame([{"time": t, "vehicle_id": v, "level": lv, "outcome": o, "box_vehicle_id": s}
                           for t, v, lv, o, s in rows])
    kinds = wrong_episode_kinds(fusion, 0.1)
    assert kinds == {"wrong_on_meant_vehicle": 1, "wrong_on_other_vehicle": 1, "wrong_on_no_vehicle": 1}
    assert sum(kinds.values()) == highlight_counts(None, fusion, 0.1)["highlights_wrong"] == 3
    assert all(math.isnan(wrong_episode_kinds(None, 0.1)[k]) for k in WRONG_KINDS)
