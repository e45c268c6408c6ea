"""The guidance study (paper Section V, Fig. 8 and 9): paired trips with and without guidance.

Trip k runs the scenario with seed k twice: the same traffic seed and the same driver draw
(`vcfusion.driver.params.draw_driver(seed)`), once with the driver using the AR guidance and
once without (the baseline, a "legacy vehicle"). Both arms run the whole pipeline: cloud twins
with their process models (the lane-change predictor writes `lc_prob`), the guidance source
(the vision-fusion AR overlay when wired, else the cloud fallback; the output says which), the
driver model. Per trip and arm: TTC / acceleration / jerk metrics (`vcfusion.metrics.safety`)
and MOVESTAR fuel and emissions per km on the 1 Hz ego speed (`vcfusion.metrics.movestar`).

The effect of guidance is the paired difference (on - off) per trip; the summary gives its
mean with a t-based 95% confidence interval, the paired t-test p-value, and the relative
change of the arm means, next to the paper's values.

libsumo holds one simulation per process: trips run in worker processes (vcfusion.workers), each running
its two arms one after the other.
"""

from __future__ import annotations

import importlib
import json
import math
import time as wallclock
import traceback
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from vcfusion.runio import write_json, write_table
from vcfusion.workers import JobFailed, run_jobs

ARMS = ("off", "on")

# (column, label, unit, paper baseline, paper with guidance, paper relative change %)
SAFETY_METRICS = [
    ("avg_ttc_s", "average TTC to the lane-change vehicle", "s", None, None, 30.31),
    ("avg_ttc_clipped_s", "average TTC, clipped at 20 s", "s", None, None, None),
    ("min_ttc_s", "minimum TTC to the lane-change vehicle", "s", None, None, None),
    ("tet_s", "TET (TTC < metrics.ttc_threshold_s)", "s", None, None, None),
    ("tit_s2", "TIT (TTC < metrics.ttc_threshold_s)", "s^2", None, None, None),
    ("avg_abs_accel_mps2", "average |acceleration|", "m/s^2", 2.57, 2.07, None),
    ("max_abs_jerk_mps3", "maximum |jerk|", "m/s^3", 40.14, 35.91, None),
    ("max_decel_mps2", "maximum deceleration", "m/s^2", None, None, None),
    ("min_gap_to_target_m", "minimum gap to the lane-change vehicle", "m", None, None, None),
    ("collisions", "collisions of the ego", "", None, None, None),
]
EMISSION_METRICS = [
    ("fuel_g_per_km", "fuel", "g/km", 53.82, 51.37, None),
    ("co_g_per_km", "CO", "g/km", None, None, -38.32),
    ("hc_g_per_km", "HC", "g/km", None, None, None),
    ("nox_g_per_km", "NOx", "g/km", None, None, None),
    ("pm25_g_per_km", "PM2.5 (elemental + organic)", "g/km", None, None, None),
    ("co2_g_per_km", "CO2", "g/km", None, None, None),
]
# The raw mean TTC is dominated by near-zero closing speeds (unbounded): the figure shows the
# mean of TTC clipped at 20 s; both are in the tables and the summary.
FIG8 = ["avg_ttc_clipped_s", "avg_abs_accel_mps2", "max_abs_jerk_mps3"]
FIG9 = ["fuel_g_per_km", "co_g_per_km", "hc_g_per_km", "nox_g_per_km", "pm25_g_per_km", "co2_g_per_km"]


class StudyError(RuntimeError):
    """The study cannot give a meaningful result (message for the user)."""


def load_process_model(spec: str, scenario):
    """'module:factory' -> (name, model); factory(scenario) returns a ProcessModel."""
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise ValueError(f"--process-model: expected 'module:factory', got {spec!r}")
    try:
        factory = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"--process-model: cannot load {spec!r}: {exc}") from None
    return (f"{module_name}:{attr}", factory(scenario))


def run_arm(scenario, seed: int, guidance: bool, process_model_specs: tuple[str, ...] = ()) -> dict:
    """One arm of one trip: metrics row (no run folder is written)."""
    from vcfusion.metrics.movestar import trip_emissions
    from vcfusion.metrics.safety import trip_metrics
    from vcfusion.metrics.traffic import ego_movestar_type
    from vcfusion.run import build_cosimulation

    extra = [load_process_model(s, scenario) for s in process_model_specs]
    cosim = build_cosimulation(scenario, seed, guidance_enabled=guidance, extra_process_models=extra)
    result = cosim.run()
    tables = result.tables
    dt = scenario.simulation.step_s
    row = {"seed": seed, "arm": "on" if guidance else "off", "end_reason": result.summary["end_reason"],
           "cut_ins_ahead_of_ego": result.summary.get("cut_ins_ahead_of_ego", 0)}
    m = scenario.metrics  # the same thresholds and definitions as the runs' metrics tables
    row.update(trip_metrics(tables, scenario.ego.lane, dt, m.ttc_threshold_s, m.jerk_window_s, m.ttc_clip_s))
    row["ttc_threshold_s"] = m.ttc_threshold_s
    ego = tables["ego"]
    em = trip_emissions(ego["time"].to_numpy(), ego["speed"].to_numpy(), ego_movestar_type(scenario, tables["vehicles"]))
    pk = em["per_km"]
    row.update({
        "fuel_g_per_km": pk["Fuel"], "co_g_per_km": pk["CO"], "hc_g_per_km": pk["HC"], "nox_g_per_km": pk["NOx"],
        "pm25_g_per_km": (pk["PM2.5_Ele"] + pk["PM2.5_Org"]) if pk["CO"] is not None else None,
        "co2_g_per_km": pk["CO2"], "fuel_g": em["totals"]["Fuel"], "movestar_tt_s": em["TT_s"],
    })
    guidance_table = tables.get("guidance")
    sources = sorted(set(guidance_table["source"])) if guidance_table is not None and len(guidance_table) else ["none"]
    row["guidance_source"] = "+".join(sources)
    events = tables.get("driver_events")
    target = row["target_id"]
    row["response_time_s"] = math.nan
    row["response_cue"] = ""
    if target and events is not None and len(events):
        mine = events[events["vehicle_id"] == target]
        if len(mine):
            if guidance:
                first = mine.sort_values("response_time").iloc[0]
            else:
                first = mine[mine["cue"] == "lateral"].sort_values("response_time").iloc[0] \
                    if (mine["cue"] == "lateral").any() else None
            if first is not None:
                row["response_time_s"] = float(first["response_time"])
                row["response_cue"] = str(first["cue"])
    row["process_models"] = ",".join(name for name, _ in cosim.process_models) or "(none)"
    for k, v in cosim.controller.p.to_dict().items():
        row[f"driver_{k}"] = v
    return row


def run_trip(scenario_path: str, seed: int, process_model_specs: tuple[str, ...]) -> tuple[int, list[dict] | None, str | None]:
    """Both arms of trip `seed` (worker entry point)."""
    from vcfusion.scenario import load_scenario

    try:
        scenario = load_scenario(scenario_path)
        return seed, [run_arm(scenario, seed, g, process_model_specs) for g in (False, True)], None
    except Exception as exc:  # one failing trip must not stop the study
        return seed, None, f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}"


def paired_summary(trips: pd.DataFrame, metrics=SAFETY_METRICS + EMISSION_METRICS) -> pd.DataFrame:
    """Mean per arm, mean paired difference (on - off) with a t-based 95% CI, p-value."""
    from scipy import stats

    off = trips[trips["arm"] == "off"].set_index("seed")
    on = trips[trips["arm"] == "on"].set_index("seed")
    rows = []
    for col, label, unit, paper_off, paper_on, paper_rel in metrics:
        both = pd.concat([off[col].astype(float), on[col].astype(float)], axis=1, keys=["off", "on"]).dropna()
        n = len(both)
        diff = both["on"] - both["off"]
        mean_off, mean_on = both["off"].mean(), both["on"].mean()
        if n >= 2 and diff.std(ddof=1) > 0:
            half = stats.t.ppf(0.975, n - 1) * diff.std(ddof=1) / math.sqrt(n)
            p = float(stats.ttest_rel(both["on"], both["off"]).pvalue)
        else:
            half, p = (0.0 if n >= 2 else math.nan), (1.0 if n >= 2 else math.nan)
        if paper_rel is None and paper_off is not None:
            paper_rel = 100.0 * (paper_on - paper_off) / paper_off
        rows.append({
            "metric": col, "label": label, "unit": unit, "n_pairs": n,
            "mean_off": mean_off, "mean_on": mean_on,
            "mean_diff": diff.mean() if n else math.nan, "ci95_low": diff.mean() - half if n else math.nan,
            "ci95_high": diff.mean() + half if n else math.nan, "p_value": p,
            "rel_change_pct": 100.0 * (mean_on - mean_off) / mean_off if n and mean_off else math.nan,
            "paper_off": paper_off, "paper_on": paper_on, "paper_rel_change_pct": paper_rel,
        })
    return pd.DataFrame(rows)


def _verdict(r) -> str:
    if not r.n_pairs or math.isnan(r.ci95_low):
        return "no data"
    if r.ci95_low > 0:
        return "higher with guidance"
    if r.ci95_high < 0:
        return "lower with guidance"
    return "no significant difference"


def format_summary(summary: pd.DataFrame, info: dict) -> str:
    lines = [f"guidance study {info['scenario']}: {info['trips_ok']} paired trips "
             f"({info['trips_failed']} failed) in {info['wall_s']:.0f} s wall with {info['workers']} workers",
             f"  guidance source: {info['guidance_source']}; process models: {info['process_models']}",
             f"  trips with a cut-in ahead of the ego: {info['trips_with_target']} of {info['trips_ok']}",
             f"  mean response time gained with guidance (on the lane-change vehicle): "
             f"{info['mean_response_gain_s']:.2f} s over {info['response_pairs']} trips",
             "",
             f"  {'metric':<46} {'off':>9} {'on':>9} {'diff (on-off) [95% CI]':>32} {'rel':>8} "
             f"{'p':>7}  paper (off -> on, rel)  verdict"]
    for r in summary.itertuples(index=False):
        paper = ""
        if r.paper_off is not None and not (isinstance(r.paper_off, float) and math.isnan(r.paper_off)):
            paper = f"{r.paper_off:g} -> {r.paper_on:g}"
        if r.paper_rel_change_pct is not None and not (isinstance(r.paper_rel_change_pct, float)
                                                       and math.isnan(r.paper_rel_change_pct)):
            paper += f" ({r.paper_rel_change_pct:+.2f}%)"
        unit = f" [{r.unit}]" if r.unit else ""
        lines.append(
            f"  {(r.label + unit)[:46]:<46} {r.mean_off:9.4g} {r.mean_on:9.4g} "
            f"{r.mean_diff:+9.3g} [{r.ci95_low:+9.3g}, {r.ci95_high:+9.3g}] {r.rel_change_pct:+7.2f}% "
            f"{r.p_value:7.3g}  {paper:<22}  {_verdict(r)}")
    return "\n".join(lines)


def plot_figures(trips: pd.DataFrame, summary: pd.DataFrame, renders: Path, source: str) -> list[Path]:
    """Fig. 8 (TTC, |accel|, jerk) and Fig. 9 (fuel and emissions) like the paper's, with 95% CIs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    renders.mkdir(parents=True, exist_ok=True)
    by_metric = summary.set_index("metric")
    paths = []
    for name, cols, title in (("guidance_fig8_safety_comfort.png", FIG8, "Safety and comfort (cf. paper Fig. 8)"),
                              ("guidance_fig9_fuel_emissions.png", FIG9, "Fuel and emissions (cf. paper Fig. 9)")):
        fig, axes = plt.subplots(1, len(cols), figsize=(3.1 * len(cols), 3.6))
        for ax, col in zip(np.atleast_1d(axes), cols):
            r = by_metric.loc[col]
            means, errs = [], []
            for arm in ARMS:
                x = trips.loc[trips["arm"] == arm, col].astype(float).dropna()
                means.append(x.mean())
                errs.append(1.96 * x.std(ddof=1) / math.sqrt(len(x)) if len(x) > 1 else 0.0)
            ax.bar(["without", "with"], means, yerr=errs, capsize=4, color=["#999999", "#d9a400"])
            ax.set_title(f"{r['label']}\n[{r['unit']}]", fontsize=8)
            note = f"diff {r['mean_diff']:+.3g}\n95% CI [{r['ci95_low']:+.3g}, {r['ci95_high']:+.3g}]"
            paper_rel = r["paper_rel_change_pct"]
            if paper_rel is not None and not (isinstance(paper_rel, float) and math.isnan(paper_rel)):
                note += f"\npaper {paper_rel:+.1f}%"
            ax.text(0.5, 0.02, note, transform=ax.transAxes, ha="center", va="bottom", fontsize=7,
                    bbox={"facecolor": "white", "alpha": 0.8, "lw": 0})
            ax.tick_params(labelsize=8)
        fig.suptitle(f"{title}: {by_metric['n_pairs'].max()} paired trips, guidance source: {source}", fontsize=9)
        fig.tight_layout()
        path = renders / name
        tmp = path.with_suffix(".tmp.png")
        fig.savefig(tmp, dpi=120)
        plt.close(fig)
        tmp.replace(path)
        paths.append(path)
    return paths


def run_guidance_study(scenario_path: Path, trips: int, workers: int, out: Path, renders: Path,
                       first_seed: int = 0, process_model_specs: tuple[str, ...] = (),
                       progress: bool = True) -> dict:
    """Run the paired trips, write OUT/trips.parquet|csv, summary.csv|json|txt and the figures."""
    from vcfusion.scenario import load_scenario

    scenario = load_scenario(scenario_path)
    if scenario.ego is None:
        raise StudyError(f"{scenario_path}: the guidance study needs an ego (the scenario has no 'ego' block)")
    for spec in process_model_specs:  # fail fast, before any worker starts
        load_process_model(spec, scenario)
    started = wallclock.perf_counter()
    seeds = list(range(first_seed, first_seed + trips))
    rows: list[dict] = []
    failed: list[tuple[int, str]] = []
    bar = tqdm(total=len(seeds), unit="trip", desc=f"guidance study {scenario.name}", disable=not progress)
    jobs = [(str(scenario_path), s, tuple(process_model_specs)) for s in seeds]
    try:
        for index, outcome in run_jobs(run_trip, jobs, workers):
            # a JobFailed: the trip's worker process died (its other trips go on in a new one)
            seed, result, error = (seeds[index], None, outcome.cause) if isinstance(outcome, JobFailed) else outcome
            if error:
                failed.append((seed, error))
                bar.write(f"trip {seed} failed: {error.splitlines()[0]}")
            else:
                rows.extend(result)
            bar.update(1)
    finally:
        bar.close()
    failed.sort()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # as a batch's: the failed trips and their causes (the command then exits with 1)
    if failed:
        write_json(out / "failures.json", {str(s): e for s, e in failed})
    else:
        (out / "failures.json").unlink(missing_ok=True)
    if not rows:
        raise StudyError(f"all {len(seeds)} trips failed; first error: {failed[0][1] if failed else '?'}")
    table = pd.DataFrame(rows).sort_values(["seed", "arm"]).reset_index(drop=True)
    sources = sorted(set("+".join(table["guidance_source"]).split("+")))
    if sources == ["none"]:
        raise StudyError("no process model writes 'lc_prob' to the cloud twins, so no guidance was ever shown "
                         "and both arms are the same driver: wire the lane-change predictor in "
                         "run.build_cosimulation or pass --process-model module:factory")
    summary = paired_summary(table)
    on = table[table["arm"] == "on"].set_index("seed")
    off = table[table["arm"] == "off"].set_index("seed")
    gain = (off["response_time_s"] - on["response_time_s"]).dropna()
    info = {
        "scenario": scenario.name, "scenario_file": str(scenario_path), "seeds": [seeds[0], seeds[-1]],
        "trips_ok": int(table["seed"].nunique()), "trips_failed": len(failed), "workers": workers,
        "wall_s": wallclock.perf_counter() - started,
        "guidance_source": "+".join(s for s in sources if s != "none") + (
            " (cloud = fallback: guidance items made from the cloud lc_prob, no vision fusion)" if "cloud" in sources else ""),
        "process_models": ", ".join(sorted(set(table["process_models"]))),
        "trips_with_target": int(on["target_id"].notna().sum()),
        "mean_response_gain_s": float(gain.mean()) if len(gain) else math.nan, "response_pairs": int(len(gain)),
    }
    write_table(out / "trips.parquet", table)
    tmp = out / "trips.csv.tmp"
    table.to_csv(tmp, index=False)
    tmp.replace(out / "trips.csv")
    tmp = out / "summary.csv.tmp"
    summary.to_csv(tmp, index=False)
    tmp.replace(out / "summary.csv")
    text = format_summary(summary, info)
    write_json(out / "summary.json", info | {"metrics": json.loads(summary.to_json(orient="records")),
                                             "failed": {str(s): e for s, e in failed}})
    (out / "summary.txt").write_text(text + "\n")
    figures = plot_figures(table, summary, Path(renders), info["guidance_source"].split(" ")[0])
    return {"info": info, "summary": summary, "text": text, "figures": figures, "trips": table, "failed": failed}
