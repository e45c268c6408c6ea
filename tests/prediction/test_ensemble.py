"""Ensembles of lane-change GRUs (vcfusion.prediction.ensemble, `vcfusion ensemble-models`): one
member equals the member, two give the mean of the two, mismatched members are refused."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from vcfusion.commands import main
from vcfusion.prediction.cloud import LaneChangePredictor
from vcfusion.prediction.ensemble import EnsembleModel, build_ensemble, check_members, save_ensemble
from vcfusion.prediction.features import SEQUENCE_INPUT_SETS
from vcfusion.prediction.model import ModelFileError, load_model, model_kind, save_model
from vcfusion.prediction.sequence import SequenceModel, SequenceState, save_sequence_model
from vcfusion.traffic.network import Road

NAMES = SEQUENCE_INPUT_SETS["lateral"]
ROAD = Road("hw", (0.0, 0.0), (2000.0, 0.0), 3, 3.5, 25.0)


def _gru(seed, names=NAMES, hidden=6, tau=5.0, threshold=0.4, scaling_seed=None) -> SequenceModel:
    """A random GRU; `scaling_seed` draws its standardisation apart (members fine-tuned from one file share it)."""
    rng = np.random.default_rng(seed)
    f = len(names)
    scaling = np.random.default_rng(seed if scaling_seed is None else scaling_seed)
    mean, std = scaling.normal(0, 1, f), scaling.uniform(0.5, 3, f)
    return SequenceModel(
        tuple(names), mean=mean, std=std,
        w_ih=rng.normal(0, 0.4, (3 * hidden, f)), w_hh=rng.normal(0, 0.4, (3 * hidden, hidden)),
        b_ih=rng.normal(0, 0.3, 3 * hidden), b_hh=rng.normal(0, 0.3, 3 * hidden),
        w_out=rng.normal(0, 1.0, (1, hidden)), b_out=rng.normal(0, 0.5, 1), tau=tau, tau_g=2.0, period_s=0.1,
        threshold=threshold, thresholds={"aggressive": threshold}, smoothing="aggressive", tau_a_ticks=7,
        calibration=(0.9, -0.2 + 0.1 * seed))


def _stream(seed=0) -> pd.DataFrame:
    """Two vehicles, one of them with a gap longer than the state-reset gap."""
    rng = np.random.default_rng(seed)
    rows = [{"seed": 0, "vehicle_id": vid, "time": round(0.1 * k, 6)}
            for vid, ticks in (("a", range(0, 50)), ("b", [*range(5, 20), *range(40, 60)])) for k in ticks]
    stream = pd.DataFrame(rows)
    for i, name in enumerate(NAMES):
        stream[name] = rng.normal(0, 1 + i % 3, len(stream)).astype(np.float32)
    return stream


def _files(tmp_path, *models):
    return [str(save_sequence_model(m, tmp_path / f"m{k}.npz")) for k, m in enumerate(models)]


def test_an_ensemble_of_one_equals_its_member(tmp_path):
    member = _gru(1)
    (a,) = _files(tmp_path, member)
    out = tmp_path / "e1.npz"
    assert main(["ensemble-models", a, "--out", str(out)]) == 0
    ens = load_model(out)
    assert isinstance(ens, EnsembleModel) and model_kind(out) == "gru" and ens.hidden == member.hidden
    assert ens.calibration == (1.0, 0.0) and ens.threshold == member.threshold and ens.tau_a_ticks == 7
    assert ens.info["ensemble"]["members"] == ["m0.npz"]
    stream = _stream()
    np.testing.assert_allclose(ens.stream_proba(stream, list(NAMES)), member.stream_proba(stream, list(NAMES)),
                               rtol=0, atol=1e-6)
    # the cloud's per-twin states: tick by tick the same probabilities as the member's
    mine, theirs = SequenceState(ens), SequenceState(member)
    for time, tick in stream.groupby("time", sort=True):
        x = tick[list(NAMES)].to_numpy(np.float32)
        np.testing.assert_allclose(mine(tick["vehicle_id"].tolist(), time, x),
                                   theirs(tick["vehicle_id"].tolist(), time, x), rtol=0, atol=1e-6)


@pytest.mark.parametrize("alike", [False, True])
def test_an_ensemble_of_two_is_the_mean_of_the_two(tmp_path, alike):
    # alike: one hidden size and standardisation, the members stepped as one batch (else one by one)
    m0, m1 = (_gru(2, scaling_seed=9), _gru(3, scaling_seed=9)) if alike else (_gru(2), _gru(3, hidden=5))
    files = _files(tmp_path, m0, m1)
    out = tmp_path / "e2.npz"
    assert main(["ensemble-models", *files, "--out", str(out)]) == 0
    ens = load_model(out)
    assert ens._stacked == alike
    stream = _stream(1)
    p0, p1 = m0.stream_proba(stream, list(NAMES)), m1.stream_proba(stream, list(NAMES))
    assert np.abs(p0 - p1).max() > 0.1  # members that differ: the mean is not either one
    expected = (p0.astype(np.float64) + p1) / 2.0
    offline = ens.stream_proba(stream, list(NAMES))
    np.testing.assert_allclose(offline, expected, rtol=0, atol=1e-6)
    # online (the cloud's states, the twins of a tick in any order) = offline
    state = SequenceState(ens)
    online = np.full(len(stream), np.nan)
    for time, tick in stream.groupby("time", sort=True):
        tick = tick.sample(frac=1.0, random_state=int(time * 10))
        online[tick.index] = state(tick["vehicle_id"].tolist(), time, tick[list(NAMES)].to_numpy(np.float32))
    np.testing.assert_allclose(online, expected, rtol=0, atol=1e-6)
    # a Platt scaling of the ensemble (vcfusion retune) applies to the logit of the mean
    ens.calibration = (2.0, 0.5)
    logit = np.log(expected) - np.log1p(-expected)
    np.testing.assert_allclose(ens.stream_proba(stream, list(NAMES)), 1 / (1 + np.exp(-(2.0 * logit + 0.5))),
                               rtol=0, atol=1e-5)


def test_the_cloud_predictor_runs_an_ensemble_and_set_decision_keeps_it(tmp_path):
    from vcfusion.prediction.bench import _twins, bench_model

    files = _files(tmp_path, _gru(4), _gru(5))
    out = tmp_path / "e.npz"
    assert main(["ensemble-models", *files, "--out", str(out)]) == 0
    preds = [LaneChangePredictor(load_model(p), ROAD, 0.1) for p in (out, *files)]
    assert preds[0].lateral and preds[0].availability
    rng = np.random.default_rng(0)
    twins = _twins(8, ROAD, rng)
    for k in range(5):
        probs = [p(twins.__class__(**{**twins.__dict__, "time": 0.1 * k}))["lc_prob"] for p in preds]
        np.testing.assert_allclose(probs[0], (probs[1] + probs[2]) / 2, rtol=0, atol=1e-6)
    lines = bench_model(out, n_twins=10, repeats=3)
    assert "GRU ensemble of 2" in lines[0] and "whole process model" in lines[-1]
    chosen = tmp_path / "e-set.npz"
    assert main(["set-decision", str(out), "--out", str(chosen), "--smoothing", "aggressive", "--threshold", "0.3",
                 "--tau-ticks", "20", "--reason", "test"]) == 0
    again = load_model(chosen)
    assert isinstance(again, EnsembleModel) and len(again.members) == 2 and again.threshold == 0.3
    assert again.info["decision_set"]["replaced"]["threshold"] == 0.4 and "ensemble" in again.info


@pytest.mark.parametrize("other, needle", [
    (lambda first: save_sequence_model(_gru(7, names=SEQUENCE_INPUT_SETS["availability"]), first.with_name("o.npz")),
     "inputs differ from"),
    (lambda first: save_sequence_model(_gru(7, tau=4.0), first.with_name("o.npz")), "label window tau, s 4.0 differs"),
    (lambda first: save_model(_mlp(), first.with_name("o.npz")), "expected a GRU file"),
    (lambda first: save_ensemble(build_ensemble([first]), first.with_name("o.npz")), "an ensemble of 1 GRUs"),
])
def test_mismatched_members_are_refused(tmp_path, capsys, other, needle):
    (first,) = _files(tmp_path, _gru(6))
    bad = other(Path(first))
    out = tmp_path / "e.npz"
    assert main(["ensemble-models", first, str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert needle in err and str(bad) in err and not out.exists()


def test_members_with_their_inputs_in_another_order_are_refused():
    with pytest.raises(ValueError, match="b.npz: inputs differ from a.npz's: the same inputs in another order"):
        check_members([_gru(6), _gru(7, names=tuple(reversed(NAMES)))], ["a.npz", "b.npz"])


def _mlp():
    from vcfusion.prediction.features import FEATURE_NAMES
    from vcfusion.prediction.model import LaneChangeModel

    rng = np.random.default_rng(0)
    f = len(FEATURE_NAMES)
    return LaneChangeModel(FEATURE_NAMES, np.zeros(f), np.ones(f),
                           [(rng.normal(0, 1, (4, f)), np.zeros(4)), (rng.normal(0, 1, (1, 4)), np.zeros(1))],
                           tau=5.0, tau_g=2.0, period_s=0.1)


def test_a_damaged_ensemble_file_names_the_member_and_field(tmp_path):
    files = _files(tmp_path, _gru(8), _gru(9))
    good = save_ensemble(build_ensemble(files), tmp_path / "e.npz")
    with np.load(good, allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
        arrays = {k: data[k] for k in data.files if k != "meta" and k != "m1_w_hh"}
    bad = tmp_path / "bad.npz"
    np.savez(bad, meta=np.array(json.dumps(meta)), **arrays)
    with pytest.raises(ModelFileError, match=r"bad.npz: members\[1\]: w_hh: missing array"):
        load_model(bad)
    from vcfusion.prediction.train_sequence import _init_model

    with pytest.raises(ModelFileError, match="--init: an ensemble of 2 GRUs"):
        _init_model(good)


def test_saturated_members_give_finite_logits_and_exact_probabilities(tmp_path):
    import dataclasses

    from vcfusion.prediction.sequence import segment_bounds

    sure = dataclasses.replace(_gru(10), w_out=np.zeros((1, 6)), b_out=np.array([80.0]))  # P = 1 in float32
    never = dataclasses.replace(_gru(11), w_out=np.zeros((1, 6)), b_out=np.array([-200.0]))  # P = 0
    stream = _stream(2)
    x, names = stream[list(NAMES)].to_numpy(np.float32), list(NAMES)
    for members, expected in (((sure,), 1.0), ((never,), 0.0), ((sure, never), 0.5)):
        ens = build_ensemble(_files(tmp_path, *members))
        logits = ens.sequence_logits(x, segment_bounds(stream, 0.1, ens.reset_gap_ticks))
        assert np.isfinite(logits).all()  # a Platt fit (vcfusion retune) can use them
        np.testing.assert_array_equal(ens.stream_proba(stream, names), np.float32(expected))
