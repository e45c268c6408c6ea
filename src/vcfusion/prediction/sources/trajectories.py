"""Recorded trajectories replayed as cloud twins: the part common to the NGSIM and highD imports.

A reader turns one recording (one driving direction) into a :class:`Recording`: a straight
:class:`Road` of the main lanes and the raw samples of every vehicle (time; s, the footprint
centre along the driving direction; d, left of the main lanes' right edge, NaN where unknown;
lane index, 0 = rightmost in the driving direction, -1 = not on a main lane; speed and
acceleration along the road; length / width / height / class). This module then
1. makes twins reporting every V2C period (:func:`twin_tracks`): duplicate samples dropped, a
   vehicle's track split where it has a gap longer than MAX_GAP_S (real NGSIM reuses vehicle
   ids over time) or leaves the main lanes (ramps, auxiliary lanes), shorter gaps interpolated,
   everything resampled to the period; each piece is one twin, `ID`, then `ID.1`, `ID.2`, ...;
2. removes lane flicker (:func:`clean_lane_flicker`);
3. finds the lane changes in the lane sequence (:func:`lane_changes_of_track`);
4. writes the dataset folder layout of `vcfusion dataset` (:func:`import_recordings`), with the
   features and labels of the very same code as for simulated runs (`dataset.build_samples`:
   the FeatureExtractor replayed snapshot by snapshot over a `twins` table, Fig. 5 labels).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.prediction.dataset import (DATASET_JSON, README, SAMPLES_VERSION, DatasetError, build_samples,
                                         split_seeds)
from vcfusion.prediction.features import FEATURE_NAMES
from vcfusion.studies.batch import seed_folder
from vcfusion.traffic.lanechanges import (  # noqa: F401 - the settled rule, re-exported
    LANE_CHANGE_COLUMNS, LATERAL_SETTLED_MPS, LATERAL_SMOOTH_S, lateral_speed,
)
from vcfusion.traffic.network import Road

PERIOD_S = 0.1  # the V2C period the twins report at (the simulated runs' default)
MAX_GAP_S = 1.0  # a longer gap in a vehicle's samples starts a new twin (NGSIM reuses ids)
MIN_LANE_DWELL_S = 1.0  # a shorter visit to a lane, back to the lane it came from, is flicker
# Start / end of a lane change: the lateral speed towards the new lane, of the lateral position
# smoothed over LATERAL_SMOOTH_S, is at most LATERAL_SETTLED_MPS (the rule and its constants live
# in vcfusion.traffic.lanechanges, which applies it to SUMO's sublane model too).
# A change whose end was not seen (track ends, lateral position unknown) is labelled as ending
# this long after its midpoint: about half of the ~5 s a highway lane change takes.
END_AFTER_MID_S = 2.5
CHUNK_S = 300.0  # default length of the time chunks that play the role of seeds

# Documented defaults where a recording gives no (or a zero) size: by class.
CLASS_SIZE_M = {"motorcycle": (2.0, 0.8, 1.2), "passenger": (4.5, 1.8, 1.5), "truck": (10.0, 2.5, 3.5)}

SAMPLE_COLUMNS = ["vehicle_id", "time", "s", "d", "lane", "speed", "accel", "length", "width", "height", "vclass"]


class RealDataError(DatasetError):
    """A recording that cannot be imported; the message names the file and field."""


@dataclass(frozen=True)
class Recording:
    """One driving direction of one recording, as the reader made it (see the module docstring)."""

    name: str
    road: Road
    samples: pd.DataFrame  # SAMPLE_COLUMNS
    sample_period_s: float  # the recording's own sampling period
    source: dict  # file names, direction, reader's data-quality counts


def straight_road(name: str, num_lanes: int, lane_width_m: float, length_m: float, speed_limit_mps: float) -> Road:
    """The replay road: along +x from the origin, so a twin's x is its s and y its d - width."""
    return Road(edge_id=name, start=(0.0, 0.0), end=(float(max(length_m, 1.0)), 0.0), num_lanes=int(num_lanes),
                lane_width_m=float(lane_width_m), speed_limit_mps=float(speed_limit_mps))


def size_defaults(vclass: np.ndarray, length: np.ndarray, width: np.ndarray, height: np.ndarray) -> dict:
    """Replace missing / zero / negative sizes by the class defaults (CLASS_SIZE_M); counts of the
    filled lengths and widths in 'filled' (heights are not recorded by NGSIM or highD)."""
    out = {}
    filled = {}
    for k, (name, values) in enumerate((("length", length), ("width", width), ("height", height))):
        v = np.asarray(values, dtype=float).copy()
        bad = ~(v > 0)
        default = np.array([CLASS_SIZE_M.get(c, CLASS_SIZE_M["passenger"])[k] for c in vclass])
        v[bad] = default[bad]
        out[name] = v
        if name != "height":  # never recorded: always the class default
            filled[name] = int(bad.sum())
    out["filled"] = filled
    return out


def clean_lane_flicker(lane: np.ndarray, min_samples: int) -> tuple[np.ndarray, int]:
    """Set back visits shorter than min_samples to a lane, between two stretches in one same lane
    (a vehicle on the line whose lane id flips back and forth is not changing lanes). Returns the
    cleaned lanes and the number of visits removed."""
    lane = np.array(lane, copy=True)
    removed = 0
    while True:
        starts = np.flatnonzero(np.r_[True, lane[1:] != lane[:-1]])
        stops = np.r_[starts[1:], len(lane)]
        short = [k for k in range(1, len(starts) - 1)
                 if stops[k] - starts[k] < min_samples and lane[starts[k - 1]] == lane[starts[k + 1]]]
        if not short:
            return lane, removed
        k = short[0]
        lane[starts[k]:stops[k]] = lane[starts[k - 1]]
        removed += 1


def lane_changes_of_track(t: np.ndarray, lane: np.ndarray, d: np.ndarray, period_s: float) -> list[dict]:
    """The lane changes of one twin: every step of its (cleaned) lane sequence.

    mid = the first sample in the new lane (when the map-matched lane flips, as for a SUMO change);
    start = the last sample before it at which the lateral speed towards the new lane was at most
    LATERAL_SETTLED_MPS, end = the first one from it on; searched back / forward without crossing
    the neighbouring changes or an unknown lateral position (NaN then, and the labels take
    mid + END_AFTER_MID_S as the end).
    """
    steps = np.flatnonzero(lane[1:] != lane[:-1]) + 1
    if not len(steps):
        return []
    v = lateral_speed(d, period_s)
    out = []
    for k, b in enumerate(steps):
        lo = steps[k - 1] if k else 0
        hi = steps[k + 1] if k + 1 < len(steps) else len(t)
        direction = 1 if lane[b] > lane[b - 1] else -1  # lane index and d both grow to the left
        toward = direction * v
        start = end = np.nan
        for j in range(b - 1, lo - 1, -1):
            if np.isnan(toward[j]):
                break
            if toward[j] <= LATERAL_SETTLED_MPS:
                start = t[j]
                break
        for j in range(b, hi):
            if np.isnan(toward[j]):
                break
            if toward[j] <= LATERAL_SETTLED_MPS:
                end = t[j]
                break
        out.append({"index": int(b), "start_time": start, "mid_time": float(t[b]), "end_time": end,
                    "from_lane": int(lane[b - 1]), "to_lane": int(lane[b]), "direction": direction})
    return out


def _piece_ids(vid: str, n: int) -> list[str]:
    return [vid if k == 0 else f"{vid}.{k}" for k in range(n)]


def twin_tracks(rec: Recording, period_s: float = PERIOD_S) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame, dict]:
    """(twins, vehicles, lane_changes) tables of a recording and data-quality counts.

    twins: the run-folder `twins` schema (time, vehicle_id, measured_time, x = s, y = d - road
    width, z, heading (NaN: not recorded), speed, accel, lane) plus `d_known`; vehicles: one row
    per twin; lane_changes: LANE_CHANGE_COLUMNS, reason 'unknown'.
    """
    raw = rec.samples
    n_raw = len(raw)
    raw = raw.assign(time=np.round(raw["time"].to_numpy(float), 6))
    raw = raw.drop_duplicates(["vehicle_id", "time"], keep="first")
    quality = {"raw_samples": n_raw, "duplicate_samples": n_raw - len(raw),
               "samples_off_main_lanes": int((raw["lane"] < 0).sum()), "vehicles": int(raw["vehicle_id"].nunique()),
               "tracks_split_at_gaps": 0, "gaps_interpolated": 0, "lane_flicker_removed": 0,
               "lateral_unknown_samples": int(raw["d"].isna().sum())}
    raw = raw.sort_values(["vehicle_id", "time"], kind="stable")
    vid = raw["vehicle_id"].to_numpy(str)
    cuts = np.flatnonzero(vid[1:] != vid[:-1]) + 1
    bounds = zip(np.r_[0, cuts], np.r_[cuts, len(vid)])
    cols = {c: raw[c].to_numpy() for c in SAMPLE_COLUMNS}
    min_dwell = max(1, int(round(MIN_LANE_DWELL_S / period_s)))
    twins, vehicles, events = [], [], []
    for a, b in bounds:
        t = cols["time"][a:b].astype(float)
        gaps = np.diff(t)
        split = np.flatnonzero(gaps > MAX_GAP_S + 1e-6) + 1
        quality["tracks_split_at_gaps"] += len(split)
        quality["gaps_interpolated"] += int(((gaps > 1.5 * rec.sample_period_s) & (gaps <= MAX_GAP_S + 1e-6)).sum())
        pieces = []
        for p0, p1 in zip(np.r_[0, split], np.r_[split, len(t)]):
            tp = t[p0:p1]
            grid = np.arange(math.ceil(tp[0] / period_s - 1e-6), math.floor(tp[-1] / period_s + 1e-6) + 1) * period_s
            if not len(grid):
                continue
            grid = np.round(grid, 6)
            held = a + p0 + np.searchsorted(tp, grid + 1e-6, side="right") - 1  # last raw sample at or before
            # flicker first, off the main lanes too: a moment on a ramp's or a shoulder's lane id is
            # not a vehicle leaving the road (cut there, it became two twins and lost its labels)
            lane, removed = clean_lane_flicker(cols["lane"][held].astype(np.int64), min_dwell)
            quality["lane_flicker_removed"] += removed
            interp = {c: np.interp(grid, tp, cols[c][a + p0:a + p1].astype(float)) for c in ("s", "d", "speed", "accel")}
            # split where the vehicle is off the main lanes (it left the modelled road there)
            on = lane >= 0
            edges = np.flatnonzero(np.diff(np.r_[0, on.astype(np.int8), 0]))
            for q0, q1 in zip(edges[::2], edges[1::2]):
                pieces.append((grid[q0:q1], lane[q0:q1], {c: v[q0:q1] for c, v in interp.items()}, held[q0:q1]))
        for twin_id, (tg, lane, vals, held) in zip(_piece_ids(str(vid[a]), len(pieces)), pieces):
            accel = vals["accel"]
            if np.isnan(accel).any():  # not recorded: from the speed
                accel = np.gradient(vals["speed"], period_s) if len(tg) > 1 else np.zeros(len(tg))
            d = vals["d"]
            twins.append((twin_id, tg, vals["s"], d, vals["speed"], accel, lane))
            vehicles.append({"vehicle_id": twin_id, "source_id": str(vid[a]), "vclass": str(cols["vclass"][held[0]]),
                             **{c: float(np.median(cols[c][held].astype(float))) for c in ("length", "width", "height")}})
            for ev in lane_changes_of_track(tg, lane, d, period_s):
                i = ev.pop("index")
                events.append({"vehicle_id": twin_id, **ev, "pos_m": float(vals["s"][i]),
                               "speed_mps": float(vals["speed"][i])})
    road = rec.road
    # one table at the end (a DataFrame per twin costs more than the rest of the import)
    ids = np.repeat(np.array([p[0] for p in twins], dtype=object), [len(p[1]) for p in twins]) if twins \
        else np.zeros(0, dtype=object)
    time, s, d, speed, accel, lane = (np.concatenate([p[k] for p in twins]) if twins else np.zeros(0)
                                      for k in range(1, 7))
    d_known = ~np.isnan(d)
    d_filled = np.where(d_known, d, road.lane_centre_d(lane))
    twins_table = pd.DataFrame({
        "time": time, "vehicle_id": ids.astype(str), "measured_time": time, "x": s,
        # unknown lateral position: the lane centre (the lane is what the features use)
        "y": d_filled - road.width_m, "z": np.zeros(len(time)), "heading": np.full(len(time), np.nan),
        "speed": speed, "accel": accel, "lane": lane.astype(np.int16), "d_known": d_known,
    }).sort_values(["time", "vehicle_id"], kind="stable").reset_index(drop=True)
    veh = pd.DataFrame(vehicles, columns=["vehicle_id", "source_id", "vclass", "length", "width", "height"])
    veh.insert(1, "vtype", [f"{rec.source.get('format', 'recorded')}-{c}" for c in veh["vclass"]])
    veh["group"] = ""
    ev = pd.DataFrame(events, columns=["vehicle_id", "start_time", "mid_time", "end_time", "from_lane", "to_lane",
                                       "direction", "pos_m", "speed_mps"])
    ev = ev.sort_values(["mid_time", "vehicle_id"], kind="stable").reset_index(drop=True)
    lane_changes = pd.DataFrame({
        "event_id": np.arange(len(ev), dtype=np.int64), "vehicle_id": ev["vehicle_id"].astype(str).to_numpy(),
        "start_time": ev["start_time"].to_numpy(float), "mid_time": ev["mid_time"].to_numpy(float),
        "end_time": ev["end_time"].to_numpy(float), "from_lane": ev["from_lane"].to_numpy(np.int64),
        "to_lane": ev["to_lane"].to_numpy(np.int64), "direction": ev["direction"].to_numpy(np.int64),
        "reason": np.full(len(ev), "unknown", dtype=object), "pos_m": ev["pos_m"].to_numpy(float),
        "speed_mps": ev["speed_mps"].to_numpy(float), "leader_gap_m": np.full(len(ev), np.nan),
        "follower_gap_m": np.full(len(ev), np.nan),
    })[LANE_CHANGE_COLUMNS]
    quality |= {"twins": int(len(veh)), "twin_samples": int(len(twins_table)), "lane_changes": int(len(lane_changes)),
                "lane_changes_end_unseen": int(lane_changes["end_time"].isna().sum())}
    return twins_table, veh, lane_changes, quality


def _road_dict(road: Road) -> dict:
    """The road's fields for JSON (an unknown speed limit as null, not NaN)."""
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in asdict(road).items()}


def import_recordings(recordings: list[Recording], out: Path, tau: float, tau_g: float, chunk_s: float = CHUNK_S,
                      source: dict | None = None, progress: bool = True) -> dict:
    """Write a dataset folder (the layout of `vcfusion dataset`) from recordings; returns counts.

    A *seed* of an imported dataset is a time chunk of `chunk_s` of one recording (one driving
    direction): it holds the twins that first appear in that chunk, with their whole tracks, so a
    vehicle never straddles two seeds; seeds are numbered in recording order, then time, and split
    70/15/15 in that order (later traffic tests, as for held-out simulation seeds). Features see
    every twin of the recording (neighbours in other chunks included). The whole folder is written
    next to `out` and renamed at the end: an interrupted import leaves nothing.
    """
    from tqdm import tqdm

    from vcfusion.runio import atomic_folder, write_json, write_run_folder

    if tau <= 0 or tau_g < 0:
        raise RealDataError(f"--tau/--tau-g: expected tau > 0 and tau_g >= 0, got {tau}, {tau_g}")
    if not chunk_s > 0:
        raise RealDataError(f"--chunk: expected a positive chunk length in seconds, got {chunk_s}")
    out = Path(out)
    if out.exists():
        raise RealDataError(f"--out: {out} already exists; an import writes a new dataset folder")
    seeds_meta: dict[str, dict] = {}
    recs_meta = []
    counts = {"seeds": 0, "samples": 0, "window_positive": 0, "window_negative": 0, "lane_changes": 0}
    next_seed = 0
    with atomic_folder(out, "dataset folder") as tmp:
        for rec in tqdm(recordings, desc="recordings", unit="rec", disable=not progress):
            twins, vehicles, lane_changes, quality = twin_tracks(rec)
            recs_meta.append({"name": rec.name, **rec.source, "road": _road_dict(rec.road), "quality": quality})
            if not len(twins):
                continue
            tables = {"twins": twins, "vehicles": vehicles, "lane_changes": lane_changes}
            samples = build_samples(tables, rec.road, PERIOD_S, 0, tau, tau_g, END_AFTER_MID_S)
            t0 = float(twins["time"].min())
            first = twins.groupby("vehicle_id", sort=False)["time"].min()
            chunk_of = ((first - t0) // chunk_s).astype(int)
            for chunk in sorted(chunk_of.unique()):
                seed = next_seed
                next_seed += 1
                ids = set(chunk_of.index[chunk_of == chunk])
                mine = lambda df: df[df["vehicle_id"].isin(ids)].reset_index(drop=True)  # noqa: E731
                seed_samples = mine(samples).assign(seed=np.int32(seed))
                seed_tables = {"twins": mine(twins), "vehicles": mine(vehicles), "lane_changes": mine(lane_changes),
                               "samples": seed_samples}
                span = (t0 + chunk * chunk_s, t0 + (chunk + 1) * chunk_s)
                info = {"recording": rec.name, "chunk": int(chunk), "first_seen_from_s": span[0],
                        "first_seen_before_s": span[1], "twins": len(ids),
                        "lane_changes": int(len(seed_tables["lane_changes"])),
                        "vehicle_hours": float(len(seed_samples) * PERIOD_S / 3600.0)}
                manifest = {"source": {**rec.source, "recording": rec.name}, "road": _road_dict(rec.road),
                            "period_s": PERIOD_S, "seed": seed, "dataset": {"tau": tau, "tau_g": tau_g},
                            "chunk": info}
                write_run_folder(seed_folder(tmp / "runs", seed), seed_tables, manifest, info)
                seeds_meta[str(seed)] = info
                lab = seed_samples["window_label"]
                counts["samples"] += int(len(lab))
                counts["window_positive"] += int((lab == 1).sum())
                counts["window_negative"] += int((lab == 0).sum())
                counts["lane_changes"] += info["lane_changes"]
        seeds = [int(s) for s in seeds_meta]
        if not seeds:
            raise RealDataError(f"{', '.join(r.source.get('file', r.name) for r in recordings)}: no vehicle "
                                f"on the main lanes; nothing to import")
        counts["seeds"] = len(seeds)
        meta = {"scenario": (source or {}).get("format", "recorded"), "source": source or {},
                "tau": tau, "tau_g": tau_g, "period_s": PERIOD_S, "feature_names": list(FEATURE_NAMES),
                "samples_version": SAMPLES_VERSION,
                "lanechange_end_after_mid_s": END_AFTER_MID_S, "chunk_s": chunk_s,
                "import": {"max_gap_s": MAX_GAP_S, "min_lane_dwell_s": MIN_LANE_DWELL_S,
                           "lateral_smooth_s": LATERAL_SMOOTH_S, "lateral_settled_mps": LATERAL_SETTLED_MPS},
                "recordings": recs_meta, "seeds": seeds_meta, "splits": split_seeds(seeds), "counts": counts}
        write_json(tmp / DATASET_JSON, meta)
        (tmp / "README.md").write_text(README.format(features=", ".join(FEATURE_NAMES)) + IMPORT_README)
    return {"counts": counts, "splits": meta["splits"], "recordings": recs_meta}


IMPORT_README = """
## Imported recordings

This dataset was imported from recorded trajectories (`vcfusion dataset --from-ngsim / --from-highd /
--from-commonroad`,
vcfusion.prediction.sources): each vehicle is replayed as a twin reporting every 0.1 s, its lane
counted 0 = rightmost in its driving direction and s along it. A *seed* is a time chunk of one
recording (one driving direction; `dataset.json` `seeds` says which); it holds the twins first
seen in it. Lane changes are the steps of the lane sequence (`lc_reason` 'unknown'); see
`dataset.json` `recordings[].quality` for what the import repaired (duplicates, gaps, flicker).
`twins.parquet` has `d_known`: false where the recording gave no lateral position (y is then
the lane centre).
"""
