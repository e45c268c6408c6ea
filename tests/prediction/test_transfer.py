"""Sim-to-real pieces (issue 46): availability flags and lateral inputs, frozen real-data splits,
the bootstrap interval over vehicles and the `vcfusion sim-to-real` table, on small fixtures."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vcfusion.commands import main
from vcfusion.prediction.features import (AVAILABILITY_NAMES, FEATURE_NAMES, LATERAL_NAMES, LATERAL_REFERENCE_S,
                                          SEQUENCE_INPUT_SETS, FeatureExtractor, availability_flags,
                                          features_from_twins_table, with_derived_columns)
from vcfusion.prediction.model import load_model
from vcfusion.prediction.sequence import SequenceModel, save_sequence_model
from vcfusion.prediction.sources.ngsim import NGSIM_COLUMNS
from vcfusion.prediction.transfer import bootstrap
from vcfusion.records import TwinStates
from vcfusion.traffic.network import Road

ROAD = Road("hw", (0.0, 0.0), (2000.0, 0.0), 3, 3.5, 25.0)  # y = 0 is the left edge, lanes downwards
SHIPPED_MLP = Path(__file__).resolve().parents[2] / "src" / "vcfusion" / "assets" / "lane_change_mlp.npz"


def _twins(lane, s, speed, d=None, ids=None, time=1.0):
    n = len(lane)
    d = (np.asarray(lane) + 0.5) * ROAD.lane_width_m if d is None else np.asarray(d, float)
    x, y = ROAD.to_world(np.asarray(s, float), d)
    return TwinStates(time=time, ids=tuple(ids or [f"v{i}" for i in range(n)]), measured_time=np.ones(n), x=x, y=y,
                      z=np.zeros(n), heading=np.zeros(n), speed=np.asarray(speed, float), accel=np.zeros(n),
                      lane=np.asarray(lane, np.int16), length=np.full(n, 4.0), width=np.full(n, 1.8),
                      height=np.full(n, 1.5), outputs={})


def test_availability_flags_mark_missing_neighbours_not_free_lanes():
    # v0 lane 1 s=100 with a leader v1 (s=130) and nobody behind; v2 in lane 2 (leftmost) at s=200:
    # its right-lane follower is v1 (66 m); v3 off the road
    tw = _twins(lane=[1, 1, 2, -1], s=[100, 130, 200, 50], speed=[20, 20, 20, 20])
    f = FeatureExtractor(ROAD, 0.1).from_twins(tw, extras=True, availability=True)
    names = SEQUENCE_INPUT_SETS["availability"]
    assert f.shape == (4, len(names))
    flag = {n: f[:, names.index(n)] for n in AVAILABILITY_NAMES}
    col = {n: f[:, names.index(n)] for n in FEATURE_NAMES}
    # v0: own leader seen; no follower: the gap reads the free-lane sentinel, the flag says "none seen"
    assert flag["lead_found_own"][0] == 1 and flag["foll_found_own"][0] == 0 and col["gap_foll_own"][0] == 150.0
    assert flag["lead_found_left"][0] == 1  # v2 is 96 m ahead in lane 2
    assert flag["lead_found_right"][0] == 0 and flag["foll_found_right"][0] == 0  # lane 0 exists, empty
    # v2: no lane to its left (flag 0 with the lane-missing sentinel 0), a right-lane follower 66 m back
    assert flag["lead_found_left"][2] == 0 and col["gap_lead_left"][2] == 0.0
    assert flag["foll_found_right"][2] == 1 and col["gap_foll_right"][2] == pytest.approx(66.0)
    assert (f[3, [names.index(n) for n in AVAILABILITY_NAMES]] == 0).all()  # off the road: nothing observed
    # the samples path (flags derived from stored columns) gives the same flags
    frame = with_derived_columns(pd.DataFrame(f[:, :len(FEATURE_NAMES)], columns=list(FEATURE_NAMES)),
                                 AVAILABILITY_NAMES)
    np.testing.assert_array_equal(frame[list(AVAILABILITY_NAMES)].to_numpy(), availability_flags(f[:, :len(FEATURE_NAMES)]))


def test_lateral_inputs_follow_a_drift_and_say_when_a_source_has_no_lateral_position():
    """A twin drifting left at 0.4 m/s: lateral speed -> 0.4 m/s, drift -> v T (1 - exp(-t / T));
    a twin whose source has no lateral position (d_known false): flag 0, inputs 0."""
    rows = []
    for k in range(101):  # 10 s at 0.1 s
        t = k * 0.1
        for vid, s0, d0, rate, known in (("drift", 100.0, 5.25, 0.4, True), ("blind", 300.0, 5.25, 0.0, False)):
            x, y = ROAD.to_world(np.array([s0 + 25 * t]), np.array([d0 + rate * t]))
            rows.append({"time": round(t, 1), "vehicle_id": vid, "x": x[0], "y": y[0], "lane": 1, "speed": 25.0,
                         "accel": 0.0, "d_known": known})
    twins = pd.DataFrame(rows)
    vehicles = pd.DataFrame({"vehicle_id": ["drift", "blind"], "length": [4.5, 4.5]})
    f = features_from_twins_table(twins, vehicles, ROAD, 0.1)
    last = f[f["time"] == 10.0].set_index("vehicle_id")
    assert last.loc["drift", "lateral_known"] == 1
    assert last.loc["drift", "lateral_speed_mps"] == pytest.approx(0.4, rel=0.05)
    assert last.loc["drift", "lateral_drift_m"] == pytest.approx(
        0.4 * LATERAL_REFERENCE_S * (1 - np.exp(-1.0)), rel=0.05)
    blind = f[f["vehicle_id"] == "blind"]
    assert (blind[list(LATERAL_NAMES)].to_numpy() == 0).all()
    # the longitudinal features do not see the lateral position at all
    assert (f[f["vehicle_id"] == "drift"]["gap_lead_own"] == 150.0).all()


def _tiny_gru(names, seed=0, hidden=4, threshold=0.5) -> SequenceModel:
    rng = np.random.default_rng(seed)
    f = len(names)
    return SequenceModel(tuple(names), np.zeros(f), np.full(f, 10.0), rng.normal(0, 0.5, (3 * hidden, f)),
                         rng.normal(0, 0.5, (3 * hidden, hidden)), np.zeros(3 * hidden), np.zeros(3 * hidden),
                         rng.normal(0, 1.0, (1, hidden)), np.array([0.0]), tau=5.0, tau_g=2.0, period_s=0.1,
                         threshold=threshold, thresholds={"aggressive": threshold}, smoothing="aggressive",
                         tau_a_ticks=10, tau_c_ticks=10)


def test_cloud_path_equals_the_dataset_path_for_a_lateral_model():
    """The cloud's per-tick inputs of a "lateral" GRU (flags and lateral motion from the GNSS
    position) give the probabilities the offline stream gives from the logged twins table."""
    from vcfusion.prediction.cloud import LaneChangePredictor

    names = SEQUENCE_INPUT_SETS["lateral"]
    model = _tiny_gru(names)
    pred = LaneChangePredictor(model, ROAD, 0.1)
    assert pred.lateral and pred.availability
    rows, online = [], []
    for k in range(40):
        t = round(1.0 + 0.1 * k, 1)
        d = [5.25 + 0.05 * k, 1.75, 5.25]
        tw = _twins(lane=[1, 0, 1], s=[100 + 2.5 * k, 90 + 2.0 * k, 160 + 2.2 * k], speed=[25, 20, 22], d=d,
                    ids=["a", "b", "c"], time=t)
        online.append(pred(tw)["lc_prob"])
        for i, vid in enumerate(tw.ids):
            rows.append({"time": t, "vehicle_id": vid, "x": tw.x[i], "y": tw.y[i], "lane": int(tw.lane[i]),
                         "speed": tw.speed[i], "accel": 0.0})
    feats = features_from_twins_table(pd.DataFrame(rows), pd.DataFrame({"vehicle_id": ["a", "b", "c"],
                                                                        "length": [4.0] * 3}), ROAD, 0.1)
    feats = with_derived_columns(feats.assign(seed=0), names).sort_values(["seed", "vehicle_id", "time"])
    offline = model.stream_proba(feats.reset_index(drop=True), list(names))
    by_vid = pd.Series(offline, index=pd.MultiIndex.from_arrays([feats["vehicle_id"], feats["time"]]))
    for k, prob in enumerate(online):
        t = round(1.0 + 0.1 * k, 1)
        np.testing.assert_allclose(prob, [by_vid[(v, t)] for v in ("a", "b", "c")], atol=1e-5)


def test_bootstrap_interval_on_a_known_case():
    # two vehicles: A predicts its change and raises no alarm, B misses its change and raises 2 alarms
    table = pd.DataFrame({"lane_changes": [1, 1], "predicted": [1, 0], "before_mid": [1, 0],
                          "advance_sum_s": [4.0, 0.0], "false_alarms": [0, 2], "false_alarms_censored": [0, 1],
                          "hours": [1.0, 1.0], "judged_hours": [0.5, 0.5]})
    got = bootstrap(table, n_boot=2000, seed=0)
    # judged: B's one uncensored false alarm over the 1.0 judged hours of both
    assert got["false_alarms_judged_per_veh_h"]["value"] == 1.0
    assert got["predicted"]["value"] == 0.5 and got["false_alarms_per_veh_h"]["value"] == 1.0
    # resamples: AA (1/4), AB (1/2), BB (1/4): both extremes are inside the 95 % interval
    assert (got["predicted"]["low"], got["predicted"]["high"]) == (0.0, 1.0)
    assert (got["false_alarms_per_veh_h"]["low"], got["false_alarms_per_veh_h"]["high"]) == (0.0, 2.0)
    assert got["advance_s"]["value"] == 4.0 and got["advance_s"]["low"] == got["advance_s"]["high"] == 4.0
    # identical vehicles: no spread
    same = pd.concat([table.iloc[[0]]] * 5, ignore_index=True)
    b = bootstrap(same, n_boot=200, seed=1)
    assert b["predicted"]["low"] == b["predicted"]["high"] == 1.0


# ---------------------------------------------------------------- a tiny NGSIM recording

def _ngsim_vehicle(vid, front_ft, speed_ftps, lane_id, change=None, local_x=True):
    rows = []
    for k in range(0, 601):  # 60 s at 10 Hz
        t = k / 10
        x, lane = (lane_id - 0.5) * 12.0, lane_id
        if change is not None:
            ts, to = change
            u = float(np.clip((t - ts) / 4.0, 0, 1))
            x = (lane_id - 0.5) * 12.0 + (to - lane_id) * 12.0 * (1 - np.cos(np.pi * u)) / 2
            lane = to if u >= 0.5 else lane_id
        rows.append({"Vehicle_ID": vid, "Frame_ID": 1000 + k, "Total_Frames": 0, "Global_Time": 1118846980200 + 100 * k,
                     "Local_X": x if local_x else 0.0, "Local_Y": front_ft + speed_ftps * t, "Global_X": 0.0,
                     "Global_Y": 0.0, "v_Length": 15.0, "v_Width": 6.0, "v_Class": 2, "v_Vel": speed_ftps,
                     "v_Acc": 0.0, "Lane_ID": lane, "Preceding": 0, "Following": 0, "Space_Headway": 0.0,
                     "Time_Headway": 0.0})
    return rows


@pytest.fixture(scope="module")
def tiny_recording(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny")
    rows = []
    for i in range(12):  # 12 vehicles, 6 of them change lanes (every other one); vehicle 11 has no Local_X
        lane = 1 + i % 5
        change = (10.0 + 3 * i, lane + (1 if lane < 5 else -1)) if i % 2 == 0 else None
        rows += _ngsim_vehicle(i + 1, 60.0 * i, 45.0 + i, lane, change, local_x=i != 11)
    csv = root / "ngsim.csv"
    pd.DataFrame(rows)[list(NGSIM_COLUMNS)].to_csv(csv, index=False)
    data = root / "rec"
    assert main(["dataset", "--from-ngsim", str(csv), "--out", str(data)]) == 0
    return root, data


def test_frozen_split_by_vehicle_and_the_sim_to_real_table(tiny_recording, tmp_path):
    _, data = tiny_recording
    # the import says which vehicle had no lateral position: its lateral inputs are flagged unknown
    rec = pd.concat([pd.read_parquet(f) for f in sorted((data / "runs").glob("seed_*/samples.parquet"))])
    assert (rec.loc[rec["vehicle_id"] == "12", "lateral_known"] == 0).all()
    assert (rec.loc[rec["vehicle_id"] == "12", ["lateral_speed_mps", "lateral_drift_m"]].to_numpy() == 0).all()
    assert (rec.loc[rec["vehicle_id"] == "1", "lateral_known"] == 1).all()
    split = tmp_path / "split.json"
    assert main(["real-split", "freeze", str(data), "--by", "vehicle", "--out", str(split), "--seed", "3"]) == 0
    frozen = json.loads(split.read_text())
    parts = frozen["parts"]
    units = [u for p in parts.values() for u in p]
    assert sorted(units, key=int) == [str(i) for i in range(1, 13)] and len(set(units)) == 12  # whole vehicles, once
    assert all(frozen["counts"][p]["lane_changes"] >= 1 for p in parts)  # each part has changes to score
    assert "default_rng(3)" in frozen["rule"] and "/" not in "".join(frozen["source"]["files"])
    # drawing again gives the same split; refusing to overwrite a frozen one
    again = tmp_path / "again.json"
    assert main(["real-split", "freeze", str(data), "--by", "vehicle", "--out", str(again), "--seed", "3"]) == 0
    assert json.loads(again.read_text())["parts"] == parts
    assert main(["real-split", "freeze", str(data), "--by", "vehicle", "--out", str(split)]) == 2

    ds = tmp_path / "split-ds"
    assert main(["real-split", "apply", str(data), str(split), "--out", str(ds)]) == 0
    meta = json.loads((ds / "dataset.json").read_text())
    samples = pd.concat([pd.read_parquet(f) for f in sorted((ds / "runs").glob("seed_*/samples.parquet"))])
    test_seeds = meta["splits"]["test"]
    held = set(samples.loc[samples["seed"].isin(test_seeds), "vehicle_id"])
    assert held == set(parts["held_out"])

    # a split that misses a vehicle of the dataset is refused before anything is written
    bad = dict(frozen, parts={**parts, "held_out": parts["held_out"][1:]})
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    assert main(["real-split", "apply", str(data), str(tmp_path / "bad.json"), "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()

    gru = tmp_path / "gru.npz"
    save_sequence_model(_tiny_gru(SEQUENCE_INPUT_SETS["lateral"], threshold=0.3), gru)
    out = tmp_path / "table"
    assert main(["sim-to-real", "--model", f"tiny GRU={gru}", "--model", f"MLP={SHIPPED_MLP}",
                 "--eval", f"held-out={ds}:test", "--eval", f"every vehicle={data}:all", "--out", str(out),
                 "--bootstrap", "100"]) == 0
    table = pd.read_csv(out / "sim_to_real.csv")
    assert len(table) == 4 and "tiny GRU" in (out / "sim_to_real.md").read_text()
    assert "judged false alarms / veh-h" in (out / "sim_to_real.md").read_text()
    assert "false_alarms_judged_per_veh_h_low" in table.columns
    row = table[(table["model"] == "MLP") & (table["eval"] == "every vehicle")].iloc[0]
    assert row["vehicles"] == 12 and row["lane_changes"] == 6
    held_row = table[(table["model"] == "MLP") & (table["eval"] == "held-out")].iloc[0]
    assert held_row["lane_changes"] == frozen["counts"]["held_out"]["lane_changes"]
    # the point values are `vcfusion evaluate`'s default variant on the same vehicles
    for model, label in ((SHIPPED_MLP, "MLP"), (gru, "tiny GRU")):
        ev = tmp_path / f"eval-{label}"
        assert main(["evaluate", str(model), str(data), "--split", "all", "--no-baselines", "--out", str(ev)]) == 0
        default = json.loads((ev / "evaluation.json").read_text())["default"]
        r = table[(table["model"] == label) & (table["eval"] == "every vehicle")].iloc[0]
        assert r["predicted"] == pytest.approx(default["predicted"])
        assert r["false_alarms_per_veh_h"] == pytest.approx(default["false_alarms_per_veh_h"])
        if default["predicted"]:
            assert r["advance_s"] == pytest.approx(default["advance_final_mean_s"])
        assert r["predicted_low"] <= r["predicted"] <= r["predicted_high"]

    # re-tuning on the split's validation part with the judged (censoring-aware) rate: recorded in the file
    rt = tmp_path / "gru-judged.npz"
    assert main(["retune", str(gru), str(ds), "--out", str(rt), "--false-alarm-rate", "judged"]) == 0
    info = load_model(rt).info["retuned"]
    assert info["false_alarm_rate"] == "judged"
    assert info["tuning"]["aggressive"]["validation"]["judged_vehicle_hours"] > 0


def test_an_ensemble_file_scores_in_evaluate_and_sim_to_real(tiny_recording, tmp_path):
    """`vcfusion ensemble-models` output is read as a model file by the scoring commands, and the
    figures are the ensemble's (not a member's)."""
    _, data = tiny_recording
    members = [save_sequence_model(_tiny_gru(SEQUENCE_INPUT_SETS["lateral"], seed=s, threshold=0.3),
                                   tmp_path / f"g{s}.npz") for s in (0, 1)]
    ens = tmp_path / "ens.npz"
    assert main(["ensemble-models", *map(str, members), "--out", str(ens)]) == 0
    out = tmp_path / "table"
    assert main(["sim-to-real", "--model", f"ensemble={ens}", "--eval", f"every vehicle={data}:all", "--out", str(out),
                 "--bootstrap", "20"]) == 0
    row = pd.read_csv(out / "sim_to_real.csv").iloc[0]
    ev = tmp_path / "ev"
    assert main(["evaluate", str(ens), str(data), "--split", "all", "--no-baselines", "--out", str(ev)]) == 0
    report = json.loads((ev / "evaluation.json").read_text())
    assert row["false_alarms_per_veh_h"] == pytest.approx(report["default"]["false_alarms_per_veh_h"])
    assert "GRU ensemble of 2" in json.dumps(report)
    from vcfusion.prediction.dataset import load_dataset
    from vcfusion.prediction.features import stored_columns, with_derived_columns
    from vcfusion.prediction.train import stream_with_events

    names = list(SEQUENCE_INPUT_SETS["lateral"])
    stream, _ = stream_with_events(load_dataset(data), "all", columns=["seed", "vehicle_id", "time",
                                                                        *stored_columns(names)])
    with_derived_columns(stream, names, 0.1)
    p0, p1 = (load_model(m).stream_proba(stream, names) for m in members)
    assert np.abs(p0 - p1).max() > 0.05
    np.testing.assert_allclose(load_model(ens).stream_proba(stream, names), (p0 + p1) / 2, atol=1e-6)
