"""Metrics of one run: at the end of a run (CoSimulation.run) and for an existing run folder
(`vcfusion metrics`), the same function on the same tables.

Writes four tables: `metrics` (one row per vehicle), `conflicts` (one row per conflict
episode), `metric_histograms` (TTC and headway distributions of the counted vehicles) and
`sumo_emissions` (SUMO's per-vehicle emission totals, kept so a folder can be re-evaluated);
returns the `metrics` block of summary.json.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from vcfusion.metrics.safety import colliding_pairs
from vcfusion.metrics.sumo_emissions import emission_table
from vcfusion.runio import write_json
from vcfusion.metrics.traffic import (EGO_ID, HEADWAY_EDGES, MOVESTAR_KEYS, SUMO_KEYS, TTC_EDGES, RunMetrics,
                                      compute_run_metrics, histogram_percentile)

METRIC_TABLES = ("metrics", "conflicts", "metric_histograms")
EGO_KEYS = {  # summary key -> metrics.parquet column
    # (its mean speed is the summary's ego_mean_speed_mps already)
    "travel_time_s": "travel_time_s", "travel_distance_m": "distance_m",
    "mean_abs_accel_mps2": "mean_abs_accel_mps2", "max_decel_mps2": "max_decel_mps2",
    "max_abs_jerk_mps3": "max_abs_jerk_mps3", "min_ttc_s": "min_ttc_s", "tet_s": "tet_s", "tit_s2": "tit_s2",
    "max_drac_mps2": "max_drac_mps2", "min_time_headway_s": "min_time_headway_s", "conflicts": "conflicts",
    "movestar_fuel_g_per_km": "movestar_fuel_g_per_km", "movestar_co2_g_per_km": "movestar_co2_g_per_km",
    "movestar_co_g_per_km": "movestar_co_g_per_km", "movestar_nox_g_per_km": "movestar_nox_g_per_km",
    "sumo_fuel_g_per_km": "sumo_fuel_g_per_km", "sumo_co2_g_per_km": "sumo_co2_g_per_km",
}


def add_run_metrics(scenario, tables, session) -> dict:
    """At the end of a run (`session`: its closed SumoSession): SUMO's totals from its tripinfo and
    its parked vehicles, the metric tables into `tables` (a RunTables), the summary block back."""
    sumo = emission_table(session.tripinfo_file, session.parked_emissions, session.emission_classes)
    tables.add_arrow("sumo_emissions", sumo)
    sim = scenario.simulation
    ego = tables.arrow("ego", ["time", "s", "speed"]) if scenario.ego is not None else None
    trajectories = tables.sources()["trajectories"]
    if isinstance(trajectories, pd.DataFrame):  # an empty run: no samples were streamed
        trajectories = pa.Table.from_pandas(trajectories, preserve_index=False)
    result = compute_run_metrics(scenario.metrics, sim.trajectory_period_s, sim.step_s, trajectories,
                                 tables["vehicles"], ego, tables.get("lane_changes"), sumo)
    for name, table in zip(METRIC_TABLES, (result.vehicles, result.conflicts, result.histograms)):
        tables.add_arrow(name, table)
    return summary_block(scenario.metrics, result, tables["collisions"], sumo_available=True)


def folder_metrics(folder: Path, cfg, simulation) -> tuple[RunMetrics, dict, bool]:
    """Recompute a run folder's metrics from its tables (no simulation). The third value says
    whether the folder has SUMO's emission totals (folders written before them do not)."""
    folder = Path(folder)

    def table(name: str) -> pd.DataFrame | None:
        path = folder / f"{name}.parquet"
        return pd.read_parquet(path) if path.is_file() else None

    sumo = table("sumo_emissions")
    ego_path = folder / "ego.parquet"
    ego = pq.read_table(ego_path, columns=["time", "s", "speed"]) if ego_path.is_file() else None
    vehicles = table("vehicles")
    result = compute_run_metrics(cfg, simulation.trajectory_period_s, simulation.step_s, folder / "trajectories.parquet",
                                 vehicles, ego if ego is not None and ego.num_rows else None, table("lane_changes"), sumo)
    collisions = table("collisions")
    return result, summary_block(cfg, result, collisions, sumo_available=sumo is not None), sumo is not None


def _clean(value):
    """JSON-safe: NaN/inf -> None, NumPy scalars -> Python."""
    if value is None:
        return None
    if isinstance(value, (np.integer, int)) and not isinstance(value, bool):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    return value


def _ratio(num: float, den: float) -> float | None:
    return num / den if den > 0 and math.isfinite(num) else None


def metrics_settings(cfg, sumo_available: bool = True) -> dict:
    """summary.json's `metrics.settings`: the definitions a run's metrics were computed with (a
    batch and a report pool only runs of one)."""
    return {"ttc_threshold_s": cfg.ttc_threshold_s, "jerk_window_s": cfg.jerk_window_s,
            "leader_range_m": cfg.leader_range_m, "movestar": dict(cfg.movestar),
            "exclude_groups": list(cfg.exclude_groups),
            "sumo_emissions": cfg.sumo_emissions if sumo_available else "missing: the run folder has no "
            "sumo_emissions.parquet (written before SUMO's emissions were recorded)"}


def summary_block(cfg, result: RunMetrics, collisions: pd.DataFrame | None, sumo_available: bool) -> dict:
    """summary.json's `metrics`: the ego, the traffic (counted vehicles) and the settings used."""
    col = result.columns
    distinct = colliding_pairs(collisions)
    pairs, ego_collisions = len(distinct), sum(EGO_ID in pair for pair in distinct)
    block: dict = {"settings": metrics_settings(cfg, sumo_available)}
    ids = col["vehicle_id"].tolist()
    if EGO_ID in ids:
        i = ids.index(EGO_ID)
        block["ego"] = {k: _clean(col[c][i]) for k, c in EGO_KEYS.items()} | {
            "lane_changes": int(col["lane_changes"][i]), "collisions": ego_collisions}
    counted = col["counted"].astype(bool)
    km = float(col["distance_m"][counted].sum()) / 1000.0
    traffic: dict = {"vehicles": int(counted.sum()), "vehicle_km": km,
                     "vehicle_h": float(col["travel_time_s"][counted].sum()) / 3600.0}
    # MOVESTAR rates whole seconds: a vehicle on the road for less than one has no rating (no km either)
    light = counted & (col["movestar_type"] > 0) & (col["movestar_seconds"] > 0)
    mkm = float(col["movestar_distance_m"][light].sum()) / 1000.0
    traffic["movestar_vehicle_km"] = mkm
    for k in MOVESTAR_KEYS.values():
        traffic[f"movestar_{k}_per_km"] = _ratio(_sum(col[f"movestar_{k}"][light]), mkm)
    with_sumo = counted & np.isfinite(col["sumo_co2_g"].astype(float))
    skm = float(col["distance_m"][with_sumo].sum()) / 1000.0
    traffic["sumo_vehicle_km"] = skm
    for k in SUMO_KEYS:
        traffic[f"sumo_{k}_g_per_km"] = _ratio(_sum(col[f"sumo_{k}_g"][with_sumo]), skm)
    # the whole traffic: each vehicle by MOVESTAR where it has a MOVESTAR type, else by SUMO's model
    by_sumo = with_sumo & ~light
    traffic["rated_vehicle_km"] = mkm + float(col["distance_m"][by_sumo].sum()) / 1000.0
    for k in ("fuel", "co2", "co", "hc", "nox"):
        grams = _sum(col[f"movestar_{k}_g"][light]) if light.any() else 0.0
        grams += _sum(col[f"sumo_{k}_g"][by_sumo]) if by_sumo.any() else 0.0
        traffic[f"{k}_g_per_km"] = _ratio(grams, traffic["rated_vehicle_km"])
    conflicts = int(col["conflicts"][counted].sum())
    traffic.update({
        "conflicts": conflicts, "conflicts_per_vehicle_km": _ratio(float(conflicts), km),
        "tet_s": float(col["tet_s"][counted].sum()), "tit_s2": float(col["tit_s2"][counted].sum()),
        "min_ttc_s": _extreme(col["min_ttc_s"][counted], np.min), "max_drac_mps2": _extreme(col["max_drac_mps2"][counted], np.max),
        "min_time_headway_s": _extreme(col["min_time_headway_s"][counted], np.min),
    })
    for q in (1, 5, 15, 50):
        traffic[f"ttc_p{q:02d}_s"] = histogram_percentile(TTC_EDGES, result.ttc_counts, q)
    traffic["time_headway_p05_s"] = histogram_percentile(HEADWAY_EDGES, result.headway_counts, 5)
    traffic["collisions"] = pairs
    block["traffic"] = {k: _clean(x) for k, x in traffic.items()}
    return block


def _sum(x: np.ndarray) -> float:
    return float(np.sum(x)) if len(x) else math.nan


def _extreme(x: np.ndarray, fn) -> float:
    x = x[np.isfinite(x)]
    return float(fn(x)) if len(x) else math.nan


def batch_row(summary: dict) -> dict:
    """A run's row of batch_summary.parquet: its plain summary fields, and the metrics block as
    ego_* and traffic_* columns."""
    block = summary.get("metrics") or {}
    return {k: v for k, v in summary.items() if not isinstance(v, (dict, list))} | {
        f"{group}_{k}": v for group in ("ego", "traffic") for k, v in (block.get(group) or {}).items()}


def write_summary_metrics(folder: Path, block: dict) -> None:
    """Replace the metrics block of a run folder's summary.json (atomically)."""
    path = Path(folder) / "summary.json"
    summary = json.loads(path.read_text())
    summary["metrics"] = block
    tmp = path.with_suffix(".json.tmp")
    write_json(tmp, summary)
    tmp.replace(path)


def format_run_metrics(summary: dict) -> str:
    """The metrics block as lines under the run summary ('' when the run has none)."""
    block = summary.get("metrics")
    if not block:
        return ""

    def f(value, fmt=".3g"):
        return "n/a" if value is None else format(value, fmt)

    tr = block["traffic"]
    threshold = block["settings"]["ttc_threshold_s"]
    lines = [f"  metrics ({tr['vehicles']} vehicles, {tr['vehicle_km']:.2f} vehicle-km): "
             f"{tr['conflicts']} conflicts (TTC < {threshold:g} s), min TTC {f(tr['min_ttc_s'])} s, "
             f"TTC 5th percentile {f(tr['ttc_p05_s'])} s, min time headway {f(tr['min_time_headway_s'])} s",
             f"    fuel {f(tr['fuel_g_per_km'])} g/km, CO2 {f(tr['co2_g_per_km'])} g/km, NOx {f(tr['nox_g_per_km'])} g/km "
             f"(MOVESTAR light-duty, SUMO's model for the rest)"]
    if summary.get("network_max_height_m"):
        lines.append(f"    MOVESTAR's rates are for zero grade, but this network has elevation (lanes up to "
                     f"{summary['network_max_height_m']:g} m off z = 0)")
    ego = block.get("ego")
    if ego:
        lines.append(f"    ego: min TTC {f(ego['min_ttc_s'])} s, TET {f(ego['tet_s'])} s, mean |a| "
                     f"{f(ego['mean_abs_accel_mps2'])} m/s^2, max |jerk| {f(ego['max_abs_jerk_mps3'])} m/s^3, "
                     f"fuel {f(ego['movestar_fuel_g_per_km'])} g/km")
    return "\n".join(lines)
