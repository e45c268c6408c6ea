"""Time-window labelling of lane changes (paper Fig. 5) and the every-tick stream view.

For a vehicle whose next lane change ends at time E, a sample at time t has the
time-to-lane-change ttl = E - t (ttl >= 0). With window size tau and gap tau_g:
- positive window: 0 <= ttl < tau (the tau seconds up to and including the end point);
- gap: tau <= ttl < tau + tau_g (left out of training);
- negative window: tau + tau_g <= ttl < 2 tau + tau_g, the positive window moved back by
  tau + tau_g as in the paper (so with tau_g = 0 the windows are adjacent and every tick of the
  2 tau before the end is in one of them);
- everything else is outside the windows (`window_label` = -1) and is used only by the
  every-tick stream (`stream_label`: 1 in the positive window, 0 elsewhere), which is what a
  deployed model sees.
Only the vehicle's *next* lane change counts, so a sample in the positive window of one change
is never a negative of a later one. A change whose end was not observed (vehicle left the
road, run ended) gets end = mid + `end_after_mid_s`.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

WINDOW_POSITIVE, WINDOW_NEGATIVE, WINDOW_NONE = 1, 0, -1
_EPS = 1e-6  # times are on a 0.1 s grid; this absorbs float error in E - t


def event_end_times(events, end_after_mid_s: float) -> np.ndarray:
    """End of each lane change of a lane_changes table (DataFrame or columns); midpoint +
    end_after_mid_s where the trajectory never showed it centred in its new lane."""
    end = np.asarray(events["end_time"], dtype=float)
    return np.where(np.isnan(end), np.asarray(events["mid_time"], dtype=float) + end_after_mid_s, end)


def label_samples(time: np.ndarray, vehicle_id: np.ndarray, events: pd.DataFrame, tau: float, tau_g: float,
                  end_after_mid_s: float = 1.5) -> pd.DataFrame:
    """Labels of samples (time, vehicle_id) given the run's lane_changes table.

    Returns columns event_id (next lane change of the vehicle, -1 if none), time_to_lc
    (s, NaN if none), time_since_lc (since the previous change's end, NaN if none),
    window_label (1 / 0 / -1) and stream_label (0 / 1), aligned with the inputs.
    """
    if tau <= 0 or tau_g < 0:
        raise ValueError(f"expected tau > 0 and tau_g >= 0, got tau={tau}, tau_g={tau_g}")
    time = np.asarray(time, dtype=float)
    vehicle_id = np.asarray(vehicle_id, dtype=str)
    n = len(time)
    event_id = np.full(n, -1, dtype=np.int64)
    ttl = np.full(n, np.nan)
    since = np.full(n, np.nan)
    if len(events):
        ends = event_end_times(events, end_after_mid_s)
        ev = pd.DataFrame({"vehicle_id": events["vehicle_id"].astype(str).to_numpy(), "end": ends,
                           "event_id": events["event_id"].to_numpy(np.int64)})
        rows_by_vehicle = pd.Series(np.arange(n)).groupby(vehicle_id).indices
        for vid, group in ev.groupby("vehicle_id", sort=False):
            rows = rows_by_vehicle.get(vid)
            if rows is None:
                continue
            group = group.sort_values("end", kind="stable")
            e_end = group["end"].to_numpy()
            e_id = group["event_id"].to_numpy()
            t = time[rows]
            nxt = np.searchsorted(e_end, t - _EPS, side="left")  # first end >= t
            has_next = nxt < len(e_end)
            k = np.minimum(nxt, len(e_end) - 1)
            event_id[rows] = np.where(has_next, e_id[k], -1)
            ttl[rows] = np.where(has_next, np.maximum(e_end[k] - t, 0.0), np.nan)
            prev = nxt - 1
            since[rows] = np.where(prev >= 0, t - e_end[np.maximum(prev, 0)], np.nan)
    with np.errstate(invalid="ignore"):
        pos = (ttl >= -_EPS) & (ttl < tau - _EPS)
        neg = (ttl >= tau + tau_g - _EPS) & (ttl < 2 * tau + tau_g - _EPS)
    window = np.where(pos, WINDOW_POSITIVE, np.where(neg, WINDOW_NEGATIVE, WINDOW_NONE)).astype(np.int8)
    return pd.DataFrame({
        "event_id": event_id, "time_to_lc": ttl, "time_since_lc": since,
        "window_label": window, "stream_label": pos.astype(np.int8),
    })
