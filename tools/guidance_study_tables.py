"""The figures the docs quote from a finished `vcfusion study guidance` folder, as markdown rows.

    python tools/guidance_study_tables.py STUDY_FOLDER [--close-m 50]

Prints, from the folder's trips.parquet and summary.json:
- the highlight row per guided arm (episodes right / wrong / missed / unseen, wrong and missed as
  shares of those drawn, per update, collision seeds) in the format of the guidance-loop tables;
- each camera arm's wrong share of drawn episodes with a 95 % interval, and its difference to the
  `oracle` arm's (paired by seed), both from resampling the seeds (`studies.matrix.highlight_table`,
  as `vcfusion guidance-matrix` tables them);
- each guided arm against `none` (paired difference and 95 % CI, `paired_summary`) for the minimum
  gap to the cut-in vehicle, fuel (also in % of `none`'s mean), average |a|, maximum |jerk|, TTC;
- the same minimum-gap difference on the trips whose cut-in comes within `--close-m` metres of the
  ego in the `none` arm (a subgroup chosen after a run: the docs say so where they quote it);
- mean speed and trip time per arm, how the trips ended, the seeds with wrong or missed episodes,
  and the wrong episodes by the vehicle in the box (the meant one, another, none; studies that log
  them).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from vcfusion.studies.guidance import REFERENCE_ARM, SAFETY_METRICS, WRONG_KINDS, paired_summary
from vcfusion.studies.matrix import WRONG_SHARE_RESAMPLES, highlight_table, read_study

METRICS = ("min_gap_to_target_m", "min_gap_stay_m", "fuel_g_per_km", "avg_abs_accel_mps2", "max_abs_jerk_mps3", "avg_ttc_clipped_s")


def _wrong_share_line(r: dict) -> str:
    """A camera arm's wrong share of drawn episodes with its 95 % interval and its difference to the
    oracle arm's (a row of `studies.matrix.highlight_table`)."""
    line = (f"{r['arm']}: wrong % of drawn {r['wrong_pct_of_drawn']:.1f} "
            f"[{r['wrong_pct_ci95_low']:.1f}, {r['wrong_pct_ci95_high']:.1f}]")
    if r["wrong_minus_oracle_pct"] == r["wrong_minus_oracle_pct"]:
        line += (f", minus oracle {r['wrong_minus_oracle_pct']:+.1f} [{r['wrong_minus_oracle_ci95_low']:+.1f}, "
                 f"{r['wrong_minus_oracle_ci95_high']:+.1f}]")
    return line


def _diff(row) -> str:
    return f"{row.mean_diff:+.2f} [{row.ci95_low:+.2f}, {row.ci95_high:+.2f}] (n = {row.n_pairs})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--close-m", type=float, default=50.0,
                    help="the subgroup: trips whose cut-in comes within this gap of the ego unguided [m]")
    args = ap.parse_args()
    study = read_study(args.folder)
    trips = study.trips
    seeds = sorted(trips["seed"].unique())
    print(f"{study.name}: {len(seeds)} paired trips, seeds {seeds[0]}-{seeds[-1]}, {study.wall_s:.0f} s wall "
          f"(last sitting; {study.trips_from_log} trips from the log), failed {study.failed_seeds or 'none'}")
    ref = trips[trips["arm"] == REFERENCE_ARM].set_index("seed")
    print(f"\nunguided: mean minimum gap to the cut-in vehicle {ref['min_gap_to_target_m'].mean():.1f} m, "
          f"trips with a cut-in ahead {int(ref['min_gap_to_target_m'].notna().sum())}, ego collisions in seeds "
          f"{ref.index[ref['collisions'].fillna(0) > 0].tolist() or 'none'}")
    print("\n| arm | right | wrong | missed | unseen | wrong / missed % of drawn | per update: wrong / missed % of drawn "
          "| ego collisions (seeds) |")
    highlights = highlight_table(trips, study.name)
    for r in highlights:
        ups = ("-" if r["updates_right"] != r["updates_right"] else
               f"{r['updates_wrong_pct_of_drawn']:.1f} / {r['updates_missed_pct_of_drawn']:.1f} "
               f"(of {r['updates_right'] + r['updates_wrong']:,.0f})")
        print(f"| {r['arm']} | {r['highlights_right']} | {r['highlights_wrong']} | {r['missed_warnings']} | "
              f"{r['unseen_warnings']} | {r['wrong_pct_of_drawn']:.1f} / {r['missed_pct_of_drawn']:.1f} | {ups} | "
              f"{r['collision_seeds'] or 'none'} |")
    print(f"\n95 % intervals from {WRONG_SHARE_RESAMPLES:,} resamples of the seeds:")
    for r in highlights:
        if r["wrong_pct_ci95_low"] == r["wrong_pct_ci95_low"]:  # the camera arms
            print("  " + _wrong_share_line(r))
    summary = paired_summary(trips)
    fuel_ref = ref["fuel_g_per_km"].mean()
    print("\narm - none [95 % CI]:")
    for r in summary[summary["metric"].isin(METRICS)].itertuples(index=False):
        extra = (f" = {100 * r.mean_diff / fuel_ref:+.1f} % [{100 * r.ci95_low / fuel_ref:+.1f}, "
                 f"{100 * r.ci95_high / fuel_ref:+.1f}]" if r.metric == "fuel_g_per_km" else "")
        print(f"  {r.arm:7s} {r.metric:22s} {_diff(r)}{extra}")
    close = ref.index[ref["min_gap_to_target_m"] < args.close_m]
    gap_metric = [m for m in SAFETY_METRICS if m[0] == "min_gap_to_target_m"]
    sub = paired_summary(trips[trips["seed"].isin(close)], metrics=gap_metric)
    print(f"\ncut-in within {args.close_m:g} m unguided ({len(close)} trips; a subgroup chosen after the run):")
    for r in sub.itertuples(index=False):
        print(f"  {r.arm:7s} min gap {_diff(r)}")
    print("\nper arm (mean):")
    print(trips.groupby("arm", sort=False)[["mean_speed_mps", "trip_time_s", "avg_abs_accel_mps2"]].mean().round(3)
          .to_string())
    print("\nhow the trips ended:")
    print(trips.groupby(["arm", "end_reason"], sort=False).size().to_string())
    for arm in [a for a in trips["arm"].unique() if a != REFERENCE_ARM]:
        t = trips[trips["arm"] == arm]
        wrong = {int(s): int(n) for s, n in t.loc[t["highlights_wrong"] > 0, ["seed", "highlights_wrong"]].values}
        missed = {int(s): int(n) for s, n in t.loc[t["missed_warnings"] > 0, ["seed", "missed_warnings"]].values}
        print(f"{arm}: episodes wrong by seed {wrong or 'none'}, missed by seed {missed or 'none'}")
        if set(WRONG_KINDS) <= set(t) and t[list(WRONG_KINDS)].notna().any().any():  # studies that log them
            kinds = ", ".join(f"{k.removeprefix('wrong_on_').replace('_', ' ')} {int(t[k].sum())}" for k in WRONG_KINDS)
            print(f"{arm}: wrong episodes by the vehicle in the box: {kinds}")


if __name__ == "__main__":
    from vcfusion.errors import InputError

    pd.set_option("display.width", 160)
    try:
        main()
    except InputError as exc:  # one line naming the file, exit 2 (as the vcfusion command does)
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
