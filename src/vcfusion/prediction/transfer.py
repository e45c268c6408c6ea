"""The sim-to-real table (issue 46): lane-change models x evaluation sets, with 95 % bootstrap
intervals over vehicles.

Each model is scored with its own decision settings (the smoothing, threshold and windows stored in
its file, tuned on the validation data it names: a model re-tuned on a real recording's validation
part is a separate file, `vcfusion retune`), on the every-tick stream of one split of a dataset,
exactly as `vcfusion evaluate` scores its default variant (:func:`vcfusion.prediction.events.event_scores`).

Interval: the vehicles of the scored split (a vehicle = one (seed, vehicle_id) track) are
resampled with replacement `n_boot` times (`numpy.random.default_rng(seed)`); each statistic is
recomputed as a ratio of sums over the resampled vehicles (lane changes predicted / lane
changes, sum of advances / predicted changes, false alarms / vehicle-hours), and the 2.5 and 97.5
percentiles are the interval. Vehicles, not samples: a vehicle's ticks are not independent.
`censored_false_alarms_share`: the share of the false alarms whose confirming window (run end +
horizon) runs past the vehicle's last tick (:func:`vcfusion.prediction.events.event_scores`).
`false_alarms_judged_per_veh_h`: the judged (censoring-aware) rate, the uncensored false alarms
over the vehicle-hours at which a confirming window fits in the track (each track less its last
`horizon` seconds); shown beside the headline rate, which counts every false alarm over every
vehicle-hour. Undefined ("-") for a set without such exposure (tracks all shorter than the horizon).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.metrics.cluster_bootstrap import cluster_weights, percentile_interval, ratio_draws
from vcfusion.prediction.dataset import load_dataset
from vcfusion.prediction.events import event_scores, judged_ticks, smooth_stream, smoothing_bounds, track_bounds
from vcfusion.prediction.features import stored_columns, with_derived_columns
from vcfusion.prediction.model import load_model
from vcfusion.prediction.train import stream_with_events

STATISTICS = ("predicted", "before_mid", "advance_s", "false_alarms_per_veh_h", "false_alarms_judged_per_veh_h",
              "censored_false_alarms_share")


def vehicle_table(model_path: Path, dataset: Path, split: str = "test", horizon_s: float = 10.0) -> tuple[pd.DataFrame, dict]:
    """One row per vehicle of `split`: hours, judged hours (those at which a confirming window fits
    in the track), false alarms (and of them censored), lane changes, predicted, predicted before
    the midpoint, sum of advances (final run); and the model's decision settings used."""
    model = load_model(model_path)
    info = load_dataset(dataset)
    names = list(model.feature_names)
    if model.kind == "gru":
        from vcfusion.prediction.train_sequence import check_sequence_columns

        check_sequence_columns([info], names)
    stream, events = stream_with_events(info, split, columns=["seed", "vehicle_id", "time", *stored_columns(names)])
    with_derived_columns(stream, names, info.period_s)
    prob = model.stream_proba(stream, names)
    method = model.smoothing
    threshold = model.threshold_for(method)
    raw = (prob > threshold).astype(np.int8)
    dec = smooth_stream(smoothing_bounds(stream), raw, method, tau_a=model.tau_a_ticks, tau_c=model.tau_c_ticks,
                        threshold=model.conservative_threshold)
    fa: dict = {}
    censored: dict = {}
    summary, per_event = event_scores(stream, dec, events, info.period_s, horizon_s, track_bounds(stream), fa,
                                      censored)
    ticks = stream.groupby(["seed", "vehicle_id"], sort=True).size().rename("ticks")
    table = ticks.to_frame()
    table["hours"] = table["ticks"] * info.period_s / 3600.0
    judged = stream.groupby(["seed", "vehicle_id"], sort=True)["time"].agg(
        lambda t: judged_ticks(t.to_numpy(dtype=float), horizon_s))
    table["judged_hours"] = judged.reindex(table.index).to_numpy() * info.period_s / 3600.0
    table["false_alarms"] = [fa.get(k, 0) for k in table.index]
    table["false_alarms_censored"] = [censored.get(k, 0) for k in table.index]
    ev = per_event.assign(advance=per_event["advance_final_s"].fillna(0.0))
    agg = ev.groupby(["seed", "vehicle_id"]).agg(lane_changes=("predicted", "size"), predicted=("predicted", "sum"),
                                                before_mid=("before_mid", "sum"), advance_sum_s=("advance", "sum"))
    table = table.join(agg, how="left").fillna({"lane_changes": 0, "predicted": 0, "before_mid": 0,
                                                "advance_sum_s": 0.0})
    for c in ("lane_changes", "predicted", "before_mid"):
        table[c] = table[c].astype(int)
    settings = {"smoothing": method, "threshold": threshold, "tau_a_ticks": model.tau_a_ticks,
                "tau_c_ticks": model.tau_c_ticks, "summary": summary}
    return table.reset_index(), settings


def _ratios(w: np.ndarray, t: pd.DataFrame) -> dict[str, np.ndarray]:
    """The statistics of weighted vehicle sets: w (B, V) counts of each vehicle in each resample."""
    col = lambda name: t[name].to_numpy(dtype=float)  # noqa: E731
    judged_false_alarms = col("false_alarms") - col("false_alarms_censored")
    return {"predicted": ratio_draws(w, col("predicted"), col("lane_changes")),
            "before_mid": ratio_draws(w, col("before_mid"), col("lane_changes")),
            "advance_s": ratio_draws(w, col("advance_sum_s"), col("predicted")),
            "false_alarms_per_veh_h": ratio_draws(w, col("false_alarms"), col("hours")),
            "false_alarms_judged_per_veh_h": ratio_draws(w, judged_false_alarms, col("judged_hours")),
            "censored_false_alarms_share": ratio_draws(w, col("false_alarms_censored"), col("false_alarms"))}


def bootstrap(table: pd.DataFrame, n_boot: int = 1000, seed: int = 0, level: float = 0.95) -> dict[str, dict]:
    """Point value and percentile interval of each statistic (STATISTICS) over vehicles (rows)."""
    v = len(table)
    point = {k: float(x[0]) for k, x in _ratios(np.ones((1, v)), table).items()}
    if v == 0:
        return {k: {"value": float("nan"), "low": float("nan"), "high": float("nan")} for k in STATISTICS}
    boots = _ratios(cluster_weights(v, n_boot, seed), table)
    out = {}
    for k in STATISTICS:
        low, high = percentile_interval(boots[k], level)
        out[k] = {"value": point[k], "low": low, "high": high}
    return out


def sim_to_real_table(models: list[tuple[str, Path]], evals: list[tuple[str, Path, str]], out: Path,
                      n_boot: int = 1000, seed: int = 0, horizon_s: float = 10.0, progress: bool = True) -> pd.DataFrame:
    """Score every model on every (label, dataset, split); write OUT/sim_to_real.{csv,md,json}."""
    from tqdm import tqdm

    rows = []
    jobs = [(m, e) for m in models for e in evals]
    for (mlabel, mpath), (elabel, dpath, split) in tqdm(jobs, desc="sim-to-real", disable=not progress, leave=False):
        table, settings = vehicle_table(mpath, dpath, split, horizon_s)
        stats = bootstrap(table, n_boot, seed)
        row = {"model": mlabel, "model_file": Path(mpath).name, "eval": elabel, "dataset": Path(dpath).name,
               "split": split, "vehicles": int(len(table)), "vehicle_hours": float(table["hours"].sum()),
               "lane_changes": int(table["lane_changes"].sum()), "smoothing": settings["smoothing"],
               "threshold": settings["threshold"]}
        for k in STATISTICS:
            row[k], row[f"{k}_low"], row[f"{k}_high"] = stats[k]["value"], stats[k]["low"], stats[k]["high"]
        rows.append(row)
    df = pd.DataFrame(rows)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "sim_to_real.csv", index=False)
    (out / "sim_to_real.md").write_text(markdown_table(df, n_boot, seed))
    (out / "sim_to_real.json").write_text(json.dumps({"bootstrap": {"resamples": n_boot, "seed": seed, "unit": "vehicle",
                                                                    "level": 0.95},
                                                      "horizon_s": horizon_s, "rows": rows}, indent=1, default=float))
    return df


def _cell(row, k: str, pct: bool = False, digits: int = 1) -> str:
    v, lo, hi = row[k], row[f"{k}_low"], row[f"{k}_high"]
    if not np.isfinite(v):
        return "-"
    f = (lambda x: f"{100 * x:.{digits}f}") if pct else (lambda x: f"{x:.{digits}f}")  # noqa: E731
    return f"{f(v)}{' %' if pct else ''} [{f(lo)}, {f(hi)}]" if np.isfinite(lo) else f"{f(v)}{' %' if pct else ''}"


def markdown_table(df: pd.DataFrame, n_boot: int, seed: int) -> str:
    lines = ["| model | evaluation set | vehicles | veh-h | lane changes | predicted | before midpoint | "
             "mean advance (s) | false alarms / veh-h | judged false alarms / veh-h | of them censored |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for _, r in df.iterrows():
        lines.append(f"| {r['model']} | {r['eval']} | {r['vehicles']} | {r['vehicle_hours']:.2f} | {r['lane_changes']} | "
                     f"{_cell(r, 'predicted', True)} | {_cell(r, 'before_mid', True)} | {_cell(r, 'advance_s', digits=2)} | "
                     f"{_cell(r, 'false_alarms_per_veh_h')} | {_cell(r, 'false_alarms_judged_per_veh_h')} | "
                     f"{_cell(r, 'censored_false_alarms_share', True, 0)} |")
    lines.append("")
    lines.append(f"[low, high]: 95 % bootstrap interval over vehicles ({n_boot} resamples, seed {seed}); each model "
                 "with the decision settings stored in its file. Censored: false alarms whose confirming window "
                 "(run end + horizon) runs past the vehicle's last tick. Judged: the false alarms that are not "
                 "censored over the vehicle-hours at which the confirming window fits in the track (censoring-aware).")
    return "\n".join(lines) + "\n"
