"""Safety, comfort and emission metrics of every vehicle of a run (`metrics.parquet`).

Inputs are the run's tables, so a run folder can be re-evaluated later (`vcfusion metrics`):
the trajectories (every vehicle every `simulation.trajectory_period_s`), the ego's own log
(every SUMO step), vehicles, lane_changes, collisions and SUMO's emission totals
(`sumo_emissions`, see sumo_emissions.py). Thresholds and definitions: the scenario's
`metrics:` block (MetricsConfig).

Definitions (per vehicle; dt = the trajectory period, the ego's kinematics use its own log):
- **Leader** at a sample: the nearest vehicle ahead in the same lane (`lane`, ordered by `s`
  at the same time) within `leader_range_m`, bumper to bumper. The search only needs the
  (lane, s) columns: exact on the straight road the project supports, and it carries over to a
  road frame of any network.
- **gap** = leader's rear - own front (`s` is the footprint centre, so +- half the lengths);
  **closing** = own speed - leader's speed.
- **TTC** = gap / closing where closing > 0 and gap > 0 (constant-velocity TTC, as SUMO's SSM
  device for a following situation), else undefined. Minimum over the trip; `ttc_samples`.
- **TET** = dt x samples with TTC < threshold; **TIT** = dt x sum(threshold - TTC) over them
  (Minderhoud & Bovy 2001).
- **DRAC** = closing^2 / (2 gap) where TTC is defined (the deceleration that avoids the crash,
  as SSM's DRAC for following); maximum over the trip.
- **Time headway** = gap / own speed (speed > 0; SSM's TGAP): minimum over the trip.
- **Conflicts**: episodes of consecutive samples with TTC < threshold to the same leader (a new
  leader while below the threshold is a new conflict). Each is a row of `conflicts.parquet`.
- **Kinematics** (safety.kinematics): travel time, distance (s of the last minus the first
  sample), mean speed, mean |a| (a = speed difference per sample), maximum deceleration,
  maximum |jerk| after the `jerk_window_s` moving average.
- **MOVESTAR** on whole-second means of the speed (movestar.trip_emissions) for the types that
  `metrics.movestar` maps to a MOVESTAR source type; per km on MOVESTAR's own distance (the sum
  of its 1 Hz speeds), as movestar() reports it.
- **SUMO emissions** (every vehicle, its vType's HBEFA/PHEMlight class): totals from the run's
  sumo_emissions table, per km on the distance above.

Streaming: the trajectories are read one record batch (<= one Parquet row group) at a time;
a vehicle's samples are kept only while it is on the road and turned into its row once it has
been absent for more than one sample (`_GONE_AFTER_PERIODS`), so memory follows the vehicles on
the road, not the run length.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from vcfusion.metrics.movestar import (KM_PER_MILE, METERS_PER_MILE, OUTPUT_KEYS, check_speeds,
                                      movestar_trips, resample_to_1hz, samples_per_second)
from vcfusion.metrics.safety import kinematics
from vcfusion.records import EGO_ID

BATCH_ROWS = 65_536
# A vehicle missing from the trajectories for more than this many periods has left the road (every
# vehicle on the road has a row every period). A SUMO teleport can bring it back: its later samples
# are a second stretch, combined into the same row, and no acceleration, jerk or conflict spans
# the absence (as one period apart, a 5 s absence read as a 100 m/s^2 deceleration).
_GONE_AFTER_PERIODS = 1.5
TRAJECTORY_COLUMNS = ["time", "vehicle_id", "lane", "s", "speed"]
# Distribution bins (histograms in metric_histograms.parquet; percentiles read from them).
TTC_EDGES = np.round(np.linspace(0.0, 60.0, 1201), 6)  # 0.05 s
HEADWAY_EDGES = np.round(np.linspace(0.0, 10.0, 501), 6)  # 0.02 s
# metric_histograms.parquet's bins (the same every run; each run adds its counts)
_HISTOGRAM_BINS = pa.table({
    "measure": ["ttc_s"] * len(TTC_EDGES) + ["time_headway_s"] * len(HEADWAY_EDGES),
    "bin_low": np.concatenate((TTC_EDGES, HEADWAY_EDGES)),
    "bin_high": np.concatenate((TTC_EDGES[1:], [np.inf], HEADWAY_EDGES[1:], [np.inf]))})
# movestar() output -> metrics column movestar_<name> (per km: movestar_<name>_per_km)
MOVESTAR_KEYS = {"CO": "co_g", "HC": "hc_g", "NOx": "nox_g", "PM2.5": "pm25_g", "CO2": "co2_g",
                 "Energy": "energy_kj", "Fuel": "fuel_g"}
SUMO_KEYS = ("co", "co2", "hc", "nox", "pmx", "fuel")


CONFLICT_SCHEMA = {"vehicle_id": pa.string(), "leader_id": pa.string(), "start_time": pa.float64(),
                   "end_time": pa.float64(), "duration_s": pa.float64(), "min_ttc_s": pa.float64(),
                   "s_start": pa.float64(), "lane": pa.int64()}


@dataclass
class RunMetrics:
    """The tables are Arrow (built from arrays without pandas: they are made at the end of every run)."""

    vehicles: pa.Table  # metrics.parquet: one row per vehicle
    conflicts: pa.Table  # conflicts.parquet: one row per conflict episode
    histograms: pa.Table  # metric_histograms.parquet: TTC and headway counts (counted vehicles)
    columns: dict[str, np.ndarray]  # the vehicles' columns as arrays (what the summary reads)
    ttc_counts: np.ndarray  # the same counts, per TTC_EDGES bin (the last: beyond the last edge)
    headway_counts: np.ndarray  # per HEADWAY_EDGES bin


def movestar_type(cfg, vtype: str, vclass: str) -> int | None:
    """The MOVESTAR source type of a vehicle type (None: SUMO's model only). A vehicle whose
    speed limit the scenario sets runs on a copy of its type named 'TYPE@VEHICLE' (SUMO)."""
    return cfg.movestar.get(vtype.split("@")[0], cfg.movestar.get(vclass))


def sumo_model_rates(cfg, vtype: str, vclass: str) -> bool:
    """Whether SUMO's emission model rates vehicles of this type (metrics.sumo_emissions)."""
    if cfg.sumo_emissions == "others":
        return movestar_type(cfg, vtype, vclass) is None
    return cfg.sumo_emissions == "all"


def ego_movestar_type(scenario, vehicles: pd.DataFrame) -> int:
    row = vehicles.set_index("vehicle_id").loc[EGO_ID]
    found = movestar_type(scenario.metrics, row["vtype"], row["vclass"])
    if found is None:
        raise ValueError(f"metrics.movestar: expected a MOVESTAR type (1 or 2) for the ego's vType {row['vtype']!r} "
                         f"or vClass {row['vclass']!r}, got none")
    return found


def _batches(source: pa.Table | Path, columns: list[str]):
    if isinstance(source, pa.Table):
        yield from source.select(columns).to_batches(max_chunksize=BATCH_ROWS)
    else:
        yield from pq.ParquetFile(source).iter_batches(batch_size=BATCH_ROWS, columns=columns)


def _time_slices(source, columns: list[str]):
    """Record batches cut at time boundaries: all vehicles of one sample time are in one piece."""
    carry = None
    for batch in _batches(source, columns):
        table = pa.Table.from_batches([batch]) if carry is None else pa.concat_tables([carry, pa.Table.from_batches([batch])])
        if table.num_rows == 0:
            continue
        t = table.column("time").to_numpy()
        cut = int(np.searchsorted(t, t[-1], side="left"))  # rows of the last time may go on in the next batch
        if cut:
            yield table.slice(0, cut)
        carry = table.slice(cut)
    if carry is not None and carry.num_rows:
        yield carry


def leaders(time: np.ndarray, lane: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Row index of each row's leader (nearest ahead by s in the same lane at the same time), -1 if
    none; the rows in time order (as a run's tables are). A vehicle off the route's lanes (lane -1:
    on a ramp before it joins, on an exit after it leaves) has no leader and leads no one: its
    lane is unknown, and every road off the route shares that -1."""
    if len(time) == 0:
        return np.zeros(0, dtype=np.int64)
    # one integer key per (time, lane): two sort keys instead of three
    group = np.cumsum(np.concatenate(([0], time[1:] != time[:-1]))) * 65536 + lane.astype(np.int64)
    order = np.lexsort((s, group))
    follower, ahead = order[:-1], order[1:]
    same = (group[ahead] == group[follower]) & (lane[follower] >= 0)
    found = np.full(len(time), -1, dtype=np.int64)
    found[follower[same]] = ahead[same]
    return found


class _Buffers:
    """Per-vehicle column chunks of the vehicles on the road."""

    COLUMNS = ("time", "s", "speed", "lane", "gap", "ttc", "drac", "headway", "leader")

    def __init__(self):
        self.chunks: dict[int, dict[str, list[np.ndarray]]] = {}
        self.last_time: dict[int, float] = {}

    def add(self, code: int, columns: dict[str, np.ndarray]) -> None:
        mine = self.chunks.setdefault(code, {c: [] for c in self.COLUMNS})
        for c in self.COLUMNS:
            mine[c].append(columns[c])
        self.last_time[code] = float(columns["time"][-1])

    def pop(self, code: int) -> dict[str, np.ndarray]:
        mine = self.chunks.pop(code)
        self.last_time.pop(code)
        return {c: np.concatenate(v) for c, v in mine.items()}


def compute_run_metrics(cfg, trajectory_period_s: float, step_s: float, trajectories: pa.Table | Path,
                        vehicles: pd.DataFrame, ego: pa.Table | None, lane_changes: pd.DataFrame | None,
                        sumo_emissions: pd.DataFrame | pa.Table | None) -> RunMetrics:
    """The per-vehicle table, the conflict episodes and the distributions of one run (streamed)."""
    dt = trajectory_period_s
    gone_after_s = _GONE_AFTER_PERIODS * dt
    info = _VehicleFacts(vehicles)
    codes: dict[str, int] = {}
    ids: list[str] = []
    lengths: list[float] = []
    buffers = _Buffers()
    stretches: list[tuple[np.ndarray, dict[str, np.ndarray]]] = []  # (vehicle codes, their figures)
    conflicts: list[dict] = []
    excluded = {vid for vid, group in info.group.items() if group in set(cfg.exclude_groups)}
    ttc_counts = np.zeros(len(TTC_EDGES), dtype=np.int64)  # last bin: >= the last edge
    headway_counts = np.zeros(len(HEADWAY_EDGES), dtype=np.int64)

    def finish(done: list[int]) -> None:
        """Turn the buffered stretches of these vehicles into their figures, all at once."""
        if not done:
            return
        series = [buffers.pop(c) for c in done]
        vids = [ids[c] for c in done]
        figures, episodes, counted_rows = _stretches(series, dt, cfg, [movestar_type(cfg, *info.types(v)) for v in vids],
                                                     [v not in excluded for v in vids])
        stretches.append((np.array(done, dtype=np.int64), figures))
        for e in episodes:
            conflicts.append({"vehicle_id": vids[e.pop("stretch")], "leader_id": ids[e.pop("leader")], **e})
        _count(counted_rows["ttc"], TTC_EDGES, ttc_counts)
        _count(counted_rows["headway"], HEADWAY_EDGES, headway_counts)

    for piece in _time_slices(trajectories, TRAJECTORY_COLUMNS):
        encoded = pc.dictionary_encode(piece.column("vehicle_id").combine_chunks())
        for vid in encoded.dictionary.to_pylist():
            if vid not in codes:
                codes[vid] = len(ids)
                ids.append(vid)
                lengths.append(info.length.get(vid, math.nan))
        local = np.array([codes[v] for v in encoded.dictionary.to_pylist()], dtype=np.int64)
        code = local[encoded.indices.to_numpy(zero_copy_only=False)]
        time = piece.column("time").to_numpy()
        lane = piece.column("lane").to_numpy()
        s = piece.column("s").to_numpy()
        speed = piece.column("speed").to_numpy()
        columns = follow_measures(time, lane, s, speed, code, np.asarray(lengths), cfg.leader_range_m)
        # the piece's rows by vehicle (time order kept within each) in one gather; a vehicle's rows
        # are then a slice, cut where it was absent for long (a teleport: a new stretch begins)
        order = np.argsort(code, kind="stable")
        by_vehicle = {k: v[order] for k, v in columns.items()}
        sorted_code, sorted_time = code[order], by_vehicle["time"]
        cut = (sorted_code[1:] != sorted_code[:-1]) | (np.diff(sorted_time) > gone_after_s)
        bounds = np.flatnonzero(cut) + 1
        for a, b in zip(np.concatenate(([0], bounds)).tolist(), np.concatenate((bounds, [len(order)])).tolist()):
            c = int(sorted_code[a])
            if c in buffers.chunks and buffers.last_time[c] < sorted_time[a] - gone_after_s:
                finish([c])  # back after a long absence: the stretch so far is finished
            # copies: a view would keep the whole batch alive as long as this vehicle is on the road
            buffers.add(c, {k: v[a:b].copy() for k, v in by_vehicle.items()})
        now = float(time[-1])
        finish([c for c, last in buffers.last_time.items() if last < now - gone_after_s])
    finish(list(buffers.chunks))

    columns = _per_vehicle(cfg, stretches, ids, info)
    vids = columns["vehicle_id"].tolist()
    if ego is not None and ego.num_rows and EGO_ID in vids:
        i = vids.index(EGO_ID)
        for k, value in _ego_from_own_log(cfg, ego, step_s, info).items():
            columns[k][i] = value
    columns["counted"] = np.array([v not in excluded for v in vids], dtype=bool)
    columns["lane_changes"] = _lane_changes(vids, lane_changes)
    columns.update(_sumo_columns(vids, columns["distance_m"], sumo_emissions))
    # per km as movestar() computes it (per mile on its own distance, then per km)
    td = np.where(columns["movestar_distance_m"] > 0, columns["movestar_distance_m"], np.nan)
    for k in MOVESTAR_KEYS.values():
        columns[f"movestar_{k}_per_km"] = columns[f"movestar_{k}"] * METERS_PER_MILE / td / KM_PER_MILE
    conflicts.sort(key=lambda c: (c["start_time"], c["vehicle_id"]))
    conflict_table = pa.table({name: pa.array([c[name] for c in conflicts], type=kind)
                               for name, kind in CONFLICT_SCHEMA.items()})
    histograms = _HISTOGRAM_BINS.append_column("count", pa.array(np.concatenate((ttc_counts, headway_counts))))
    return RunMetrics(pa.table(columns), conflict_table, histograms, columns, ttc_counts, headway_counts)


def follow_measures(time, lane, s, speed, code, lengths, leader_range_m) -> dict[str, np.ndarray]:
    """Per row: gap, TTC, DRAC and time headway to its leader, and the leader's code (-1: none)."""
    lead = leaders(time, lane, s)
    has = lead >= 0
    half = lengths[code] / 2.0
    gap = np.full(len(time), np.nan)
    gap[has] = (s[lead[has]] - half[lead[has]]) - (s[has] + half[has])
    has &= gap <= leader_range_m  # NaN gaps (unknown length) drop out here too
    gap[~has] = np.nan
    closing = np.where(has, speed - np.where(has, speed[lead], 0.0), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        defined = has & (closing > 0) & (gap > 0)
        ttc = np.where(defined, gap / closing, np.nan)
        drac = np.where(defined, closing * closing / (2.0 * gap), np.nan)
        headway = np.where(has & (speed > 0) & (gap > 0), gap / speed, np.nan)
    leader = np.where(has, code[np.where(has, lead, 0)], -1)
    return {"time": time, "s": s, "speed": speed, "lane": lane, "gap": gap, "ttc": ttc, "drac": drac,
            "headway": headway, "leader": leader}


def conflict_episodes(ttc: np.ndarray, leader: np.ndarray, threshold_s: float) -> list[tuple[int, int]]:
    """[start, stop) sample ranges of TTC < threshold to one and the same leader."""
    below = np.isfinite(ttc) & (ttc < threshold_s)
    if not below.any():
        return []
    continues = np.zeros(len(ttc), dtype=bool)
    continues[1:] = below[1:] & below[:-1] & (leader[1:] == leader[:-1])
    starts = np.flatnonzero(below & ~continues)
    ends = np.flatnonzero(below & ~np.concatenate((continues[1:], [False]))) + 1
    return list(zip(starts.tolist(), ends.tolist()))


def _stretches(series: list[dict[str, np.ndarray]], dt: float, cfg, movestar_types: list[int | None],
               counted: list[bool]) -> tuple[dict[str, np.ndarray], list[dict], dict[str, np.ndarray]]:
    """Additive and extreme figures of many vehicles' continuous stretches of samples at once (per
    vehicle the definitions of safety.kinematics, safety.exposure, conflict_episodes and
    movestar.trip_emissions, on the stretches concatenated), their conflict episodes, and the TTC
    and headway samples of the counted vehicles (for the distributions)."""
    n = np.array([len(x["time"]) for x in series])
    m, total = len(series), int(n.sum())
    starts = np.concatenate(([0], np.cumsum(n)[:-1]))
    ends = starts + n - 1
    col = {k: np.concatenate([x[k] for x in series]) for k in _Buffers.COLUMNS}
    t, v, ttc = col["time"], col["speed"], col["ttc"]
    seg = np.repeat(np.arange(m), n)
    # kinematics: a = forward difference (sample i to i + 1 of the same stretch)
    a = np.diff(v) / dt
    a_ok = seg[:-1] == seg[1:]
    a_seg = seg[:-1][a_ok]
    # distance travelled: the speed integrated between samples (trapezoids), not the difference of
    # s, which is the position projected on the scenario's route: a vehicle that leaves it by an
    # exit or joins it from a ramp was off it for part of its trip (26-30 m short over a 1.4 km trip)
    travelled = np.bincount(a_seg, weights=0.5 * (v[:-1] + v[1:])[a_ok] * dt, minlength=m)
    abs_accel_sum = np.bincount(a_seg, weights=np.abs(a[a_ok]), minlength=m)
    min_a = np.full(m, np.inf)
    np.minimum.at(min_a, a_seg, a[a_ok])
    accel_samples = np.maximum(n - 1, 0)
    max_decel = np.where(accel_samples > 0, np.maximum(0.0, -min_a), np.nan)
    # jerk after the moving average over w accelerations: valid where its w + 1 accelerations
    # (w + 2 samples) are of one stretch
    w = max(1, int(round(cfg.jerk_window_s / dt)))
    smooth = sum(a[k:len(a) - w + 1 + k] for k in range(w)) / w if w > 1 else a
    jerk = np.diff(smooth) / dt
    j_ok = seg[:len(jerk)] == seg[w + 1:w + 1 + len(jerk)]
    max_jerk = np.full(m, -np.inf)
    np.maximum.at(max_jerk, seg[:len(jerk)][j_ok], np.abs(jerk[j_ok]))
    max_jerk[np.isinf(max_jerk)] = np.nan
    # safety against the leader
    threshold = cfg.ttc_threshold_s
    below = np.isfinite(ttc) & (ttc < threshold)
    episodes, per_stretch = _episodes(col, seg, below, dt)
    figures = {
        "first_time": t[starts], "samples": n, "travel_time_s": t[ends] - t[starts] + dt,
        "distance_m": travelled, "speed_sum": np.add.reduceat(v, starts),
        "abs_accel_sum": abs_accel_sum, "accel_samples": accel_samples, "max_decel_mps2": max_decel,
        "max_abs_jerk_mps3": max_jerk,
        "ttc_samples": np.bincount(seg, weights=np.isfinite(ttc), minlength=m).astype(np.int64),
        "min_ttc_s": np.fmin.reduceat(ttc, starts),
        "tet_s": np.bincount(seg, weights=below, minlength=m) * dt,
        "tit_s2": np.bincount(seg, weights=np.where(below, threshold - ttc, 0.0), minlength=m) * dt,
        "max_drac_mps2": np.fmax.reduceat(col["drac"], starts),
        "min_time_headway_s": np.fmin.reduceat(col["headway"], starts),
        "min_gap_m": np.fmin.reduceat(col["gap"], starts), "conflicts": per_stretch,
        **_movestar_stretches(t, v, seg, starts, ends, dt, movestar_types)}
    keep = np.repeat(np.asarray(counted, dtype=bool), n)
    return figures, episodes, {"ttc": ttc[keep], "headway": col["headway"][keep]}


def _episodes(col: dict[str, np.ndarray], seg: np.ndarray, below: np.ndarray, dt: float) -> tuple[list[dict], np.ndarray]:
    """Conflict episodes (conflict_episodes, per stretch) and their number per stretch."""
    ttc, leader = col["ttc"], col["leader"]
    continues = np.zeros(len(ttc), dtype=bool)
    continues[1:] = below[1:] & below[:-1] & (leader[1:] == leader[:-1]) & (seg[1:] == seg[:-1])
    first = np.flatnonzero(below & ~continues)
    stop = np.flatnonzero(below & ~np.concatenate((continues[1:], [False]))) + 1
    lowest = np.minimum.reduceat(np.concatenate((ttc, [np.inf])), np.column_stack((first, stop)).ravel())[::2] if len(first) else []
    episodes = [{"stretch": int(seg[a]), "leader": int(leader[a]), "start_time": float(col["time"][a]),
                 "end_time": float(col["time"][b - 1] + dt), "duration_s": float((b - a) * dt),
                 "min_ttc_s": float(low), "s_start": float(col["s"][a]), "lane": int(col["lane"][a])}
                for a, b, low in zip(first, stop, lowest)]
    return episodes, np.bincount(seg[first], minlength=seg[-1] + 1 if len(seg) else 0).astype(np.int64)


def _movestar_stretches(t, v, seg, starts, ends, dt, movestar_types: list[int | None]) -> dict[str, np.ndarray]:
    """MOVESTAR totals of the stretches that have a type: movestar.trip_emissions on each (whole-
    second means of the speed from its first sample, a partial last second dropped), all at once."""
    m = len(starts)
    out = {f"movestar_{k}": np.full(m, np.nan) for k in MOVESTAR_KEYS.values()}
    out["movestar_distance_m"] = np.full(m, np.nan)
    out["movestar_seconds"] = np.zeros(m, dtype=np.int64)
    types = np.array([x or 0 for x in movestar_types])
    sec = np.floor(t - t[starts][seg] + 1e-6).astype(np.int64)  # as resample_to_1hz
    nsec = sec[ends] + 1
    bucket = np.concatenate(([0], np.cumsum(nsec)[:-1]))[seg] + sec
    counts = np.bincount(bucket, minlength=int(nsec.sum()))
    sums = np.bincount(bucket, weights=v, minlength=int(nsec.sum()))
    owner = np.repeat(np.arange(m), nsec)
    keep = (counts >= samples_per_second(dt)) & (types[owner] > 0)
    if not keep.any():
        return out
    trips = owner[keep]
    first = np.flatnonzero(np.concatenate(([True], trips[1:] != trips[:-1])))
    rated = trips[first]
    totals, distance = movestar_trips(sums[keep] / counts[keep], first, types[rated])
    by_key = dict(zip(OUTPUT_KEYS, totals.T))
    by_key["PM2.5"] = by_key.pop("PM2.5_Ele") + by_key.pop("PM2.5_Org")
    for key, name in MOVESTAR_KEYS.items():
        out[f"movestar_{name}"][rated] = by_key[key]
    out["movestar_distance_m"][rated] = distance
    out["movestar_seconds"][rated] = np.diff(np.concatenate((first, [len(trips)])))
    return out


def _movestar(time: np.ndarray, speed: np.ndarray, vehicle_type: int | None) -> dict:
    """MOVESTAR of one vehicle's log (the ego's, every SUMO step)."""
    out = {f"movestar_{k}": math.nan for k in MOVESTAR_KEYS.values()}
    out["movestar_distance_m"], out["movestar_seconds"] = math.nan, 0
    if vehicle_type is None:
        return out
    try:
        v = check_speeds(resample_to_1hz(time, speed))
    except ValueError:  # less than one whole second on the road: no 1 Hz sample to rate
        return out
    # movestar()'s totals without its per-second opmodes and VSP lists (trip_emissions = movestar of these)
    sums, distance = movestar_trips(v, np.array([0]), np.array([vehicle_type]))
    totals = {name: float(x) for name, x in zip(OUTPUT_KEYS, sums[0])}
    totals["PM2.5"] = totals.pop("PM2.5_Ele") + totals.pop("PM2.5_Org")
    out.update({f"movestar_{MOVESTAR_KEYS[k]}": float(v) for k, v in totals.items()})
    out["movestar_distance_m"], out["movestar_seconds"] = float(distance[0]), int(v.size)
    return out


class _VehicleFacts:
    """vehicles.parquet as plain dicts by vehicle id."""

    def __init__(self, vehicles: pd.DataFrame):
        ids = vehicles["vehicle_id"].tolist()
        self.vtype = {v: str(x) for v, x in zip(ids, vehicles["vtype"].tolist())}
        self.vclass = {v: str(x) for v, x in zip(ids, vehicles["vclass"].tolist())}
        self.group = {v: str(x) for v, x in zip(ids, vehicles["group"].tolist())}
        self.length = {v: float(x) for v, x in zip(ids, vehicles["length"].tolist())}

    def types(self, vid: str) -> tuple[str, str]:
        return self.vtype.get(vid, ""), self.vclass.get(vid, "")


# how the figures of a vehicle's stretches combine (a vehicle back after a SUMO teleport has two)
_SUMMED = ("samples", "travel_time_s", "distance_m", "speed_sum", "abs_accel_sum", "accel_samples", "ttc_samples",
           "tet_s", "tit_s2", "conflicts", *(f"movestar_{k}" for k in MOVESTAR_KEYS.values()),
           "movestar_distance_m", "movestar_seconds")
_MOVESTAR_TOTALS = (*(f"movestar_{k}" for k in MOVESTAR_KEYS.values()), "movestar_distance_m")
_LOWEST = ("first_time", "min_ttc_s", "min_time_headway_s", "min_gap_m")
_HIGHEST = ("max_decel_mps2", "max_abs_jerk_mps3", "max_drac_mps2")
# the metrics table's columns before those added per vehicle (counted, lane changes, SUMO, per km)
_OWN_COLUMNS = ("vehicle_id", "vtype", "vclass", "group", "first_time_s", "samples", "travel_time_s", "distance_m",
                "mean_speed_mps", "mean_abs_accel_mps2", "max_decel_mps2", "max_abs_jerk_mps3", "ttc_samples",
                "min_ttc_s", "tet_s", "tit_s2", "max_drac_mps2", "min_time_headway_s", "min_gap_m", "conflicts",
                "movestar_type", *(f"movestar_{k}" for k in MOVESTAR_KEYS.values()), "movestar_distance_m",
                "movestar_seconds")


def _per_vehicle(cfg, stretches: list[tuple[np.ndarray, dict[str, np.ndarray]]], ids: list[str],
                 info: _VehicleFacts) -> dict[str, np.ndarray]:
    """One row per vehicle (sorted by id) from the figures of its stretches."""
    if not stretches:
        return {k: np.array([], dtype=object if k in ("vehicle_id", "vtype", "vclass", "group") else float)
                for k in _OWN_COLUMNS}
    codes = np.concatenate([c for c, _ in stretches])
    fig = {k: np.concatenate([f[k] for _, f in stretches]) for k in stretches[0][1]}
    vehicles, row = np.unique(codes, return_inverse=True)
    if len(vehicles) < len(codes):  # several stretches of a vehicle: combine them
        m = len(vehicles)
        # a stretch MOVESTAR did not rate (under a whole second) has NaN totals: it adds nothing
        combined = {k: np.bincount(row, weights=np.nan_to_num(fig[k], nan=0.0), minlength=m).astype(fig[k].dtype)
                    for k in _SUMMED}
        unrated = combined["movestar_seconds"] == 0
        for k in _MOVESTAR_TOTALS:
            combined[k][unrated] = np.nan
        for keys, fn, start in ((_LOWEST, np.fmin, np.inf), (_HIGHEST, np.fmax, -np.inf)):
            for k in keys:
                out = np.full(m, start)
                fn.at(out, row, fig[k])
                combined[k] = np.where(np.isinf(out), np.nan, out)
        fig = combined
    else:
        fig = {k: x[np.argsort(row)] for k, x in fig.items()}
    vids = [ids[c] for c in vehicles]
    order = np.argsort(np.array(vids, dtype=object), kind="stable")
    fig = {k: x[order] for k, x in fig.items()}
    vids = [vids[i] for i in order]
    types = [info.types(v) for v in vids]
    with np.errstate(invalid="ignore", divide="ignore"):
        columns = {"vehicle_id": np.array(vids, dtype=object), "vtype": np.array([x[0] for x in types], dtype=object),
                   "vclass": np.array([x[1] for x in types], dtype=object),
                   "group": np.array([info.group.get(v, "") for v in vids], dtype=object),
                   "first_time_s": fig["first_time"], "samples": fig["samples"].astype(np.int64),
                   "travel_time_s": fig["travel_time_s"], "distance_m": fig["distance_m"],
                   "mean_speed_mps": fig["speed_sum"] / fig["samples"],
                   "mean_abs_accel_mps2": np.where(fig["accel_samples"] > 0,
                                                   fig["abs_accel_sum"] / fig["accel_samples"], np.nan)}
    columns.update({k: fig[k] for k in ("max_decel_mps2", "max_abs_jerk_mps3")})
    columns["ttc_samples"] = fig["ttc_samples"].astype(np.int64)
    columns.update({k: fig[k] for k in ("min_ttc_s", "tet_s", "tit_s2", "max_drac_mps2", "min_time_headway_s",
                                        "min_gap_m")})
    columns["conflicts"] = fig["conflicts"].astype(np.int64)
    columns["movestar_type"] = np.array([movestar_type(cfg, *x) or 0 for x in types], dtype=np.int64)
    columns.update({f"movestar_{k}": fig[f"movestar_{k}"] for k in MOVESTAR_KEYS.values()})
    columns["movestar_distance_m"] = fig["movestar_distance_m"]
    columns["movestar_seconds"] = fig["movestar_seconds"].astype(np.int64)
    return columns


def _ego_from_own_log(cfg, ego: pa.Table, step_s: float, info: _VehicleFacts) -> dict:
    """The ego's travel, comfort and MOVESTAR figures from its own log every SUMO step: the same
    numbers the guidance study reports for the trip (its safety figures stay those of the 0.1 s
    trajectory, like every vehicle's)."""
    t, s, v = (ego.column(c).to_numpy() for c in ("time", "s", "speed"))
    kin = kinematics(t, s, v, step_s, cfg.jerk_window_s)
    return {"samples": len(t), "travel_time_s": kin["trip_time_s"], "distance_m": kin["ego_distance_m"],
            "mean_speed_mps": kin["mean_speed_mps"], "mean_abs_accel_mps2": kin["avg_abs_accel_mps2"],
            "max_decel_mps2": kin["max_decel_mps2"], "max_abs_jerk_mps3": kin["max_abs_jerk_mps3"],
            **_movestar(t, v, movestar_type(cfg, *info.types(EGO_ID)))}


def _lane_changes(vids: list[str], lane_changes: pd.DataFrame | None) -> np.ndarray:
    if lane_changes is None or "vehicle_id" not in lane_changes or not len(lane_changes):
        return np.zeros(len(vids), dtype=np.int64)
    made = Counter(lane_changes["vehicle_id"].tolist())
    return np.array([made.get(v, 0) for v in vids], dtype=np.int64)


def _sumo_columns(vids: list[str], distance_m: np.ndarray, sumo: pd.DataFrame | pa.Table | None) -> dict[str, np.ndarray]:
    """SUMO's emission totals and per km (NaN and no class where the run folder has none)."""
    names = [f"{k}_g" for k in SUMO_KEYS] + ["electricity_wh"]
    found: dict[str, tuple] = {}
    if sumo is not None and len(sumo):
        if isinstance(sumo, pd.DataFrame):
            sumo = pa.Table.from_pandas(sumo[["vehicle_id", "emission_class", *names]], preserve_index=False)
        values = zip(sumo.column("emission_class").to_pylist(), *(sumo.column(c).to_pylist() for c in names))
        found = dict(zip(sumo.column("vehicle_id").to_pylist(), values))
    blank = ("",) + (math.nan,) * len(names)
    got = [found.get(v, blank) for v in vids]
    out = {"sumo_emission_class": np.array([g[0] for g in got], dtype=object)}
    for i, name in enumerate(names, start=1):
        out[f"sumo_{name}"] = np.array([g[i] for g in got], dtype=float)
    km = np.where(distance_m > 0, distance_m, np.nan) / 1000.0
    for k in SUMO_KEYS:
        out[f"sumo_{k}_g_per_km"] = out[f"sumo_{k}_g"] / km
    return out


def _count(values: np.ndarray, edges: np.ndarray, counts: np.ndarray) -> None:
    x = values[np.isfinite(values)]
    if x.size:
        bins = np.minimum(np.searchsorted(edges, x, side="right") - 1, len(edges) - 1)
        counts += np.bincount(bins, minlength=len(edges))


def histogram_percentile(edges: np.ndarray, counts: np.ndarray, q: float) -> float | None:
    """The q-th percentile (0-100) of a distribution counted in bins [edges[i], edges[i+1]) (the
    last bin open: beyond the last edge), linear within its bin (resolution: the bin width);
    None when it lies in the open last bin or there are no samples."""
    counts = np.asarray(counts, dtype=float)
    total = counts.sum()
    if total == 0:
        return None
    target = q / 100.0 * total
    cum = np.cumsum(counts)
    i = int(np.searchsorted(cum, target, side="left"))
    if i >= len(edges) - 1:
        return None
    low, high = float(edges[i]), float(edges[i + 1])
    before = cum[i - 1] if i else 0.0
    return low + (high - low) * (target - before) / counts[i] if counts[i] else low
