"""A small search over SUMO lane-change model settings that brings simulated lane changes closer to
recorded ones: `vcfusion calibrate-lane-changes`.

Each candidate is a `lane_change_model:` block (vcfusion.scenario.LaneChangeModelConfig) put on a
base scenario (a scenario file that `extends` it); its seeds are simulated into a dataset and
compared with the recorded datasets by vcfusion.prediction.manoeuvres. The objective is the mean
KS distance, over the recorded datasets, of the quantities a lane-change model shapes
(OBJECTIVE: duration, peak lateral speed, lateral offset and speed at -5, -3, -1, +1 s from
the crossing); gaps and neighbour speeds are reported but not scored, since they follow the
traffic's density more than the lane-change model. The table lists every candidate tried.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import yaml

from vcfusion.prediction.manoeuvres import PROFILE_KS_TAUS, dataset_kinematics, ks_table

OBJECTIVE = ("duration_s", "lateral_speed_peak_mps",
             *[f"lateral_offset_at_{t:+g}s_m" for t in PROFILE_KS_TAUS],
             *[f"lateral_speed_at_{t:+g}s_mps" for t in PROFILE_KS_TAUS])

# The candidates of the documented search (name -> lane_change_model block; None: SUMO's LC2013
# with the scenario's global --lanechange.duration, the project's default).
CANDIDATES: dict[str, dict | None] = {
    "lc2013-default": None,
    "lc2013-fixed5": {"model": "LC2013", "duration": {"distribution": "fixed", "median_s": 5.0}},
    "lc2013-logn5": {"model": "LC2013", "duration": {"distribution": "lognormal", "median_s": 5.0, "sigma": 0.3,
                                                     "min_s": 2.0, "max_s": 12.0}},
    "lc2013-logn6": {"model": "LC2013", "duration": {"distribution": "lognormal", "median_s": 6.0, "sigma": 0.35,
                                                     "min_s": 2.0, "max_s": 12.0}},
    "sl2015-sumo": {"model": "SL2015", "lateral_resolution_m": 0.8},
    "sl2015-acc05-v1": {"model": "SL2015", "lateral_resolution_m": 0.8, "lc_accel_lat_mps2": 0.5,
                        "max_speed_lat_mps": 1.0},
    "sl2015-acc03-logn4": {"model": "SL2015", "lateral_resolution_m": 0.8, "lc_accel_lat_mps2": 0.3,
                           "duration": {"distribution": "lognormal", "median_s": 4.0, "sigma": 0.3, "min_s": 2.0,
                                        "max_s": 12.0}},
    "sl2015-acc03-logn4-sigma03": {"model": "SL2015", "lateral_resolution_m": 0.8, "lc_accel_lat_mps2": 0.3,
                                   "lc_sigma": 0.3,
                                   "duration": {"distribution": "lognormal", "median_s": 4.0, "sigma": 0.3,
                                                "min_s": 2.0, "max_s": 12.0}},
    "sl2015-acc02-logn35": {"model": "SL2015", "lateral_resolution_m": 0.8, "lc_accel_lat_mps2": 0.2,
                            "duration": {"distribution": "lognormal", "median_s": 3.5, "sigma": 0.3, "min_s": 2.0,
                                         "max_s": 12.0}},
}
# Second stage: the sublane model around the first stage's best (lcSigma 0.3, lcAccelLat 0.3,
# lognormal durations of median 4 s): lateral imperfection x lateral acceleration x duration.
for _sigma in (0.3, 0.6):
    for _acc in (0.3, 0.6, 1.0):
        for _median in (3.0, 4.0):
            CANDIDATES[f"sl2015-sigma{_sigma:g}-acc{_acc:g}-logn{_median:g}"] = {
                "model": "SL2015", "lateral_resolution_m": 0.8, "lc_sigma": _sigma, "lc_accel_lat_mps2": _acc,
                "duration": {"distribution": "lognormal", "median_s": _median, "sigma": 0.3, "min_s": 1.5,
                             "max_s": 12.0}}

# Third stage: the second stage's best sat at its largest lcSigma (0.6): larger ones.
for _sigma in (0.9, 1.2):
    for _acc in (0.6, 1.0):
        for _median in (3.5, 4.0):
            CANDIDATES[f"sl2015-sigma{_sigma:g}-acc{_acc:g}-logn{_median:g}"] = {
                "model": "SL2015", "lateral_resolution_m": 0.8, "lc_sigma": _sigma, "lc_accel_lat_mps2": _acc,
                "duration": {"distribution": "lognormal", "median_s": _median, "sigma": 0.3, "min_s": 1.5,
                             "max_s": 12.0}}


def candidate_scenario(base: Path, block: dict | None, out: Path) -> Path:
    """A scenario file at `out` that extends `base` with the lane_change_model block."""
    text = {"extends": str(Path(base).resolve())}
    if block is not None:
        text["lane_change_model"] = block
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(text, sort_keys=False))
    return out


def score(ks: pd.DataFrame) -> float:
    """The objective: mean KS over OBJECTIVE and the recorded datasets (NaN rows left out)."""
    return float(ks[ks["quantity"].isin(OBJECTIVE)]["ks"].mean())


def run_search(base: Path, seeds: list[int], real_roots: list[Path], out: Path, names: list[str] | None = None,
               workers: int = 1, tau: float = 5.0, tau_g: float = 2.0, progress: bool = True,
               candidates: list[str] | None = None) -> pd.DataFrame:
    """Simulate every candidate (or those named; datasets under out/NAME, resumable) and score it;
    writes out/search.csv, out/search.md and out/ks_all.csv (every quantity, every candidate)."""
    from vcfusion.prediction.dataset import DatasetError, build_dataset

    unknown = [c for c in candidates or [] if c not in CANDIDATES]
    if unknown:
        raise DatasetError(f"--candidates: {', '.join(unknown)}: no such candidate; expected some of "
                           f"{', '.join(CANDIDATES)}")

    out = Path(out)
    reals = [(name, dataset_kinematics(Path(r), name))
             for r, name in zip(real_roots, names or [Path(r).name for r in real_roots])]
    rows, all_ks = [], []
    for name, block in CANDIDATES.items():
        if candidates is not None and name not in candidates:
            continue
        scenario = candidate_scenario(base, block, out / "scenarios" / f"{name}.yaml")
        data = out / name
        report = build_dataset(scenario, seeds, data, workers, tau, tau_g, progress=progress)
        sim = dataset_kinematics(data, name)
        ks = pd.concat([ks_table(sim, real, name, rname) for rname, real in reals], ignore_index=True)
        all_ks.append(ks)
        row = {"candidate": name, "seeds_done": len(seeds) - len(report["failed"]),
               "lane_changes": int(len(sim[0])), "objective": score(ks)}
        for q in ("duration_s", "lateral_speed_peak_mps", "lateral_offset_at_-3s_m", "lateral_speed_at_-1s_mps",
                  "gap_target_lead_m", "gap_target_lag_m"):
            sub = ks[ks["quantity"] == q]
            row[f"ks_{q}"] = float(sub["ks"].mean())
            row[f"median_{q}"] = float(sub["median_sim"].iloc[0]) if len(sub) else float("nan")
        row["block"] = yaml.safe_dump(block, default_flow_style=True).strip() if block else "(none)"
        rows.append(row)
    table = pd.DataFrame(rows)
    table.to_csv(out / "search.csv", index=False)
    pd.concat(all_ks, ignore_index=True).to_csv(out / "ks_all.csv", index=False)
    medians = {q: float(pd.concat([r[1][0] for r in reals])[q].median()) for q in
               ("duration_s", "lateral_speed_peak_mps", "gap_target_lead_m", "gap_target_lag_m")}
    lines = ["| candidate | lane changes | objective (mean KS) | KS duration | KS peak lat. speed | "
             "KS offset -3 s | KS lat. speed -1 s | median duration s | median peak m/s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in table.to_dict("records"):
        lines.append(f"| {r['candidate']} | {r['lane_changes']} | {r['objective']:.3f} | {r['ks_duration_s']:.3f} | "
                     f"{r['ks_lateral_speed_peak_mps']:.3f} | {r['ks_lateral_offset_at_-3s_m']:.3f} | "
                     f"{r['ks_lateral_speed_at_-1s_mps']:.3f} | {r['median_duration_s']:.2f} | "
                     f"{r['median_lateral_speed_peak_mps']:.2f} |")
    lines.append(f"| (recorded, pooled) | | | | | | | {medians['duration_s']:.2f} | "
                 f"{medians['lateral_speed_peak_mps']:.2f} |")
    (out / "search.md").write_text("\n".join(lines) + "\n")
    return table
