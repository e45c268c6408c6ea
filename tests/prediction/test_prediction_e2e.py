"""End to end on real SUMO: tiny dataset -> quick training -> evaluation; and the cloud predictor
in the tick loop gives exactly what the dataset path computes from the logged twins table."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from vcfusion.commands import main
from vcfusion.prediction.dataset import SAMPLES_VERSION
from vcfusion.prediction.features import FEATURE_NAMES, features_from_twins_table
from vcfusion.prediction.model import load_model
from vcfusion.prediction.smoothing import smooth
from vcfusion.run import execute_run
from vcfusion.scenario import load_scenario
from vcfusion.traffic.network import read_road

REPO = Path(__file__).resolve().parents[2]


def _short_dense(tmp_path: Path, seconds: float, **prediction) -> Path:
    raw = yaml.safe_load((REPO / "scenarios" / "dense.yaml").read_text())
    raw["network"] = str(REPO / "sumo_net" / "highway.net.xml")
    raw["vehicle_types"] = str(REPO / "sumo_net" / "vtypes.add.xml")
    raw["simulation"]["max_time_s"] = seconds
    raw["prediction"] = prediction or {"enabled": False}
    path = tmp_path / "dense_short.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.slow
def test_dataset_train_evaluate_on_real_sumo(tmp_path, capsys):
    scenario = _short_dense(tmp_path, 30.0)
    data = tmp_path / "data"
    assert main(["dataset", str(scenario), "--seeds", "0-2", "--out", str(data), "--workers", "1",
                 "--tau", "4", "--tau-g", "2"]) == 0
    meta = json.loads((data / "dataset.json").read_text())
    assert meta["splits"] == {"train": [0], "validation": [1], "test": [2]}
    assert meta["lanechange_end_after_mid_s"] == load_scenario(scenario).simulation.lanechange_duration_s / 2
    assert meta["counts"]["window_positive"] > 100 and meta["counts"]["window_negative"] > 100
    samples = pd.read_parquet(data / "runs" / "seed_0000" / "samples.parquet")
    for col in ["seed", "time", "vehicle_id", "event_id", "time_to_lc", "window_label", "stream_label", *FEATURE_NAMES]:
        assert col in samples
    assert (data / "README.md").read_text().count("window_label") >= 1
    # labels agree with the run's lane changes: a positive is within tau of its event's end
    lc = pd.read_parquet(data / "runs" / "seed_0000" / "lane_changes.parquet").set_index("event_id")
    pos = samples[samples["window_label"] == 1]
    ends = lc.loc[pos["event_id"], "end_time"].to_numpy()
    ok = ~np.isnan(ends)
    assert np.all((ends[ok] - pos["time"].to_numpy()[ok] < 4.0 + 1e-6) & (ends[ok] >= pos["time"].to_numpy()[ok] - 1e-6))

    # a feature change (names, or meaning: a folder from before the samples version): refused without
    # --refeature, also by training; with it, samples recomputed from the twins tables
    meta["feature_names"] = meta["feature_names"][:-1]
    assert meta.pop("samples_version") == SAMPLES_VERSION
    (data / "dataset.json").write_text(json.dumps(meta))
    assert main(["train", str(data), "--out", str(tmp_path / "stale.npz")]) == 2
    assert "samples_version: 1" in capsys.readouterr().err and not (tmp_path / "stale.npz").exists()
    (data / "runs" / "seed_0001" / "samples.parquet").unlink()
    capsys.readouterr()
    assert main(["dataset", str(scenario), "--seeds", "0-2", "--out", str(data), "--workers", "1",
                 "--tau", "4", "--tau-g", "2"]) == 2
    assert "--refeature" in capsys.readouterr().err
    assert main(["dataset", str(scenario), "--seeds", "0-2", "--out", str(data), "--workers", "1",
                 "--tau", "4", "--tau-g", "2", "--refeature"]) == 0
    assert "recomputed the features of 3 existing runs" in capsys.readouterr().out
    assert json.loads((data / "dataset.json").read_text())["feature_names"] == list(FEATURE_NAMES)
    assert json.loads((data / "dataset.json").read_text())["samples_version"] == SAMPLES_VERSION
    pd.testing.assert_frame_equal(pd.read_parquet(data / "runs" / "seed_0000" / "samples.parquet"), samples)
    assert (data / "runs" / "seed_0001" / "samples.parquet").is_file()
    # the scenario edited: refused before anything is written (dataset.json lost its splits, and with
    # --refeature every run's samples were recomputed with the edited scenario, before the refusal)
    kept = {p: p.read_bytes() for p in [data / "dataset.json", *data.glob("runs/*/samples.parquet")]}
    (tmp_path / "edited").mkdir()
    edited = _short_dense(tmp_path / "edited", 31.0)
    for extra in ([], ["--refeature"]):
        assert main(["dataset", str(edited), "--seeds", "0-2", "--out", str(data), "--workers", "1",
                     "--tau", "4", "--tau-g", "2", *extra]) == 2
        assert "holds a run that is not this scenario's run of seed 0" in capsys.readouterr().err
        assert {p: p.read_bytes() for p in kept} == kept

    model_file = tmp_path / "m.npz"
    assert main(["train", str(data), "--out", str(model_file), "--epochs", "3", "--hidden", "16"]) == 0
    model = load_model(model_file)
    assert model.tau == 4.0 and model.tau_g == 2.0 and model.info["fit"]["epochs_run"] <= 3
    assert model.calibration != (1.0, 0.0)  # Platt scaling fitted on the validation stream
    assert main(["evaluate", str(model_file), str(data), "--out", str(tmp_path / "eval")]) == 0
    report = (tmp_path / "eval" / "report.md").read_text()
    for needle in ("MLP | aggressive", "MLP | conservative", "logistic regression | original", "gap/speed rule",
                   "ROC AUC", "false alarms / veh-h"):
        assert needle in report
    assert (tmp_path / "eval" / "evaluation.png").stat().st_size > 10_000
    metrics = pd.read_csv(tmp_path / "eval" / "metrics.csv")
    assert len(metrics) == 9 and metrics["lane_changes"].iloc[0] > 10
    # a seed added to the folder: the seeds already there stay in the dataset (its index listed the
    # command's seeds only, and training then found no validation seed)
    assert main(["dataset", str(scenario), "--seeds", "3", "--out", str(data), "--workers", "1",
                 "--tau", "4", "--tau-g", "2"]) == 0
    meta = json.loads((data / "dataset.json").read_text())
    assert sorted(sum(meta["splits"].values(), [])) == [0, 1, 2, 3] and meta["counts"]["seeds"] == 4


@pytest.mark.slow
def test_cloud_predictor_matches_dataset_path(tmp_path):
    """lc_prob logged by the tick loop == the model applied to features rebuilt from the twins table."""
    path = _short_dense(tmp_path, 20.0, enabled=True, smoothing="aggressive", tau_a_ticks=5, threshold=0.5)
    scenario = load_scenario(path)
    # noisy channel so that loss/latency/jitter are part of what must match
    result = execute_run(scenario, 4, tmp_path / "run")
    twins = pd.read_parquet(tmp_path / "run" / "twins.parquet")
    vehicles = pd.read_parquet(tmp_path / "run" / "vehicles.parquet")
    assert {"lc_prob", "lc_decision"} <= set(twins.columns)
    feats = features_from_twins_table(twins, vehicles, read_road(scenario.network), scenario.v2c.period_s)
    merged = twins[["time", "vehicle_id", "lc_prob", "lc_decision"]].merge(feats, on=["time", "vehicle_id"], validate="one_to_one")
    model = load_model()  # the shipped default, MLP or GRU: run offline along each twin's track
    stream = merged.assign(seed=0).sort_values(["vehicle_id", "time"], kind="stable")
    prob = pd.Series(model.stream_proba(stream.reset_index(drop=True), list(model.feature_names)),
                     index=stream.index).reindex(merged.index).to_numpy()
    np.testing.assert_allclose(prob, merged["lc_prob"].to_numpy(), atol=1e-5)
    assert merged["lc_prob"].std() > 0.01
    for _, g in merged.sort_values("time").groupby("vehicle_id"):
        expected = smooth((g["lc_prob"].to_numpy() > 0.5).astype(int), "aggressive", tau_a=5)
        np.testing.assert_array_equal(g["lc_decision"].to_numpy(), expected)
    assert result.summary["v2c_reports_lost"] > 0


@pytest.mark.slow
def test_accident_run_reports_cloud_flags(tmp_path):
    scenario = load_scenario(REPO / "scenarios" / "accident.yaml")
    result = execute_run(scenario, 0, tmp_path / "run")
    twins = pd.read_parquet(tmp_path / "run" / "twins.parquet")
    assert twins["lc_prob"].between(0, 1).all() and set(twins["lc_decision"].unique()) <= {0, 1}
    # The driver model's draw reaches the summary of every run, however the run is started.
    assert result.summary["driver"]["guidance_enabled"] is True
    flags = result.summary["lane_change_flags"]
    into = result.tables["lane_changes"]
    assert len(flags) == int(into["into_ego_lane"].sum()) > 0
    for f in flags:
        assert {"final_run_before_end_s", "first_before_end_s", "final_run_before_mid_s", "ahead_of_ego"} <= set(f)
        if f["first_before_end_s"] is not None:
            assert f["first_before_end_s"] >= f["final_run_before_end_s"] >= 0


def _short_onramp(tmp_path: Path, seconds: float) -> Path:
    raw = yaml.safe_load((REPO / "scenarios" / "onramp.yaml").read_text())
    raw["network"] = str(REPO / "sumo_net" / "onramp.net.xml")
    raw["vehicle_types"] = str(REPO / "sumo_net" / "vtypes.add.xml")
    raw["simulation"]["max_time_s"] = seconds
    path = tmp_path / "onramp_short.yaml"
    path.write_text(yaml.safe_dump(raw))
    return path


@pytest.mark.slow
def test_gru_on_two_families_end_to_end(tmp_path):
    """Two tiny family datasets -> GRU trained on both (1 epoch) -> evaluation.json -> the cloud
    predictor runs the GRU in a real SUMO run, and its per-tick probabilities equal the model run
    offline over the logged twins table (per-twin states carried tick by tick == whole tracks)."""
    from vcfusion.prediction.features import SEQUENCE_EXTRA_NAMES

    data = {}
    for name, scenario in (("dense", _short_dense(tmp_path, 20.0)), ("onramp", _short_onramp(tmp_path, 20.0))):
        data[name] = tmp_path / name
        assert main(["dataset", str(scenario), "--seeds", "0-2", "--out", str(data[name]), "--workers", "1"]) == 0
    onramp_samples = pd.read_parquet(data["onramp"] / "runs" / "seed_0000" / "samples.parquet")
    assert onramp_samples["lane_end_ahead_m"].min() < 250.0  # the acceleration lane ends ahead of its vehicles
    model_file = tmp_path / "gru.npz"
    # the model records the folders as named (a link is not followed to a machine's own disk layout:
    # shipped weights carry these paths)
    link = tmp_path / "onramp-link"
    link.symlink_to(data["onramp"])
    assert main(["train", str(data["dense"]), str(link), "--kind", "gru", "--epochs", "1",
                 "--hidden", "8", "--out", str(model_file)]) == 0
    model = load_model(model_file)
    assert model.kind == "gru" and model.feature_names == (*FEATURE_NAMES, *SEQUENCE_EXTRA_NAMES)
    assert model.info["datasets"] == [str(data["dense"]), str(link)] and model.info["fit"]["epochs_run"] == 1
    assert main(["evaluate", str(model_file), str(data["onramp"]), "--out", str(tmp_path / "eval"),
                 "--no-baselines"]) == 0
    summary = json.loads((tmp_path / "eval" / "evaluation.json").read_text())
    assert summary["default"]["predictor"] == "GRU" and summary["lane_changes"] > 5
    assert 0.0 <= summary["default"]["predicted"] <= 1.0 and summary["baselines"]["fitted"] is False

    path = _short_dense(tmp_path, 15.0, enabled=True, model=str(model_file))
    scenario = load_scenario(path)
    execute_run(scenario, 4, tmp_path / "run")
    twins = pd.read_parquet(tmp_path / "run" / "twins.parquet")
    vehicles = pd.read_parquet(tmp_path / "run" / "vehicles.parquet")
    feats = features_from_twins_table(twins, vehicles, read_road(scenario.network), scenario.v2c.period_s)
    merged = twins[["time", "vehicle_id", "lc_prob"]].merge(feats, on=["time", "vehicle_id"], validate="one_to_one")
    stream = merged.assign(seed=0).sort_values(["vehicle_id", "time"], kind="stable").reset_index(drop=True)
    offline = model.stream_proba(stream, list(model.feature_names))
    np.testing.assert_allclose(offline, stream["lc_prob"].to_numpy(), atol=1e-5)
    assert stream["lc_prob"].std() > 1e-3


def test_a_dataset_without_a_lane_change_is_refused_for_training_in_one_line(tmp_path, capsys):
    # one lane driven, every car at its desired speed: no lane change in any seed. Training crashed
    # (MLP: load_state_dict(None); GRU: "calibration needs both classes"), and so did evaluate's baselines
    path = tmp_path / "nolc.yaml"
    path.write_text(f"""
name: nolc
network: {(REPO / "sumo_net" / "highway.net.xml").as_posix()}
vehicle_types: {(REPO / "sumo_net" / "vtypes.add.xml").as_posix()}
simulation: {{step_s: 0.1, max_time_s: 15}}
vehicles:
  - {{name: cars, count: 6, lanes: [0], pos_m: [10, 1200], speed_mps: 15, desired_speed_mps: 15, min_spacing_m: 100}}
""")
    data = tmp_path / "ds"
    assert main(["dataset", str(path), "--seeds", "0-2", "--out", str(data), "--workers", "1"]) == 0
    assert json.loads((data / "dataset.json").read_text())["counts"]["lane_changes"] == 0
    capsys.readouterr()
    for argv in (["train", str(data), "--out", str(tmp_path / "m.npz")],
                 ["train", str(data), "--kind", "gru", "--out", str(tmp_path / "g.npz")],
                 ["evaluate", str(REPO / "src" / "vcfusion" / "assets" / "lane_change_gru.npz"), str(data),
                  "--split", "all", "--out", str(tmp_path / "ev")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "split 'train': 0 positive" in err and "training needs both" in err and len(err.splitlines()) == 1
    assert not any((tmp_path / name).exists() for name in ("m.npz", "g.npz", "ev"))
    assert main(["evaluate", str(REPO / "src" / "vcfusion" / "assets" / "lane_change_gru.npz"), str(data),
                 "--split", "all", "--no-baselines", "--out", str(tmp_path / "ev")]) == 0


def test_a_feature_constant_in_training_is_not_blown_up_on_new_traffic():
    from vcfusion.prediction.model import feature_scaling

    # `length` constant (no trucks in training): a 12 m truck was standardised with std 1e-6 to ~7e6
    x = np.array([[4.5, 10.0], [4.5, 20.0], [4.5, 30.0]], np.float32)
    mean, std = feature_scaling(x)
    assert std.tolist() == [1.0, pytest.approx(np.std([10.0, 20.0, 30.0]))]
    assert (np.array([12.0, 20.0]) - mean)[0] / std[0] == pytest.approx(7.5)
