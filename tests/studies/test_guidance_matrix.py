"""`vcfusion guidance-matrix`: the guidance study over several scenarios, per scenario and pooled."""

from pathlib import Path

import pandas as pd
import pytest

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
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "m" / "matrix_summary.csv"), summary)


def test_matrix_needs_two_trips(capsys):
    assert main(["guidance-matrix", str(REPO / "scenarios" / "accident.yaml"), "--trips", "1", "--out", "x"]) == 2
    assert "--trips" in capsys.readouterr().err
