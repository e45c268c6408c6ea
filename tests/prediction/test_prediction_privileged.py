"""The privileged ceiling: SUMO's lane-change state logged per tick (`vcfusion dataset --privileged`),
a ceiling model trained on it (`vcfusion train --privileged`) and scored by `vcfusion evaluate`."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from vcfusion.commands import main
from vcfusion.prediction.features import FEATURE_NAMES
from vcfusion.prediction.model import load_model
from vcfusion.prediction.privileged import (
    LCA_BLOCKED, LCA_LEFT, LCA_RIGHT, LCA_SPEEDGAIN, LCA_UNKNOWN, PRIVILEGED_NAMES, add_privileged, state_columns,
)
from vcfusion.run import build_cosimulation
from vcfusion.scenario import load_scenario

REPO = Path(__file__).resolve().parents[2]


def test_state_bits_and_join():
    cols = state_columns(np.array([LCA_LEFT | LCA_SPEEDGAIN, LCA_UNKNOWN | LCA_LEFT, 0]),
                         np.array([LCA_RIGHT | LCA_BLOCKED, 0, LCA_RIGHT]))
    assert list(cols["sumo_wants_left"]) == [1, 0, 0]  # an unknown state wants nothing
    assert list(cols["sumo_speedgain_left"]) == [1, 0, 0]
    assert list(cols["sumo_wants_right"]) == [1, 0, 1] and list(cols["sumo_blocked_right"]) == [1, 0, 0]
    lc_state = pd.DataFrame({"time": [0.1, 0.1], "vehicle_id": ["a", "b"], "state_left": [LCA_LEFT, 0],
                             "state_right": [0, 0], "desired_speed": [30.0, 20.0], "speed": [25.0, 20.0],
                             "sumo_speedgain_urge_left": [0.5, 0.0], "sumo_speedgain_urge_right": [0.0, 0.0],
                             "sumo_keepright_urge": [0.0, 1.0]})
    samples = pd.DataFrame({"time": [0.1, 0.1, 0.2], "vehicle_id": ["b", "a", "a"], "x": [1.0, 2.0, 3.0]})
    out = add_privileged(samples, lc_state)
    assert list(out["x"]) == [1.0, 2.0, 3.0]  # row order kept
    assert list(out["sumo_wants_left"]) == [0, 1, 0] and list(out["sumo_state_known"]) == [1, 1, 0]
    assert list(out["sumo_desired_minus_speed"]) == [0.0, 5.0, 0.0]  # no state at 0.2 s: 0, flagged unknown


def _short_dense(tmp_path: Path, seconds: float) -> Path:
    raw = yaml.safe_load((REPO / "scenarios" / "dense.yaml").read_text())
    raw["network"] = str(REPO / "sumo_net" / "highway.net.xml")
    raw["vehicle_types"] = str(REPO / "sumo_net" / "vtypes.add.xml")
    raw["simulation"]["max_time_s"] = seconds
    raw["prediction"] = {"enabled": False}
    path = tmp_path / "dense_short.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.slow
def test_privileged_dataset_ceiling_model_and_evaluation(tmp_path, capsys):
    scenario = _short_dense(tmp_path, 30.0)
    data = tmp_path / "data"
    assert main(["dataset", str(scenario), "--seeds", "0-2", "--out", str(data), "--workers", "1",
                 "--privileged"]) == 0
    meta = json.loads((data / "dataset.json").read_text())
    assert meta["privileged_names"] == list(PRIVILEGED_NAMES) and meta["feature_names"] == list(FEATURE_NAMES)
    run = data / "runs" / "seed_0000"
    samples = pd.read_parquet(run / "samples.parquet")
    assert set(PRIVILEGED_NAMES) <= set(samples.columns) and samples["sumo_state_known"].mean() > 0.5
    # logging the state does not change the run: the same lane changes and twins as a plain run
    plain = build_cosimulation(load_scenario(scenario), 0).run()
    lc = pd.read_parquet(run / "lane_changes.parquet")
    pd.testing.assert_frame_equal(lc, plain.tables["lane_changes"].reset_index(drop=True), check_dtype=False)
    pd.testing.assert_frame_equal(pd.read_parquet(run / "twins.parquet"), plain.tables["twins"], check_dtype=False)
    # against SUMO's own lanechange-output: before each change's midpoint, from a second before
    # its start, SUMO's state wanted that direction
    state = samples.set_index(["vehicle_id", "time"]).sort_index()
    hits = []
    for ev in lc.itertuples():
        side = "left" if ev.direction > 0 else "right"
        g = state.loc[ev.vehicle_id] if ev.vehicle_id in state.index.get_level_values(0) else None
        if g is None or np.isnan(ev.start_time):
            continue
        g = g[(g.index >= ev.start_time - 1.0) & (g.index <= ev.mid_time + 1e-6)]
        hits.append(bool((g[f"sumo_wants_{side}"] > 0).any()))
    assert len(hits) >= 20 and np.mean(hits) >= 0.9
    # a dataset folder cannot switch between plain and privileged
    capsys.readouterr()
    assert main(["dataset", str(scenario), "--seeds", "0-2", "--out", str(data), "--workers", "1"]) == 2
    assert "privileged_names" in capsys.readouterr().err

    ceiling = tmp_path / "ceiling.npz"
    assert main(["train", str(data), "--out", str(ceiling), "--epochs", "3", "--hidden", "16", "--privileged"]) == 0
    assert load_model(ceiling, expected_features=FEATURE_NAMES + PRIVILEGED_NAMES).info["config"]["privileged"]
    assert main(["evaluate", str(ceiling), str(data), "--split", "all", "--out", str(tmp_path / "eval")]) == 0
    result = json.loads((tmp_path / "eval" / "evaluation.json").read_text())
    assert result["default"]["predictor"] == "MLP + SUMO state (privileged)"
    assert {v["predictor"] for v in result["variants"]} == {"MLP + SUMO state (privileged)", "logistic regression",
                                                           "gap/speed rule", "SUMO wants to change (privileged)"}
    wants = [v for v in result["variants"] if v["predictor"] == "SUMO wants to change (privileged)"]
    assert all(0.0 <= v["predicted"] <= 1.0 for v in wants)
    # the shipped (observable) model on the same privileged dataset: the gap to the ceiling
    shipped = REPO / "src" / "vcfusion" / "assets" / "lane_change_mlp.npz"
    assert main(["evaluate", str(shipped), str(data), "--split", "all", "--out", str(tmp_path / "eval2")]) == 0
    result = json.loads((tmp_path / "eval2" / "evaluation.json").read_text())
    assert result["default"]["predictor"] == "MLP"
    # a plain dataset has no SUMO state to train a ceiling on
    del meta["privileged_names"]
    (data / "dataset.json").write_text(json.dumps(meta))
    capsys.readouterr()
    assert main(["train", str(data), "--out", str(tmp_path / "x.npz"), "--privileged"]) == 2
    assert "--privileged" in capsys.readouterr().err and not (tmp_path / "x.npz").exists()
    # ... nor can the ceiling score it: said as such (it read "feature list does not match this version of
    # vcfusion.prediction.features ... retrain")
    assert main(["evaluate", str(ceiling), str(data), "--split", "all", "--out", str(tmp_path / "eval3")]) == 2
    err = capsys.readouterr().err
    assert "a privileged (ceiling) model" in err and "vcfusion dataset --privileged" in err and "retrain" not in err
