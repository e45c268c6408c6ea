"""`vcfusion guidance-matrix`: the guidance study over several scenarios, per scenario and pooled."""

from pathlib import Path

import pandas as pd
import pytest

from support.study_folders import write_study_folder
from vcfusion.commands import main

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_matrix_of_two_short_scenarios(tmp_path, capsys):
    paths = []
    for name in ("accident", "curved"):
        p = tmp_path / f"short_{name}.yaml"
        p.write_text(f"extends: {REPO / 'scenarios' / (name + '.yaml')}\nname: {name}\nsimulation: {{max_time_s: 5.0}}\n")
        paths.append(str(p))
    assert main(["guidance-matrix", *paths, "--trips", "2", "--workers", "1", "--arms", "none,cloud",
                 "--out", str(tmp_path / "m")]) == 0
    summary = pd.read_csv(tmp_path / "m" / "matrix_summary.csv")
    assert set(summary["group"]) == {"accident", "curved", "pooled"}
    assert dict(summary.groupby("group")["split"].first()) == {"accident": "tuned-on", "curved": "held-out",
                                                                 "pooled": "held-out+tuned-on"}
    fuel = summary[summary["metric"] == "fuel_g_per_km"].set_index("group")["n_pairs"]
    assert fuel["pooled"] == fuel["accident"] + fuel["curved"] == 4  # pooled: every trip of every scenario
    hl = pd.read_csv(tmp_path / "m" / "matrix_highlights.csv")
    assert list(hl["group"]) == ["accident", "curved", "pooled"] and (hl["arm"] == "cloud").all()
    assert hl.loc[2, "highlights_right"] == hl.loc[0, "highlights_right"] + hl.loc[1, "highlights_right"]
    text = capsys.readouterr().out
    assert "accident [tuned-on]" in text and "curved [held-out]" in text and "ego collisions in seeds" in text
    for name in ("accident", "curved"):  # each scenario's own study folder
        assert (tmp_path / "m" / name / "trips.parquet").is_file()
    # the same command again (as after an interruption) takes every trip from the scenarios' trip logs
    assert main(["guidance-matrix", *paths, "--trips", "2", "--workers", "1", "--arms", "none,cloud",
                 "--out", str(tmp_path / "m")]) == 0
    text = capsys.readouterr().out
    assert text.count("2 of 2 trips taken from") == 2
    assert text.count("(2 trips taken from an earlier sitting's log)") == 2  # the matrix's lines say so too
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "m" / "matrix_summary.csv"), summary)
    # the same studies tabled from their folders (as when each scenario ran on its own): the same tables
    assert main(["guidance-matrix", "--from-studies", str(tmp_path / "m" / "accident"),
                 str(tmp_path / "m" / "curved"), "--out", str(tmp_path / "read")]) == 0
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "read" / "matrix_summary.csv"), summary)
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "read" / "matrix_highlights.csv"), hl)


def test_matrix_needs_two_trips(capsys):
    assert main(["guidance-matrix", str(REPO / "scenarios" / "accident.yaml"), "--trips", "1", "--out", "x"]) == 2
    assert "--trips" in capsys.readouterr().err


def _study_folder(folder: Path, scenario: str, arms: tuple[str, ...]) -> Path:
    """Three seeds; fuel falls by the seed in each guided arm, one wrong episode in seed 2."""
    rows = [{"seed": seed, "arm": arm, "fuel_g_per_km": 40.0 - i * seed, "highlights_right": 3 * (arm != "none"),
             "highlights_wrong": int(arm != "none" and seed == 2), "unseen_warnings": 2 * (arm != "none")}
            for seed in (1, 2, 3) for i, arm in enumerate(arms)]
    return write_study_folder(folder, scenario, rows, failed={"7": "boom"}, trips_from_log=2)


def test_studies_run_one_by_one_are_tabled_per_scenario_and_pooled(tmp_path, capsys):
    a = _study_folder(tmp_path / "a", "exit_camera", ("none", "fusion"))
    b = _study_folder(tmp_path / "b", "onramp_camera", ("none", "fusion"))
    assert main(["guidance-matrix", "--from-studies", str(a), str(b), "--tuned-on", "onramp_camera",
                 "--out", str(tmp_path / "m")]) == 0
    hl = pd.read_csv(tmp_path / "m" / "matrix_highlights.csv").set_index("group")
    assert dict(hl["split"]) == {"exit_camera": "held-out", "onramp_camera": "tuned-on", "pooled": "held-out+tuned-on"}
    assert list(hl["highlights_right"]) == [9, 9, 18] and list(hl["highlights_wrong"]) == [1, 1, 2]
    assert hl.loc["pooled", "wrong_pct_of_drawn"] == pytest.approx(100 * 2 / 20)
    # resampling the six scenario-seeds: draws without either seed 2 hold no wrong episode
    assert hl.loc["pooled", "wrong_pct_ci95_low"] == 0.0 < 10.0 < hl.loc["pooled", "wrong_pct_ci95_high"]
    assert hl["wrong_minus_oracle_pct"].isna().all()  # no oracle arm
    fuel = pd.read_csv(tmp_path / "m" / "matrix_summary.csv").query("metric == 'fuel_g_per_km'").set_index("group")
    assert list(fuel["n_pairs"]) == [3, 3, 6]  # pooled: paired within each scenario and seed
    assert fuel.loc["pooled", "mean_diff"] == pytest.approx(-2.0)  # fusion - none = -seed, seeds 1-3 twice
    text = capsys.readouterr().out
    assert ("exit_camera [held-out]: 12 s (2 trips taken from an earlier sitting's log), failed trips [7]" in text
            and "seeds 1-3" in text)


def test_studies_of_other_arms_or_no_study_are_refused(tmp_path, capsys):
    a = _study_folder(tmp_path / "a", "exit_camera", ("none", "fusion"))
    b = _study_folder(tmp_path / "b", "onramp_camera", ("none", "cloud"))
    assert main(["guidance-matrix", "--from-studies", str(a), str(b), "--out", str(tmp_path / "m")]) == 2
    assert "the same arms" in capsys.readouterr().err
    assert main(["guidance-matrix", "--from-studies", str(a), str(tmp_path), "--out", str(tmp_path / "m")]) == 2
    assert f"{tmp_path / 'summary.json'}: expected the file" in capsys.readouterr().err
    assert main(["guidance-matrix", "--from-studies", str(a), str(a), "--out", str(tmp_path / "m")]) == 2
    assert "the same scenario" in capsys.readouterr().err
    assert main(["guidance-matrix", str(REPO / "scenarios" / "accident.yaml"), "--from-studies", str(a),
                 "--out", str(tmp_path / "m")]) == 2
    assert "not both" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()  # nothing written by a refused command
