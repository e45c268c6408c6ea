"""The threshold curve of one decision rule on pooled streams of several recordings, and the
threshold a per-recording false-alarm budget allows (`tools/real_alarms_cv.py`).

Each row of the curve is one threshold of the aggressive smoothing (hold `tau_ticks`), scored
with :func:`vcfusion.prediction.events.event_scores` on all streams together ("all") and on each
recording's alone: `{part}_predicted`, `{part}_advance_s`, `{part}_fa` (false alarms),
`{part}_fa_censored`, `{part}_fa_per_veh_h` (the headline rate: every false alarm over all
vehicle-hours), `{part}_fa_judged`, `{part}_judged_veh_h` and `{part}_fa_judged_per_veh_h` (the
judged, censoring-aware rate: uncensored false alarms over the exposure where the confirming
window fits in the track).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from vcfusion.prediction.events import (FALSE_ALARM_RATES, _runs, event_scores, smooth_stream, smoothing_bounds,
                                        track_bounds)

# the curve's column of each false-alarm rate of :data:`vcfusion.prediction.events.FALSE_ALARM_RATES`
RATE_COLUMN = {"all": "fa_per_veh_h", "judged": "fa_judged_per_veh_h"}
assert set(RATE_COLUMN) == set(FALSE_ALARM_RATES)


def threshold_curve(stream: pd.DataFrame, events: pd.DataFrame, thresholds, tau_ticks: int, period_s: float,
                    horizon_s: float, source: str = "source") -> pd.DataFrame:
    """stream: seed, vehicle_id, time, prob and `source` (the recording of each row), sorted by
    seed, vehicle, time; events: the lane changes (seed, event_id, vehicle_id, end, mid)."""
    prob, stretches = stream["prob"].to_numpy(), smoothing_bounds(stream)
    names = list(dict.fromkeys(stream[source].tolist()))
    parts = {"all": None, **{n: (stream[source] == n).to_numpy() for n in names}}
    rows = []
    for thr in thresholds:
        dec = smooth_stream(stretches, (prob > thr).astype(np.int8), "aggressive", tau_ticks, tau_ticks)
        row = {"threshold": float(thr)}
        for name, mask in parts.items():
            s = stream if mask is None else stream[mask].reset_index(drop=True)
            d = dec if mask is None else dec[mask]
            e = events[events["seed"].isin(s["seed"].unique())]
            summary, _ = event_scores(s, d, e, period_s, horizon_s, track_bounds(s))
            row |= {f"{name}_predicted": summary["predicted_share"], f"{name}_advance_s": summary["advance_final_mean_s"],
                    f"{name}_fa_per_veh_h": summary["false_alarms_per_vehicle_hour"],
                    f"{name}_fa_censored": summary["false_alarms_censored"], f"{name}_fa": summary["false_alarms"],
                    f"{name}_fa_judged": summary["false_alarms_judged"],
                    f"{name}_judged_veh_h": summary["judged_vehicle_hours"],
                    f"{name}_fa_judged_per_veh_h": summary["false_alarms_judged_per_vehicle_hour"]}
        rows.append(row)
    return pd.DataFrame(rows)


def choose_threshold(curve: pd.DataFrame, budget: float, recordings, rate: str = "all") -> pd.Series | None:
    """The curve's row predicting most lane changes (ties: larger mean advance, then the lower
    pooled rate) whose false-alarm rate `rate` ("all" or "judged") is <= budget in each of
    `recordings`; None if no row is. A recording without judged exposure cannot bound the judged
    rate: ValueError, not a pass."""
    if rate not in RATE_COLUMN:
        raise ValueError(f"false-alarm rate: expected one of {sorted(RATE_COLUMN)}, got {rate!r}")
    col = RATE_COLUMN[rate]
    for name in recordings:
        if rate == "judged" and not (curve[f"{name}_judged_veh_h"] > 0).all():
            raise ValueError(f"{name}: no judged exposure (no track outlasts the confirming window), so its judged "
                             f"false-alarm rate cannot be bounded")
    ok = curve[np.logical_and.reduce([(curve[f"{n}_{col}"] <= budget).to_numpy() for n in recordings])]
    if not len(ok):
        return None
    return ok.sort_values(["all_predicted", "all_advance_s", f"all_{col}"], ascending=[False, False, True]).iloc[0]


def _rate_column(rate: str) -> str:
    if rate not in RATE_COLUMN:
        raise ValueError(f"false-alarm rate: expected one of {sorted(RATE_COLUMN)}, got {rate!r}")
    return RATE_COLUMN[rate]


def at_share(curve: pd.DataFrame, share: float, rate: str = "all", recording: str = "all") -> pd.Series | None:
    """The curve's row predicting at least `share` of the lane changes of `recording` ("all": pooled)
    with its lowest false-alarm rate `rate` (ties: larger mean advance): two models compared at
    matched recall. None if no row reaches the share."""
    col = f"{recording}_{_rate_column(rate)}"
    ok = curve[curve[f"{recording}_predicted"] >= share - 1e-12]
    if not len(ok):
        return None
    return ok.sort_values([col, f"{recording}_advance_s"], ascending=[True, False]).iloc[0]


def at_pooled_rate(curve: pd.DataFrame, budget: float, rate: str = "all", recording: str = "all") -> pd.Series | None:
    """The curve's row predicting most lane changes of `recording` ("all": pooled) with its false-alarm
    rate `rate` <= budget (ties: larger mean advance): two models compared at matched false alarms.
    None if none."""
    col = f"{recording}_{_rate_column(rate)}"
    ok = curve[curve[col] <= budget + 1e-12]
    if not len(ok):
        return None
    return ok.sort_values([f"{recording}_predicted", f"{recording}_advance_s"], ascending=[False, False]).iloc[0]


def weak_judged_bounds(row: pd.Series, budget: float, recordings) -> list[str]:
    """Notes on the recordings whose judged exposure is under 1 / budget hours: there a single judged
    false alarm exceeds the budget, so the bound only says that none was judged false (short tracks:
    CommonRoad's 8 s scenarios leave little time in which a 10 s confirming window fits)."""
    return [f"{n}: judged exposure {row[f'{n}_judged_veh_h']:.3f} veh-h < 1 / budget = {1 / budget:.3f} veh-h: one "
            f"judged false alarm would exceed the budget; the bound there is that none was judged false "
            f"({int(row[f'{n}_fa_censored'])} censored)"
            for n in recordings if row[f"{n}_judged_veh_h"] < 1.0 / budget]


def censored_alarm_outcomes(stream: pd.DataFrame, decisions: np.ndarray, events: pd.DataFrame, horizon_s: float,
                            short: str, long: str, source: str = "source") -> dict:
    """How the censored false alarms of recording `short` (short tracks) might have turned out,
    estimated on recording `long` (long tracks, windows observed).

    Each censored false alarm of `short` gives the span observed after its run's start (track end
    - run start). Each alarm run [a, b] of `long` is cut at a + span, for every span: when no
    change of the vehicle ends in [a, cut] and the cut run's window passes the cut, it is
    *censored-like*, and the full track says whether a change ends in [a, b + horizon] (true) or
    not (false). Pairs whose full window passes the long track's own end are left out. Returns
    the counts over (run, span) pairs and over distinct runs (censored-like for some span).
    stream: seed, vehicle_id, time, `source`, sorted by seed, vehicle, time; decisions: 0/1 per row."""
    eps = 1e-6
    seeds, vids = stream["seed"].to_numpy(), stream["vehicle_id"].to_numpy()
    times, src = stream["time"].to_numpy(dtype=float), stream[source].to_numpy()
    ends_of = {k: g["end"].to_numpy(dtype=float) for k, g in events.groupby(["seed", "vehicle_id"], sort=False)}
    spans, runs = [], []
    for a0, b0 in track_bounds(stream):
        if src[a0] not in (short, long):
            continue
        t, ends = times[a0:b0], ends_of.get((seeds[a0], vids[a0]), np.zeros(0))
        for s0, s1 in zip(*_runs(decisions[a0:b0])):
            a, b = t[s0], t[s1]
            true = bool(np.any((ends >= a - eps) & (ends <= b + horizon_s + eps)))
            if src[a0] == short and not true and b + horizon_s > t[-1] + eps:
                spans.append(t[-1] - a)
            elif src[a0] == long:
                runs.append((a, b, t[-1], ends, true))
    pairs = pairs_false = runs_like = runs_false = 0
    for a, b, last, ends, true in runs:
        if b + horizon_s > last + eps:  # the full window is not observed on the long track either
            continue
        like = 0
        for span in spans:
            cut = a + span
            if np.any((ends >= a - eps) & (ends <= cut + eps)) or min(b, cut) + horizon_s <= cut + eps:
                continue  # confirmed within the cut track, or its window observed there
            like += 1
        pairs += like
        pairs_false += like * (not true)
        if like:
            runs_like += 1
            runs_false += int(not true)
    return {"short_censored_false_alarms": len(spans),
            "short_span_median_s": float(np.median(spans)) if spans else float("nan"),
            "long_runs": len(runs), "pairs": pairs, "pairs_false": pairs_false,
            "runs": runs_like, "runs_false": runs_false}
