"""Lateral motion over the vehicle's own lane-keeping sway (SWAY_NAMES, the "sway" input set):
the value on hand-made histories, causality, the floor and the cap, the availability flag, and the
same values from the cloud's per-tick path and from a dataset's samples."""

import numpy as np
import pandas as pd
import pytest

from vcfusion.prediction.features import (LATERAL_NAMES, SEQUENCE_INPUT_SETS, SWAY_DRIFT_FLOOR_M, SWAY_MIN_HISTORY_S,
                                          SWAY_NAMES, SWAY_SPEED_FLOOR_MPS, SWAY_WARMUP_S, SWAY_WINDOW_S,
                                          FeatureExtractor, features_from_twins_table, stored_columns,
                                          with_derived_columns)
from vcfusion.records import TwinStates
from vcfusion.traffic.network import Road

ROAD = Road("hw", (0.0, 0.0), (2000.0, 0.0), 3, 3.5, 25.0)
PERIOD = 0.1
WARMUP = round(SWAY_WARMUP_S / PERIOD)  # ticks of known lateral position kept out of the scale
FIRST = WARMUP + round(SWAY_MIN_HISTORY_S / PERIOD)  # first tick with sway_known = 1


def _cloud(v, drift, known=None, ids=("a",)):
    """SWAY_NAMES of one twin fed tick by tick through FeatureExtractor.sway (the cloud's path)."""
    ex = FeatureExtractor(ROAD, PERIOD)
    known = np.ones(len(v)) if known is None else np.asarray(known, float)
    rows = [ex.sway(ids, round(k * PERIOD, 1), np.array([[known[k], v[k], drift[k]]]))[0] for k in range(len(v))]
    return np.array(rows)


def _weighted_rms(x):
    """RMS of x under the exponential weights of the window, the newest value weighted most."""
    a = 1 - np.exp(-PERIOD / SWAY_WINDOW_S)
    w = a * (1 - a) ** np.arange(len(x))[::-1]
    return np.sqrt(np.sum(w * np.asarray(x) ** 2) / np.sum(w))


def test_known_answer_on_a_hand_made_history():
    n = FIRST + 10
    rng = np.random.default_rng(0)
    v = rng.uniform(-0.3, 0.3, n)
    drift = rng.uniform(-0.8, 0.8, n)
    out = _cloud(v, drift)
    # no value before the history is long enough: flag 0 and zeros
    assert (out[:FIRST] == 0).all()
    assert (out[FIRST:, 0] == 1).all()
    for k in (FIRST, n - 1):
        hist_v = v[WARMUP:k].astype(np.float32).astype(float)  # the ticks before k, after the warm-up
        hist_d = drift[WARMUP:k].astype(np.float32).astype(float)
        assert out[k, 1] == pytest.approx(np.float32(v[k]) / max(_weighted_rms(hist_v), SWAY_SPEED_FLOOR_MPS), rel=1e-9)
        assert out[k, 2] == pytest.approx(np.float32(drift[k]) / max(_weighted_rms(hist_d), SWAY_DRIFT_FLOOR_M),
                                          rel=1e-9)
    # a steady sway of 0.2 m/s and 0.5 m: a 0.6 m/s, 1.5 m tick reads 3 and 3
    steady = _cloud(np.r_[np.full(FIRST, 0.2), 0.6], np.r_[np.full(FIRST, 0.5), 1.5])
    assert steady[-1] == pytest.approx([1.0, 3.0, 3.0], rel=1e-6)


def test_causal_the_current_and_later_ticks_do_not_enter_the_scale():
    n = FIRST + 30
    rng = np.random.default_rng(1)
    v, drift = rng.normal(0, 0.2, n), rng.normal(0, 0.5, n)
    base = _cloud(v, drift)
    k = FIRST + 5
    later_v, later_d = v.copy(), drift.copy()
    later_v[k + 1:] *= 7.0  # a change after tick k
    later_d[k + 1:] += 3.0
    np.testing.assert_array_equal(_cloud(later_v, later_d)[:k + 1], base[:k + 1])
    # the current tick is divided by the scale of the ticks before it: doubling it doubles the value
    now_v = v.copy()
    now_v[k] *= 2.0
    assert _cloud(now_v, drift)[k, 1] == pytest.approx(2 * base[k, 1], rel=1e-6)


def test_floor_cap_and_restart():
    # a steady vehicle (no sway at all): the floor, not a division by zero
    out = _cloud(np.r_[np.zeros(FIRST), 0.05], np.r_[np.zeros(FIRST), 0.05])
    assert out[-1] == pytest.approx([1.0, 0.05 / SWAY_SPEED_FLOOR_MPS, 0.05 / SWAY_DRIFT_FLOOR_M])
    # a history of 2 m/s counts as 0.5 m/s (the cap): one change cannot inflate the scale
    out = _cloud(np.r_[np.full(FIRST, 2.0), 1.0], np.zeros(FIRST + 1))
    assert out[-1, 1] == pytest.approx(1.0 / 0.5)
    # the lateral position unknown for a tick: the history starts again
    known = np.ones(2 * FIRST)
    known[FIRST + 3] = 0
    out = _cloud(np.full(2 * FIRST, 0.2), np.full(2 * FIRST, 0.5), known)
    assert out[FIRST + 2, 0] == 1 and (out[FIRST + 3: 2 * FIRST, 0] == 0).all()


def _twins(ids, s, d, time):
    n = len(ids)
    x, y = ROAD.to_world(np.asarray(s, float), np.asarray(d, float))
    return TwinStates(time=time, ids=tuple(ids), measured_time=np.ones(n), x=x, y=y, z=np.zeros(n),
                      heading=np.zeros(n), speed=np.full(n, 25.0), accel=np.zeros(n), lane=np.ones(n, np.int16),
                      length=np.full(n, 4.0), width=np.full(n, 1.8), height=np.full(n, 1.5), outputs={})


def test_cloud_and_samples_paths_give_the_same_values():
    """The cloud's FeatureExtractor on successive snapshots and the samples a dataset stores (the
    twins table replayed, float32 columns, in any row order) give identical SWAY_NAMES, with a twin
    that appears late, one missing from one snapshot and a tick without any twin."""
    ex = FeatureExtractor(ROAD, PERIOD)
    rng = np.random.default_rng(2)
    names = SEQUENCE_INPUT_SETS["sway"]
    online, rows = {}, []
    for k in range(110):
        t = round(1.0 + PERIOD * k, 1)
        if k == 60:  # no twin reported this tick: the cloud is not called, the replay has no rows
            continue
        ids = ["a", "b"] + (["c"] if k >= 20 else [])
        if k == 45:
            ids.remove("b")  # b missing from one snapshot: its memory starts again
        d = [5.25 + 0.3 * np.sin(0.4 * k) + rng.normal(0, 0.02) for _ in ids]
        tw = _twins(ids, [100 + 2.5 * k + 30 * j for j in range(len(ids))], d, t)
        f = ex.from_twins(tw, extras=True, sway=True)
        assert f.shape == (len(ids), len(names))
        for i, vid in enumerate(ids):
            online[(vid, t)] = f[i, -len(SWAY_NAMES):]
            rows.append({"time": t, "vehicle_id": vid, "x": tw.x[i], "y": tw.y[i], "lane": 1, "speed": 25.0,
                         "accel": 0.0})
    feats = features_from_twins_table(pd.DataFrame(rows), pd.DataFrame({"vehicle_id": ["a", "b", "c"],
                                                                        "length": [4.0] * 3}), ROAD, PERIOD)
    samples = feats[["time", "vehicle_id", *LATERAL_NAMES]].assign(seed=3)
    for name in LATERAL_NAMES:  # what build_samples stores
        samples[name] = samples[name].astype(np.float32)
    samples = samples.sample(frac=1.0, random_state=0).reset_index(drop=True)  # any row order
    assert set(stored_columns(names)) >= set(LATERAL_NAMES) and not set(SWAY_NAMES) & set(stored_columns(names))
    with_derived_columns(samples, SWAY_NAMES, PERIOD)
    offline = {(v, t): row for v, t, row in zip(samples["vehicle_id"], samples["time"],
                                                 samples[list(SWAY_NAMES)].to_numpy(np.float64))}
    assert offline.keys() == online.keys()
    for key, value in online.items():
        np.testing.assert_array_equal(offline[key], value.astype(np.float32), err_msg=str(key))
    known = {key: value[0] for key, value in online.items()}
    assert known[("a", round(1.0 + PERIOD * FIRST, 1))] == 1
    assert known[("b", 5.6)] == 0  # b starts again after its missing snapshot (t = 5.5)
    assert known[("a", 7.1)] == 0  # the empty tick (t = 7.0): a gap of two periods starts again
    assert known[("a", round(7.1 + PERIOD * FIRST, 1))] == 1


def test_the_period_is_required():
    frame = pd.DataFrame({"seed": [0], "vehicle_id": ["a"], "time": [0.0], "lateral_known": [1.0],
                          "lateral_speed_mps": [0.0], "lateral_drift_m": [0.0]})
    with pytest.raises(ValueError, match="period"):
        with_derived_columns(frame, SWAY_NAMES)
    with pytest.raises(ValueError, match="lateral_drift_m"):
        with_derived_columns(frame.drop(columns="lateral_drift_m"), SWAY_NAMES, PERIOD)


def test_a_sway_model_in_the_cloud_gives_the_offline_probabilities():
    """A "sway" GRU run by the cloud's predictor tick by tick gives the probabilities of the offline
    stream built from the logged twins table (inputs derived when read)."""
    from vcfusion.prediction.cloud import LaneChangePredictor
    from vcfusion.prediction.sequence import SequenceModel

    names = SEQUENCE_INPUT_SETS["sway"]
    rng = np.random.default_rng(0)
    f, h = len(names), 4
    model = SequenceModel(tuple(names), np.zeros(f), np.full(f, 10.0), rng.normal(0, 0.5, (3 * h, f)),
                          rng.normal(0, 0.5, (3 * h, h)), np.zeros(3 * h), np.zeros(3 * h), rng.normal(0, 1.0, (1, h)),
                          np.array([0.0]), tau=5.0, tau_g=2.0, period_s=PERIOD, threshold=0.5,
                          thresholds={"aggressive": 0.5}, smoothing="aggressive", tau_a_ticks=10, tau_c_ticks=10)
    model.w_ih[:, names.index("lateral_speed_over_sway")] *= 20  # the input matters
    pred = LaneChangePredictor(model, ROAD, PERIOD)
    assert pred.sway and pred.lateral and pred.availability
    online, rows = {}, []
    for k in range(70):
        t = round(1.0 + PERIOD * k, 1)
        ids = ["a", "b"]
        d = [5.25 + 0.2 * np.sin(0.5 * k), 5.25 + (0.05 * (k - 50) if k > 50 else 0.0)]
        tw = _twins(ids, [100 + 2.5 * k, 160 + 2.5 * k], d, t)
        for vid, p in zip(ids, pred(tw)["lc_prob"]):
            online[(vid, t)] = p
        rows += [{"time": t, "vehicle_id": v, "x": tw.x[i], "y": tw.y[i], "lane": 1, "speed": 25.0, "accel": 0.0}
                 for i, v in enumerate(ids)]
    feats = features_from_twins_table(pd.DataFrame(rows), pd.DataFrame({"vehicle_id": ["a", "b"], "length": [4.0] * 2}),
                                      ROAD, PERIOD)
    feats = with_derived_columns(feats.assign(seed=0), names, PERIOD).sort_values(["seed", "vehicle_id", "time"])
    assert feats["sway_known"].max() == 1 and feats["lateral_speed_over_sway"].abs().max() > 1
    offline = model.stream_proba(feats.reset_index(drop=True), list(names))
    for (vid, t), p in zip(zip(feats["vehicle_id"], feats["time"]), offline):
        assert online[(vid, t)] == pytest.approx(p, abs=1e-5)


def test_a_lateral_gru_extended_with_the_sway_inputs_keeps_its_probabilities():
    from vcfusion.prediction.sequence import SequenceModel
    from vcfusion.prediction.train_sequence import extend_inputs

    lateral, sway = SEQUENCE_INPUT_SETS["lateral"], SEQUENCE_INPUT_SETS["sway"]
    rng = np.random.default_rng(3)
    f, h = len(lateral), 4
    model = SequenceModel(tuple(lateral), rng.normal(0, 1, f), np.full(f, 2.0), rng.normal(0, 0.5, (3 * h, f)),
                          rng.normal(0, 0.5, (3 * h, h)), np.zeros(3 * h), np.zeros(3 * h), rng.normal(0, 1.0, (1, h)),
                          np.array([0.0]), tau=5.0, tau_g=2.0, period_s=PERIOD)
    wide = extend_inputs(model, sway, [0.5, 0.0, 0.0], [0.5, 1.0, 1.0])
    assert wide.feature_names == sway and wide.w_ih.shape == (3 * h, len(sway))
    x = rng.normal(0, 1, (30, len(sway))).astype(np.float32)
    np.testing.assert_allclose(wide.sequence_logits(x, [(0, 30)]), model.sequence_logits(x[:, :f], [(0, 30)]),
                               rtol=0, atol=1e-5)  # float32 sums in another order
    assert model.w_ih.shape == (3 * h, f)  # the original is not changed
    with pytest.raises(ValueError, match="model's"):
        extend_inputs(model, sway[1:], [0.0] * 3, [1.0] * 3)
    with pytest.raises(ValueError, match="std > 0"):
        extend_inputs(model, sway, [0.0] * 3, [1.0, 0.0, 1.0])
