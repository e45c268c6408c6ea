"""Safety and comfort metrics of one trip, on the ego's 0.01 s trajectory.

Definitions (the same for both arms of the guidance study):

- **Acceleration** a[i] = (v[i+1] - v[i]) / dt from the logged ego speed (this is exactly the
  acceleration the driver model applied; SUMO integrates the speed we impose).
  ``avg_abs_accel_mps2`` = mean |a| over the whole trip, unfiltered.
- **Jerk**: the acceleration smoothed by a centred moving average over ``jerk_window_s``
  (default 0.1 s, the control period: the command is piecewise constant over a tick, so the
  raw 0.01 s difference of a step would read 10x the rate at which the driver moved the
  pedal), then differentiated: j = diff(a_smooth) / dt. A continuous jerk ramp passes
  unchanged. ``max_abs_jerk_mps3`` = max |j|.
- **TTC to the lane-change vehicle** (the paper's "silver vehicle"): the first cut-in ahead of
  the ego (``lane_changes`` rows with ``into_ego_lane`` whose rear is ahead of the ego's front by at
  most ``cut_in_range_m`` at its mid time, the scenario's ``metrics.leader_range_m``: a change into
  the ego's lane a kilometre ahead is nobody's cut-in; earliest ``mid_time``). From its mid time (the moment its centre enters the ego lane) until it
  first leaves the ego lane again (or the trip ends), at every ego sample:
  gap = its rear bumper - the ego's front bumper (along the road), closing speed =
  v_ego - v_target; TTC = gap / closing, defined only where closing > 0 (constant-velocity
  TTC, as SUMO's SSM device defines it for a following situation). The target's 0.1 s
  trajectory is interpolated linearly to the ego's sample times.
  ``avg_ttc_s`` = mean TTC over the samples where it is defined; ``min_ttc_s`` = minimum;
  ``ttc_samples`` = how many there were (0: the ego never closed on it, TTC undefined -> NaN).
  Because TTC grows without bound as the closing speed goes to 0, the raw mean is dominated
  by near-zero closing speeds; ``avg_ttc_clipped_s`` is the mean of min(TTC, ``ttc_clip_s``)
  (default 20 s) over the same samples (winsorised: no sample is dropped).
- **TET / TIT** (Minderhoud & Bovy 2001) on that same TTC series: TET = time with
  TTC < threshold (s); TIT = integral of (threshold - TTC) over that time (s^2). The threshold
  and the jerk window are the scenario's ``metrics:`` block (default 1.5 s, SSAM), shared with
  the per-vehicle run metrics (vcfusion.metrics.traffic). NaN, like TTC, for a trip without a
  cut-in ahead of the ego.
- **Minimum gap to the cut-in vehicle**: ``min_gap_to_target_m`` = the least gap (as above,
  while the vehicle stays in the ego's lane) over the ``cut_in_window_s`` (the scenario's
  ``metrics.cut_in_window_s``, 10 s) from the cut-in's mid time: the ego's response to the cut-in,
  not a queue it meets behind the same vehicle a minute later (curved seeds 5042 and 5124,
  docs/components/guidance-loop.md). ``min_gap_after_cut_in_s`` is when it came (s after the mid
  time). ``min_gap_stay_m`` is the least gap over the whole stay, the window left out.
- **Collisions**: SUMO collisions involving the ego.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from vcfusion.records import EGO_ID


def colliding_pairs(collisions: pd.DataFrame | None) -> set[tuple[str, str]]:
    """The (collider, victim) pairs of a collisions table: SUMO reports a pair every step it stays
    in contact, so a collision is a pair, not a row."""
    if collisions is None or not len(collisions):
        return set()
    return set(zip(collisions["collider"].tolist(), collisions["victim"].tolist()))


def acceleration_from_speed(speed: np.ndarray, dt: float) -> np.ndarray:
    """Forward difference: a[i] applies over [t_i, t_i + dt]."""
    v = np.asarray(speed, dtype=float)
    return np.diff(v) / dt


def jerk_from_acceleration(accel: np.ndarray, dt: float, window_s: float = 0.1) -> np.ndarray:
    """Jerk after a centred moving average of `window_s` (see the module doc)."""
    a = np.asarray(accel, dtype=float)
    n = max(1, int(round(window_s / dt)))
    if a.size < n + 1:
        return np.zeros(0)
    smooth = np.convolve(a, np.ones(n) / n, mode="valid") if n > 1 else a
    return np.diff(smooth) / dt


def ttc_series(gap_m: np.ndarray, ego_speed: np.ndarray, target_speed: np.ndarray) -> np.ndarray:
    """Constant-velocity TTC = gap / closing speed where the ego closes in (else NaN)."""
    gap = np.asarray(gap_m, dtype=float)
    closing = np.asarray(ego_speed, dtype=float) - np.asarray(target_speed, dtype=float)
    ttc = np.full(gap.shape, np.nan)
    ok = (closing > 0) & (gap > 0)
    ttc[ok] = gap[ok] / closing[ok]
    return ttc


def exposure(ttc: np.ndarray, dt: float, threshold_s: float) -> tuple[float, float]:
    """(TET s, TIT s^2) of a TTC series sampled every dt; NaN samples are not exposed."""
    t = np.asarray(ttc, dtype=float)
    below = np.isfinite(t) & (t < threshold_s)
    return float(below.sum() * dt), float(np.sum(threshold_s - t[below]) * dt)


def cut_ins(lane_changes, range_m: float):
    """Per lane change (a DataFrame, or a dict of column arrays): whether it is a cut-in, into the
    ego's lane with its rear ahead of the ego's front by at most range_m (bumper to bumper along the
    road at its mid time)."""
    gap = lane_changes["gap_to_ego_m"]
    return lane_changes["into_ego_lane"] & lane_changes["ahead_of_ego"] & (gap <= range_m)


def cut_in_target(lane_changes: pd.DataFrame, range_m: float) -> pd.Series | None:
    """The first cut-in (:func:`cut_ins`) ahead of the ego (None if there is none)."""
    if lane_changes is None or lane_changes.empty or "into_ego_lane" not in lane_changes:
        return None
    cut = lane_changes[cut_ins(lane_changes, range_m)]
    if cut.empty:
        return None
    return cut.sort_values("mid_time").iloc[0]


def target_ttc(ego: pd.DataFrame, trajectories: pd.DataFrame, target_id: str, target_length: float,
               from_time: float, ego_lane: int) -> pd.DataFrame:
    """Per ego sample from `from_time`: gap, closing speed and TTC to the target."""
    e = ego[ego["time"] >= from_time - 1e-9]
    tr = trajectories[trajectories["vehicle_id"] == target_id].sort_values("time")
    if e.empty or tr.empty:
        return pd.DataFrame(columns=["time", "gap_m", "closing_mps", "ttc_s"])
    t = e["time"].to_numpy()
    inside = (t >= tr["time"].iloc[0] - 1e-9) & (t <= tr["time"].iloc[-1] + 1e-9)
    rear = np.interp(t, tr["time"], tr["s"]) - target_length / 2.0
    v_target = np.interp(t, tr["time"], tr["speed"])
    # The lane at the latest 0.1 s sample not after t (a lane is not interpolated).
    idx = np.clip(np.searchsorted(tr["time"].to_numpy(), t + 1e-9) - 1, 0, len(tr) - 1)
    in_lane = (tr["lane"].to_numpy()[idx] == ego_lane) & inside
    # "still in the ego lane": the cut-in's own stay, up to the first sample it is out of the lane
    # again (curved seed 4174: a target that left at 32 s and changed back in behind the ego at
    # 63 s gave a minimum gap of -17.5 m)
    has_left = np.maximum.accumulate(np.maximum.accumulate(in_lane) & ~in_lane)
    valid = in_lane & ~has_left
    gap = rear - e["s"].to_numpy()
    ego_speed = e["speed"].to_numpy()
    ttc = ttc_series(gap, ego_speed, v_target)
    ttc[~valid] = np.nan
    return pd.DataFrame({"time": t, "gap_m": np.where(valid, gap, np.nan),
                         "closing_mps": np.where(valid, ego_speed - v_target, np.nan), "ttc_s": ttc})


def kinematics(time: np.ndarray, s: np.ndarray, speed: np.ndarray, dt: float, jerk_window_s: float = 0.1) -> dict:
    """Travel and comfort figures of one vehicle's samples every dt (time order); the same
    definitions for the guidance study's ego and every vehicle of a run's metrics table."""
    speed = np.asarray(speed, dtype=float)
    accel = acceleration_from_speed(speed, dt)
    jerk = jerk_from_acceleration(accel, dt, jerk_window_s)
    n = len(speed)
    return {
        "trip_time_s": float(time[-1] - time[0] + dt) if n else 0.0,
        "ego_distance_m": float(s[-1] - s[0]) if n else 0.0,
        "mean_speed_mps": float(speed.mean()) if n else math.nan,
        "min_speed_mps": float(speed.min()) if n else math.nan,
        "avg_abs_accel_mps2": float(np.abs(accel).mean()) if accel.size else math.nan,
        "max_decel_mps2": float(max(0.0, -accel.min())) if accel.size else math.nan,
        "max_abs_jerk_mps3": float(np.abs(jerk).max()) if jerk.size else math.nan,
    }


def trip_metrics(tables: dict[str, pd.DataFrame], ego_lane: int, dt: float, cut_in_range_m: float,
                 ttc_threshold_s: float = 1.5, jerk_window_s: float = 0.1, ttc_clip_s: float = 20.0,
                 cut_in_window_s: float = 10.0) -> dict:
    """Safety/comfort metrics of one run's tables (see the module doc for the definitions).
    The thresholds come from the scenario's `metrics:` block (MetricsConfig)."""
    ego = tables["ego"].sort_values("time")
    out = kinematics(ego["time"].to_numpy(), ego["s"].to_numpy(), ego["speed"].to_numpy(), dt, jerk_window_s)
    out["collisions"] = sum(EGO_ID in pair for pair in colliding_pairs(tables.get("collisions")))
    target = cut_in_target(tables.get("lane_changes"), cut_in_range_m)
    out.update({"target_id": None, "target_mid_time_s": math.nan, "target_gap_at_mid_m": math.nan,
                "avg_ttc_s": math.nan, "avg_ttc_clipped_s": math.nan, "min_ttc_s": math.nan, "ttc_samples": 0,
                # no cut-in ahead: no exposure to measure (0 would pair a trip without a cut-in with
                # one that had it, where TTC and gap are left out)
                "tet_s": math.nan, "tit_s2": math.nan, "min_gap_to_target_m": math.nan,
                "min_gap_after_cut_in_s": math.nan, "min_gap_stay_m": math.nan})
    if target is not None:
        vehicles = tables["vehicles"].set_index("vehicle_id")
        series = target_ttc(ego, tables["trajectories"], target["vehicle_id"],
                            float(vehicles.loc[target["vehicle_id"], "length"]), float(target["mid_time"]), ego_lane)
        ttc = series["ttc_s"].to_numpy()
        defined = np.isfinite(ttc)
        tet, tit = exposure(ttc, dt, ttc_threshold_s)
        out.update({
            "target_id": str(target["vehicle_id"]),
            "target_mid_time_s": float(target["mid_time"]),
            "target_gap_at_mid_m": float(target["gap_to_ego_m"]),
            "avg_ttc_s": float(ttc[defined].mean()) if defined.any() else math.nan,
            "avg_ttc_clipped_s": float(np.minimum(ttc[defined], ttc_clip_s).mean()) if defined.any() else math.nan,
            "min_ttc_s": float(ttc[defined].min()) if defined.any() else math.nan,
            "ttc_samples": int(defined.sum()),
            "tet_s": tet, "tit_s2": tit,
        })
        gap = series["gap_m"].to_numpy(dtype=float)
        after = series["time"].to_numpy() - float(target["mid_time"])
        if np.isfinite(gap).any():
            out["min_gap_stay_m"] = float(np.nanmin(gap))
        in_window = np.where(after <= cut_in_window_s + 1e-9, gap, np.nan)
        if np.isfinite(in_window).any():
            k = int(np.nanargmin(in_window))
            out.update({"min_gap_to_target_m": float(in_window[k]), "min_gap_after_cut_in_s": float(after[k])})
    return out
