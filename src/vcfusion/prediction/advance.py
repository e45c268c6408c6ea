"""What limits how early a lane change can be predicted: signal separability before the crossing.

A lane change is predicted early only if some causal signal of the changing vehicle, seconds
before its centre crosses the line (the midpoint M), stands out from the same signal of vehicles
that keep their lane: every lane-keeping tick above the alarm threshold is a candidate false
alarm. This module measures that, model-free, on a decision stream (sorted by seed, vehicle,
time; the layout of `vcfusion.prediction.train.stream_with_events`):

- :func:`lane_keeping_mask`: the ticks of lane keeping, far from any change of the vehicle;
- :func:`separability`: for each time k before M, the median signal of the changes seen then,
  the share of lane-keeping ticks above that median, and the AUC (changing vs lane keeping);
- :func:`window_auc`: the AUC of ticks in a window before M (direction-aware for the side
  quantities: the target lane's side for the changes, both existing sides for lane keeping);
- :func:`ema_lateral_speed`, :func:`kalman_lateral_speed`: causal lateral-speed estimators of a
  position series, per track (the cloud's `lateral_speed_mps` is the first with 0.5 s / 2 s:
  `vcfusion.prediction.features.LATERAL_NAMES`), to compare estimators on recorded positions.

Used by `tools/real_advance_limits.py` (docs/components/real-data.md, "What limits the advance").
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.stats import mannwhitneyu

# lane keeping: no change of the vehicle ending within this long after the tick (the scoring
# horizon 10 s plus 2 s), and none ending within this long before it (settling after a change)
KEEP_BEFORE_END_S = 12.0
KEEP_AFTER_END_S = 5.0


def track_starts(stream: pd.DataFrame, period_s: float) -> np.ndarray:
    """True at the first row of each stretch of consecutive ticks of one (seed, vehicle)."""
    seed = stream["seed"].to_numpy()
    vid = stream["vehicle_id"].astype(str).to_numpy()
    t = stream["time"].to_numpy(dtype=float)
    new = np.ones(len(t), dtype=bool)
    if len(t) > 1:
        new[1:] = (seed[1:] != seed[:-1]) | (vid[1:] != vid[:-1]) | (np.abs(np.diff(t) - period_s) > 1e-3)
    return new


def lane_keeping_mask(stream: pd.DataFrame, events: pd.DataFrame) -> np.ndarray:
    """True at ticks t with no change of the vehicle ending in (t - KEEP_AFTER_END_S, t + KEEP_BEFORE_END_S)."""
    keep = np.ones(len(stream), dtype=bool)
    if not len(events):
        return keep
    key = stream["seed"].astype(str) + "|" + stream["vehicle_id"].astype(str)
    t = stream["time"].to_numpy(dtype=float)
    rows = pd.Series(np.arange(len(stream))).groupby(key.to_numpy()).apply(np.asarray)
    for seed, vid, end in zip(events["seed"], events["vehicle_id"].astype(str), events["end"]):
        idx = rows.get(f"{seed}|{vid}")
        if idx is None:
            continue
        near = (t[idx] > end - KEEP_BEFORE_END_S) & (t[idx] < end + KEEP_AFTER_END_S)
        keep[idx[near]] = False
    return keep


def auc(positive: np.ndarray, negative: np.ndarray) -> float:
    """P(a positive's value > a negative's), ties counted half (Mann-Whitney U / (n_pos n_neg))."""
    positive, negative = np.asarray(positive, float), np.asarray(negative, float)
    if not len(positive) or not len(negative):
        return float("nan")
    return float(mannwhitneyu(positive, negative).statistic / (len(positive) * len(negative)))


def _rows_at(stream: pd.DataFrame, events: pd.DataFrame, before_s: float) -> np.ndarray:
    """Row index of each change's tick `before_s` before its midpoint (-1 where not observed)."""
    index = pd.Series(np.arange(len(stream)), index=pd.MultiIndex.from_arrays(
        [stream["seed"].to_numpy(), stream["vehicle_id"].astype(str).to_numpy(),
         np.round(stream["time"].to_numpy(dtype=float), 1)]))
    index = index[~index.index.duplicated()]
    keys = list(zip(events["seed"], events["vehicle_id"].astype(str),
                    np.round(events["mid"].to_numpy(float) - before_s, 1)))
    return index.reindex(keys).fillna(-1).to_numpy(dtype=int)


def separability(stream: pd.DataFrame, events: pd.DataFrame, signals: dict[str, np.ndarray],
                 before_s=(6, 5, 4, 3, 2, 1.5, 1, 0.5, 0)) -> pd.DataFrame:
    """Per time before the midpoint and signal: changes observed then (`n`), the median value of
    the changing vehicles (`median`), the share of lane-keeping ticks above it (`lk_above`, 0-1:
    the alarm rate a threshold there would cost) and the AUC changing vs lane keeping."""
    keep = lane_keeping_mask(stream, events)
    rows = []
    for k in before_s:
        at = _rows_at(stream, events, k)
        at = at[at >= 0]
        for name, values in signals.items():
            v = np.asarray(values, dtype=float)
            med = float(np.median(v[at])) if len(at) else float("nan")
            rows.append({"before_mid_s": float(k), "signal": name, "n": int(len(at)), "median": med,
                         "lk_above": float(np.mean(v[keep] > med)) if len(at) else float("nan"),
                         "auc": auc(v[at], v[keep])})
    return pd.DataFrame(rows)


def change_direction(stream: pd.DataFrame, events: pd.DataFrame) -> np.ndarray:
    """+1 (to the left: a higher lane index) or -1 per change, from the lane before and at its midpoint."""
    at = _rows_at(stream, events, 0.0)
    before = _rows_at(stream, events, 0.1)
    lane = stream["lane"].to_numpy(dtype=float)
    out = np.zeros(len(events), dtype=int)
    ok = (at >= 0) & (before >= 0)
    out[ok] = np.sign(lane[at[ok]] - lane[before[ok]]).astype(int)
    return out


def window_auc(stream: pd.DataFrame, events: pd.DataFrame, columns: list[str], side_columns: list[str],
               windows=((5.0, 3.0), (3.0, 1.5), (1.5, 0.0)), period_s: float = 0.1) -> pd.DataFrame:
    """AUC of each column, ticks of changes from `lo` to `hi` s before their midpoint vs lane-keeping
    ticks. `side_columns` are patterns with `{side}` (left / right): a change reads its target side,
    a lane keeper both sides where the lane exists (`{side}_lane_exists`)."""
    keep = lane_keeping_mask(stream, events)
    direction = change_direction(stream, events)
    exists = {side: stream[f"{side}_lane_exists"].to_numpy() > 0.5 for side in ("left", "right")}
    rows = []
    for lo, hi in windows:
        picks, sides = [], []
        for k in np.arange(hi, lo + period_s / 2, period_s):
            at = _rows_at(stream, events, float(k))
            ok = (at >= 0) & (direction != 0)
            picks.append(at[ok])
            sides.append(direction[ok])
        at = np.concatenate(picks)
        side = np.concatenate(sides)
        seen = _rows_at(stream, events, float(hi)) >= 0
        row = {"window": f"{lo:g}-{hi:g} s before the crossing", "changes": int((seen & (direction != 0)).sum()),
               "ticks": int(len(at))}
        for c in columns:
            v = stream[c].to_numpy(dtype=float)
            row[c] = auc(v[at], v[keep])
        for pattern in side_columns:
            left, right = (stream[pattern.format(side=s)].to_numpy(dtype=float) for s in ("left", "right"))
            target = np.where(side > 0, left[at], right[at])
            target_ok = np.where(side > 0, exists["left"][at], exists["right"][at])
            ref = np.concatenate([left[keep & exists["left"]], right[keep & exists["right"]]])
            row[pattern.format(side="target")] = auc(target[target_ok], ref)
        rows.append(row)
    return pd.DataFrame(rows)


def ema_lateral_speed(d: np.ndarray, start: np.ndarray, period_s: float, fast_s: float, slow_s: float) -> np.ndarray:
    """(fast EMA - slow EMA of d) / (slow_s - fast_s) per track (`start` True at a track's first
    tick, where both averages start at d): a steady drift's speed after a transient of ~slow_s."""
    d = np.asarray(d, dtype=float)
    a_f, a_s = 1.0 - np.exp(-period_s / fast_s), 1.0 - np.exp(-period_s / slow_s)
    out = np.zeros(len(d))
    f = s = 0.0
    for i, x in enumerate(d):
        if start[i]:
            f = s = x
        else:
            f += a_f * (x - f)
            s += a_s * (x - s)
        out[i] = (f - s) / (slow_s - fast_s)
    return out


def kalman_lateral_speed(d: np.ndarray, start: np.ndarray, period_s: float, sigma_m: float,
                         accel_psd: float, speed0_std_mps: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Causal constant-velocity Kalman filter of a position series per track: measurement noise
    std `sigma_m` (m), white lateral acceleration of spectral density `accel_psd` (m^2/s^3); a
    track starts at its first position with speed 0 +- speed0_std_mps. Returns (position, speed)."""
    d = np.asarray(d, dtype=float)
    r, q, dt = sigma_m ** 2, accel_psd, period_s
    pos, vel = np.zeros(len(d)), np.zeros(len(d))
    x0 = x1 = p11 = p12 = p22 = 0.0
    for i, z in enumerate(d):
        if start[i]:
            x0, x1, p11, p12, p22 = z, 0.0, r, 0.0, speed0_std_mps ** 2
        else:
            x0 += dt * x1
            p11 += dt * (2 * p12 + dt * p22) + q * dt ** 3 / 3
            p12 += dt * p22 + q * dt ** 2 / 2
            p22 += q * dt
            gain0, gain1 = p11 / (p11 + r), p12 / (p11 + r)
            innovation = z - x0
            x0 += gain0 * innovation
            x1 += gain1 * innovation
            p22 -= gain1 * p12
            p12 -= gain0 * p12
            p11 -= gain0 * p11
        pos[i], vel[i] = x0, x1
    return pos, vel


def position_noise(d: np.ndarray, start: np.ndarray) -> dict:
    """White-noise content of a position series: the robust std of second differences within tracks
    over sqrt(6) (white noise of std s gives 6 s^2) and the lag-1 autocorrelation of the first
    differences (near 0 for white noise, near 1 for a smoothed series)."""
    d = np.asarray(d, dtype=float)
    same1 = ~start[1:]
    same2 = same1[1:] & same1[:-1]
    d2 = (d[2:] - 2 * d[1:-1] + d[:-2])[same2]
    d1 = np.diff(d)
    mad = float(np.median(np.abs(d2 - np.median(d2))) * 1.4826) if len(d2) else float("nan")
    pairs = same1[1:] & same1[:-1]
    a, b = d1[1:][pairs], d1[:-1][pairs]
    a, b = a - a.mean(), b - b.mean()
    return {"white_noise_std_m": mad / np.sqrt(6.0),
            "first_difference_lag1_autocorrelation": float(np.mean(a * b) / np.mean(b * b)) if len(a) else float("nan")}
