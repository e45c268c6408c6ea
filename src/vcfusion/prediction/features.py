"""Longitudinal features of every cloud twin, one V2C tick at a time.

The features use only what the cloud knows about each twin: its map-matched lane (from the
noisy, late GNSS position), its position along the road, speed, acceleration and length, and
the same facts of the other twins. There is NO lateral position, lateral speed, heading,
steering, blinker or SUMO lane-change state among them: the paper's long-term prediction
(Section IV-A) works without lateral cues, and so do we.

One stateful :class:`FeatureExtractor` is used identically at run time (the cloud's process
model, fed every snapshot) and to build datasets (fed the run's `twins` table, snapshot by
snapshot, see :func:`features_from_twins_table`): the per-twin memory (smoothed speed, a
leaky maximum speed) is updated from the snapshots, so both paths see the same numbers.

Neighbours. For each twin and each of its lanes {right, own, left}, the leader is the
nearest twin in that lane whose centre is ahead (larger s), the follower the nearest behind.
Gaps are bumper to bumper along the road (negative when side by side in an adjacent lane);
speed differences are neighbour minus own speed. Sentinels:
- lane does not exist (own lane is the rightmost/leftmost, or the twin is off the road):
  gap = 0 m, speed difference = 0, and `right_lane_exists` / `left_lane_exists` = 0;
- lane exists but no twin within `RANGE_M` (or a gap beyond it): gap = RANGE_M, difference 0.
`stopped_ahead_*` is the distance from the front bumper to the rear of the nearest stopped
twin (speed < STOPPED_MPS) ahead in that lane, BLOCK_RANGE_M when none (and 0 for a missing
lane) — an accident or a queue ahead, derived from the twins only.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from vcfusion.traffic.network import Road

RANGE_M = 150.0
BLOCK_RANGE_M = 400.0
STOPPED_MPS = 1.0
DENSITY_RANGE_M = 100.0
SPEED_EMA_S = 3.0  # time constant of the smoothed speed
SPEED_MAX_DECAY_MPS2 = 0.05  # the leaky maximum forgets this fast: a slow estimate of the desired speed

# Short-history features: the cloud keeps two exponential moving averages (EMA) per twin of its
# speed and of the gap / speed difference to the leader and follower in every lane of the
# road, a fast one (HISTORY_FAST_S) and a slow one (HISTORY_SLOW_S).
# `<name>_trend` = fast EMA - slow EMA: a noise-robust rate of change over the last ~1-2 s
# (about (HISTORY_SLOW_S - HISTORY_FAST_S) x the derivative for a steady ramp).
# `<name>_mean` = slow EMA: the recent level, because SUMO's lane-change model (LC2013) decides
# speedGain / keepRight changes by accumulating the neighbour lane's advantage over seconds.
# The averages are kept per lane by ABSOLUTE index and only then mapped to own / left / right
# with the current map-matched lane: when a twin's lane flips at the middle of a lane change,
# its "own lane" history continues with the history of the new lane (which it watched as a
# neighbour lane), so the flip leaves no jump in the history features (no back door for the
# lateral position); a side lane that does not exist gives trend 0 and mean 0 (the sentinel).
HISTORY_FAST_S = 0.5
HISTORY_SLOW_S = 2.0
_LANE_QUANTITIES = ("gap_lead", "dv_lead", "gap_foll", "dv_foll")  # order of tick_features' `_per_lane`
HISTORY_TREND_SOURCES: tuple[str, ...] = (
    "speed", "gap_lead_own", "dv_lead_own",
    "gap_lead_left", "dv_lead_left", "gap_foll_left", "dv_foll_left",
    "gap_lead_right", "dv_lead_right", "gap_foll_right", "dv_foll_right",
)
HISTORY_MEAN_SOURCES: tuple[str, ...] = HISTORY_TREND_SOURCES[1:]

SIDES = ("right", "own", "left")
_LANE_OFFSET = {"right": -1, "own": 0, "left": 1}

FEATURE_NAMES: tuple[str, ...] = (
    "speed", "accel", "length", "lane", "lanes_to_left",
    "right_lane_exists", "left_lane_exists",
    "speed_minus_ema", "speed_below_recent_max",
    *[f"{kind}_{side}" for side in SIDES for kind in
      ("gap_lead", "dv_lead", "gap_foll", "dv_foll", "stopped_ahead", "n_ahead")],
    *[f"{name}_trend" for name in HISTORY_TREND_SOURCES],
    *[f"{name}_mean" for name in HISTORY_MEAN_SOURCES],
)

_N_TICK = FEATURE_NAMES.index("speed_trend")  # features before the history block (filled as blocks)
assert FEATURE_NAMES[_N_TICK:] == ("speed_trend", *[f"{n}_trend" for n in HISTORY_MEAN_SOURCES],
                                   *[f"{n}_mean" for n in HISTORY_MEAN_SOURCES])

_LANE_KEY = 1.0e6  # lane * _LANE_KEY + s sorts twins by lane, then along the road


def _neighbour_index(keys_sorted: np.ndarray, query: np.ndarray, lane_of_sorted: np.ndarray,
                     target_lane: np.ndarray, ahead: bool) -> np.ndarray:
    """Index (into the sorted arrays) of the nearest twin ahead/behind in target_lane, -1 if none."""
    if ahead:
        pos = np.searchsorted(keys_sorted, query, side="right")
    else:
        pos = np.searchsorted(keys_sorted, query, side="left") - 1
    ok = (pos >= 0) & (pos < len(keys_sorted))
    pos_c = np.minimum(np.maximum(pos, 0), max(len(keys_sorted) - 1, 0))  # np.clip is slow on small arrays
    if len(keys_sorted):
        ok &= lane_of_sorted[pos_c] == target_lane
    return np.where(ok, pos_c, -1)


def tick_features(s: np.ndarray, lane: np.ndarray, speed: np.ndarray, accel: np.ndarray,
                  length: np.ndarray, num_lanes: int, per_lane: bool = False) -> dict[str, np.ndarray]:
    """The memoryless features of all twins of one tick (vectorised); s is the footprint centre.

    per_lane: also return `_per_lane`, (N, num_lanes, 4): gap_lead, dv_lead, gap_foll, dv_foll
    of each twin towards every lane of the road by absolute index (own lane included).
    """
    n = len(s)
    lane = np.asarray(lane, dtype=np.int64)
    on_road = lane >= 0
    out: dict[str, np.ndarray] = {
        "speed": speed.astype(float), "accel": accel.astype(float), "length": length.astype(float),
        "lane": lane.astype(float),
        "lanes_to_left": np.where(on_road, num_lanes - 1 - lane, 0).astype(float),
        "right_lane_exists": (on_road & (lane >= 1)).astype(float),
        "left_lane_exists": (on_road & (lane <= num_lanes - 2)).astype(float),
    }
    idx_on = np.flatnonzero(on_road)
    keys = lane[idx_on] * _LANE_KEY + s[idx_on]
    order = np.argsort(keys, kind="stable")
    keys_sorted = keys[order]
    members = idx_on[order]  # twin index of each sorted position
    lane_sorted = lane[members]
    stopped = members[speed[members] < STOPPED_MPS]
    stopped_keys = lane[stopped] * _LANE_KEY + s[stopped]
    front = s + length / 2

    def lead_follow(target: np.ndarray, exists: np.ndarray):
        """gap / speed difference to the leader and the follower of every twin in lane `target`
        (the twin itself is never its own neighbour: equal keys are skipped on both sides)."""
        query = target * _LANE_KEY + s
        res = []
        for ahead in (True, False):
            pos = _neighbour_index(keys_sorted, query, lane_sorted, target, ahead=ahead)
            j = members[np.maximum(pos, 0)] if len(members) else np.zeros(n, dtype=np.int64)
            if ahead:
                gap = (s[j] - length[j] / 2) - front
            else:
                gap = (s - length / 2) - (s[j] + length[j] / 2)
            found = exists & (pos >= 0) & (gap <= RANGE_M)
            res += [np.where(found, gap, np.where(exists, RANGE_M, 0.0)), np.where(found, speed[j] - speed, 0.0)]
        return res

    # Leader / follower towards every lane of the road by absolute index, then picked per side.
    lanes_q = (np.stack([np.stack(lead_follow(np.full(n, k), on_road), axis=-1) for k in range(num_lanes)], axis=1)
               if n else np.zeros((0, num_lanes, 4)))
    if per_lane:
        out["_per_lane"] = lanes_q
    rows = np.arange(n)
    for side in SIDES:
        target = lane + _LANE_OFFSET[side]
        exists = on_road & (target >= 0) & (target < num_lanes)
        query = target * _LANE_KEY + s
        picked = np.where(exists[:, None], lanes_q[rows, np.minimum(np.maximum(target, 0), num_lanes - 1)], 0.0)
        gap_lead, dv_lead, gap_foll, dv_foll = picked.T
        stopped_ahead = np.zeros(n)
        n_ahead = np.zeros(n)
        if n:
            if len(stopped):
                order_st = np.argsort(stopped_keys, kind="stable")
                st_sorted = stopped[order_st]
                pos = _neighbour_index(stopped_keys[order_st], query, lane[st_sorted], target, ahead=True)
                j = st_sorted[np.maximum(pos, 0)]
                dist = (s[j] - length[j] / 2) - front
                found = exists & (pos >= 0) & (dist <= BLOCK_RANGE_M)
                stopped_ahead[:] = np.where(found, dist, np.where(exists, BLOCK_RANGE_M, 0.0))
            else:
                stopped_ahead[:] = np.where(exists, BLOCK_RANGE_M, 0.0)
            count = (np.searchsorted(keys_sorted, query + DENSITY_RANGE_M, side="right")
                     - np.searchsorted(keys_sorted, query, side="right"))
            n_ahead[:] = np.where(exists, count, 0)
        out[f"gap_lead_{side}"] = gap_lead
        out[f"dv_lead_{side}"] = dv_lead
        out[f"gap_foll_{side}"] = gap_foll
        out[f"dv_foll_{side}"] = dv_foll
        out[f"stopped_ahead_{side}"] = stopped_ahead
        out[f"n_ahead_{side}"] = n_ahead
    return out


class FeatureExtractor:
    """Per-twin feature memory plus :func:`tick_features`; call once per snapshot, in time order.

    Memory per twin (one row of `_state`): the speed EMA (SPEED_EMA_S) and leaky maximum speed,
    then the fast and slow EMAs of the speed and of the per-lane quantities (see
    HISTORY_FAST_S). A twin seen for the first time starts every average at its current value
    (zero trend); a twin missing from a snapshot is forgotten.
    """

    def __init__(self, road: Road, period_s: float):
        self.road = road
        self.period_s = period_s
        self._alpha = 1.0 - np.exp(-period_s / SPEED_EMA_S)
        self._decay = SPEED_MAX_DECAY_MPS2 * period_s
        self._alpha_fast = 1.0 - np.exp(-period_s / HISTORY_FAST_S)
        self._alpha_slow = 1.0 - np.exp(-period_s / HISTORY_SLOW_S)
        self._n_hist = 1 + road.num_lanes * len(_LANE_QUANTITIES)  # speed + per-lane quantities
        self._ids = np.array([], dtype=str)
        self._state = np.zeros((0, 2 + 2 * self._n_hist))
        split = [name.rsplit("_", 1) for name in HISTORY_MEAN_SOURCES]  # e.g. ("gap_lead", "left")
        self._src_offset = np.array([_LANE_OFFSET[side] for _, side in split])
        self._src_quantity = np.array([_LANE_QUANTITIES.index(q) for q, _ in split])

    def _carry(self, ids: np.ndarray, fresh: np.ndarray) -> np.ndarray:
        """Previous memory aligned to `ids`; rows of new twins are `fresh` (their current values)."""
        state = fresh.copy()
        if len(self._ids) and len(ids):
            order = np.argsort(self._ids)
            prev_sorted = self._ids[order]
            pos = np.minimum(np.searchsorted(prev_sorted, ids), len(prev_sorted) - 1)
            known = prev_sorted[pos] == ids
            state[known] = self._state[order[pos[known]]]
        return state

    def __call__(self, ids, x: np.ndarray, y: np.ndarray, lane: np.ndarray, speed: np.ndarray,
                 accel: np.ndarray, length: np.ndarray) -> np.ndarray:
        """(N, len(FEATURE_NAMES)) float64 features of the N twins of one snapshot."""
        ids = np.asarray(ids, dtype=str)
        if not len(ids):
            self._ids, self._state = ids, np.zeros((0, self._state.shape[1]))
            return np.zeros((0, len(FEATURE_NAMES)))
        n = len(ids)
        num_lanes = self.road.num_lanes
        speed = np.asarray(speed, dtype=float)
        lane = np.asarray(lane, dtype=np.int64)
        s, _ = self.road.to_road_frame(x, y)  # only s is used: the lateral coordinate is dropped here
        cols = tick_features(np.asarray(s, dtype=float), lane, speed, np.asarray(accel, dtype=float),
                             np.asarray(length, dtype=float), num_lanes, per_lane=True)
        current = np.concatenate([speed[:, None], cols.pop("_per_lane").reshape(n, -1)], axis=1)
        fresh = np.concatenate([speed[:, None], speed[:, None], current, current], axis=1)
        prev = self._carry(ids, fresh)
        h = self._n_hist
        ema = prev[:, 0] + self._alpha * (speed - prev[:, 0])
        vmax = np.maximum(speed, prev[:, 1] - self._decay)
        fast = prev[:, 2:2 + h] + self._alpha_fast * (current - prev[:, 2:2 + h])
        slow = prev[:, 2 + h:] + self._alpha_slow * (current - prev[:, 2 + h:])
        self._ids = ids
        self._state = np.concatenate([ema[:, None], vmax[:, None], fast, slow], axis=1)
        cols["speed_minus_ema"] = speed - ema
        cols["speed_below_recent_max"] = vmax - speed
        target = lane[:, None] + self._src_offset[None, :]  # (N, sources) absolute lane of each source
        exists = (lane[:, None] >= 0) & (target >= 0) & (target < num_lanes)
        column = 1 + np.minimum(np.maximum(target, 0), num_lanes - 1) * len(_LANE_QUANTITIES) + self._src_quantity[None, :]
        trend = np.where(exists, np.take_along_axis(fast - slow, column, axis=1), 0.0)
        mean = np.where(exists, np.take_along_axis(slow, column, axis=1), 0.0)
        out = np.empty((n, len(FEATURE_NAMES)))
        out[:, :_N_TICK] = np.stack([cols[name] for name in FEATURE_NAMES[:_N_TICK]], axis=-1)
        out[:, _N_TICK] = fast[:, 0] - slow[:, 0]  # speed_trend
        out[:, _N_TICK + 1:_N_TICK + 1 + len(HISTORY_MEAN_SOURCES)] = trend
        out[:, _N_TICK + 1 + len(HISTORY_MEAN_SOURCES):] = mean
        return out

    def from_twins(self, twins) -> np.ndarray:
        """Features of a TwinStates snapshot (the run-time path)."""
        return self(twins.ids, twins.x, twins.y, twins.lane, twins.speed, twins.accel, twins.length)


def features_from_twins_table(twins: pd.DataFrame, vehicles: pd.DataFrame, road: Road,
                              period_s: float) -> pd.DataFrame:
    """Replay a run's `twins` table snapshot by snapshot through a FeatureExtractor.

    Returns time, vehicle_id and one column per feature, in the table's row order per tick.
    Lengths come from the `vehicles` table (they are what each vehicle reports to the cloud).
    """
    length_of = vehicles.set_index("vehicle_id")["length"]
    twins = twins.sort_values(["time", "vehicle_id"], kind="stable").reset_index(drop=True)
    length = length_of.reindex(twins["vehicle_id"]).to_numpy(dtype=float)
    extractor = FeatureExtractor(road, period_s)
    times = twins["time"].to_numpy()
    bounds = np.flatnonzero(np.diff(times)) + 1
    starts = np.concatenate([[0], bounds]) if len(times) else np.zeros(0, dtype=int)
    ends = np.concatenate([bounds, [len(times)]]) if len(times) else np.zeros(0, dtype=int)
    ids = twins["vehicle_id"].to_numpy(dtype=str)
    x, y = twins["x"].to_numpy(float), twins["y"].to_numpy(float)
    lane = twins["lane"].to_numpy()
    speed, accel = twins["speed"].to_numpy(float), twins["accel"].to_numpy(float)
    blocks = [extractor(ids[a:b], x[a:b], y[a:b], lane[a:b], speed[a:b], accel[a:b], length[a:b])
              for a, b in zip(starts, ends)]
    values = np.concatenate(blocks) if blocks else np.zeros((0, len(FEATURE_NAMES)))
    out = pd.DataFrame(values, columns=list(FEATURE_NAMES))
    out.insert(0, "vehicle_id", twins["vehicle_id"].astype(str).to_numpy())
    out.insert(0, "time", times)
    return out
