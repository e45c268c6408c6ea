import numpy as np
import pandas as pd
import pytest

from vcfusion.prediction.features import (BLOCK_RANGE_M, DENSITY_RANGE_M, FEATURE_NAMES, RANGE_M, SIDES,
                                         STOPPED_MPS, FeatureExtractor, tick_features)
from vcfusion.prediction.labels import label_samples
from vcfusion.records import TwinStates
from vcfusion.traffic.network import Road

ROAD = Road("hw", (0.0, 0.0), (2000.0, 0.0), 3, 3.5, 25.0)  # y = 0 is the left edge, lanes downwards


def _events(rows):
    return pd.DataFrame(rows, columns=["event_id", "vehicle_id", "mid_time", "end_time"])


def test_fig5_windows_on_a_hand_made_event():
    # One change of v1 ending at t = 20 s; tau = 3, tau_g = 2 -> positive 0 <= ttl < 3 (t in (17, 20]),
    # gap 3 <= ttl < 5, negative 5 <= ttl < 8 (t in (12, 15]): the positive window moved back by 5 s.
    t = np.round(np.arange(0.0, 25.0, 0.5), 6)
    ev = _events([(7, "v1", 18.5, 20.0)])
    lab = label_samples(t, np.full(len(t), "v1"), ev, tau=3.0, tau_g=2.0)
    by_t = dict(zip(t, lab["window_label"]))
    assert [by_t[x] for x in (20.0, 19.5, 17.5, 17.0 + 0.5)] == [1, 1, 1, 1]
    assert by_t[17.0] == -1  # ttl == tau: first tick of the gap (windows are half-open)
    assert by_t[15.5] == -1 and by_t[16.0] == -1  # the gap tau_g
    assert by_t[15.0] == 0 and by_t[12.5] == 0 and by_t[12.0] == -1  # negative: 5 <= ttl < 8
    # each negative tick is a positive tick moved back by tau + tau_g
    pos_t = np.sort(t[lab["window_label"] == 1])
    np.testing.assert_allclose(np.sort(t[lab["window_label"] == 0]), pos_t - 5.0)
    assert by_t[20.5] == -1 and by_t[24.5] == -1  # after the change: no next change
    # equal window sizes (the paper balances positives and negatives this way)
    assert (lab["window_label"] == 1).sum() == (lab["window_label"] == 0).sum() == 6
    assert lab.loc[t == 19.0, "time_to_lc"].item() == pytest.approx(1.0)
    assert (lab.loc[t <= 20.0, "event_id"] == 7).all() and (lab.loc[t > 20.0, "event_id"] == -1).all()
    # stream view: positive exactly on the positive window, everything else negative
    assert ((lab["stream_label"] == 1) == (lab["window_label"] == 1)).all()


def test_next_change_wins_and_other_vehicles_untouched():
    t = np.round(np.arange(0.0, 30.0, 1.0), 6)
    ev = _events([(0, "a", 9.0, 10.0), (1, "a", 19.0, 20.0)])
    vids = np.array(["a"] * len(t) + ["b"] * len(t))
    lab = label_samples(np.concatenate([t, t]), vids, ev, tau=3.0, tau_g=1.0)
    a = lab.iloc[: len(t)]
    # the second change's negative window 4 <= ttl < 7 -> t = 14..16 (t = 13, ttl = 7, is not in it)
    assert list(a["window_label"].iloc[13:18]) == [-1, 0, 0, 0, -1]
    assert list(a["window_label"].iloc[8:11]) == [1, 1, 1]  # positive of the first change
    assert a["time_since_lc"].iloc[12] == pytest.approx(2.0)
    assert (lab.iloc[len(t):]["window_label"] == -1).all()


def _twins(lane, s, speed, length=None, ids=None):
    n = len(lane)
    length = np.full(n, 4.0) if length is None else np.asarray(length, float)
    d = (np.asarray(lane) + 0.5) * ROAD.lane_width_m
    x, y = ROAD.to_world(np.asarray(s, float), d)
    return TwinStates(time=1.0, ids=tuple(ids or [f"v{i}" for i in range(n)]), measured_time=np.ones(n), x=x, y=y,
                      z=np.zeros(n), heading=np.zeros(n), speed=np.asarray(speed, float), accel=np.zeros(n),
                      lane=np.asarray(lane, np.int16), length=length, width=np.full(n, 1.8),
                      height=np.full(n, 1.5), outputs={})


def test_features_leaders_followers_gaps_and_sentinels():
    # v0 in lane 1 at s=100; v1 ahead in lane 1 (s=130); v2 behind in lane 1 (s=80);
    # v3 in lane 2 at s=105 (left leader, overlapping), v4 stopped in lane 0 at s=300.
    tw = _twins(lane=[1, 1, 1, 2, 0], s=[100, 130, 80, 105, 300], speed=[20, 15, 22, 25, 0])
    f = FeatureExtractor(ROAD, 0.1).from_twins(tw)
    col = {n: f[:, i] for i, n in enumerate(FEATURE_NAMES)}
    assert col["gap_lead_own"][0] == pytest.approx(130 - 2 - (100 + 2))  # 26 m bumper to bumper
    assert col["dv_lead_own"][0] == pytest.approx(-5.0)
    assert col["gap_foll_own"][0] == pytest.approx((100 - 2) - (80 + 2))  # 16 m
    assert col["dv_foll_own"][0] == pytest.approx(2.0)
    assert col["gap_lead_left"][0] == pytest.approx(105 - 2 - 102)  # side by side: 1 m
    assert col["gap_foll_left"][0] == RANGE_M and col["dv_foll_left"][0] == 0.0  # nobody behind on the left
    assert col["stopped_ahead_right"][0] == pytest.approx(300 - 2 - 102)
    assert col["stopped_ahead_own"][0] == BLOCK_RANGE_M
    assert col["gap_lead_right"][0] == RANGE_M  # 196 m > range: sentinel
    assert col["n_ahead_own"][0] == 1 and col["n_ahead_left"][0] == 1
    # lane index relative to the right edge; lanes that do not exist
    assert col["lane"].tolist() == [1, 1, 1, 2, 0] and col["lanes_to_left"].tolist() == [1, 1, 1, 0, 2]
    assert col["left_lane_exists"][3] == 0 and col["gap_lead_left"][3] == 0 and col["dv_lead_left"][3] == 0
    assert col["right_lane_exists"][4] == 0 and col["gap_foll_right"][4] == 0
    # v3 (lane 2): its right-lane follower is v0 (100 < 105) and leader v1
    assert col["gap_foll_right"][3] == pytest.approx((105 - 2) - (100 + 2))
    assert col["gap_lead_right"][3] == pytest.approx(130 - 2 - 107)


def _reference_tick_features(s, lane, speed, length, num_lanes):
    """One twin and one side at a time, straight from the module's definitions (slow, obvious)."""
    out = {}
    for side, offset in zip(SIDES, (-1, 0, 1)):
        cols = {k: [] for k in ("gap_lead", "dv_lead", "gap_foll", "dv_foll", "stopped_ahead", "n_ahead")}
        for i in range(len(s)):
            target = lane[i] + offset
            if lane[i] < 0 or not 0 <= target < num_lanes:
                for k in cols:
                    cols[k].append(0.0)
                continue
            others = [j for j in range(len(s)) if j != i and lane[j] == target]
            ahead = [j for j in others if s[j] > s[i]]
            behind = [j for j in others if s[j] < s[i]]
            lead = min(ahead, key=lambda j: s[j]) if ahead else None
            foll = max(behind, key=lambda j: s[j]) if behind else None
            gl = s[lead] - length[lead] / 2 - (s[i] + length[i] / 2) if lead is not None else np.inf
            gf = s[i] - length[i] / 2 - (s[foll] + length[foll] / 2) if foll is not None else np.inf
            cols["gap_lead"].append(gl if gl <= RANGE_M else RANGE_M)
            cols["dv_lead"].append(speed[lead] - speed[i] if gl <= RANGE_M else 0.0)
            cols["gap_foll"].append(gf if gf <= RANGE_M else RANGE_M)
            cols["dv_foll"].append(speed[foll] - speed[i] if gf <= RANGE_M else 0.0)
            stopped = [j for j in ahead if speed[j] < STOPPED_MPS]
            st = min(stopped, key=lambda j: s[j]) if stopped else None
            dist = s[st] - length[st] / 2 - (s[i] + length[i] / 2) if st is not None else np.inf
            cols["stopped_ahead"].append(dist if dist <= BLOCK_RANGE_M else BLOCK_RANGE_M)
            cols["n_ahead"].append(float(sum(s[i] < s[j] <= s[i] + DENSITY_RANGE_M for j in others)))
        out.update({f"{k}_{side}": np.array(v) for k, v in cols.items()})
    return out


@pytest.mark.parametrize("seed", range(5))
def test_tick_features_equal_a_twin_by_twin_reference(seed):
    """The all-pairs vectorised neighbours agree with a plain per-twin search, including twins off
    the road, stopped twins, empty lanes and gaps beyond the range."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 40))
    s = np.round(rng.uniform(0, 600, n), 1)
    lane = rng.integers(-1, 3, n)
    speed = np.where(rng.random(n) < 0.2, 0.0, rng.uniform(5, 35, n))
    length = rng.choice([4.5, 12.0], n)
    got = tick_features(s, lane, speed, np.zeros(n), length, 3)
    want = _reference_tick_features(s, lane, speed, length, 3)
    for name, value in want.items():
        np.testing.assert_allclose(got[name], value, rtol=0, atol=1e-9, err_msg=name)


def test_features_ignore_lateral_position_within_the_lane():
    """No feature may change when only the lateral position (within the lane) or heading changes."""
    tw = _twins(lane=[1, 1, 2], s=[100, 130, 90], speed=[20, 15, 25])
    moved = TwinStates(**{**tw.__dict__, "y": tw.y + np.array([1.2, -1.0, 0.7]), "heading": tw.heading + 0.1})
    a = FeatureExtractor(ROAD, 0.1).from_twins(tw)
    b = FeatureExtractor(ROAD, 0.1).from_twins(moved)
    np.testing.assert_array_equal(a, b)
    forbidden = ("lateral", "lat_", "steer", "blinker", "heading", "offset", "_d")
    assert not [n for n in FEATURE_NAMES if any(w in n for w in forbidden)]


def test_feature_memory_follows_twin_ids_across_snapshots():
    ex = FeatureExtractor(ROAD, 0.1)
    ex.from_twins(_twins([1, 1], [100, 200], [20, 30], ids=["a", "b"]))
    f = ex.from_twins(_twins([1, 1, 0], [102, 203, 50], [18, 30, 10], ids=["a", "b", "c"]))
    col = {n: f[:, i] for i, n in enumerate(FEATURE_NAMES)}
    assert col["speed_below_recent_max"][0] == pytest.approx(20 - 0.05 * 0.1 - 18)
    assert col["speed_below_recent_max"][1] == 0.0 and col["speed_below_recent_max"][2] == 0.0
    assert col["speed_minus_ema"][0] < 0 and col["speed_minus_ema"][2] == 0.0


def _col(f):
    return {n: f[:, i] for i, n in enumerate(FEATURE_NAMES)}


def test_history_trends_follow_a_closing_gap():
    """A leader 2 m/s slower: the own-lane gap shrinks 0.2 m per tick, so its trend (fast - slow EMA)
    tends to -(HISTORY_SLOW_S - HISTORY_FAST_S) x 2 m/s = -3 m and its mean lags the gap by ~2 s x 2 m/s."""
    from vcfusion.prediction.features import HISTORY_FAST_S, HISTORY_SLOW_S

    ex = FeatureExtractor(ROAD, 0.1)
    for k in range(200):  # 20 s
        f = _col(ex.from_twins(_twins([1, 1], [100 + 20 * 0.1 * k, 160 + 18 * 0.1 * k], [20, 18], ids=["a", "b"])))
    ramp = -2.0
    assert f["gap_lead_own_trend"][0] == pytest.approx((HISTORY_SLOW_S - HISTORY_FAST_S) * ramp, rel=0.03)
    assert f["gap_lead_own_mean"][0] - f["gap_lead_own"][0] == pytest.approx(-HISTORY_SLOW_S * ramp, rel=0.03)
    assert f["speed_trend"][0] == pytest.approx(0.0, abs=1e-9)  # constant speed
    assert f["dv_lead_own_trend"][0] == pytest.approx(0.0, abs=1e-9)
    # first snapshot of a twin: every average starts at the current value
    g = _col(FeatureExtractor(ROAD, 0.1).from_twins(_twins([1, 1], [100, 160], [20, 18], ids=["a", "b"])))
    assert g["gap_lead_own_trend"][0] == 0.0 and g["gap_lead_own_mean"][0] == g["gap_lead_own"][0]
    # missing lanes: trend 0 and mean = the instantaneous sentinel 0
    assert g["gap_lead_right_trend"].tolist() == [0.0, 0.0] or ROAD.num_lanes < 2
    h = _col(FeatureExtractor(ROAD, 0.1).from_twins(_twins([0, 2], [100, 160], [20, 18])))
    assert h["gap_lead_right_mean"][0] == 0.0 and h["gap_foll_left_mean"][1] == 0.0


def test_history_is_kept_per_absolute_lane_so_a_lane_flip_leaves_no_trace():
    """Twin 'a' drives in lane 1 beside a steady lane-2 queue, then its map-matched lane flips to 2.
    After the flip its own-lane history must be the history of lane 2 it watched as its left lane
    (so the flip itself adds no jump to the trends), exactly as for a twin that was always there."""
    ex = FeatureExtractor(ROAD, 0.1)
    lane_a = [1] * 50 + [2] * 5
    for k, la in enumerate(lane_a):
        f = _col(ex.from_twins(_twins([la, 2, 1], [100 + 2.0 * k, 140 + 1.8 * k, 60 + 2.0 * k], [20, 18, 20],
                                      ids=["a", "lead2", "foll1"])))
        if k == 49:
            before = f
    # before the flip, lane 2 is a's left lane; after, its own lane: same history, continued
    assert before["gap_lead_left_trend"][0] == pytest.approx(f["gap_lead_own_trend"][0], rel=0.05)
    assert abs(f["gap_lead_own_mean"][0] - before["gap_lead_left_mean"][0]) < 2.0  # 5 ticks of a -0.2 m ramp
    # ... and lane 1 (own before) is now its right lane, with the follower it had there
    assert f["gap_foll_right_mean"][0] == pytest.approx(before["gap_foll_own"][0], abs=0.5)


def test_history_of_a_lane_starts_when_the_twin_has_it():
    """Off the road (a ramp) or before its lane begins, a twin has no gap to average: the averages
    of that lane start at the first value once it has the lane, not at the sentinel 0 averaged in
    (averaging the sentinel, a ramp vehicle's gap_lead_own_mean reads 27 m against a gap of 150 m)."""
    ex = FeatureExtractor(ROAD, 0.1)
    for k in range(30):  # 'r' on the ramp (lane -1), 'm' on the main line 60 m ahead of it
        f = _col(ex.from_twins(_twins([-1, 0], [100 + 2.0 * k, 160 + 2.0 * k], [20, 20], ids=["r", "m"])))
    assert f["gap_lead_own_mean"][0] == 0.0  # the sentinel while off the road
    f = _col(ex.from_twins(_twins([0, 0], [160.0, 220.0], [20, 20], ids=["r", "m"])))
    assert f["gap_lead_own"][0] == pytest.approx(56.0)
    assert f["gap_lead_own_mean"][0] == pytest.approx(56.0)
    assert f["gap_lead_own_trend"][0] == 0.0

    class RightLaneBeginsAt200:  # the road frame's interface: lane 0 exists from s = 200 on
        num_lanes = num_tracks = 3
        all_lanes_everywhere = False

        @staticmethod
        def lanes_present(s):
            return np.column_stack([np.asarray(s) >= 200, np.ones(len(s)), np.ones(len(s))]).astype(bool)

    ex = FeatureExtractor(RightLaneBeginsAt200(), 0.1)
    ones = np.ones(2)
    for k in range(30):  # 'a' in lane 1 passes s = 200 at k = 25; 'b' in lane 0 beyond, 30 m ahead
        f = _col(ex(("a", "b"), np.array([175 + 1.0 * k, 205 + 1.0 * k]), np.array([1, 0]), 10 * ones,
                    0 * ones, 4 * ones))
        if k == 24:
            assert f["gap_lead_right_mean"][0] == 0.0 and f["right_lane_exists"][0] == 0.0
        if k == 25:
            assert f["gap_lead_right"][0] == pytest.approx(26.0)
            assert f["gap_lead_right_mean"][0] == pytest.approx(26.0)


def _reference_history(steps, num_lanes=3, period_s=0.1):
    """The per-twin memory update written out with NumPy, one twin at a time: speed EMA, leaky
    maximum, fast/slow EMAs of speed and per-lane quantities; then the history columns."""
    from vcfusion.prediction.features import (HISTORY_FAST_S, HISTORY_MEAN_SOURCES, HISTORY_SLOW_S,
                                             SPEED_EMA_S, SPEED_MAX_DECAY_MPS2, _N_TICK)

    a_speed, a_fast, a_slow = (1.0 - np.exp(-period_s / t) for t in (SPEED_EMA_S, HISTORY_FAST_S, HISTORY_SLOW_S))
    memory, outputs = {}, []
    for ids, s, lane, speed in steps:
        per_lane = tick_features(s, lane, speed, np.zeros(len(s)), np.full(len(s), 4.5), num_lanes,
                                 per_lane=True)["_per_lane"]
        out = np.zeros((len(ids), len(FEATURE_NAMES) - _N_TICK + 2))
        new_memory = {}
        for i, vid in enumerate(ids):
            # off the road the twin has no lanes: no per-lane quantities, whose averages start
            # again at the current values once it is back on a lane (this road has every lane everywhere)
            lanes = per_lane[i].ravel() if lane[i] >= 0 else np.full(per_lane[i].size, np.nan)
            current = np.concatenate([[speed[i]], lanes])
            ema, vmax, fast, slow = memory.get(vid, (speed[i], speed[i], current, current))
            fast, slow = np.where(np.isnan(fast), current, fast), np.where(np.isnan(slow), current, slow)
            ema = ema + a_speed * (speed[i] - ema)
            vmax = max(speed[i], vmax - SPEED_MAX_DECAY_MPS2 * period_s)
            fast = fast + a_fast * (current - fast)
            slow = slow + a_slow * (current - slow)
            new_memory[vid] = (ema, vmax, fast, slow)
            row = [speed[i] - ema, vmax - speed[i], fast[0] - slow[0]]
            trends, means = [], []
            for name in HISTORY_MEAN_SOURCES:
                quantity, side = name.rsplit("_", 1)
                target = lane[i] + {"right": -1, "own": 0, "left": 1}[side]
                if lane[i] < 0 or not 0 <= target < num_lanes:
                    trends.append(0.0)
                    means.append(0.0)
                    continue
                col = 1 + target * 4 + ("gap_lead", "dv_lead", "gap_foll", "dv_foll").index(quantity)
                trends.append(fast[col] - slow[col])
                means.append(slow[col])
            out[i] = row + trends + means
        memory = new_memory
        outputs.append(out)
    return outputs


def test_compiled_history_equals_a_twin_by_twin_reference():
    """Twins come, go and come back (memory restarts), change lanes and leave the road."""
    from vcfusion.prediction.features import _N_TICK

    rng = np.random.default_rng(7)
    pool = [f"v{i}" for i in range(12)]
    steps = []
    for _ in range(60):
        ids = tuple(sorted(rng.choice(pool, size=int(rng.integers(1, 10)), replace=False)))
        n = len(ids)
        steps.append((ids, rng.uniform(0, 400, n), rng.integers(-1, 3, n), rng.uniform(0, 30, n)))
    ex = FeatureExtractor(ROAD, 0.1)
    want = _reference_history(steps)
    for (ids, s, lane, speed), expected in zip(steps, want):
        got = ex(ids, s, lane, speed, np.zeros(len(ids)), np.full(len(ids), 4.5))
        cols = [FEATURE_NAMES.index("speed_minus_ema"), FEATURE_NAMES.index("speed_below_recent_max"),
                *range(_N_TICK, len(FEATURE_NAMES))]
        np.testing.assert_allclose(got[:, cols], expected, rtol=0, atol=1e-9)
