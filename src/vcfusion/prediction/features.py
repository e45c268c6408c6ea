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

from vcfusion.prediction.memory import TwinMemory
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

_LANE_KEY = 1.0e6  # lane * _LANE_KEY + s orders twins by lane, then along the road


_SIDE_OFFSETS = np.array([_LANE_OFFSET[side] for side in SIDES])
_PER_SIDE = ("gap_lead", "dv_lead", "gap_foll", "dv_foll", "stopped_ahead", "n_ahead")
_N_OWN = FEATURE_NAMES.index("gap_lead_right")  # own-state columns before the per-side block
_HISTORY_OWN = ("speed_minus_ema", "speed_below_recent_max")  # filled by FeatureExtractor


def _tick_matrix(s: np.ndarray, lane: np.ndarray, speed: np.ndarray, accel: np.ndarray, length: np.ndarray,
                 num_lanes: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, _N_TICK) memoryless features in FEATURE_NAMES order (the two history columns of the own
    block left 0) and (N, num_lanes, 4) gap_lead, dv_lead, gap_foll, dv_foll towards every lane.

    All twin pairs at once, (lanes, N, N) comparisons of the sort keys: a tick holds tens to a few
    hundred twins, where a handful of dense array operations beats per-lane sorting and searching
    (this runs for every twin on every V2C tick, so it is written for few NumPy calls).
    """
    n = len(s)
    on_road = lane >= 0
    own = np.zeros((n, _N_OWN))
    own[:, 0], own[:, 1], own[:, 2], own[:, 3] = speed, accel, length, lane
    own[:, 4] = np.where(on_road, num_lanes - 1 - lane, 0)
    own[:, 5] = on_road & (lane >= 1)
    own[:, 6] = on_road & (lane <= num_lanes - 2)
    if n == 0:
        return np.zeros((0, _N_TICK)), np.zeros((0, num_lanes, 4))
    lanes = np.arange(num_lanes)
    keys = lane * _LANE_KEY + s  # off-road twins are never anyone's neighbour (in_lane below)
    # query[k, i]: twin i's position moved to lane k; its neighbours there have larger/smaller keys
    query = (lanes[:, None] * _LANE_KEY + s[None, :])[:, :, None]
    in_lane = ((lane[None, :] == lanes[:, None]) & on_road[None, :])[:, None, :]  # twin j is in lane k
    ahead = in_lane & (keys > query)  # (lanes, N_i, N_j); equal keys are nobody's neighbour
    behind = in_lane & (keys < query)
    # nearest ahead (smallest key; ties: lowest index) of all twins and of the stopped ones
    ahead_both = np.empty((2, *ahead.shape), dtype=bool)
    ahead_both[0] = ahead
    np.logical_and(ahead, speed < STOPPED_MPS, out=ahead_both[1])
    lead, stop = np.argmin(np.where(ahead_both, keys, np.inf), axis=-1)  # (lanes, N) each
    has_lead, has_stop = ahead_both.any(axis=-1)
    # nearest behind (largest key; ties: highest index, as a stable sort by key orders them)
    foll = n - 1 - np.argmax(np.where(behind, keys, -np.inf)[..., ::-1], axis=-1)
    has_foll = behind.any(axis=-1)
    front = s + length / 2
    rear = s - length / 2
    gap_lead = rear[lead] - front
    gap_foll = rear - front[foll]
    stop_dist = rear[stop] - front
    found_lead = has_lead & (gap_lead <= RANGE_M)
    found_foll = has_foll & (gap_foll <= RANGE_M)
    per_lane = np.empty((num_lanes, n, len(_PER_SIDE)))  # (lanes, N, per-side features)
    per_lane[..., 0] = np.where(found_lead, gap_lead, RANGE_M)
    per_lane[..., 1] = np.where(found_lead, speed[lead] - speed, 0.0)
    per_lane[..., 2] = np.where(found_foll, gap_foll, RANGE_M)
    per_lane[..., 3] = np.where(found_foll, speed[foll] - speed, 0.0)
    per_lane[..., 4] = np.where(has_stop & (stop_dist <= BLOCK_RANGE_M), stop_dist, BLOCK_RANGE_M)
    per_lane[..., 5] = (ahead & (keys <= query + DENSITY_RANGE_M)).sum(axis=-1)
    per_lane = np.where(on_road[None, :, None], per_lane, 0.0)  # a twin off the road has no lanes
    # own lane and both sides, picked from the absolute lanes; 0 where the lane does not exist
    target = lane[None, :] + _SIDE_OFFSETS[:, None]  # (sides, N)
    exists = on_road & (target >= 0) & (target < num_lanes)
    picked = per_lane[np.minimum(np.maximum(target, 0), num_lanes - 1), np.arange(n)]  # (sides, N, 6)
    picked = np.where(exists[:, :, None], picked, 0.0)
    out = np.concatenate([own, picked.transpose(1, 0, 2).reshape(n, -1)], axis=1)
    return out, per_lane[..., :4].transpose(1, 0, 2)


def tick_features(s: np.ndarray, lane: np.ndarray, speed: np.ndarray, accel: np.ndarray,
                  length: np.ndarray, num_lanes: int, per_lane: bool = False) -> dict[str, np.ndarray]:
    """The memoryless features of all twins of one tick (vectorised); s is the footprint centre.

    per_lane: also return `_per_lane`, (N, num_lanes, 4): gap_lead, dv_lead, gap_foll, dv_foll
    of each twin towards every lane of the road by absolute index (own lane included).
    """
    matrix, lanes_q = _tick_matrix(np.asarray(s, dtype=float), np.asarray(lane, dtype=np.int64),
                                   np.asarray(speed, dtype=float), np.asarray(accel, dtype=float),
                                   np.asarray(length, dtype=float), num_lanes)
    out = {name: matrix[:, i] for i, name in enumerate(FEATURE_NAMES[:_N_TICK]) if name not in _HISTORY_OWN}
    if per_lane:
        out["_per_lane"] = lanes_q
    return out


class FeatureExtractor:
    """Per-twin feature memory plus :func:`tick_features`; call once per snapshot, in time order.

    Memory per twin (one row of a :class:`TwinMemory`): the speed EMA (SPEED_EMA_S) and leaky maximum speed,
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
        self._memory = TwinMemory(2 + 2 * self._n_hist)
        # one update for the whole memory row: EMA rates per column (the leaky maximum, column 1,
        # is overwritten after)
        self._alphas = np.concatenate([[self._alpha, 0.0], np.full(self._n_hist, self._alpha_fast),
                                       np.full(self._n_hist, self._alpha_slow)])
        self._col_speed_minus_ema = FEATURE_NAMES.index("speed_minus_ema")
        self._col_below_max = FEATURE_NAMES.index("speed_below_recent_max")
        split = [name.rsplit("_", 1) for name in HISTORY_MEAN_SOURCES]  # e.g. ("gap_lead", "left")
        self._src_offset = np.array([_LANE_OFFSET[side] for _, side in split])
        self._src_quantity = np.array([_LANE_QUANTITIES.index(q) for q, _ in split])

    def __call__(self, ids, x: np.ndarray, y: np.ndarray, lane: np.ndarray, speed: np.ndarray,
                 accel: np.ndarray, length: np.ndarray) -> np.ndarray:
        """(N, len(FEATURE_NAMES)) float64 features of the N twins of one snapshot."""
        if not len(ids):
            self._memory.keep(ids, np.zeros((0, 2 + 2 * self._n_hist)))
            return np.zeros((0, len(FEATURE_NAMES)))
        n = len(ids)
        num_lanes = self.road.num_lanes
        speed = np.asarray(speed, dtype=float)
        lane = np.asarray(lane, dtype=np.int64)
        s, _ = self.road.to_road_frame(x, y)  # only s is used: the lateral coordinate is dropped here
        out = np.empty((n, len(FEATURE_NAMES)))
        out[:, :_N_TICK], lanes_q = _tick_matrix(np.asarray(s, dtype=float), lane, speed,
                                                 np.asarray(accel, dtype=float), np.asarray(length, dtype=float),
                                                 num_lanes)
        current = np.concatenate([speed[:, None], lanes_q.reshape(n, -1)], axis=1)
        fresh = np.concatenate([speed[:, None], speed[:, None], current, current], axis=1)
        prev = self._memory.carried(ids, fresh)
        h = self._n_hist
        state = prev + self._alphas * (fresh - prev)
        state[:, 1] = np.maximum(speed, prev[:, 1] - self._decay)  # leaky maximum, not an average
        self._memory.keep(ids, state)
        ema, vmax, fast, slow = state[:, 0], state[:, 1], state[:, 2:2 + h], state[:, 2 + h:]
        out[:, self._col_speed_minus_ema] = speed - ema
        out[:, self._col_below_max] = vmax - speed
        target = lane[:, None] + self._src_offset[None, :]  # (N, sources) absolute lane of each source
        exists = (lane[:, None] >= 0) & (target >= 0) & (target < num_lanes)
        column = 1 + np.minimum(np.maximum(target, 0), num_lanes - 1) * len(_LANE_QUANTITIES) + self._src_quantity[None, :]
        rows = np.arange(n)[:, None]
        out[:, _N_TICK] = fast[:, 0] - slow[:, 0]  # speed_trend
        out[:, _N_TICK + 1:_N_TICK + 1 + len(HISTORY_MEAN_SOURCES)] = np.where(exists, (fast - slow)[rows, column], 0.0)
        out[:, _N_TICK + 1 + len(HISTORY_MEAN_SOURCES):] = np.where(exists, slow[rows, column], 0.0)
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
