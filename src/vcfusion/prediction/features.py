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
- lane does not exist (own lane is the rightmost/leftmost, or the twin is off the road, or the
  lane is absent at the twin's s: before an acceleration lane begins, after a lane drop):
  gap = 0 m, speed difference = 0, and `right_lane_exists` / `left_lane_exists` = 0;
Lanes are the road frame's tracks (index from the right, stable across edges); the features
`lane` and `lanes_to_left` count the lanes present at the twin's s right and left of its own
(on a road whose lanes never change, the lane index and the lanes beyond it).
- lane exists but no twin within `RANGE_M` (or a gap beyond it): gap = RANGE_M, difference 0.
`stopped_ahead_*` is the distance from the front bumper to the rear of the nearest stopped
twin (speed < STOPPED_MPS) ahead in that lane, BLOCK_RANGE_M when none (and 0 for a missing
lane) — an accident or a queue ahead, derived from the twins only.
"""

from __future__ import annotations

import numba
import numpy as np
import pandas as pd

from vcfusion.prediction.memory import TwinMemory
from vcfusion.traffic.roadframe import RoadFrame

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
# lateral position); a side lane that does not exist gives trend 0 and mean 0 (the sentinel), and
# the averages of a lane start afresh when it appears (a ramp vehicle joining the main line, an
# acceleration lane beginning): the sentinel is never averaged in.
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

# Inputs of the sequence model beyond FEATURE_NAMES (columns of the datasets' samples too; the
# MLP's input list stays FEATURE_NAMES, so the shipped MLP file keeps loading).
SEQUENCE_EXTRA_NAMES: tuple[str, ...] = ("lane_end_ahead_m",)

# Availability flags (issue 46), inputs of a sequence model trained with them (SEQUENCE_INPUT_SETS
# "availability"): 1 where a neighbour was observed within RANGE_M, 0 where the twin's lane on that
# side does not exist, the twin is off the road, or no twin was seen there. Without them a missing
# neighbour reads as a free lane (gap RANGE_M, speed difference 0), which is what a truncated
# recording (NGSIM sorted by vehicle id), a short window (CommonRoad) or a partly connected fleet
# show the cloud. They are functions of FEATURE_NAMES (computed when read: datasets need no
# rebuild), from the data every source has; no lateral quantity is among the features, so none is
# flagged.
AVAILABILITY_NAMES: tuple[str, ...] = tuple(f"{kind}_found_{side}" for side in ("own", "left", "right")
                                            for kind in ("lead", "foll"))
# Lateral motion (issue 46), inputs of a sequence model of the "lateral" input set only (the
# paper's features and the shipped models use no lateral quantity): recorded drivers drift
# towards the line for seconds before a change (docs/components/real-data.md), which no
# longitudinal feature shows. From the twin's position across the road d (the road frame's,
# left positive: the cloud's GNSS position, a recording's lateral position), per twin:
# `lateral_speed_mps` = (fast - slow EMA of d) / (HISTORY_SLOW_S - HISTORY_FAST_S), the lateral
# speed of a steady drift; `lateral_drift_m` = d - its LATERAL_REFERENCE_S EMA, the displacement
# of the last ~10 s. Neither uses the lane geometry, so the map-matched lane's flip leaves no jump.
# `lateral_known` = 0 where the source has no lateral position (an NGSIM release without Local_X:
# the twins table's `d_known`); the two quantities are then 0 and their averages start afresh
# when it is known again.
LATERAL_REFERENCE_S = 10.0
LATERAL_NAMES: tuple[str, ...] = ("lateral_known", "lateral_speed_mps", "lateral_drift_m")
# Lateral motion over the vehicle's own lane-keeping sway (issue 46), inputs of a sequence model of
# the "sway" input set only: recorded lane keeping sways 0.1-0.3 m/s for about a second, more for
# some drivers than for others, which hides an early drift in `lateral_speed_mps`
# (docs/components/real-data.md, "The positions are not noisy; lane-keeping sway is"). Per twin,
# from its own LATERAL_NAMES of the ticks BEFORE the current one (causal: the current and later
# ticks never enter the scale):
# `lateral_speed_over_sway` = lateral_speed_mps / max(RMS of lateral_speed_mps, SWAY_SPEED_FLOOR_MPS),
# `lateral_drift_over_sway` = lateral_drift_m / max(RMS of lateral_drift_m, SWAY_DRIFT_FLOOR_M),
# each RMS an exponentially weighted mean of the squares (time constant SWAY_WINDOW_S, normalised by
# its weight so that a short history is an ordinary mean), each square capped (one lane change
# barely moves the scale); `sway_known` = 1 once the twin's lateral position has been known for
# SWAY_WARMUP_S + SWAY_MIN_HISTORY_S without a break (the two quantities are 0 before). The history
# restarts where the lateral position is unknown, where the twin is new or was missing from a
# snapshot, and after a gap of more than 1.5 V2C periods. They are functions of LATERAL_NAMES
# (computed when read, like AVAILABILITY_NAMES: datasets need no rebuild), by one compiled step
# (:func:`_sway_step`) in the cloud (:meth:`FeatureExtractor.sway`) and on a dataset's samples
# (:func:`with_derived_columns`), both from the float32 values the samples store.
SWAY_WINDOW_S = 30.0  # time constant of the RMS: the 30 s of the lead (real-data.md, the sway as an alarm alone)
SWAY_WARMUP_S = HISTORY_SLOW_S  # lateral_speed_mps settles this long after d is first known: not in the RMS
SWAY_MIN_HISTORY_S = 2.0  # s of RMS history before the quantities are given (sway_known = 1)
SWAY_SPEED_FLOOR_MPS = 0.1  # a steady vehicle's scale: the lead's floor; recorded sway is 0.1-0.3 m/s
SWAY_SPEED_CAP_MPS = 0.5  # squares capped at 0.25 m^2/s^2 (the lead's): a change is 0.5-1 m/s for ~3 s
SWAY_DRIFT_FLOOR_M = 0.1  # a steady vehicle's scale of lateral_drift_m
SWAY_DRIFT_CAP_M = 1.0  # squares capped at 1 m^2: a change drifts ~3.5 m
SWAY_NAMES: tuple[str, ...] = ("sway_known", "lateral_speed_over_sway", "lateral_drift_over_sway")
# the model input lists this version computes for a sequence model: a model file records its own
SEQUENCE_INPUT_SETS: dict[str, tuple[str, ...]] = {
    "base": (*FEATURE_NAMES, *SEQUENCE_EXTRA_NAMES),
    "availability": (*FEATURE_NAMES, *SEQUENCE_EXTRA_NAMES, *AVAILABILITY_NAMES),
    "lateral": (*FEATURE_NAMES, *SEQUENCE_EXTRA_NAMES, *AVAILABILITY_NAMES, *LATERAL_NAMES),
    "sway": (*FEATURE_NAMES, *SEQUENCE_EXTRA_NAMES, *AVAILABILITY_NAMES, *LATERAL_NAMES, *SWAY_NAMES),
}

_LANE_KEY = 1.0e6  # lane * _LANE_KEY + s orders twins by lane, then along the road


_SIDE_OFFSETS = np.array([_LANE_OFFSET[side] for side in SIDES])
_PER_SIDE = ("gap_lead", "dv_lead", "gap_foll", "dv_foll", "stopped_ahead", "n_ahead")
_N_FEATURES = len(FEATURE_NAMES)
_N_OWN = FEATURE_NAMES.index("gap_lead_right")  # own-state columns before the per-side block
_HISTORY_OWN = ("speed_minus_ema", "speed_below_recent_max")  # filled by FeatureExtractor


@numba.njit(cache=True)
def _tick_matrix(s: np.ndarray, lane: np.ndarray, speed: np.ndarray, accel: np.ndarray, length: np.ndarray,
                 present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, len(FEATURE_NAMES)) features with the memoryless ones filled (the history columns are
    left 0 for :func:`_history`) and (N, num_lanes, 4) gap_lead, dv_lead, gap_foll, dv_foll towards every lane.
    `present`: (N, num_lanes) whether each lane exists at each twin's s (RoadFrame.lanes_present).

    Compiled (numba): it runs for every twin on every V2C tick, and on the tens of twins of a tick
    NumPy's per-call overhead, not arithmetic, was the cost (~40 array calls, ~125 us a tick; this
    is a few us). Neighbours are searched over all pairs with the sort keys lane * _LANE_KEY + s,
    so "ahead"/"behind" and ties are decided exactly as by a stable sort of those keys.
    """
    n = s.shape[0]
    num_lanes = present.shape[1]
    out = np.zeros((n, _N_FEATURES))
    lanes_q = np.zeros((n, num_lanes, 4))
    cell = np.zeros((num_lanes, len(_PER_SIDE)))  # one twin's per-side features towards every lane
    for i in range(n):
        li = lane[i]
        on_road = li >= 0
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = speed[i], accel[i], length[i], li
        if not on_road:  # a twin off the road has no lanes: every per-lane feature stays 0
            continue
        # `lane` counts the lanes present right of the own one (the track where every lane is
        # everywhere): a main line's rightmost lane is lane 0 where no acceleration lane is beside it
        to_right = 0
        for k in range(li):
            to_right += present[i, k]
        to_left = 0
        for k in range(li + 1, num_lanes):
            to_left += present[i, k]
        out[i, 3] = to_right
        out[i, 4] = to_left
        out[i, 5] = 1.0 if li >= 1 and present[i, li - 1] != 0 else 0.0
        out[i, 6] = 1.0 if li <= num_lanes - 2 and present[i, li + 1] != 0 else 0.0
        front_i = s[i] + length[i] / 2
        rear_i = s[i] - length[i] / 2
        for k in range(num_lanes):
            query = k * _LANE_KEY + s[i]  # twin i moved to lane k
            lead = stop = foll = -1
            lead_key = stop_key = np.inf
            foll_key = -np.inf
            n_ahead = 0
            for j in range(n):
                if lane[j] != k:  # off-road twins (lane -1) are never anyone's neighbour
                    continue
                key = lane[j] * _LANE_KEY + s[j]
                if key > query:  # nearest ahead: smallest key, ties the lowest index
                    if key < lead_key:
                        lead, lead_key = j, key
                    if speed[j] < STOPPED_MPS and key < stop_key:
                        stop, stop_key = j, key
                    if key <= query + DENSITY_RANGE_M:
                        n_ahead += 1
                elif key < query and key >= foll_key:  # nearest behind: largest key, ties the highest index
                    foll, foll_key = j, key
                # equal keys are nobody's neighbour
            cell[k, 0], cell[k, 1], cell[k, 2], cell[k, 3] = RANGE_M, 0.0, RANGE_M, 0.0
            cell[k, 4], cell[k, 5] = BLOCK_RANGE_M, n_ahead
            if lead >= 0:
                gap = (s[lead] - length[lead] / 2) - front_i
                if gap <= RANGE_M:
                    cell[k, 0], cell[k, 1] = gap, speed[lead] - speed[i]
            if foll >= 0:
                gap = rear_i - (s[foll] + length[foll] / 2)
                if gap <= RANGE_M:
                    cell[k, 2], cell[k, 3] = gap, speed[foll] - speed[i]
            if stop >= 0:
                gap = (s[stop] - length[stop] / 2) - front_i
                if gap <= BLOCK_RANGE_M:
                    cell[k, 4] = gap
            for q in range(4):
                lanes_q[i, k, q] = cell[k, q]
        # own lane and both sides, picked from the absolute lanes; 0 where the lane does not exist
        for side in range(3):
            target = li + _SIDE_OFFSETS[side]
            if 0 <= target < num_lanes and present[i, target] != 0:
                for q in range(len(_PER_SIDE)):
                    out[i, _N_OWN + side * len(_PER_SIDE) + q] = cell[target, q]
    return out, lanes_q


@numba.njit(cache=True)
def _history(out: np.ndarray, lanes_q: np.ndarray, speed: np.ndarray, lane: np.ndarray, present: np.ndarray,
             previous: np.ndarray,
             memory: np.ndarray, alphas: np.ndarray, decay: float, src_offset: np.ndarray,
             src_quantity: np.ndarray, col_speed_minus_ema: int, col_below_max: int) -> np.ndarray:
    """Update every twin's memory row from this tick and fill the history columns of `out`.

    Memory row: [speed EMA, leaky max speed, fast EMAs (speed, then lane-major per-lane
    quantities), slow EMAs (same)]; `previous[i]` is twin i's row in `memory`, -1 for a new twin,
    whose averages start at the current values. Returns the new memory, one row per twin.
    """
    n, num_lanes = lanes_q.shape[0], lanes_q.shape[1]
    h = 1 + num_lanes * 4
    state = np.empty((n, 2 + 2 * h))
    fresh = np.empty(2 + 2 * h)
    n_src = src_offset.shape[0]
    for i in range(n):
        fresh[0] = fresh[1] = fresh[2] = fresh[2 + h] = speed[i]
        for t in range(num_lanes):
            # a lane the twin does not have (off the road, or absent at its s) has no quantities:
            # NaN, so that its averages start afresh when the lane is there again, instead of
            # averaging the sentinel 0 in (a ramp vehicle's gap means read ~0 for seconds after it joined)
            known = lane[i] >= 0 and present[i, t] != 0
            for q in range(4):
                fresh[3 + t * 4 + q] = fresh[3 + h + t * 4 + q] = lanes_q[i, t, q] if known else np.nan
        for c in range(2 + 2 * h):
            prev = fresh[c] if previous[i] < 0 else memory[previous[i], c]
            if np.isnan(prev):
                prev = fresh[c]
            state[i, c] = prev + alphas[c] * (fresh[c] - prev)
        prev_max = state[i, 1] - decay  # column 1 has rate 0 above: the previous leaky maximum
        state[i, 1] = speed[i] if speed[i] >= prev_max else prev_max  # leaky maximum, not an average
        out[i, col_speed_minus_ema] = speed[i] - state[i, 0]
        out[i, col_below_max] = state[i, 1] - speed[i]
        out[i, _N_TICK] = state[i, 2] - state[i, 2 + h]  # speed_trend
        for m in range(n_src):
            target = lane[i] + src_offset[m]
            if lane[i] >= 0 and 0 <= target < num_lanes and present[i, target] != 0:
                column = 2 + 1 + target * 4 + src_quantity[m]
                out[i, _N_TICK + 1 + m] = state[i, column] - state[i, column + h]
                out[i, _N_TICK + 1 + n_src + m] = state[i, column + h]
            else:
                out[i, _N_TICK + 1 + m] = 0.0
                out[i, _N_TICK + 1 + n_src + m] = 0.0
    return state


# sway memory row: [known ticks without a break, RMS weight, mean square of lateral_speed_mps,
# mean square of lateral_drift_m, time of the twin's last tick]
_SWAY_WIDTH = 5


@numba.njit(cache=True)
def _sway_step(state: np.ndarray, fresh: bool, known: float, v: float, drift: float, t: float,
               params: np.ndarray, out: np.ndarray) -> None:
    """One tick of one twin: writes SWAY_NAMES into `out` from the state of the ticks before, then
    updates `state` (in place) with this tick. params: alpha, warmup ticks, min ticks, max gap s,
    speed floor, speed cap^2, drift floor, drift cap^2."""
    alpha, warmup, min_ticks, max_gap = params[0], params[1], params[2], params[3]
    if fresh or known < 0.5 or t - state[4] > max_gap:
        state[0] = state[1] = state[2] = state[3] = 0.0
    out[0] = out[1] = out[2] = 0.0
    state[4] = t
    if known < 0.5:
        return
    if state[0] >= warmup + min_ticks:
        out[0] = 1.0
        out[1] = v / max(np.sqrt(state[2] / state[1]), params[4])
        out[2] = drift / max(np.sqrt(state[3] / state[1]), params[6])
    if state[0] >= warmup:  # the lateral speed has settled: this tick enters the RMS of the next ones
        state[1] += alpha * (1.0 - state[1])
        state[2] += alpha * (min(v * v, params[5]) - state[2])
        state[3] += alpha * (min(drift * drift, params[7]) - state[3])
    state[0] += 1.0


@numba.njit(cache=True)
def _sway_tick(memory: np.ndarray, previous: np.ndarray, lateral: np.ndarray, t: float,
               params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SWAY_NAMES of the N twins of one snapshot and their new memory rows (`previous[i]`: twin i's
    row in `memory`, -1 for a new twin); `lateral`: (N, 3) LATERAL_NAMES."""
    n = lateral.shape[0]
    state = np.zeros((n, _SWAY_WIDTH))
    out = np.zeros((n, 3))
    for i in range(n):
        if previous[i] >= 0:
            state[i] = memory[previous[i]]
        _sway_step(state[i], previous[i] < 0, lateral[i, 0], lateral[i, 1], lateral[i, 2], t, params, out[i])
    return out, state


@numba.njit(cache=True)
def _sway_tracks(new_track: np.ndarray, known: np.ndarray, v: np.ndarray, drift: np.ndarray, t: np.ndarray,
                 params: np.ndarray) -> np.ndarray:
    """SWAY_NAMES of rows sorted by track and time (`new_track`: the first row of a twin's track)."""
    out = np.zeros((len(t), 3))
    state = np.zeros(_SWAY_WIDTH)
    for i in range(len(t)):
        _sway_step(state, new_track[i], known[i], v[i], drift[i], t[i], params, out[i])
    return out


def sway_params(period_s: float) -> np.ndarray:
    """The constants of :func:`_sway_step` for a V2C period."""
    ticks = lambda seconds: float(round(seconds / period_s))  # noqa: E731
    return np.array([1.0 - np.exp(-period_s / SWAY_WINDOW_S), ticks(SWAY_WARMUP_S), ticks(SWAY_MIN_HISTORY_S),
                     1.5 * period_s, SWAY_SPEED_FLOOR_MPS, SWAY_SPEED_CAP_MPS ** 2, SWAY_DRIFT_FLOOR_M,
                     SWAY_DRIFT_CAP_M ** 2])


def _as_stored(values: np.ndarray) -> np.ndarray:
    """float64 copies of the float32 values a dataset's samples store (both paths read these)."""
    return np.ascontiguousarray(np.asarray(values, dtype=np.float32), dtype=np.float64)


def _lanes_present(road, s: np.ndarray) -> np.ndarray:
    """(N, num_lanes) uint8: the lanes present at each s (all of them on a lane count)."""
    if isinstance(road, (int, np.integer)):
        return np.ones((len(s), int(road)), dtype=np.uint8)
    if road.all_lanes_everywhere:  # the per-tick path on the straight road: no lookup
        return np.ones((len(s), road.num_tracks), dtype=np.uint8)
    return np.ascontiguousarray(road.lanes_present(s), dtype=np.uint8)


def lane_end_ahead_m(road, s: np.ndarray, lane: np.ndarray) -> np.ndarray:
    """Distance from s to where the twin's own lane ends ahead (a lane drop, the end of an
    acceleration lane), BLOCK_RANGE_M when it does not end within that, 0 off the road.

    Not among FEATURE_NAMES (the MLP's fixed input list) but one of SEQUENCE_EXTRA_NAMES: the
    datasets' samples carry it as an extra column and the sequence model takes it as an input."""
    s = np.asarray(s, dtype=float)
    lane = np.asarray(lane, dtype=np.int64)
    if road.all_lanes_everywhere:  # every lane runs to the route's end (the per-tick path on the straight road)
        return np.where(lane >= 0, BLOCK_RANGE_M, 0.0)
    end = road.lane_end_ahead(np.maximum(lane, 0), s)
    out = np.minimum(np.nan_to_num(end - s, nan=0.0, posinf=BLOCK_RANGE_M), BLOCK_RANGE_M)
    return np.where(lane >= 0, out, 0.0)


def _kernel_inputs(s, lane, speed, accel, length) -> tuple[np.ndarray, ...]:
    """Contiguous float64 (lane: int64) arrays: one compiled signature whatever the caller's views."""
    return (np.ascontiguousarray(s, dtype=float), np.ascontiguousarray(lane, dtype=np.int64),
            *(np.ascontiguousarray(v, dtype=float) for v in (speed, accel, length)))


def tick_features(s: np.ndarray, lane: np.ndarray, speed: np.ndarray, accel: np.ndarray,
                  length: np.ndarray, num_lanes, per_lane: bool = False) -> dict[str, np.ndarray]:
    """The memoryless features of all twins of one tick (vectorised); s is the footprint centre.

    num_lanes: the road's lane count (every lane everywhere), or the road frame whose lanes
    present at each twin's s count.

    per_lane: also return `_per_lane`, (N, num_lanes, 4): gap_lead, dv_lead, gap_foll, dv_foll
    of each twin towards every lane of the road by absolute index (own lane included).
    """
    args = _kernel_inputs(s, lane, speed, accel, length)
    matrix, lanes_q = _tick_matrix(*args, _lanes_present(num_lanes, args[0]))
    out = {name: matrix[:, i] for i, name in enumerate(FEATURE_NAMES[:_N_TICK]) if name not in _HISTORY_OWN}
    if per_lane:
        out["_per_lane"] = lanes_q
    return out


class FeatureExtractor:
    """Per-twin feature memory plus :func:`tick_features`; call once per snapshot, in time order.

    Memory per twin (one row of a :class:`TwinMemory`): the speed EMA (SPEED_EMA_S) and leaky maximum speed,
    then the fast and slow EMAs of the speed and of the per-lane quantities (see
    HISTORY_FAST_S). A twin seen for the first time starts every average at its current value
    (zero trend); a twin missing from a snapshot is forgotten; a lane the twin does not have at a
    tick (off the road, or absent at its s) has no averages, which start at the current values
    when it has the lane again.
    """

    def __init__(self, road: RoadFrame, period_s: float):
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
        # lateral motion (LATERAL_NAMES): fast, slow and reference EMA of d per twin
        self._lateral = TwinMemory(3)
        self._alpha_lateral = np.array([self._alpha_fast, self._alpha_slow,
                                        1.0 - np.exp(-period_s / LATERAL_REFERENCE_S)])
        self._sway = TwinMemory(_SWAY_WIDTH)  # SWAY_NAMES: the twin's own sway scale
        self._sway_params = sway_params(period_s)
        self._col_speed_minus_ema = FEATURE_NAMES.index("speed_minus_ema")
        self._col_below_max = FEATURE_NAMES.index("speed_below_recent_max")
        split = [name.rsplit("_", 1) for name in HISTORY_MEAN_SOURCES]  # e.g. ("gap_lead", "left")
        self._src_offset = np.array([_LANE_OFFSET[side] for _, side in split])
        self._src_quantity = np.array([_LANE_QUANTITIES.index(q) for q, _ in split])

    def __call__(self, ids, s: np.ndarray, lane: np.ndarray, speed: np.ndarray, accel: np.ndarray,
                 length: np.ndarray) -> np.ndarray:
        """(N, len(FEATURE_NAMES)) float64 features of the N twins of one snapshot; `s` along the
        road (RoadFrame.to_frame of the twins' positions: their lateral coordinate is never used)."""
        s, lane, speed, accel, length = _kernel_inputs(s, lane, speed, accel, length)
        present = _lanes_present(self.road, s)
        out, lanes_q = _tick_matrix(s, lane, speed, accel, length, present)
        state = _history(out, lanes_q, speed, lane, present, self._memory.previous_rows(ids), self._memory.state,
                         self._alphas, self._decay, self._src_offset, self._src_quantity,
                         self._col_speed_minus_ema, self._col_below_max)
        self._memory.keep(ids, state)
        return out

    def lateral(self, ids, d: np.ndarray, known: np.ndarray | None = None) -> np.ndarray:
        """(N, len(LATERAL_NAMES)) lateral-motion inputs of the N twins of one snapshot, in time
        order like __call__; `d` across the road (left positive), `known` False where the source
        has no lateral position (default: all known)."""
        d = np.asarray(d, dtype=float)
        known = np.ones(len(d), dtype=bool) if known is None else np.asarray(known, dtype=bool)
        prev = self._lateral.previous_rows(ids)
        old = np.full((len(d), 3), np.nan)
        seen = prev >= 0
        old[seen] = self._lateral.state[prev[seen]]
        old = np.where(np.isnan(old), d[:, None], old)  # a new twin (or d unknown until now) starts at d
        state = old + self._alpha_lateral * (d[:, None] - old)
        state[~known] = np.nan
        self._lateral.keep(ids, state)
        out = np.zeros((len(d), len(LATERAL_NAMES)))
        out[:, 0] = known
        out[known, 1] = (state[known, 0] - state[known, 1]) / (HISTORY_SLOW_S - HISTORY_FAST_S)
        out[known, 2] = d[known] - state[known, 2]
        return out

    def sway(self, ids, time: float, lateral: np.ndarray) -> np.ndarray:
        """(N, len(SWAY_NAMES)) lateral motion over each twin's own sway, from the (N, 3)
        LATERAL_NAMES of the same snapshot (:meth:`lateral`), in time order; `time` the snapshot's."""
        lateral = np.asarray(lateral, dtype=float)
        known = np.ascontiguousarray(lateral[:, 0], dtype=np.float64)
        stored = np.column_stack([known, _as_stored(lateral[:, 1]), _as_stored(lateral[:, 2])])
        out, state = _sway_tick(self._sway.state, self._sway.previous_rows(ids), stored, float(time),
                                self._sway_params)
        self._sway.keep(ids, state)
        return out

    def from_twins(self, twins, extras: bool = False, availability: bool = False,
                   lateral: bool = False, sway: bool = False) -> np.ndarray:
        """Features of a TwinStates snapshot (the run-time path); extras: with the
        SEQUENCE_EXTRA_NAMES columns appended (the sequence model's inputs); availability: then
        also AVAILABILITY_NAMES; lateral: then also LATERAL_NAMES; sway: then also SWAY_NAMES
        (SEQUENCE_INPUT_SETS)."""
        s, d = twins.road_frame(self.road)
        out = self(twins.ids, s, twins.lane, twins.speed, twins.accel, twins.length)
        if not extras:
            return out
        columns = [out, lane_end_ahead_m(self.road, s, twins.lane)[:, None]]
        if availability or lateral or sway:
            columns.append(availability_flags(out))
        if lateral or sway:
            columns.append(self.lateral(twins.ids, d))
        if sway:
            columns.append(self.sway(twins.ids, twins.time, columns[-1]))
        return np.hstack(columns)


def features_from_twins_table(twins: pd.DataFrame, vehicles: pd.DataFrame, road: RoadFrame,
                              period_s: float) -> pd.DataFrame:
    """Replay a run's `twins` table snapshot by snapshot through a FeatureExtractor.

    Returns time, vehicle_id and one column per feature (FEATURE_NAMES, then
    SEQUENCE_EXTRA_NAMES, then LATERAL_NAMES), sorted by time then vehicle id.
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
    s, d = road.to_road_frame(twins["x"].to_numpy(float), twins["y"].to_numpy(float))
    # a recording without lateral position says so (`d_known`); a simulated twin's GNSS position has one
    d_known = (twins["d_known"].to_numpy(dtype=bool) if "d_known" in twins.columns
               else np.ones(len(twins), dtype=bool))
    lane = twins["lane"].to_numpy()
    speed, accel = twins["speed"].to_numpy(float), twins["accel"].to_numpy(float)
    blocks = [extractor(ids[a:b], s[a:b], lane[a:b], speed[a:b], accel[a:b], length[a:b])
              for a, b in zip(starts, ends)]
    lateral = [extractor.lateral(ids[a:b], d[a:b], d_known[a:b]) for a, b in zip(starts, ends)]
    values = np.concatenate(blocks) if blocks else np.zeros((0, len(FEATURE_NAMES)))
    out = pd.DataFrame(values, columns=list(FEATURE_NAMES))
    out["lane_end_ahead_m"] = lane_end_ahead_m(road, s, lane) if len(times) else np.zeros(0)
    lateral_values = np.concatenate(lateral) if lateral else np.zeros((0, len(LATERAL_NAMES)))
    for k, name in enumerate(LATERAL_NAMES):
        out[name] = lateral_values[:, k]
    out.insert(0, "vehicle_id", twins["vehicle_id"].astype(str).to_numpy())
    out.insert(0, "time", times)
    return out


def _availability_columns(col) -> np.ndarray:
    """(N, len(AVAILABILITY_NAMES)) 0/1 flags from the FEATURE_NAMES columns `col(name)`."""
    on_road = col("lane") >= 0  # _tick_matrix leaves lane = -1 for a twin off the road
    exists = {"own": on_road, "left": on_road & (col("left_lane_exists") > 0.5),
              "right": on_road & (col("right_lane_exists") > 0.5)}
    flags = [exists[side] & (col(f"gap_{kind}_{side}") < RANGE_M) for side in ("own", "left", "right")
             for kind in ("lead", "foll")]
    return np.column_stack(flags).astype(np.float64) if flags else np.zeros((0, 0))


_FEATURE_INDEX = {name: i for i, name in enumerate(FEATURE_NAMES)}


def availability_flags(features: np.ndarray) -> np.ndarray:
    """AVAILABILITY_NAMES of an (N, len(FEATURE_NAMES)) feature matrix (the cloud's per-tick path)."""
    features = np.asarray(features)
    return _availability_columns(lambda name: features[:, _FEATURE_INDEX[name]])


def stored_columns(names) -> list[str]:
    """The sample columns a list of model inputs is computed from (AVAILABILITY_NAMES and SWAY_NAMES
    are derived; SWAY_NAMES also need the id columns seed, vehicle_id and time, which every stream has)."""
    needed = [n for n in names if n not in AVAILABILITY_NAMES and n not in SWAY_NAMES]
    if any(n in AVAILABILITY_NAMES for n in names):
        needed += [n for n in _AVAILABILITY_SOURCES if n not in needed]
    if any(n in SWAY_NAMES for n in names):
        needed += [n for n in LATERAL_NAMES if n not in needed]
    return needed


_AVAILABILITY_SOURCES = ("lane", "left_lane_exists", "right_lane_exists",
                         *[f"gap_{kind}_{side}" for side in ("own", "left", "right") for kind in ("lead", "foll")])


def sway_columns(frame: pd.DataFrame, period_s: float) -> np.ndarray:
    """(len(frame), len(SWAY_NAMES)) of a samples frame (any row order) with seed, vehicle_id, time
    and LATERAL_NAMES: each (seed, vehicle) replayed in time order by the cloud's step."""
    missing = [c for c in ("seed", "vehicle_id", "time", *LATERAL_NAMES) if c not in frame.columns]
    if missing:
        raise ValueError(f"samples: columns {missing} are needed for {list(SWAY_NAMES)}")
    vid = pd.factorize(frame["vehicle_id"].astype(str))[0]
    t = frame["time"].to_numpy(dtype=np.float64)
    seed = frame["seed"].to_numpy(dtype=np.int64)
    order = np.lexsort((t, vid, seed))
    new = np.ones(len(order), dtype=np.bool_)
    if len(order) > 1:
        new[1:] = (seed[order][1:] != seed[order][:-1]) | (vid[order][1:] != vid[order][:-1])
    values = _sway_tracks(new, _as_stored(frame["lateral_known"].to_numpy()[order]),
                          _as_stored(frame["lateral_speed_mps"].to_numpy()[order]),
                          _as_stored(frame["lateral_drift_m"].to_numpy()[order]), np.ascontiguousarray(t[order]),
                          sway_params(period_s))
    out = np.empty_like(values)
    out[order] = values
    return out


def with_derived_columns(frame: pd.DataFrame, names, period_s: float | None = None) -> pd.DataFrame:
    """`frame` (samples) with the AVAILABILITY_NAMES and SWAY_NAMES among `names` added (in place;
    returned); SWAY_NAMES need the V2C period `period_s`."""
    wanted = [n for n in names if n in AVAILABILITY_NAMES]
    if wanted:
        flags = _availability_columns(lambda name: frame[name].to_numpy(dtype=float))
        for name in wanted:
            frame[name] = flags[:, AVAILABILITY_NAMES.index(name)]
    wanted = [n for n in names if n in SWAY_NAMES]
    if wanted:
        if period_s is None:
            raise ValueError(f"{wanted}: the V2C period is needed to compute them (period_s)")
        values = sway_columns(frame, period_s)
        for name in wanted:
            frame[name] = values[:, SWAY_NAMES.index(name)].astype(np.float32)
    return frame
