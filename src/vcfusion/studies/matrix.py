"""The guidance study over several scenarios in one command (`vcfusion guidance-matrix`).

Each scenario runs the paired guidance study (`run_guidance_study`: seeds first_seed .. +trips,
the same arms) into OUT/<scenario name>/ (or, `--from-studies`, the folders of studies already run one
by one are read); then one table per scenario and a pooled one (every trip
of every scenario, paired within its scenario and seed): per metric and arm the paired difference
to ``none`` with its 95 % CI (`paired_summary`), the highlight episodes (right, wrong, missed,
unseen; wrong and missed as shares of those drawn; the wrong share's 95 % interval and its
difference to the oracle arm's, trips resampled) and the trips with an ego collision by seed.
Each scenario carries a label: ``tuned-on`` for the scenarios the chain was tuned on (given by
name), ``held-out`` for the others; the pooled table says which labels it mixes.

Writes OUT/matrix_summary.csv (metrics), OUT/matrix_highlights.csv, OUT/matrix.txt.
"""

from __future__ import annotations

import json
import time as wallclock
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.errors import InputError
from vcfusion.metrics.cluster_bootstrap import cluster_weights, percentile_interval, ratio_draws
from vcfusion.studies.guidance import (CAMERA_ARMS, DEFAULT_ARMS, EMISSION_METRICS, HIGHLIGHT_COUNTS,
                                       HIGHLIGHT_UPDATES, REFERENCE_ARM, SAFETY_METRICS, paired_summary,
                                       run_guidance_study)


class StudyFolderError(InputError):
    """A folder given as a finished guidance study is not one (a missing or foreign file)."""


KEY_METRICS = ("min_gap_to_target_m", "avg_ttc_clipped_s", "avg_abs_accel_mps2", "fuel_g_per_km", "collisions")


# percentile bootstrap of the wrong share over trips (seeds): 4,000 resamples put the interval's ends
# within about 0.1 point of their limit on 200-seed studies (curved 3000-3199: the same to 0.1 with 16,000)
WRONG_SHARE_RESAMPLES = 4000
WRONG_SHARE_COLUMNS = ("wrong_pct_ci95_low", "wrong_pct_ci95_high", "wrong_minus_oracle_pct",
                       "wrong_minus_oracle_ci95_low", "wrong_minus_oracle_ci95_high")


def wrong_share_intervals(trips: pd.DataFrame, pair_on: tuple[str, ...] = ("seed",)) -> dict[str, dict]:
    """Per camera arm, its wrong highlight episodes in % of those drawn (right + wrong) with a 95 %
    percentile interval, and its difference to the ``oracle`` arm's (paired), both from resampling
    the trips (the `pair_on` values: a seed, or a scenario and seed in a pool) with replacement
    (vcfusion.metrics.cluster_bootstrap). Over the trips every camera arm ran, so all arms are
    evaluated on the same resamples. Keys: WRONG_SHARE_COLUMNS (the differences nan where there is
    no oracle arm)."""
    arms = [a for a in trips["arm"].unique() if a in CAMERA_ARMS]
    if not arms:
        return {}
    t = trips[trips["arm"].isin(arms)].assign(drawn=trips["highlights_right"] + trips["highlights_wrong"])
    per_trip = t.pivot(index=list(pair_on), columns="arm", values=["highlights_wrong", "drawn"]).dropna()
    if per_trip.empty:
        return {}
    weights = cluster_weights(len(per_trip), WRONG_SHARE_RESAMPLES, seed=0)
    shares = {}  # arm -> (point, per resample), %
    for a in arms:
        wrong, drawn = per_trip[("highlights_wrong", a)].to_numpy(), per_trip[("drawn", a)].to_numpy()
        shares[a] = (100 * wrong.sum() / drawn.sum() if drawn.sum() else np.nan,
                     100 * ratio_draws(weights, wrong, drawn))
    out = {}
    for a, (point, draws) in shares.items():
        low, high = percentile_interval(draws)
        row = dict.fromkeys(WRONG_SHARE_COLUMNS, np.nan) | {"wrong_pct_ci95_low": low, "wrong_pct_ci95_high": high}
        if a != "oracle" and "oracle" in shares:
            low, high = percentile_interval(draws - shares["oracle"][1])
            row |= {"wrong_minus_oracle_pct": point - shares["oracle"][0], "wrong_minus_oracle_ci95_low": low,
                    "wrong_minus_oracle_ci95_high": high}
        out[a] = row
    return out


def highlight_table(trips: pd.DataFrame, group: str) -> dict:
    """Highlight episode sums of one scenario (or the pool, trips paired within scenario and seed)
    per guided arm, with the shares and, for the camera arms, the wrong share's 95 % intervals
    (:func:`wrong_share_intervals`)."""
    pair_on = ("scenario", "seed") if "scenario" in trips else ("seed",)
    intervals = wrong_share_intervals(trips, pair_on)
    rows = []
    for arm, t in trips[trips["arm"] != REFERENCE_ARM].groupby("arm", sort=False):
        sums = {k: int(t[k].sum()) for k in HIGHLIGHT_COUNTS}
        drawn = sums["highlights_right"] + sums["highlights_wrong"]
        ups = {k: (int(t[k].sum()) if k in t and t[k].notna().any() else float("nan")) for k in HIGHLIGHT_UPDATES}
        drawn_ups = ups["updates_right"] + ups["updates_wrong"]
        hit = t.loc[t["collisions"].fillna(0) > 0, "seed"].tolist()
        ref = trips[(trips["arm"] == REFERENCE_ARM) & (trips["collisions"].fillna(0) > 0)]
        rows.append({"group": group, "arm": arm, "trips": int(len(t)), **sums,
                     "wrong_pct_of_drawn": 100 * sums["highlights_wrong"] / drawn if drawn else float("nan"),
                     "missed_pct_of_drawn": 100 * sums["missed_warnings"] / drawn if drawn else float("nan"),
                     **ups,
                     "updates_wrong_pct_of_drawn": (100 * ups["updates_wrong"] / drawn_ups if drawn_ups
                                                    else float("nan")),
                     "updates_missed_pct_of_drawn": (100 * ups["updates_missed"] / drawn_ups if drawn_ups
                                                     else float("nan")),
                     **{k: intervals.get(arm, {}).get(k, np.nan) for k in WRONG_SHARE_COLUMNS},
                     "collision_seeds": " ".join(map(str, hit)),
                     "reference_collision_seeds": " ".join(map(str, ref["seed"].tolist()))})
    return rows


def run_matrix(scenarios: list[Path], trips: int, workers: int, out: Path, tuned_on: set[str],
               arms=DEFAULT_ARMS, first_seed: int = 0, progress: bool = True) -> dict:
    """Run the guidance study on every scenario and write the matrix tables (see the module doc)."""
    out = Path(out)
    started = wallclock.perf_counter()
    studies = []
    for path in scenarios:
        from vcfusion.scenario import load_scenario

        name = load_scenario(path).name
        if name in {s.name for s in studies}:
            raise ValueError(f"scenarios: two scenarios are named {name!r}; expected distinct names")
        t0 = wallclock.perf_counter()
        res = run_guidance_study(Path(path), trips, workers, out / name, out / name / "renders", first_seed,
                                 progress=progress, arms=tuple(arms))
        studies.append(StudyPart(name, res["trips"], wallclock.perf_counter() - t0, [s for s, _ in res["failed"]],
                                 int(res["info"]["trips_from_log"])))
    head = (f"guidance matrix: {len(studies)} scenarios x {trips} paired trips (seeds {first_seed}-"
            f"{first_seed + trips - 1}), arms {', '.join(arms)}, {wallclock.perf_counter() - started:.0f} s wall "
            f"with {workers} workers")
    return write_matrix(studies, out, tuned_on, head)


@dataclass(frozen=True)
class StudyPart:
    """One scenario's finished guidance study, as the matrix reads it."""
    name: str  # the scenario's name (its label is looked up by it)
    trips: pd.DataFrame  # the study's trip rows (`run_guidance_study`'s "trips"; OUT/trips.parquet)
    wall_s: float  # wall time of the sitting that finished the study (trips taken from a log cost none)
    failed_seeds: list[int]
    trips_from_log: int  # trips that sitting took from an earlier sitting's trip log


def read_study(folder: Path) -> StudyPart:
    """A finished `vcfusion study guidance` folder (its summary.json and trips.parquet) as a part of a
    matrix. StudyFolderError naming the folder and the file when one is missing or is no study's."""
    folder = Path(folder)
    summary, table = folder / "summary.json", folder / "trips.parquet"
    for f in (summary, table):
        if not f.is_file():
            raise StudyFolderError(f"{f}: expected the file a finished `vcfusion study guidance` writes; not found")
    try:
        info = json.loads(summary.read_text())
        name, wall, failed = str(info["scenario"]), float(info["wall_s"]), [int(s) for s in info["failed"]]
        from_log = int(info.get("trips_from_log", 0))
    except (ValueError, KeyError, TypeError) as exc:
        raise StudyFolderError(f"{summary}: expected a guidance study's summary with scenario, wall_s and "
                               f"failed; {type(exc).__name__}: {exc}") from None
    trips = pd.read_parquet(table)
    needed = {"seed", "arm", "collisions", *HIGHLIGHT_COUNTS, *(m[0] for m in SAFETY_METRICS + EMISSION_METRICS)}
    missing = sorted(needed - set(trips.columns))
    if missing:
        raise StudyFolderError(f"{table}: expected a guidance study's trip table; columns {missing} missing")
    return StudyPart(name, trips, wall, failed, from_log)


def matrix_from_studies(folders: list[Path], out: Path, tuned_on: set[str]) -> dict:
    """The matrix tables of guidance studies already run one by one (each scenario's folder of
    `vcfusion study guidance`), written as `run_matrix` writes them. The studies must have the same
    arms; their seeds may differ (each is paired within itself)."""
    studies = [read_study(f) for f in folders]
    names = [s.name for s in studies]
    if len(set(names)) != len(names):
        raise StudyFolderError(f"studies: two folders hold the study of the same scenario ({names}); expected "
                               f"one folder per scenario")
    arms = {s.name: list(dict.fromkeys(s.trips["arm"])) for s in studies}  # in the studies' own order
    if len({frozenset(a) for a in arms.values()}) != 1:
        raise StudyFolderError(f"studies: expected the same arms in every study, got {arms}")
    parts = []
    for s, folder in zip(studies, folders):
        seeds = sorted(s.trips["seed"].unique())
        parts.append(f"{s.name} {len(seeds)} trips (seeds {seeds[0]}-{seeds[-1]}) from {folder}")
    head = (f"guidance matrix of {len(studies)} studies run one by one, arms {', '.join(arms[names[0]])}: "
            + "; ".join(parts))
    return write_matrix(studies, Path(out), tuned_on, head)


def write_matrix(studies: list[StudyPart], out: Path, tuned_on: set[str], head: str) -> dict:
    """Per-scenario and pooled tables of finished studies into OUT (see the module doc)."""
    labels = {s.name: "tuned-on" if s.name in tuned_on else "held-out" for s in studies}
    table = pd.concat([s.trips.assign(scenario=s.name) for s in studies], ignore_index=True)
    summaries, highlights = [], []
    for name, t in table.groupby("scenario", sort=False):
        s = paired_summary(t.drop(columns="scenario"))
        summaries.append(s.assign(group=name, split=labels[name]))
        highlights += [r | {"split": labels[name]} for r in highlight_table(t, name)]
    mixed = "+".join(sorted(set(labels.values())))
    summaries.append(paired_summary(table, pair_on=("scenario", "seed")).assign(group="pooled", split=mixed))
    highlights += [r | {"split": mixed} for r in highlight_table(table, "pooled")]
    summary = pd.concat(summaries, ignore_index=True)
    hl = pd.DataFrame(highlights)
    out.mkdir(parents=True, exist_ok=True)
    summary.to_csv(out / "matrix_summary.csv", index=False)
    hl.to_csv(out / "matrix_highlights.csv", index=False)
    lines = [head]
    for s in studies:
        lines.append(f"  {s.name} [{labels[s.name]}]: {s.wall_s:.0f} s"
                     + (f" ({s.trips_from_log} trips taken from an earlier sitting's log)" if s.trips_from_log else "")
                     + (f", failed trips {s.failed_seeds}" if s.failed_seeds else ""))
    for group in [*labels, "pooled"]:
        label = labels.get(group, mixed)
        lines += ["", f"{group} [{label}]"]
        for r in hl[hl["group"] == group].itertuples(index=False):
            lines.append(f"  {r.arm}: highlight episodes right {r.highlights_right}, wrong {r.highlights_wrong} "
                         f"({r.wrong_pct_of_drawn:.1f} % of drawn"
                         + ("" if r.wrong_pct_ci95_low != r.wrong_pct_ci95_low else
                            f" [{r.wrong_pct_ci95_low:.1f}, {r.wrong_pct_ci95_high:.1f}]")
                         + ("" if r.wrong_minus_oracle_pct != r.wrong_minus_oracle_pct else
                            f", minus oracle {r.wrong_minus_oracle_pct:+.1f} [{r.wrong_minus_oracle_ci95_low:+.1f}, "
                            f"{r.wrong_minus_oracle_ci95_high:+.1f}]")
                         + f"), missed {r.missed_warnings} "
                         f"({r.missed_pct_of_drawn:.1f} %), unseen {r.unseen_warnings}"
                         + ("" if r.updates_right != r.updates_right else
                            f"; per update: wrong {r.updates_wrong_pct_of_drawn:.1f} %, missed "
                            f"{r.updates_missed_pct_of_drawn:.1f} % of {r.updates_right + r.updates_wrong:.0f} drawn")
                         + f"; ego collisions in seeds [{r.collision_seeds}] "
                           f"(none arm: [{r.reference_collision_seeds}])")
        part = summary[(summary["group"] == group) & summary["metric"].isin(KEY_METRICS)]
        for r in part.itertuples(index=False):
            lines.append(f"  {r.arm} vs none  {r.label[:40]:<40} n={r.n_pairs:3d}  {r.mean_diff:+9.3g} "
                         f"[{r.ci95_low:+9.3g}, {r.ci95_high:+9.3g}] {r.unit}")
    text = "\n".join(lines)
    (out / "matrix.txt").write_text(text + "\n")
    return {"summary": summary, "highlights": hl, "text": text, "trips": table}
