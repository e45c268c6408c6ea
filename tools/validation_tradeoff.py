"""A GRU file's trade-off on the validation seeds of the datasets it was trained on
(docs/components/real-data.md, "Longer training"): lane changes predicted, mean advance and false
alarms per vehicle-hour against the threshold (aggressive smoothing, tau_a given), and what the
false alarms at given thresholds are. A diagnostic of the data the decision is tuned on: nothing
held out is read.

    python tools/validation_tradeoff.py MODEL DATASET... [--tau-ticks 50] [--kinds 0.5,0.85] [--out CSV]

False alarm kinds (one alarm can be several): censored (its confirming window, run end + horizon,
runs past the vehicle's last tick), late (the vehicle's next change ends within 10 s after that
window), after a change (the run starts within 5 s of the end of the vehicle's previous change).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.prediction.dataset import DatasetError
from vcfusion.prediction.events import _runs, event_scores, smooth_stream, smoothing_bounds, track_bounds
from vcfusion.prediction.features import stored_columns, with_derived_columns
from vcfusion.prediction.model import load_model
from vcfusion.prediction.sequence import segment_bounds
from vcfusion.prediction.train import combined_stream, load_datasets

THRESHOLDS = (0.3, 0.4, 0.5, 0.6, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95)
HORIZON_S = 10.0  # the event horizon of `vcfusion evaluate` / `sim-to-real`
LATE_S = 10.0  # a change ending at most this long after an alarm's confirming window is "late"
AFTER_CHANGE_S = 5.0  # an alarm starting at most this long after the previous change is "after a change"
EPS = 1e-6


def false_alarm_kinds(stream: pd.DataFrame, decisions: np.ndarray, events: pd.DataFrame) -> pd.DataFrame:
    """One row per false alarm (same rule as `events.event_scores`) with its kinds."""
    seeds, vids = stream["seed"].to_numpy(), stream["vehicle_id"].to_numpy()
    times = stream["time"].to_numpy(float)
    ends_of = {k: np.sort(g["end"].to_numpy()) for k, g in events.groupby(["seed", "vehicle_id"])}
    rows = []
    for a, z in track_bounds(stream):
        t, d = times[a:z], decisions[a:z]
        ends = ends_of.get((seeds[a], vids[a]), np.zeros(0))
        for s0, s1 in zip(*_runs(d)):
            if np.any((ends >= t[s0] - EPS) & (ends <= t[s1] + HORIZON_S + EPS)):
                continue
            later, earlier = ends[ends > t[s1] + HORIZON_S], ends[ends < t[s0]]
            rows.append({"censored": t[s1] + HORIZON_S > t[-1] + EPS,
                         "late": bool(len(later) and later[0] - (t[s1] + HORIZON_S) <= LATE_S),
                         "after_change": bool(len(earlier) and t[s0] - earlier[-1] <= AFTER_CHANGE_S),
                         "run_s": float(t[s1] - t[s0])})
    return pd.DataFrame(rows, columns=["censored", "late", "after_change", "run_s"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("datasets", type=Path, nargs="+")
    ap.add_argument("--tau-ticks", type=int, default=50, help="Algorithm 3 hold, V2C ticks")
    ap.add_argument("--kinds", default="0.5,0.85", help="thresholds whose false alarms are classified")
    ap.add_argument("--out", type=Path, help="CSV of the curve")
    args = ap.parse_args()

    try:
        model = load_model(args.model)
        infos = load_datasets(args.datasets)
    except (DatasetError, OSError, ValueError) as exc:
        raise SystemExit(f"error: {exc}") from None
    if model.kind != "gru":
        raise SystemExit(f"error: {args.model}: a GRU file is expected (kind {model.kind!r})")
    names = list(model.feature_names)
    stream, events = combined_stream(infos, "validation",
                                     ["seed", "vehicle_id", "time", *stored_columns(names)])
    with_derived_columns(stream, names, model.period_s)
    logits = model.sequence_logits(stream[names].to_numpy(np.float32),
                                   segment_bounds(stream, model.period_s, model.reset_gap_ticks))
    prob = model.calibrated(logits)
    bounds, stretches = track_bounds(stream), smoothing_bounds(stream)
    vehicle_hours = len(stream) * model.period_s / 3600.0
    print(f"{args.model.name}: validation seeds of {len(args.datasets)} datasets, {len(events)} lane changes, "
          f"{vehicle_hours:.2f} vehicle-hours; aggressive smoothing, tau_a {args.tau_ticks} ticks")
    kinds_at = {round(float(x), 4) for x in args.kinds.split(",") if x}
    curve = []
    for thr in sorted(set(THRESHOLDS) | kinds_at):
        dec = smooth_stream(stretches, (prob > thr).astype(np.int8), "aggressive", tau_a=args.tau_ticks,
                            tau_c=args.tau_ticks)
        s = event_scores(stream, dec, events, model.period_s, HORIZON_S, bounds)[0]
        curve.append({"threshold": thr, "predicted": s["predicted_share"], "advance_s": s["advance_final_mean_s"],
                      "false_alarms_per_veh_h": s["false_alarms_per_vehicle_hour"]})
        print(f"  threshold {thr:.2f}: {100 * s['predicted_share']:5.1f} % predicted, "
              f"{s['advance_final_mean_s']:.2f} s ahead, "
              f"{s['false_alarms_per_vehicle_hour']:5.1f} false alarms / veh-h")
        if round(thr, 4) in kinds_at:
            fa = false_alarm_kinds(stream, dec, events)
            if len(fa):
                print(f"    its {len(fa)} false alarms: censored {fa.censored.mean():.0%}, late {fa.late.mean():.0%}, "
                      f"after a change {fa.after_change.mean():.0%}, none of these "
                      f"{(~(fa.censored | fa.late | fa.after_change)).mean():.0%}; "
                      f"median run {fa.run_s.median():.1f} s")
    if args.out:
        pd.DataFrame(curve).to_csv(args.out, index=False)


if __name__ == "__main__":
    main()
