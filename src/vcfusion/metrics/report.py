"""`vcfusion report BATCH_DIR`: figures and a one-page Markdown report of a batch's metrics.

Reads only the small per-run tables (metrics, conflicts, metric_histograms, batch_summary) and
three columns of the ego's log, never the trajectories.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from vcfusion.metrics.batch_table import seed_statistics

MAX_EGO_TRACES = 30  # ego time series drawn (the first seeds)


def _read(folders: list[Path], name: str, columns: list[str] | None = None) -> pd.DataFrame:
    frames = []
    for folder in folders:
        path = folder / f"{name}.parquet"
        if path.is_file():
            frames.append(pd.read_parquet(path, columns=columns).assign(run=folder.name))
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    tmp = path.with_suffix(".tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path


def emissions_by_class(metrics: pd.DataFrame) -> pd.DataFrame:
    """Per vehicle class (counted vehicles): vehicle-km and the distance-weighted fuel and CO2 per km
    of MOVESTAR (its light-duty types) and of SUMO's model (every class)."""
    rows = []
    counted = metrics[metrics["counted"]]
    for vclass, g in counted.groupby("vclass", sort=True):
        km = g["distance_m"].sum() / 1000.0
        light = g[g["movestar_type"] > 0]
        mkm = light["movestar_distance_m"].sum() / 1000.0
        sumo = g[g["sumo_co2_g"].notna()]
        skm = sumo["distance_m"].sum() / 1000.0
        rows.append({"vclass": vclass, "vehicles": len(g), "vehicle_km": km,
                     "movestar_fuel_g_per_km": light["movestar_fuel_g"].sum() / mkm if mkm > 0 else math.nan,
                     "movestar_co2_g_per_km": light["movestar_co2_g"].sum() / mkm if mkm > 0 else math.nan,
                     "sumo_fuel_g_per_km": sumo["sumo_fuel_g"].sum() / skm if skm > 0 else math.nan,
                     "sumo_co2_g_per_km": sumo["sumo_co2_g"].sum() / skm if skm > 0 else math.nan})
    return pd.DataFrame(rows)


def _markdown_table(frame: pd.DataFrame, floatfmt: str = ".4g") -> str:
    cols = list(frame.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for row in frame.itertuples(index=False):
        cells = [format(v, floatfmt) if isinstance(v, (float, np.floating)) else str(v).replace("|", "\\|")
                 for v in row]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(batch: Path, folders: list[Path], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    metrics = _read(folders, "metrics")
    if metrics.empty:
        from vcfusion.errors import UsageError

        raise UsageError(f"{batch}: no metrics.parquet in its run folders; run `vcfusion metrics {batch}` first")
    hist = _read(folders, "metric_histograms")
    conflicts = _read(folders, "conflicts")
    settings = [_settings(f) for f in folders]
    odd = next((k for k, block in enumerate(settings) if block != settings[0]), None)
    if odd is not None:
        from vcfusion.errors import UsageError
        from vcfusion.runio import differing_keys

        keys = differing_keys(settings[0], settings[odd])
        raise UsageError(f"{folders[odd]}: its metrics were computed with another metrics: block than {folders[0]}'s "
                         f"(they differ in: {', '.join(keys)}); a report pools runs of one definition: recompute "
                         f"them with one (vcfusion metrics {batch} [--scenario FILE]) first")
    summary_path = batch / "batch_summary.parquet"
    batch_summary = pd.read_parquet(summary_path) if summary_path.is_file() else pd.DataFrame()
    figures = {}
    threshold = settings[0].get("ttc_threshold_s")

    # TTC and time headway distributions (all seeds, counted vehicles)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, measure, label, upto, width in ((axes[0], "ttc_s", "TTC to the leader [s]", 20.0, 0.5),
                                            (axes[1], "time_headway_s", "time headway to the leader [s]", 5.0, 0.1)):
        h = hist[hist["measure"] == measure].groupby(["bin_low", "bin_high"], as_index=False)["count"].sum()
        total = h["count"].sum()
        shown = h[h["bin_high"] <= upto]
        # the stored bins are fine (percentiles); the figure sums them into `width` bins
        coarse = shown.groupby(np.floor(shown["bin_low"] / width + 1e-9) * width)["count"].sum()
        if total:
            ax.bar(coarse.index, coarse.to_numpy() / total / width, width=width, align="edge", color="#4477aa")
        if measure == "ttc_s" and threshold is not None:
            ax.axvline(threshold, color="#ee6677", lw=1, label=f"conflict threshold {threshold:g} s")
            ax.legend(fontsize=8)
        ax.set_xlabel(label)
        ax.set_ylabel("density (of all samples) [1/s]")
        beyond = 100.0 * h.loc[h["bin_high"] > upto, "count"].sum() / total if total else 0.0
        ax.set_title(f"{int(total)} samples, {beyond:.0f} % beyond {upto:g} s", fontsize=9)
    fig.tight_layout()
    figures["distributions"] = _save(fig, out / "ttc_headway_distributions.png")

    # fuel and CO2 per km by vehicle class
    by_class = emissions_by_class(metrics)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    x = np.arange(len(by_class))
    for ax, what in zip(axes, ("fuel", "co2")):
        ax.bar(x - 0.2, by_class[f"movestar_{what}_g_per_km"], width=0.4, label="MOVESTAR", color="#ccbb44")
        ax.bar(x + 0.2, by_class[f"sumo_{what}_g_per_km"], width=0.4, label="SUMO (vType class)", color="#66ccee")
        ax.set_xticks(x, by_class["vclass"])
        ax.set_ylabel(f"{'fuel' if what == 'fuel' else 'CO2'} [g/km]")
        ax.legend(fontsize=8)
    fig.tight_layout()
    figures["emissions"] = _save(fig, out / "fuel_co2_by_class.png")

    # conflicts over the position along the road
    fig, ax = plt.subplots(figsize=(10, 3.2))
    if len(conflicts):
        ax.hist(conflicts["s_start"], bins=np.arange(0.0, conflicts["s_start"].max() + 50.0, 50.0), color="#ee6677")
    ax.set_xlabel("position along the road where the conflict began, s [m] (50 m bins)")
    ax.set_ylabel("conflicts (all seeds)")
    ax.set_title(f"{len(conflicts)} conflicts (TTC < {threshold:g} s) over {len(folders)} runs"
                 if threshold is not None else f"{len(conflicts)} conflicts over {len(folders)} runs", fontsize=9)
    fig.tight_layout()
    figures["conflicts"] = _save(fig, out / "conflicts_by_position.png")

    # the ego over time
    ego_logs = []
    for folder in (f for f in folders if (f / "ego.parquet").is_file()):  # a run without an ego has an empty log
        e = pq.read_table(folder / "ego.parquet", columns=["time", "speed", "leader_gap_m"]).to_pandas()
        if len(e):
            ego_logs.append(e)
        if len(ego_logs) == MAX_EGO_TRACES:
            break
    if ego_logs:
        fig, axes = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
        for e in ego_logs:
            accel = np.r_[np.diff(e["speed"]) / np.diff(e["time"]), np.nan] if len(e) > 1 else np.full(len(e), np.nan)
            axes[0].plot(e["time"], e["speed"], lw=0.7, alpha=0.7)
            axes[1].plot(e["time"], accel, lw=0.5, alpha=0.6)
            axes[2].plot(e["time"], e["leader_gap_m"], lw=0.7, alpha=0.7)
        axes[0].set_ylabel("speed [m/s]")
        axes[1].set_ylabel("acceleration [m/s^2]")
        axes[2].set_ylabel("gap to leader [m]")
        axes[2].set_xlabel("time [s]")
        axes[0].set_title(f"the ego in {len(ego_logs)} runs", fontsize=9)
        fig.tight_layout()
        figures["ego"] = _save(fig, out / "ego_time_series.png")

    stats = seed_statistics(batch_summary) if len(batch_summary) else pd.DataFrame()
    lines = [f"# Metrics report: {batch.name}", "",
             f"{len(folders)} runs; {int(metrics['counted'].sum())} counted vehicle trips, "
             f"{metrics.loc[metrics['counted'], 'distance_m'].sum() / 1000.0:.1f} vehicle-km. "
             f"{_settings_line(settings[0])}", ""]
    if len(stats):
        table = stats[["label", "unit", "seeds", "mean", "ci95_low", "ci95_high", "p2_5", "p97_5"]].rename(columns={
            "ci95_low": "95% CI low", "ci95_high": "95% CI high", "p2_5": "seeds 2.5%", "p97_5": "seeds 97.5%"})
        lines += ["## Over the seeds", "", "Mean, t-based 95 % confidence interval of the mean, and the spread "
                  "of the seeds (2.5-97.5 %).", "", _markdown_table(table), ""]
    sumo_rates = {"others": "the vehicles MOVESTAR does not rate", "all": "every vehicle",
                  "none": "no vehicle"}.get(settings[0].get("sumo_emissions"),
                                            "the vehicles the runs' `metrics.sumo_emissions` names")
    lines += ["## Fuel and CO2 by vehicle class", "", "Distance-weighted over all runs (sum of grams / sum of km). "
              f"MOVESTAR rates only its light-duty types; SUMO's model {sumo_rates} (`metrics.sumo_emissions`; "
              "a class it does not rate reads nan).", "", _markdown_table(by_class), ""]
    lines += ["## Figures", ""] + [f"![{k}]({p.name})" for k, p in figures.items()] + [""]
    path = out / "report.md"
    tmp = out / "report.md.tmp"
    tmp.write_text("\n".join(lines))
    tmp.replace(path)
    return path


def _settings(folder: Path) -> dict:
    import json

    return json.loads((folder / "summary.json").read_text()).get("metrics", {}).get("settings", {})


def _settings_line(block: dict) -> str:
    if not block:
        return ""
    return (f"TTC threshold {block['ttc_threshold_s']} s (conflicts, TET/TIT), jerk window {block['jerk_window_s']} s, "
            f"leader range {block['leader_range_m']} m, MOVESTAR types {block['movestar']}, "
            f"left out of traffic figures: groups {block['exclude_groups']}; SUMO emissions: {block['sumo_emissions']}.")
