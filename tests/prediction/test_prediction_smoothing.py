import numpy as np
import pytest

from vcfusion.prediction.smoothing import StreamingSmoother, aggressive, conservative

# Paper Table I: timesteps 1..8.
TABLE_I_ORIGINAL = [0, 0, 0, 1, 0, 0, 0, 1]
TABLE_I_AGGRESSIVE = [0, 0, 0, 1, 1, 1, 1, 1]
TABLE_I_CONSERVATIVE = [0, 0, 0, 0, 0, 0, 0, 0]


def test_table_i_exact():
    assert aggressive(np.array(TABLE_I_ORIGINAL), tau_a=3).tolist() == TABLE_I_AGGRESSIVE
    assert conservative(np.array(TABLE_I_ORIGINAL), tau_c=3, threshold=0.5).tolist() == TABLE_I_CONSERVATIVE


def test_aggressive_clips_at_end_and_keeps_length():
    assert aggressive([0, 1, 0, 0, 0, 0], 2).tolist() == [0, 1, 1, 1, 0, 0]
    assert aggressive([0, 0, 0, 0, 1], 3).tolist() == [0, 0, 0, 0, 1]
    assert aggressive([1, 0, 0], 0).tolist() == [1, 0, 0]
    assert aggressive([0, 1], 30).tolist() == [0, 1]  # tau_a longer than the track
    assert aggressive([], 3).tolist() == []


def test_conservative_threshold_is_strict_and_first_steps_padded_with_zeros():
    # tau_c = 3: window of 4; two positives = 0.5 is not > 0.5; three are.
    assert conservative([1, 1, 0, 0, 1, 1, 1, 0], 3).tolist() == [0, 0, 0, 0, 0, 0, 1, 1]
    # first steps: missing history counts as 0 with denominator 4 -> 1,1,1 at start gives 0,0,1 (3/4)
    assert conservative([1, 1, 1], 3).tolist() == [0, 0, 1]
    assert conservative([1, 1, 1], 3, threshold=0.4).tolist() == [0, 1, 1]


def test_bad_input():
    with pytest.raises(ValueError, match="0 or 1"):
        aggressive([0, 2], 1)
    with pytest.raises(ValueError, match="1-D"):
        conservative(np.zeros((2, 2)), 1)


@pytest.mark.parametrize("method,kw", [("aggressive", {"tau_a": 3}), ("aggressive", {"tau_a": 0}),
                                       ("conservative", {"tau_c": 3}), ("conservative", {"tau_c": 5, "threshold": 0.3}),
                                       ("conservative", {"tau_c": 0}), ("none", {})])
def test_streaming_equals_batch(method, kw):
    rng = np.random.default_rng(0)
    # three twins that appear and disappear at different ticks
    spans = {"a": (0, 200), "b": (30, 120), "c": (100, 200)}
    raw = {vid: (rng.random(hi - lo) < 0.3).astype(np.int8) for vid, (lo, hi) in spans.items()}
    streamed = {vid: [] for vid in spans}
    smoother = StreamingSmoother(method, **kw)
    for t in range(200):
        ids = [v for v, (lo, hi) in spans.items() if lo <= t < hi]
        dec = np.array([raw[v][t - spans[v][0]] for v in ids])
        out = smoother(ids, dec)
        for v, o in zip(ids, out):
            streamed[v].append(int(o))
    for vid in spans:
        if method == "none":
            expected = raw[vid]
        elif method == "aggressive":
            expected = aggressive(raw[vid], kw["tau_a"])
        else:
            expected = conservative(raw[vid], kw["tau_c"], kw.get("threshold", 0.5))
        assert streamed[vid] == expected.tolist()


@pytest.mark.parametrize("method,tau", [("aggressive", 4), ("conservative", 3)])
def test_offline_smoothing_restarts_where_the_cloud_forgot_the_twin(method, tau):
    """A dataset stream smoothed offline (tuning, evaluation) gives the decisions the cloud drew:
    the streaming smoother forgets a twin absent from a snapshot, so the offline smoothing starts
    that twin afresh there too; a tick without any twin (every report lost) is no snapshot: the
    cloud does not call the smoother, and the offline smoothing carries on across it."""
    import pandas as pd

    from vcfusion.prediction.events import smooth_stream, smoothing_bounds

    rng = np.random.default_rng(3)
    ticks = np.round(np.arange(80) * 0.1, 6)
    empty = {40, 41}  # every report lost: no twin at all
    present = {"a": [k for k in range(80) if k not in empty and not 20 <= k < 23],  # away 3 ticks
               "b": [k for k in range(80) if k not in empty and k != 60],  # away 1 tick
               "c": [k for k in range(10, 70) if k not in empty]}
    raw = {vid: {k: int(rng.random() < 0.35) for k in ks} for vid, ks in present.items()}
    raw["a"].update({17: 1, 18: 1, 19: 1, 23: 0, 24: 0, 25: 0})  # a warning held over the absence, offline
    kw = {"tau_a": tau} if method == "aggressive" else {"tau_c": tau}
    smoother = StreamingSmoother(method, **kw)
    cloud = {}
    for k in range(80):
        ids = [v for v in present if k in raw[v]]
        if not ids:
            continue  # LaneChangePredictor returns before the smoother
        for v, d in zip(ids, smoother(ids, np.array([raw[v][k] for v in ids], np.int8))):
            cloud[(v, k)] = int(d)
    rows = [(7, v, ticks[k], raw[v][k], cloud[(v, k)]) for v in present for k in present[v]]
    stream = pd.DataFrame(rows, columns=["seed", "vehicle_id", "time", "raw", "cloud"])
    bounds = smoothing_bounds(stream)
    assert len(bounds) == 2 + 2 + 1  # a and b are split once each where they were away; c is whole
    offline = smooth_stream(bounds, stream["raw"].to_numpy(np.int8), method, tau_a=tau, tau_c=tau)
    np.testing.assert_array_equal(offline, stream["cloud"].to_numpy())


def test_frame_metrics_are_undefined_where_there_is_nothing_to_score():
    # a split without a lane change read "accuracy 0.0, F1 0.0" (null belongs in evaluation.json)
    import math

    from vcfusion.prediction.evaluate import frame_metrics

    empty = frame_metrics(np.zeros(0), np.zeros(0), np.zeros(0))
    assert all(math.isnan(empty[k]) for k in ("accuracy", "precision", "recall", "f1", "roc_auc"))
    negatives = frame_metrics(np.zeros(4), np.array([0, 1, 0, 0]), np.array([0.1, 0.9, 0.2, 0.3]))
    assert negatives["accuracy"] == 0.75 and math.isnan(negatives["f1"]) and math.isnan(negatives["recall"])
    missed = frame_metrics(np.array([1, 0, 1]), np.zeros(3), np.array([0.2, 0.1, 0.3]))
    assert missed["f1"] == 0.0 and missed["recall"] == 0.0  # positives all missed: 0, as before
