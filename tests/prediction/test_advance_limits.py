"""Separability before the crossing and the lateral-speed estimators, on small synthetic streams."""

import numpy as np
import pandas as pd
import pytest

from vcfusion.prediction.advance import (
    ema_lateral_speed, kalman_lateral_speed, lane_keeping_mask, position_noise, separability, track_starts,
    window_auc,
)

DT = 0.1


def _stream(n_keep=20, n_change=10, seconds=30.0, seed=0):
    """Lane keepers with a N(0, 1) signal; changers whose signal is N(0, 1) until 2 s before the
    midpoint (t = 20 s) and 5 until its end (22 s); the changers move from lane 1 to lane 2 (left) at t = 20 s
    and have a larger `gap_{side}` on the left from t = 15 s."""
    rng = np.random.default_rng(seed)
    t = np.round(np.arange(0, seconds, DT), 1)
    frames, events = [], []
    for v in range(n_keep + n_change):
        changer = v >= n_keep
        sig = rng.normal(size=len(t))
        lane = np.ones(len(t))
        gap_left, gap_right = rng.uniform(0, 10, len(t)), rng.uniform(0, 10, len(t))
        if changer:
            sig[(t >= 18.0) & (t <= 22.0)] = 5.0
            lane[t >= 20.0] = 2
            gap_left[(t >= 15.0) & (t < 20.0)] = 50.0
            events.append({"seed": 0, "vehicle_id": str(v), "end": 22.0, "mid": 20.0})
        frames.append(pd.DataFrame({"seed": 0, "vehicle_id": str(v), "time": t, "signal": sig, "lane": lane,
                                    "left_lane_exists": 1.0, "right_lane_exists": 1.0,
                                    "gap_left": gap_left, "gap_right": gap_right}))
    return pd.concat(frames, ignore_index=True), pd.DataFrame(events)


def test_lane_keeping_mask_leaves_out_the_ticks_around_each_change():
    stream, events = _stream(n_keep=2, n_change=1)
    keep = lane_keeping_mask(stream, events)
    changer = stream["vehicle_id"] == "2"
    t = stream["time"]
    assert keep[~changer.to_numpy()].all()
    near = changer & (t > 22.0 - 12.0) & (t < 22.0 + 5.0)
    assert not keep[near.to_numpy()].any()
    assert keep[(changer & (t <= 10.0)).to_numpy()].all()


def test_separability_is_chance_before_the_signal_and_perfect_after():
    stream, events = _stream()
    table = separability(stream, events, {"signal": stream["signal"].to_numpy()}, before_s=(4, 1))
    early = table[table["before_mid_s"] == 4].iloc[0]
    late = table[table["before_mid_s"] == 1].iloc[0]
    assert early["n"] == late["n"] == 10
    assert abs(early["auc"] - 0.5) < 0.25
    assert late["auc"] == 1.0 and late["median"] == 5.0 and late["lk_above"] == 0.0
    # about half of the lane keepers' N(0, 1) ticks exceed a median drawn from the same distribution
    assert 0.2 < early["lk_above"] < 0.8


def test_window_auc_reads_the_target_side():
    stream, events = _stream()
    table = window_auc(stream, events, ["signal"], ["gap_{side}"], windows=((4.0, 3.0), (1.5, 0.0)))
    first = table.iloc[0]
    assert first["changes"] == 10
    assert first["gap_target"] == 1.0  # the changers' left gap is larger than any lane keeper's
    assert abs(first["signal"] - 0.5) < 0.25
    assert table.iloc[1]["signal"] == 1.0


def test_ema_lateral_speed_recovers_a_steady_drift_and_restarts_per_track():
    t = np.arange(0, 20, DT)
    d = 0.3 * t
    start = np.zeros(len(t), dtype=bool)
    start[0] = True
    v = ema_lateral_speed(d, start, DT, 0.5, 2.0)
    assert v[0] == 0.0
    assert v[-1] == pytest.approx(0.3, abs=0.01)
    start[100] = True  # a new track at the same positions starts from zero again
    v2 = ema_lateral_speed(d, start, DT, 0.5, 2.0)
    assert v2[100] == 0.0 and v2[99] == pytest.approx(v[99])


def test_kalman_lateral_speed_tracks_a_noisy_drift():
    rng = np.random.default_rng(1)
    t = np.arange(0, 20, DT)
    d = np.where(t < 10, 0.0, 0.4 * (t - 10)) + rng.normal(0, 0.05, len(t))
    start = track_starts(pd.DataFrame({"seed": 0, "vehicle_id": "a", "time": t}), DT)
    pos, vel = kalman_lateral_speed(d, start, DT, sigma_m=0.05, accel_psd=0.05)
    assert abs(np.mean(vel[50:100])) < 0.1  # still: no speed
    assert np.mean(vel[170:]) == pytest.approx(0.4, abs=0.1)
    assert np.std(pos[170:] - 0.4 * (t[170:] - 10)) < 0.05


def test_position_noise_tells_white_noise_from_a_smoothed_series():
    rng = np.random.default_rng(2)
    start = np.zeros(5000, dtype=bool)
    start[0] = True
    white = rng.normal(0, 0.1, 5000)
    out = position_noise(white, start)
    assert out["white_noise_std_m"] == pytest.approx(0.1, rel=0.1)
    assert out["first_difference_lag1_autocorrelation"] == pytest.approx(-0.5, abs=0.05)
    kernel = np.convolve(np.ones(10), np.ones(10)) / 100  # triangular: smooth differences
    smooth = np.convolve(rng.normal(0, 0.1, 5020), kernel, mode="valid")[:5000]
    assert position_noise(smooth, start)["first_difference_lag1_autocorrelation"] > 0.8


def test_track_starts_splits_on_vehicle_and_on_a_gap():
    stream = pd.DataFrame({"seed": [0, 0, 0, 0, 1], "vehicle_id": ["a", "a", "a", "b", "b"],
                           "time": [0.0, 0.1, 0.5, 0.6, 0.7]})
    assert track_starts(stream, DT).tolist() == [True, False, True, True, True]
