"""How lane changes are driven, measured the same way in any lane-change dataset (simulated or
imported), and how two datasets differ: `vcfusion compare-lane-changes`.

Source of the motion. A simulated run folder has SUMO's ground-truth trajectory table
(`trajectories`: s, d, lane every trajectory period); an imported recording has the replayed
twins (`twins`: x = s, y = d - road width, `d_known`). Both are the vehicles' own motion (a
recording's positions are what its tracker measured; the simulated cloud's GNSS noise is left
out, so the comparison is of driving, not of sensors).

Each lane change between main lanes (`lane_changes`, from_lane and to_lane >= 0) is looked at
around its midpoint M (`mid_time`: the first sample in the new lane; for SUMO the moment its
lanechange-output reports), with `direction` (+1 left, -1 right):
- profiles on tau = -10 .. +3 s (0.1 s steps; NaN where the track has no sample or no lateral
  position): lateral offset = direction x (d(M + tau) - d(M)) (m, towards the new lane, 0 at the
  crossing) and lateral speed = direction x d'(M + tau) (m/s; d smoothed over
  trajectories.LATERAL_SMOOTH_S, as the import does);
- duration: from the last time before M to the first after M at which the lateral speed towards
  the new lane is at most trajectories.LATERAL_SETTLED_MPS (the imports' start / end rule, applied
  to both, so SUMO's "centred to 5 cm" does not make its changes look different); NaN if the
  track does not show both;
- at DECISION_TAU_S before M: speed of the own lane's leader minus own speed (`dv_leader`), of
  the target lane's leader (`dv_target_lead`) and follower (`dv_target_lag`) minus own speed;
- accepted gaps at the last sample before M (still in the old lane): bumper to bumper to the
  target lane's leader (`gap_target_lead`) and follower (`gap_target_lag`), m; NaN when there is
  none within GAP_RANGE_M;
- `time_since_last_change`: M minus the vehicle's previous change's M (NaN: none seen);
- `lateral_speed_peak`: the largest lateral speed towards the new lane within the duration
  window (tau -10 .. +3 s).
The two datasets' distributions of every quantity (and of the profiles at PROFILE_KS_TAUS) are
compared with the two-sample Kolmogorov-Smirnov distance (scipy.stats.ks_2samp).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.prediction.dataset import DatasetError, load_dataset
from vcfusion.traffic.lanechanges import LATERAL_SETTLED_MPS, lateral_speed

TAU_BEFORE_S, TAU_AFTER_S = 10.0, 3.0
STEP_S = 0.1
DECISION_TAU_S = 2.0  # neighbour speeds this long before the crossing (within any lane change's lateral motion)
GAP_RANGE_M = 150.0  # the features' neighbour range (features.RANGE_M)
PROFILE_KS_TAUS = (-5.0, -3.0, -1.0, 1.0)
SCALARS = ("duration_s", "lateral_speed_peak_mps", "dv_leader_mps", "dv_target_lead_mps", "dv_target_lag_mps",
           "gap_target_lead_m", "gap_target_lag_m", "time_since_last_change_s")
TAUS = np.round(np.arange(-TAU_BEFORE_S, TAU_AFTER_S + STEP_S / 2, STEP_S), 6)


@dataclass
class Motion:
    """One run's motion: every vehicle's samples sorted by (vehicle, time)."""

    table: pd.DataFrame  # time, vehicle_id, s, d (NaN unknown), lane, speed, length
    period_s: float


def _run_motion(folder: Path) -> Motion:
    manifest = json.loads((folder / "manifest.json").read_text())
    lengths = pd.read_parquet(folder / "vehicles.parquet", columns=["vehicle_id", "length"])
    traj = folder / "trajectories.parquet"
    if traj.is_file():
        t = pd.read_parquet(traj, columns=["time", "vehicle_id", "s", "d", "lane", "speed"])
    else:
        road = manifest.get("road")
        if not isinstance(road, dict) or "num_lanes" not in road:
            raise DatasetError(f"{folder}: neither a trajectories table nor an imported recording's road in "
                               "manifest.json; expected a run folder of `vcfusion dataset`")
        tw = pd.read_parquet(folder / "twins.parquet")
        width = float(road["num_lanes"]) * float(road["lane_width_m"])
        d = tw["y"].to_numpy(float) + width
        if "d_known" in tw:
            d = np.where(tw["d_known"].to_numpy(bool), d, np.nan)
        t = pd.DataFrame({"time": tw["time"], "vehicle_id": tw["vehicle_id"], "s": tw["x"], "d": d,
                          "lane": tw["lane"], "speed": tw["speed"]})
    t = t.merge(lengths, on="vehicle_id", how="left")
    t["length"] = t["length"].fillna(4.5)
    t = t.sort_values(["vehicle_id", "time"], kind="stable").reset_index(drop=True)
    times = np.unique(np.round(t["time"].to_numpy(float), 6))
    period = float(np.median(np.diff(times))) if len(times) > 1 else STEP_S
    return Motion(t, period)


def _neighbours(snap: pd.DataFrame, vid: str, lane: int, s: float, length: float) -> dict:
    """Leader / follower in `lane` of a vehicle at s (snap: every vehicle at one time)."""
    others = snap[(snap["lane"] == lane) & (snap["vehicle_id"] != vid)]
    ahead = others[others["s"] > s]
    behind = others[others["s"] < s]
    out = {"lead_dv": np.nan, "lead_gap": np.nan, "lag_dv": np.nan, "lag_gap": np.nan}
    if len(ahead):
        a = ahead.loc[ahead["s"].idxmin()]
        gap = (a["s"] - a["length"] / 2) - (s + length / 2)
        if gap <= GAP_RANGE_M:
            out["lead_gap"], out["lead_dv"] = float(gap), float(a["speed"])
    if len(behind):
        b = behind.loc[behind["s"].idxmax()]
        gap = (s - length / 2) - (b["s"] + b["length"] / 2)
        if gap <= GAP_RANGE_M:
            out["lag_gap"], out["lag_dv"] = float(gap), float(b["speed"])
    return out


def lane_change_kinematics(motion: Motion, events: pd.DataFrame) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """Per-event scalars (event_id, vehicle_id, direction, SCALARS) and the (n_events, len(TAUS))
    lateral offset and lateral speed profiles of the main-lane changes of one run."""
    t = motion.table
    ev = events[(events["from_lane"] >= 0) & (events["to_lane"] >= 0)].sort_values(["vehicle_id", "mid_time"])
    if not len(ev):
        return pd.DataFrame(columns=["event_id", "vehicle_id", "direction", *SCALARS]), \
            np.zeros((0, len(TAUS))), np.zeros((0, len(TAUS)))
    tick = np.round(t["time"].to_numpy(float) / motion.period_s).astype(np.int64)
    by_tick = pd.Series(np.arange(len(t))).groupby(tick).indices
    by_vehicle = t.groupby("vehicle_id", sort=False).indices
    time = t["time"].to_numpy(float)
    d_all = t["d"].to_numpy(float)
    rows, offsets, speeds = [], [], []
    previous_mid: dict[str, float] = {}
    for e in ev.itertuples(index=False):
        vid = str(e.vehicle_id)
        idx = by_vehicle.get(vid)
        row = {"event_id": int(e.event_id), "vehicle_id": vid, "direction": int(e.direction),
               **{k: np.nan for k in SCALARS}}
        off = np.full(len(TAUS), np.nan)
        vel = np.full(len(TAUS), np.nan)
        if idx is not None:
            tv, dv = time[idx], d_all[idx]
            k_mid = int(np.argmin(np.abs(tv - e.mid_time)))
            v_lat = e.direction * lateral_speed(dv, motion.period_s)
            pos = np.round((tv - tv[k_mid]) / STEP_S).astype(np.int64) + int(round(TAU_BEFORE_S / STEP_S))
            inside = (pos >= 0) & (pos < len(TAUS))
            off[pos[inside]] = e.direction * (dv[inside] - dv[k_mid])
            vel[pos[inside]] = v_lat[inside]
            # duration: settled before and after the crossing (the import's rule)
            lo = np.flatnonzero(inside)[0] if inside.any() else k_mid
            hi = np.flatnonzero(inside)[-1] if inside.any() else k_mid
            start = end = np.nan
            for j in range(k_mid - 1, lo - 1, -1):
                if np.isnan(v_lat[j]):
                    break
                if v_lat[j] <= LATERAL_SETTLED_MPS:
                    start = tv[j]
                    break
            for j in range(k_mid, hi + 1):
                if np.isnan(v_lat[j]):
                    break
                if v_lat[j] <= LATERAL_SETTLED_MPS:
                    end = tv[j]
                    break
            row["duration_s"] = end - start
            window = v_lat[lo:hi + 1]
            if np.isfinite(window).any():
                row["lateral_speed_peak_mps"] = float(np.nanmax(window))
            # neighbours: before the decision and at the last sample in the old lane
            own = t.iloc[idx]
            for when, keys in ((e.mid_time - DECISION_TAU_S, "decision"), (tv[k_mid] - motion.period_s, "gap")):
                k = int(np.argmin(np.abs(tv - when)))
                if abs(tv[k] - when) > motion.period_s / 2 + 1e-6:
                    continue
                me = own.iloc[k]
                snap = t.iloc[by_tick[int(round(tv[k] / motion.period_s))]]
                target = _neighbours(snap, vid, int(e.to_lane), float(me["s"]), float(me["length"]))
                if keys == "decision":
                    lead = _neighbours(snap, vid, int(me["lane"]), float(me["s"]), float(me["length"]))
                    row["dv_leader_mps"] = lead["lead_dv"] - me["speed"]
                    row["dv_target_lead_mps"] = target["lead_dv"] - me["speed"]
                    row["dv_target_lag_mps"] = target["lag_dv"] - me["speed"]
                else:
                    row["gap_target_lead_m"] = target["lead_gap"]
                    row["gap_target_lag_m"] = target["lag_gap"]
        if vid in previous_mid:
            row["time_since_last_change_s"] = float(e.mid_time - previous_mid[vid])
        previous_mid[vid] = float(e.mid_time)
        rows.append(row)
        offsets.append(off)
        speeds.append(vel)
    return pd.DataFrame(rows), np.array(offsets), np.array(speeds)


def dataset_kinematics(root: Path, label: str) -> tuple[pd.DataFrame, np.ndarray, np.ndarray]:
    """Every seed of a dataset folder: the per-event table (with dataset / seed columns; its
    attrs["vehicle_hours"]: the samples' vehicle-hours on main lanes) and profiles."""
    info = load_dataset(root)
    frames, offs, vels = [], [], []
    hours = 0.0
    for seed in info.seeds("all"):
        folder = info.run_folder(seed)
        events = pd.read_parquet(folder / "lane_changes.parquet")
        motion = _run_motion(folder)
        hours += float((motion.table["lane"] >= 0).sum()) * motion.period_s / 3600.0
        table, off, vel = lane_change_kinematics(motion, events)
        frames.append(table.assign(dataset=label, seed=seed))
        offs.append(off)
        vels.append(vel)
    events = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if not len(events):
        raise DatasetError(f"{root}: no lane change between main lanes in any seed; nothing to compare")
    events.attrs["vehicle_hours"] = hours
    return events, np.concatenate(offs), np.concatenate(vels)


def profile_summary(label: str, offsets: np.ndarray, speeds: np.ndarray) -> pd.DataFrame:
    rows = []
    for name, values in (("lateral_offset_m", offsets), ("lateral_speed_mps", speeds)):
        for j, tau in enumerate(TAUS):
            col = values[:, j]
            col = col[np.isfinite(col)]
            q = np.percentile(col, [10, 25, 50, 75, 90]) if len(col) else [np.nan] * 5
            rows.append({"dataset": label, "quantity": name, "tau_s": float(tau), "n": int(len(col)),
                         "mean": float(col.mean()) if len(col) else np.nan, "p10": q[0], "p25": q[1], "p50": q[2],
                         "p75": q[3], "p90": q[4]})
    return pd.DataFrame(rows)


def _profile_columns(offsets: np.ndarray, speeds: np.ndarray) -> dict[str, np.ndarray]:
    out = {}
    for tau in PROFILE_KS_TAUS:
        j = int(np.argmin(np.abs(TAUS - tau)))
        out[f"lateral_offset_at_{tau:+g}s_m"] = offsets[:, j]
        out[f"lateral_speed_at_{tau:+g}s_mps"] = speeds[:, j]
    return out


def ks_table(sim: tuple, real: tuple, sim_label: str, real_label: str) -> pd.DataFrame:
    """KS distance sim vs real per quantity (finite values of each side)."""
    from scipy.stats import ks_2samp

    (sev, soff, svel), (rev, roff, rvel) = sim, real
    columns_s = {q: sev[q].to_numpy(float) for q in SCALARS} | _profile_columns(soff, svel)
    columns_r = {q: rev[q].to_numpy(float) for q in SCALARS} | _profile_columns(roff, rvel)
    rows = []
    for q in columns_s:
        a, b = columns_s[q], columns_r[q]
        a, b = a[np.isfinite(a)], b[np.isfinite(b)]
        row = {"quantity": q, "sim": sim_label, "real": real_label, "n_sim": len(a), "n_real": len(b),
               "median_sim": float(np.median(a)) if len(a) else np.nan,
               "median_real": float(np.median(b)) if len(b) else np.nan, "ks": np.nan, "p_value": np.nan}
        if len(a) and len(b):
            res = ks_2samp(a, b)
            row["ks"], row["p_value"] = float(res.statistic), float(res.pvalue)
        rows.append(row)
    return pd.DataFrame(rows)


def _markdown(ks: pd.DataFrame, label: str, rates: dict) -> str:
    lines = [f"# Lane changes: simulated vs recorded ({label})", "",
             "Main-lane changes per vehicle-hour on the main lanes: "
             + ", ".join(f"{k} {v['lane_changes']} in {v['vehicle_hours']:.1f} veh-h = {v['per_vehicle_hour']:.1f}"
                         for k, v in rates.items()), "",
             "KS = two-sample Kolmogorov-Smirnov distance (0: same distribution, 1: disjoint).", "",
             "| quantity | real | n sim | n real | median sim | median real | KS | p |",
             "|---|---|---|---|---|---|---|---|"]
    for r in ks.itertuples(index=False):
        lines.append(f"| {r.quantity} | {r.real} | {r.n_sim} | {r.n_real} | {r.median_sim:.3g} | {r.median_real:.3g} "
                     f"| {r.ks:.3f} | {r.p_value:.2g} |")
    return "\n".join(lines) + "\n"


def _figures(out: Path, profiles: pd.DataFrame, events: pd.DataFrame, label: str) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, q, unit in zip(axes, ("lateral_offset_m", "lateral_speed_mps"), ("m", "m/s")):
        for ds, g in profiles[profiles["quantity"] == q].groupby("dataset", sort=False):
            line, = ax.plot(g["tau_s"], g["p50"], label=f"{ds} (median)")
            ax.fill_between(g["tau_s"], g["p25"], g["p75"], color=line.get_color(), alpha=0.2)
        ax.axvline(0.0, color="k", lw=0.5)
        ax.set_xlabel("time from the lane crossing, s")
        ax.set_ylabel(f"{q.rsplit('_', 1)[0].replace('_', ' ')} towards the new lane, {unit}")
        ax.legend(fontsize=8)
    fig.suptitle(f"Lateral motion around the crossing (band: 25-75 %); {label}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "profiles.png", dpi=110)
    plt.close(fig)
    names.append("profiles.png")
    fig, axes = plt.subplots(2, 4, figsize=(14, 6))
    for ax, q in zip(axes.flat, SCALARS):
        for ds, g in events.groupby("dataset", sort=False):
            v = np.sort(g[q].to_numpy(float))
            v = v[np.isfinite(v)]
            if len(v):
                ax.step(v, np.arange(1, len(v) + 1) / len(v), where="post", label=f"{ds} (n={len(v)})")
        ax.set_title(q, fontsize=9)
        ax.legend(fontsize=7)
    fig.suptitle(f"Distributions (ECDF) per lane change; {label}", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "quantities.png", dpi=110)
    plt.close(fig)
    names.append("quantities.png")
    return names


def compare_lane_changes(sim_root: Path, real_roots: list[Path], out: Path, label: str = "",
                         names: list[str] | None = None) -> dict:
    """Write DIR with events.parquet, profiles.parquet, ks.parquet / ks.csv / ks.md, profiles.png,
    quantities.png and compare.json (atomic: the folder appears when complete)."""
    from vcfusion.runio import atomic_folder, write_json, write_table

    out = Path(out)
    if out.exists():
        raise DatasetError(f"--out: {out} already exists; the comparison writes a new folder")
    labels = names or [Path(sim_root).name, *[Path(r).name for r in real_roots]]
    if len(labels) != 1 + len(real_roots) or len(set(labels)) != len(labels):
        raise DatasetError(f"--names: expected {1 + len(real_roots)} distinct names (SIM then each REAL), got {labels}")
    sim = dataset_kinematics(Path(sim_root), labels[0])
    reals = [dataset_kinematics(Path(r), name) for r, name in zip(real_roots, labels[1:])]
    ks = pd.concat([ks_table(sim, real, labels[0], name) for real, name in zip(reals, labels[1:])], ignore_index=True)
    events = pd.concat([sim[0], *[r[0] for r in reals]], ignore_index=True)
    profiles = pd.concat([profile_summary(n, off, vel) for n, (_, off, vel) in zip(labels, [sim, *reals])],
                         ignore_index=True)
    rates = {}
    for n, (ev, _, _) in zip(labels, [sim, *reals]):
        h = ev.attrs.get("vehicle_hours", float("nan"))
        rates[n] = {"lane_changes": int(len(ev)), "vehicle_hours": h, "per_vehicle_hour": len(ev) / h if h else None}
    with atomic_folder(out, "comparison folder") as tmp:
        write_table(tmp / "events.parquet", events)
        write_table(tmp / "profiles.parquet", profiles)
        write_table(tmp / "ks.parquet", ks)
        ks.to_csv(tmp / "ks.csv", index=False)
        (tmp / "ks.md").write_text(_markdown(ks, label or "unlabelled", rates))
        figures = _figures(tmp, profiles, events, label or "unlabelled")
        meta = {"sim": str(sim_root), "real": [str(r) for r in real_roots], "names": labels, "label": label,
                "lane_changes": {n: int((events["dataset"] == n).sum()) for n in labels}, "rates": rates,
                "decision_tau_s": DECISION_TAU_S, "gap_range_m": GAP_RANGE_M, "figures": figures,
                "tau_s": [-TAU_BEFORE_S, TAU_AFTER_S]}
        write_json(tmp / "compare.json", meta)
    return {"ks": ks, "meta": meta}
