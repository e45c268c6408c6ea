"""What limits the advance of lane-change alarms on the US-101 recordings, measured on the
cross-fitted streams of the development and validation parts (docs/components/real-data.md,
"What limits the advance"). Nothing here reads the held-out parts' scores: they are in no fold.

    python tools/real_advance_limits.py NGSIM_DS CR_DS CV_WORK_DIR --out DIR

NGSIM_DS / CR_DS: the imports (`vcfusion dataset --from-...`; their twins tables give the lateral
position); CV_WORK_DIR: a finished `tools/real_alarms_cv.py` work folder (fold models ft_cv*.npz and
fold datasets). Writes DIR/separability.{csv,md} (each signal's changing-vs-lane-keeping separation
at each time before the crossing), DIR/gap_auc.{csv,md} (gap-seeking quantities, by target side),
DIR/detectors.{csv,md} (each signal alone as an alarm, with the decision rule of
tools/real_alarms_cv.py), DIR/noise.json (the recorded lateral positions' white-noise content),
DIR/timing.{csv,md} (where the alarm of the model at --threshold falls in each manoeuvre).
A few minutes on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_alarms_cv import out_of_fold  # noqa: E402

from vcfusion.prediction.advance import (  # noqa: E402
    ema_lateral_speed, kalman_lateral_speed, position_noise, separability, track_starts, window_auc,
)
from vcfusion.prediction.events import event_scores, smooth_stream, smoothing_bounds, track_bounds  # noqa: E402

PERIOD_S = 0.1
TAU_TICKS = 50  # the hold of the decision chosen by tools/real_alarms_cv.py
BUDGET = 4.0  # false alarms / veh-h in each recording, the rule of tools/real_alarms_cv.py
# the Kalman filter compared: the best of sigma 0.1 / 0.3 m x accel_psd 0.01 / 0.05 m^2/s^3 on these streams
KF_SIGMA_M, KF_ACCEL_PSD = 0.3, 0.05
GAP_COLUMNS = ["speed", "speed_minus_ema", "accel", "dv_lead_own", "gap_lead_own", "dv_lead_own_mean"]
GAP_SIDE_COLUMNS = ["dv_lead_{side}", "gap_lead_{side}", "gap_foll_{side}", "dv_foll_{side}",
                    "dv_lead_{side}_mean", "gap_lead_{side}_mean", "gap_foll_{side}_mean"]
EXTRA = ("lane", "lateral_speed_mps", "lateral_drift_m", "left_lane_exists", "right_lane_exists",
         *GAP_COLUMNS, *[p.format(side=s) for p in GAP_SIDE_COLUMNS for s in ("left", "right")])


def markdown(table: pd.DataFrame, index: bool = True) -> str:
    """A pipe table (numbers to 2 decimals) without the optional tabulate package."""
    t = table.reset_index() if index else table
    cell = lambda v: f"{v:.2f}" if isinstance(v, (float, np.floating)) else str(v)  # noqa: E731
    lines = ["| " + " | ".join(map(str, t.columns)) + " |", "|" + "---|" * len(t.columns)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in t.itertuples(index=False)]
    return "\n".join(lines) + "\n"


def with_lateral_position(stream: pd.DataFrame, imports: dict[str, Path]) -> pd.DataFrame:
    """`d` (across the road, left positive) and `lane_offset_m` (d - the lane's centre) from the
    imports' twins tables (the replay road: y = d - its width; lanes of one width)."""
    parts = []
    for (source, seed), g in stream.groupby(["source", "original_seed"], sort=False):
        run = imports[source] / "runs" / f"seed_{int(seed):04d}"
        road = json.loads((run / "manifest.json").read_text())["road"]
        twins = pd.read_parquet(run / "twins.parquet", columns=["time", "vehicle_id", "y"])
        twins = twins.assign(vehicle_id=twins["vehicle_id"].astype(str), t=twins["time"].round(1))
        twins["d"] = twins["y"] + road["num_lanes"] * road["lane_width_m"]
        g = g.assign(t=g["time"].round(1)).merge(twins[["t", "vehicle_id", "d"]], on=["t", "vehicle_id"], how="left")
        g["lane_offset_m"] = g["d"] - (g["lane"] + 0.5) * road["lane_width_m"]
        parts.append(g.drop(columns="t"))
    out = pd.concat(parts, ignore_index=True).sort_values(["seed", "vehicle_id", "time"], kind="stable")
    if out["d"].isna().any():
        raise SystemExit(f"{int(out['d'].isna().sum())} ticks without a twins-table row: imports and folds differ")
    return out.reset_index(drop=True)


def own_average(x: np.ndarray, start: np.ndarray, tc: float) -> np.ndarray:
    """Causal EMA (time constant tc) of x per track, starting at the track's first value."""
    a, out, m = 1.0 - np.exp(-PERIOD_S / tc), np.empty(len(x)), 0.0
    for i, value in enumerate(x):
        m = value if start[i] else m + a * (value - m)
        out[i] = m
    return out


def detector(stream: pd.DataFrame, events: pd.DataFrame, values: np.ndarray) -> dict:
    """The signal alone as the alarm (> threshold, aggressive smoothing, TAU_TICKS hold): the threshold
    predicting most changes with <= BUDGET false alarms / veh-h in each recording (ties: advance)."""
    stretches = smoothing_bounds(stream)
    masks = {n: (stream["source"] == n).to_numpy() for n in ("ngsim", "cr")}
    subs = {n: stream[m].reset_index(drop=True) for n, m in masks.items()}
    best = None
    for thr in np.unique(np.quantile(values, np.linspace(0.85, 0.999, 60))):
        dec = smooth_stream(stretches, (values > thr).astype(np.int8), "aggressive", TAU_TICKS, TAU_TICKS)
        per = {}
        for n, m in masks.items():
            e = events[events["seed"].isin(subs[n]["seed"].unique())]
            per[n], _ = event_scores(subs[n], dec[m], e, PERIOD_S, 10.0, track_bounds(subs[n]))
        if max(p["false_alarms_per_vehicle_hour"] for p in per.values()) > BUDGET:
            continue
        pooled, _ = event_scores(stream, dec, events, PERIOD_S, 10.0, track_bounds(stream))
        key = (pooled["predicted_share"], pooled["advance_final_mean_s"] or 0.0)
        if best is None or key > best[0]:
            best = (key, float(thr), pooled, per)
    if best is None:
        return {"threshold": None}
    _, thr, pooled, per = best
    row = {"threshold": thr}
    for name, summ in (("all", pooled), *per.items()):
        row |= {f"{name}_predicted_pct": 100 * summ["predicted_share"],
                f"{name}_advance_s": summ["advance_final_mean_s"],
                f"{name}_fa_per_veh_h": summ["false_alarms_per_vehicle_hour"]}
    return row


def alarm_timing(stream: pd.DataFrame, events: pd.DataFrame, cv_work: Path, threshold: float) -> pd.DataFrame:
    """Per lane change, at the out-of-fold probability > threshold (aggressive, TAU_TICKS): predicted,
    advance, the crossing and the manoeuvre's start (the import's rule) relative to the end E."""
    dec = smooth_stream(smoothing_bounds(stream), (stream["prob"].to_numpy() > threshold).astype(np.int8),
                        "aggressive", TAU_TICKS, TAU_TICKS)
    _, per = event_scores(stream, dec, events, PERIOD_S, 10.0, track_bounds(stream))
    tables = []
    for seed in per["seed"].unique():  # out_of_fold's seeds: (2 fold + source) x 10^7 + the fold dataset's seed
        block, own = divmod(int(seed), 10_000_000)
        fold, j = divmod(block, 2)
        run = cv_work / f"{('ngsim', 'cr')[j]}-cv{fold}" / "runs" / f"seed_{own:04d}"
        lc = pd.read_parquet(run / "lane_changes.parquet", columns=["event_id", "vehicle_id", "start_time", "mid_time"])
        tables.append(lc.assign(seed=seed, source=("ngsim", "cr")[j], vehicle_id=lc["vehicle_id"].astype(str)))
    per = per.assign(vehicle_id=per["vehicle_id"].astype(str)).merge(
        pd.concat(tables, ignore_index=True), on=["seed", "vehicle_id", "event_id"], how="left")
    per["end_after_crossing_s"] = per["end"] - per["mid_time"]
    per["end_after_start_s"] = per["end"] - per["start_time"]
    per["alarm_before_crossing_s"] = per["advance_final_s"] - per["end_after_crossing_s"]
    per["alarm_after_start_s"] = per["end_after_start_s"] - per["advance_final_s"]
    return per


def timing_summary(per: pd.DataFrame) -> pd.DataFrame:
    rows = []
    for source, g in per.groupby("source"):
        hit, miss = g[g["predicted"]], g[~g["predicted"]]
        rows.append({"recording": source, "changes": len(g), "predicted": len(hit),
                     "mean advance s": hit["advance_final_s"].mean(),
                     "end after the crossing s (mean, all)": g["end_after_crossing_s"].mean(),
                     "end after the start s (mean, where seen)": g["end_after_start_s"].mean(),
                     "alarm before the crossing s (mean)": hit["alarm_before_crossing_s"].mean(),
                     "alarm after the start s (median)": hit["alarm_after_start_s"].median(),
                     "not predicted": len(miss), "observed before E s (median, not predicted)": miss["observed_s"].median()})
    return pd.DataFrame(rows)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("ngsim")
    p.add_argument("cr")
    p.add_argument("cv_work")
    p.add_argument("--out", required=True)
    p.add_argument("--estimators", action="store_true",
                   help="also the Kalman grid (sigma 0.05 / 0.1 / 0.3 m x q 0.01 / 0.05 / 0.2) and the lateral speed "
                        "over the vehicle's own recent sway, as alarms (about 10 more minutes)")
    p.add_argument("--threshold", type=float, default=0.53,
                   help="the model's threshold for timing.csv (default: the cross-fitted decision's 0.53)")
    a = p.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    stream, events = out_of_fold(Path(a.cv_work), EXTRA)
    stream["vehicle_id"] = stream["vehicle_id"].astype(str)
    events = events.assign(vehicle_id=events["vehicle_id"].astype(str))
    stream = with_lateral_position(stream, {"ngsim": Path(a.ngsim), "cr": Path(a.cr)})
    start = track_starts(stream, PERIOD_S)
    d = stream["d"].to_numpy()
    noise = {n: position_noise(d[(stream["source"] == n).to_numpy()], start[(stream["source"] == n).to_numpy()])
             for n in ("ngsim", "cr")}
    (out / "noise.json").write_text(json.dumps(noise, indent=1))
    per = alarm_timing(stream, events, Path(a.cv_work), a.threshold)
    per.to_csv(out / "timing.csv", index=False)
    (out / "timing.md").write_text(markdown(timing_summary(per), index=False))
    _, kf_speed = kalman_lateral_speed(d, start, PERIOD_S, KF_SIGMA_M, KF_ACCEL_PSD)
    signals = {
        "model probability (fine-tuned GRU, out of fold)": stream["prob"].to_numpy(),
        "|lateral_speed_mps| (EMA 0.5 s - 2 s, the feature)": np.abs(stream["lateral_speed_mps"].to_numpy()),
        "|lateral speed| EMA 1 s - 3 s": np.abs(ema_lateral_speed(d, start, PERIOD_S, 1.0, 3.0)),
        f"|lateral speed| Kalman (sigma {KF_SIGMA_M} m, q {KF_ACCEL_PSD})": np.abs(kf_speed),
        "|lateral_drift_m| (d - 10 s EMA, the feature)": np.abs(stream["lateral_drift_m"].to_numpy()),
        "|offset from the lane centre|": np.abs(stream["lane_offset_m"].to_numpy()),
    }
    extra = {}
    if a.estimators:
        for sigma in (0.05, 0.1, 0.3):
            for q in (0.01, 0.05, 0.2):
                extra[f"|lateral speed| Kalman (sigma {sigma} m, q {q})"] = np.abs(
                    kalman_lateral_speed(d, start, PERIOD_S, sigma, q)[1])
        v = stream["lateral_speed_mps"].to_numpy()
        for tc in (10.0, 20.0, 30.0):
            sway = np.sqrt(own_average(np.minimum(v * v, 0.25), start, tc))  # capped: one change barely moves it
            extra[f"|lateral_speed_mps| / max(own sway RMS over {tc:g} s, 0.1 m/s)"] = np.abs(v) / np.maximum(sway, 0.1)
    sep = separability(stream, events, {**signals, **extra})
    sep.to_csv(out / "separability.csv", index=False)
    wide = sep.assign(cell=[f"{m:.2f} / {100 * s:.1f} % / {u:.2f}"
                            for m, s, u in zip(sep["median"], sep["lk_above"], sep["auc"])])
    wide = wide.pivot(index="before_mid_s", columns="signal", values="cell").sort_index(ascending=False)
    (out / "separability.md").write_text(markdown(wide))
    gaps = window_auc(stream, events, GAP_COLUMNS, GAP_SIDE_COLUMNS)
    gaps.to_csv(out / "gap_auc.csv", index=False)
    (out / "gap_auc.md").write_text(markdown(gaps.set_index("window").T))
    rows = []
    for name, values in {**signals, **extra}.items():
        rows.append({"signal": name, **detector(stream, events, values)})
        print(rows[-1], flush=True)
    det = pd.DataFrame(rows)
    det.to_csv(out / "detectors.csv", index=False)
    (out / "detectors.md").write_text(markdown(det, index=False))
    print(f"{len(events)} lane changes, {len(stream) * PERIOD_S / 3600:.2f} vehicle-hours -> {out}")
    print(json.dumps(noise))
    print((out / "timing.md").read_text())
    print((out / "separability.md").read_text())
    print((out / "gap_auc.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
