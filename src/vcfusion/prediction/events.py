"""Event-level scoring of decision streams: lane changes predicted, advance time, false alarms.

For each lane change of a vehicle (end E, the previous change of the same vehicle ending at P):
- it is *predicted* when some decision of that vehicle is positive at a tick t with
  P < t and E - horizon <= t <= E (a positive exactly one horizon before the end counts, as it
  does for the false alarms below: a run ending there has the change within its horizon);
- advance (final run) = E - the first tick of the uninterrupted positive run that holds the
  last positive decision in that window (the run may start before the horizon, not before P);
- advance (first positive) = E - the first positive decision after P at all;
- `before_mid`: predicted by a positive at or before the manoeuvre's midpoint (the moment its
  centre crosses the lane line, when the map-matched lane flips).
A *false alarm* is an uninterrupted positive run [a, b] of a vehicle with no lane change of that
vehicle ending in [a, b + horizon]. Rates are per vehicle-hour of twin ticks.
A false alarm is *censored* when b + horizon lies after the vehicle's last tick: part of the
window that would have confirmed it was not observed (a short CommonRoad track, a vehicle leaving
the recorded stretch, a file cut off). Censored false alarms are still false alarms (the headline
rate counts them); they are also counted apart (`false_alarms_censored`) so that a set of short
tracks can be read with that in mind.

The *judged* (censoring-aware) false-alarm rate counts only the alarms that can be judged: the
false alarms that are not censored, divided by the *judged exposure*, the ticks t of each track
with t + horizon <= its last tick (vehicle-hours less each track's last `horizon` seconds; a track
shorter than the horizon adds none). An alarm run is judged exactly when its last tick lies in
that exposure, so numerator and denominator cover the same ticks: the rate is that of false
alarms among the alarms that could have been confirmed, the way a right-censored observation is
left out of both the events and the time at risk. It is undefined (NaN) without judged exposure.
:data:`FALSE_ALARM_RATES` names the two rates for the decision-selection code.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from vcfusion.prediction.smoothing import smooth

_EPS = 1e-6

# The false-alarm rates a decision rule can bound (summary keys of :func:`event_scores`):
# "all" counts every false alarm over all vehicle-hours (the headline rate); "judged" counts the
# uncensored ones over the judged exposure (module docstring).
FALSE_ALARM_RATES = {"all": "false_alarms_per_vehicle_hour", "judged": "false_alarms_judged_per_vehicle_hour"}


def judged_ticks(times: np.ndarray, horizon_s: float) -> int:
    """Ticks of one track (times sorted) at which an alarm run ending there could be confirmed or
    refuted: t + horizon <= the track's last tick."""
    return int(np.count_nonzero(times + horizon_s <= times[-1] + _EPS)) if len(times) else 0


def false_alarm_rate(summary: dict, which: str = "all") -> float:
    """The false-alarm rate `which` ("all" or "judged", :data:`FALSE_ALARM_RATES`) of a summary of
    :func:`event_scores`."""
    if which not in FALSE_ALARM_RATES:
        raise ValueError(f"false-alarm rate: expected one of {sorted(FALSE_ALARM_RATES)}, got {which!r}")
    return summary[FALSE_ALARM_RATES[which]]


def _runs(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (inclusive) indices of the runs of ones in a 0/1 array."""
    padded = np.concatenate([[0], d.astype(np.int8), [0]])
    diff = np.diff(padded)
    return np.flatnonzero(diff == 1), np.flatnonzero(diff == -1) - 1


def _bounds(stream: pd.DataFrame, breaks: np.ndarray | None = None) -> list[tuple[int, int]]:
    """(start, stop) row ranges of a stream sorted by seed, vehicle, time: a new range where the seed
    or the vehicle changes, or where `breaks` (one per pair of neighbouring rows) is set."""
    seeds = stream["seed"].to_numpy()
    vids = stream["vehicle_id"].to_numpy()
    new = (seeds[1:] != seeds[:-1]) | (vids[1:] != vids[:-1])
    change = np.flatnonzero(new if breaks is None else new | breaks) + 1
    starts = np.concatenate([[0], change]).astype(int)
    stops = np.concatenate([change, [len(seeds)]]).astype(int)
    return list(zip(starts.tolist(), stops.tolist())) if len(seeds) else []


def track_bounds(stream: pd.DataFrame) -> list[tuple[int, int]]:
    """(start, stop) row ranges of each (seed, vehicle) track of a stream sorted by seed, vehicle, time."""
    return _bounds(stream)


def smoothing_bounds(stream: pd.DataFrame) -> list[tuple[int, int]]:
    """(start, stop) row ranges of each track's stretches of consecutive snapshots, in a stream
    sorted by seed, vehicle, time that holds every twin of every snapshot (a dataset split).

    Why: the cloud's smoother forgets a twin absent from a snapshot
    (:class:`vcfusion.prediction.smoothing.StreamingSmoother`), so the decisions it draws after
    the twin is back start afresh; offline tuning and evaluation smooth the same stretches. A tick
    without any twin (every report lost) is no snapshot and has no rows: there the cloud's memory
    waits (:class:`vcfusion.prediction.cloud.LaneChangePredictor`), and so does this."""
    if not len(stream):
        return []
    # the snapshot count of each row's time within its seed (dense rank: 1, 2, ...)
    snapshot = stream.groupby("seed", sort=False)["time"].rank(method="dense").to_numpy()
    return _bounds(stream, np.diff(snapshot) != 1)


def smooth_stream(bounds: list[tuple[int, int]], decisions: np.ndarray, method: str, tau_a: int, tau_c: int,
                  threshold: float = 0.5) -> np.ndarray:
    """Apply a smoothing per stretch of a track (bounds from :func:`smoothing_bounds`)."""
    out = np.empty(len(decisions), dtype=np.int8)
    for a, b in bounds:
        out[a:b] = smooth(decisions[a:b], method, tau_a=tau_a, tau_c=tau_c, threshold=threshold)
    return out


def event_scores(stream: pd.DataFrame, decisions: np.ndarray, events: pd.DataFrame, period_s: float,
                 horizon_s: float, bounds: list[tuple[int, int]] | None = None,
                 false_alarms_by_vehicle: dict | None = None,
                 censored_by_vehicle: dict | None = None) -> tuple[dict, pd.DataFrame]:
    """stream: seed, vehicle_id, time sorted by (seed, vehicle_id, time); events: seed, event_id,
    vehicle_id, end, mid. Returns (summary, per-event table). `false_alarms_by_vehicle` and
    `censored_by_vehicle`: dicts that receive each (seed, vehicle_id)'s false alarms and censored
    false alarms (for intervals over vehicles)."""
    rows = []
    false_alarms = 0
    censored = 0
    alarms = 0
    judged = 0
    ev_groups = {k: g.sort_values("end") for k, g in events.groupby(["seed", "vehicle_id"], sort=False)}
    seeds = stream["seed"].to_numpy()
    vids = stream["vehicle_id"].to_numpy()
    times = stream["time"].to_numpy(dtype=float)
    for a, b in (bounds if bounds is not None else track_bounds(stream)):
        key = (seeds[a], vids[a])
        t = times[a:b]
        d = decisions[a:b].astype(np.int8)
        g = ev_groups.get(key)
        ends = g["end"].to_numpy() if g is not None else np.zeros(0)
        starts, stops = _runs(d)
        alarms += len(starts)
        judged += judged_ticks(t, horizon_s)
        for s0, s1 in zip(starts, stops):
            if not np.any((ends >= t[s0] - _EPS) & (ends <= t[s1] + horizon_s + _EPS)):
                false_alarms += 1
                if false_alarms_by_vehicle is not None:
                    false_alarms_by_vehicle[key] = false_alarms_by_vehicle.get(key, 0) + 1
                if t[s1] + horizon_s > t[-1] + _EPS:  # the confirming window runs past the track's end
                    censored += 1
                    if censored_by_vehicle is not None:
                        censored_by_vehicle[key] = censored_by_vehicle.get(key, 0) + 1
        if g is None:
            continue
        prev = -np.inf
        for ev in g.itertuples(index=False):
            region = (t > prev + _EPS) & (t <= ev.end + _EPS)
            window = region & (t > ev.end - horizon_s - _EPS)
            pos_w = np.flatnonzero(window & (d == 1))
            row = {"seed": key[0], "vehicle_id": key[1], "event_id": ev.event_id, "end": ev.end,
                   "observed_s": float(t[region][-1] - t[region][0]) if region.any() else 0.0,
                   "predicted": len(pos_w) > 0, "before_mid": bool(np.any(window & (d == 1) & (t <= ev.mid + _EPS))),
                   "advance_final_s": np.nan, "advance_first_s": np.nan}
            if len(pos_w):
                k = pos_w[-1]
                first_region = np.flatnonzero(region)[0]
                while k - 1 >= first_region and d[k - 1] == 1:
                    k -= 1
                row["advance_final_s"] = float(ev.end - t[k])
                row["advance_first_s"] = float(ev.end - t[np.flatnonzero(region & (d == 1))[0]])
            rows.append(row)
            prev = ev.end
    per_event = pd.DataFrame(rows, columns=["seed", "vehicle_id", "event_id", "end", "observed_s", "predicted",
                                            "before_mid", "advance_final_s", "advance_first_s"])
    vehicle_hours = len(stream) * period_s / 3600.0
    pred = per_event[per_event["predicted"]]
    summary = {
        "lane_changes": int(len(per_event)),
        "predicted_share": float(per_event["predicted"].mean()) if len(per_event) else float("nan"),
        "predicted_before_mid_share": float(per_event["before_mid"].mean()) if len(per_event) else float("nan"),
        "advance_final_mean_s": float(pred["advance_final_s"].mean()) if len(pred) else float("nan"),
        "advance_final_median_s": float(pred["advance_final_s"].median()) if len(pred) else float("nan"),
        "advance_first_mean_s": float(pred["advance_first_s"].mean()) if len(pred) else float("nan"),
        "advance_first_median_s": float(pred["advance_first_s"].median()) if len(pred) else float("nan"),
        "alarms": int(alarms),
        "false_alarms": int(false_alarms),
        "false_alarms_censored": int(censored),
        "vehicle_hours": float(vehicle_hours),
        "false_alarms_per_vehicle_hour": float(false_alarms / vehicle_hours) if vehicle_hours else float("nan"),
        "false_alarms_judged": int(false_alarms - censored),
        "judged_vehicle_hours": float(judged * period_s / 3600.0),
        "false_alarms_judged_per_vehicle_hour": (float((false_alarms - censored) / (judged * period_s / 3600.0))
                                                 if judged else float("nan")),
    }
    return summary, per_event
