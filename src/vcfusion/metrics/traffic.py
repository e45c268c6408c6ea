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
been absent for `_GONE_AFTER_S`, so memory follows the vehicles on the road, not the run length.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from types import SimpleNamespace
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from vcfusion.metrics.movestar import trip_emissions
from vcfusion.metrics.safety import exposure, kinematics

EGO_ID = "ego"
BATCH_ROWS = 65_536
# A vehicle missing from the trajectories this long has left (a SUMO teleport can bring it back:
# its later samples are a second segment, combined into the same row).
_GONE_AFTER_S = 60.0
TRAJECTORY_COLUMNS = ["time", "vehicle_id", "lane", "s", "speed"]
# Distribution bins (histograms in metric_histograms.parquet; percentiles read from them).
TTC_EDGES = np.round(np.linspace(0.0, 60.0, 1201), 6)  # 0.05 s
HEADWAY_EDGES = np.round(np.linspace(0.0, 10.0, 501), 6)  # 0.02 s
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
    """Row index of each row's leader (nearest ahead by s in the same lane at the same time), -1 if none."""
    order = np.lexsort((s, lane, time))
    follower, ahead = order[:-1], order[1:]
    same = (time[ahead] == time[follower]) & (lane[ahead] == lane[follower])
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
                        sumo_emissions: pd.DataFrame | None) -> RunMetrics:
    """The per-vehicle table, the conflict episodes and the distributions of one run (streamed)."""
    dt = trajectory_period_s
    info = _VehicleFacts(vehicles)
    codes: dict[str, int] = {}
    ids: list[str] = []
    lengths: list[float] = []
    buffers = _Buffers()
    segments: dict[int, list[dict]] = {}
    conflicts: list[dict] = []
    excluded = {vid for vid, group in info.group.items() if group in set(cfg.exclude_groups)}
    ttc_counts = np.zeros(len(TTC_EDGES), dtype=np.int64)  # last bin: >= the last edge
    headway_counts = np.zeros(len(HEADWAY_EDGES), dtype=np.int64)

    def finish(code: int) -> None:
        series = buffers.pop(code)
        vid = ids[code]
        segment, episodes = _segment(series, dt, cfg.ttc_threshold_s, cfg.jerk_window_s)
        segment.update(_movestar(series["time"], series["speed"], movestar_type(cfg, *info.types(vid))))
        segments.setdefault(code, []).append(segment)
        for e in episodes:
            conflicts.append({"vehicle_id": vid, "leader_id": ids[e.pop("leader")], **e})
        if vid not in excluded:
            for values, edges, counts in ((series["ttc"], TTC_EDGES, ttc_counts),
                                          (series["headway"], HEADWAY_EDGES, headway_counts)):
                _count(values, edges, counts)

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
        order = np.argsort(code, kind="stable")
        bounds = np.flatnonzero(np.diff(code[order])) + 1
        for rows in np.split(order, bounds):
            c = int(code[rows[0]])
            # back after a long absence (a teleport): the stretch so far is finished, a new one begins
            before = buffers.last_time.get(c, time[rows[0]])
            breaks = np.flatnonzero(np.diff(np.r_[before, time[rows]]) > _GONE_AFTER_S)
            for part in np.split(rows, breaks):
                if not len(part):  # the break came before this piece's first row
                    continue
                if c in buffers.chunks and buffers.last_time[c] < time[part[0]] - _GONE_AFTER_S:
                    finish(c)
                buffers.add(c, {k: v[part] for k, v in columns.items()})
        now = float(time[-1])
        for c in [c for c, last in buffers.last_time.items() if last < now - _GONE_AFTER_S]:
            finish(c)
    for c in list(buffers.chunks):
        finish(c)

    rows = sorted((_vehicle_row(cfg, ids[c], segs, info) for c, segs in segments.items()),
                  key=lambda r: r["vehicle_id"])
    if ego is not None and ego.num_rows:
        for row in rows:
            if row["vehicle_id"] == EGO_ID:
                row.update(_ego_from_own_log(cfg, ego, step_s, info))
    columns = {k: np.array([r[k] for r in rows]) for k in (rows[0] if rows else _EMPTY_ROW)}
    vids = [r["vehicle_id"] for r in rows]
    columns["counted"] = np.array([v not in excluded for v in vids], dtype=bool)
    columns["lane_changes"] = _lane_changes(vids, lane_changes)
    columns.update(_sumo_columns(vids, columns["distance_m"], sumo_emissions))
    mkm = np.where(columns["movestar_distance_m"] > 0, columns["movestar_distance_m"], np.nan) / 1000.0
    for k in MOVESTAR_KEYS.values():
        columns[f"movestar_{k}_per_km"] = columns[f"movestar_{k}"] / mkm
    conflicts.sort(key=lambda c: (c["start_time"], c["vehicle_id"]))
    conflict_table = pa.table({name: pa.array([c[name] for c in conflicts], type=kind)
                               for name, kind in CONFLICT_SCHEMA.items()})
    histograms = pa.table({
        "measure": ["ttc_s"] * len(TTC_EDGES) + ["time_headway_s"] * len(HEADWAY_EDGES),
        "bin_low": np.r_[TTC_EDGES, HEADWAY_EDGES],
        "bin_high": np.r_[TTC_EDGES[1:], np.inf, HEADWAY_EDGES[1:], np.inf],
        "count": np.r_[ttc_counts, headway_counts]})
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
    ends = np.flatnonzero(below & ~np.r_[continues[1:], False]) + 1
    return list(zip(starts.tolist(), ends.tolist()))


def _nanmin(x: np.ndarray) -> float:
    found = float(np.fmin.reduce(np.asarray(x, dtype=float), initial=math.inf))  # fmin skips NaN
    return found if found != math.inf else math.nan


def _nanmax(x: np.ndarray) -> float:
    found = float(np.fmax.reduce(np.asarray(x, dtype=float), initial=-math.inf))
    return found if found != -math.inf else math.nan


def _segment(series: dict[str, np.ndarray], dt: float, threshold: float, jerk_window_s: float) -> tuple[dict, list[dict]]:
    """Additive and extreme figures of one vehicle's continuous stretch of samples."""
    t, s, v, ttc = series["time"], series["s"], series["speed"], series["ttc"]
    kin = kinematics(t, s, v, dt, jerk_window_s)
    tet, tit = exposure(ttc, dt, threshold)
    episodes = []
    for a, b in conflict_episodes(ttc, series["leader"], threshold):
        episodes.append({"leader": int(series["leader"][a]), "start_time": float(t[a]), "end_time": float(t[b - 1] + dt),
                         "duration_s": float((b - a) * dt), "min_ttc_s": float(np.min(ttc[a:b])),
                         "s_start": float(s[a]), "lane": int(series["lane"][a])})
    seg = {"first_time": float(t[0]), "samples": len(t), "travel_time_s": kin["trip_time_s"],
           "distance_m": kin["ego_distance_m"], "speed_sum": float(v.sum()),
           "abs_accel_sum": kin["avg_abs_accel_mps2"] * (len(v) - 1) if len(v) > 1 else 0.0,
           "accel_samples": max(0, len(v) - 1), "max_decel_mps2": kin["max_decel_mps2"],
           "max_abs_jerk_mps3": kin["max_abs_jerk_mps3"],
           "ttc_samples": int(np.isfinite(ttc).sum()), "min_ttc_s": _nanmin(ttc), "tet_s": tet, "tit_s2": tit,
           "max_drac_mps2": _nanmax(series["drac"]), "min_time_headway_s": _nanmin(series["headway"]),
           "min_gap_m": _nanmin(series["gap"]), "conflicts": len(episodes)}
    return seg, episodes


def _movestar(time: np.ndarray, speed: np.ndarray, vehicle_type: int | None) -> dict:
    out = {f"movestar_{k}": math.nan for k in MOVESTAR_KEYS.values()}
    out["movestar_distance_m"], out["movestar_seconds"] = math.nan, 0
    if vehicle_type is None:
        return out
    try:
        em = trip_emissions(time, speed, vehicle_type)
    except ValueError:  # less than one whole second on the road: no 1 Hz sample to rate
        return out
    totals = dict(em["totals"])
    totals["PM2.5"] = totals.pop("PM2.5_Ele") + totals.pop("PM2.5_Org")
    out.update({f"movestar_{MOVESTAR_KEYS[k]}": float(v) for k, v in totals.items()})
    out["movestar_distance_m"], out["movestar_seconds"] = em["TD_m"], int(em["TT_s"])
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


def _vehicle_row(cfg, vid: str, segs: list[dict], info: _VehicleFacts) -> dict:
    vtype, vclass = info.types(vid)
    samples = sum(g["samples"] for g in segs)
    accel_samples = sum(g["accel_samples"] for g in segs)
    mst = movestar_type(cfg, vtype, vclass)
    row = {"vehicle_id": vid, "vtype": vtype, "vclass": vclass, "group": info.group.get(vid, ""),
           "first_time_s": segs[0]["first_time"], "samples": samples,
           "travel_time_s": sum(g["travel_time_s"] for g in segs), "distance_m": sum(g["distance_m"] for g in segs),
           "mean_speed_mps": sum(g["speed_sum"] for g in segs) / samples,
           "mean_abs_accel_mps2": sum(g["abs_accel_sum"] for g in segs) / accel_samples if accel_samples else math.nan,
           "max_decel_mps2": _nanmax(np.array([g["max_decel_mps2"] for g in segs])),
           "max_abs_jerk_mps3": _nanmax(np.array([g["max_abs_jerk_mps3"] for g in segs])),
           "ttc_samples": sum(g["ttc_samples"] for g in segs),
           "min_ttc_s": _nanmin(np.array([g["min_ttc_s"] for g in segs])),
           "tet_s": sum(g["tet_s"] for g in segs), "tit_s2": sum(g["tit_s2"] for g in segs),
           "max_drac_mps2": _nanmax(np.array([g["max_drac_mps2"] for g in segs])),
           "min_time_headway_s": _nanmin(np.array([g["min_time_headway_s"] for g in segs])),
           "min_gap_m": _nanmin(np.array([g["min_gap_m"] for g in segs])),
           "conflicts": sum(g["conflicts"] for g in segs), "movestar_type": mst or 0}
    row.update({k: sum(g[k] for g in segs) for k in _MOVESTAR_TOTALS})
    return row


_MOVESTAR_TOTALS = (*(f"movestar_{k}" for k in MOVESTAR_KEYS.values()), "movestar_distance_m", "movestar_seconds")
# the row of a vehicle with one sample: its keys are the columns of a run without any vehicle
_EMPTY_ROW = _vehicle_row(SimpleNamespace(movestar={}), "", [dict.fromkeys(
    ("first_time", "samples", "travel_time_s", "distance_m", "speed_sum", "abs_accel_sum", "accel_samples",
     "max_decel_mps2", "max_abs_jerk_mps3", "ttc_samples", "min_ttc_s", "tet_s", "tit_s2", "max_drac_mps2",
     "min_time_headway_s", "min_gap_m", "conflicts", *_MOVESTAR_TOTALS), 1)],
    _VehicleFacts(pd.DataFrame(columns=["vehicle_id", "vtype", "vclass", "group", "length"])))


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


def _sumo_columns(vids: list[str], distance_m: np.ndarray, sumo: pd.DataFrame | None) -> dict[str, np.ndarray]:
    """SUMO's emission totals and per km (NaN and no class where the run folder has none)."""
    names = [f"{k}_g" for k in SUMO_KEYS] + ["electricity_wh"]
    found: dict[str, tuple] = {}
    if sumo is not None and len(sumo):
        values = zip(sumo["emission_class"].tolist(), *(sumo[c].tolist() for c in names))
        found = dict(zip(sumo["vehicle_id"].tolist(), values))
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
