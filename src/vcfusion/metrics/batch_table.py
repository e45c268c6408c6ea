"""The metrics of a batch over its seeds: mean and 95 % interval of each summary column."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

# (batch_summary column, label, unit); the rows of the printed table and of the report
BATCH_ROWS = [
    ("traffic_vehicle_km", "vehicle-km (counted vehicles)", "km"),
    ("traffic_conflicts", "conflicts (TTC episodes below the threshold)", ""),
    ("traffic_conflicts_per_vehicle_km", "conflicts per vehicle-km", "1/km"),
    ("traffic_tet_s", "TET, all counted vehicles", "s"),
    ("traffic_tit_s2", "TIT, all counted vehicles", "s^2"),
    ("traffic_min_ttc_s", "minimum TTC", "s"),
    ("traffic_ttc_p05_s", "TTC 5th percentile", "s"),
    ("traffic_ttc_p50_s", "TTC median", "s"),
    ("traffic_max_drac_mps2", "maximum DRAC", "m/s^2"),
    ("traffic_min_time_headway_s", "minimum time headway", "s"),
    ("traffic_collisions", "collisions (vehicle pairs)", ""),
    ("traffic_fuel_g_per_km", "fuel, all rated vehicles", "g/km"),
    ("traffic_co2_g_per_km", "CO2, all rated vehicles", "g/km"),
    ("traffic_nox_g_per_km", "NOx, all rated vehicles", "g/km"),
    ("traffic_movestar_fuel_g_per_km", "MOVESTAR fuel (its light-duty types)", "g/km"),
    ("traffic_movestar_co2_g_per_km", "MOVESTAR CO2", "g/km"),
    ("traffic_movestar_nox_g_per_km", "MOVESTAR NOx", "g/km"),
    ("traffic_sumo_fuel_g_per_km", "SUMO model fuel (the vehicles it rates)", "g/km"),
    ("traffic_sumo_co2_g_per_km", "SUMO model CO2", "g/km"),
    ("traffic_sumo_nox_g_per_km", "SUMO model NOx", "g/km"),
    ("ego_min_ttc_s", "ego: minimum TTC to its leader", "s"),
    ("ego_tet_s", "ego: TET", "s"),
    ("ego_min_time_headway_s", "ego: minimum time headway", "s"),
    ("ego_mean_abs_accel_mps2", "ego: mean |acceleration|", "m/s^2"),
    ("ego_max_abs_jerk_mps3", "ego: maximum |jerk|", "m/s^3"),
    ("ego_movestar_fuel_g_per_km", "ego: MOVESTAR fuel", "g/km"),
    ("ego_sumo_co2_g_per_km", "ego: SUMO CO2", "g/km"),
]


def seed_statistics(batch: pd.DataFrame) -> pd.DataFrame:
    """Per metric over the seeds that define it: n, mean, the t-based 95 % confidence interval of
    the mean, and the 2.5-97.5 % range of the seeds themselves."""
    from scipy import stats

    rows = []
    for col, label, unit in BATCH_ROWS:
        if col not in batch:
            continue
        x = pd.to_numeric(batch[col], errors="coerce").dropna().to_numpy(dtype=float)
        n = len(x)
        if n == 0:  # e.g. SUMO's model on the ego when MOVESTAR rates it
            continue
        mean = float(x.mean()) if n else math.nan
        half = float(stats.t.ppf(0.975, n - 1) * x.std(ddof=1) / math.sqrt(n)) if n >= 2 else math.nan
        low, high = (np.percentile(x, [2.5, 97.5]) if n else (math.nan, math.nan))
        rows.append({"metric": col, "label": label, "unit": unit, "seeds": n, "mean": mean,
                     "ci95_low": mean - half, "ci95_high": mean + half, "p2_5": float(low), "p97_5": float(high)})
    return pd.DataFrame(rows)


def format_seed_statistics(stats: pd.DataFrame) -> str:
    lines = [f"  {'metric':<50} {'seeds':>5} {'mean':>10} {'95% CI of the mean':>24} {'2.5-97.5% of seeds':>24}"]
    for r in stats.itertuples(index=False):
        unit = f" [{r.unit}]" if r.unit else ""
        lines.append(f"  {(r.label + unit)[:50]:<50} {r.seeds:>5} {r.mean:>10.4g} "
                     f"{f'[{r.ci95_low:.4g}, {r.ci95_high:.4g}]':>24} {f'[{r.p2_5:.4g}, {r.p97_5:.4g}]':>24}")
    return "\n".join(lines)
