"""False alarms and lane changes predicted on the cross-fitted streams by how much each vehicle
sways in lane keeping (docs/components/real-data.md, "Lateral speed over the vehicle's own sway"):
do the sway inputs take the false alarms off the vehicles that sway most?

    python tools/sway_strata.py "NAME=CV_WORK_DIR:THRESHOLD" ... [--recording ngsim] [--groups 3]

CV_WORK_DIR: a finished `tools/real_alarms_cv.py` work folder; THRESHOLD: the decision compared
(aggressive smoothing, tau_a 50 ticks, as the tool's). A vehicle's sway: the RMS of its
`lateral_speed_mps` (squares capped at 0.25 m^2/s^2) over its lane-keeping ticks (no change of it
ending within 12 s after or 5 s before) with a known lateral position; the vehicles of the
recording are cut into --groups groups of equal count by it (the same cut for every model: the
folds hold the same vehicles). Prints, per group and model: vehicles, vehicle-hours, false alarms
(of them censored) and per vehicle-hour, lane changes predicted. Cross-fitted development figures.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_alarms_cv import out_of_fold  # noqa: E402

from vcfusion.prediction.advance import lane_keeping_mask  # noqa: E402
from vcfusion.prediction.events import event_scores, smooth_stream, smoothing_bounds, track_bounds  # noqa: E402

PERIOD_S = 0.1
TAU_TICKS = 50
SPEED_CAP_MPS2 = 0.25


def vehicle_sway(stream: pd.DataFrame, events: pd.DataFrame) -> pd.Series:
    """RMS lane-keeping lateral speed per (original_seed, vehicle_id), m/s (NaN: no such tick)."""
    keep = lane_keeping_mask(stream, events) & (stream["lateral_known"].to_numpy() > 0.5)
    v2 = np.minimum(stream["lateral_speed_mps"].to_numpy(dtype=float) ** 2, SPEED_CAP_MPS2)
    frame = pd.DataFrame({"original_seed": stream["original_seed"], "vehicle_id": stream["vehicle_id"],
                          "v2": np.where(keep, v2, np.nan)})
    return np.sqrt(frame.groupby(["original_seed", "vehicle_id"])["v2"].mean())


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("models", nargs="+", help="NAME=CV_WORK_DIR:THRESHOLD")
    p.add_argument("--recording", default="ngsim", choices=("ngsim", "cr"))
    p.add_argument("--groups", type=int, default=3)
    a = p.parse_args()
    cut, rows = None, []
    for item in a.models:
        name, _, rest = item.partition("=")
        work, _, thr = rest.rpartition(":")
        if not (name and work and thr):
            p.error(f"{item!r}: expected NAME=CV_WORK_DIR:THRESHOLD")
        stream, events = out_of_fold(Path(work), ("lateral_speed_mps", "lateral_known"))
        stream["vehicle_id"] = stream["vehicle_id"].astype(str)
        events = events.assign(vehicle_id=events["vehicle_id"].astype(str))
        stream = stream[(stream["source"] == a.recording).to_numpy()].reset_index(drop=True)
        events = events[events["seed"].isin(stream["seed"].unique())]
        sway = vehicle_sway(stream, events)
        if cut is None:  # groups of equal count, by sway (vehicles without lane keeping: the last group)
            order = sway.fillna(np.inf).sort_values(kind="stable")
            cut = pd.Series(np.arange(len(order)) * a.groups // len(order), index=order.index)
            edges = [order.groupby(cut.to_numpy()).apply(lambda s: (s.min(), s.max())).tolist()]
        group = pd.MultiIndex.from_arrays([stream["original_seed"], stream["vehicle_id"]]).map(cut)
        if group.isna().any():
            p.error(f"{work}: its vehicles differ from the first model's (not the same folds)")
        dec = smooth_stream(smoothing_bounds(stream), (stream["prob"].to_numpy() > float(thr)).astype(np.int8),
                            "aggressive", TAU_TICKS, TAU_TICKS)
        fa, cens = {}, {}
        _, per_event = event_scores(stream, dec, events, PERIOD_S, 10.0, track_bounds(stream), fa, cens)
        for g in range(a.groups):
            in_g = (group.to_numpy() == g)
            units = set(zip(stream.loc[in_g, "seed"], stream.loc[in_g, "vehicle_id"]))
            hours = in_g.sum() * PERIOD_S / 3600
            n_fa = sum(fa.get(u, 0) for u in units)
            n_cens = sum(cens.get(u, 0) for u in units)
            ev = per_event[[(s, v) in units for s, v in zip(per_event["seed"], per_event["vehicle_id"])]]
            lo, hi = edges[0][g]
            rows.append({"sway group": f"{g + 1} ({lo:.3f}-{hi:.3f} m/s)", "model": f"{name} ({float(thr):.2f})",
                         "vehicles": len(units), "veh-h": f"{hours:.2f}", "false alarms (censored)": f"{n_fa} ({n_cens})",
                         "false alarms / veh-h": f"{n_fa / hours:.1f}" if hours else "-",
                         "changes predicted": f"{int(ev['predicted'].sum())} of {len(ev)}"})
    table = pd.DataFrame(rows).sort_values(["sway group"], kind="stable")
    lines = ["| " + " | ".join(table.columns) + " |", "|" + "---|" * len(table.columns)]
    print("\n".join(lines + ["| " + " | ".join(map(str, r)) + " |" for r in table.itertuples(index=False)]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
