"""Lane-change events: SUMO's lanechange-output joined with the lateral trajectory.

SUMO reports one record per change at the moment the vehicle's centre line enters the new
lane (the manoeuvre's midpoint), with the reason. With continuous lane changing the
manoeuvre starts earlier and ends later: start is the last sample before the midpoint at
which the vehicle was still centred in its old lane, end the first sample after it at which
it is centred in the new one (to `CENTRED_TOL_M`), at the trajectory's sampling period.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.traffic.network import Road

CENTRED_TOL_M = 0.05

LANE_CHANGE_COLUMNS = [
    "event_id", "vehicle_id", "start_time", "mid_time", "end_time", "from_lane", "to_lane",
    "direction", "reason", "pos_m", "speed_mps", "leader_gap_m", "follower_gap_m",
]


def _lane_index(lane_id: str) -> int:
    return int(lane_id.rsplit("_", 1)[1])


def _gap(value: str | None) -> float:
    return float(value) if value not in (None, "None") else np.nan


def read_sumo_lanechanges(path: str | Path) -> pd.DataFrame:
    """SUMO's lanechange-output as a table (one row per change, at its midpoint)."""
    path = Path(path)
    rows = []
    if path.exists() and path.stat().st_size:
        for c in ET.parse(path).getroot().iter("change"):
            rows.append({
                "vehicle_id": c.get("id"),
                "mid_time": float(c.get("time")),
                "from_lane": _lane_index(c.get("from")),
                "to_lane": _lane_index(c.get("to")),
                "direction": int(c.get("dir")),
                "reason": c.get("reason"),
                "pos_m": float(c.get("pos")),
                "speed_mps": float(c.get("speed")),
                "leader_gap_m": _gap(c.get("leaderGap")),
                "follower_gap_m": _gap(c.get("followerGap")),
            })
    return pd.DataFrame(rows, columns=[c for c in LANE_CHANGE_COLUMNS if c not in ("event_id", "start_time", "end_time")])


def lane_change_events(sumo_changes: pd.DataFrame, trajectories: pd.DataFrame, road: Road) -> pd.DataFrame:
    """Add start and end times from the lateral trajectory; one row per lane change."""
    events = sumo_changes.sort_values(["mid_time", "vehicle_id"], kind="stable").reset_index(drop=True)
    starts = np.full(len(events), np.nan)
    ends = np.full(len(events), np.nan)
    # time and d of each changer only, as plain arrays (runs at the end of every run)
    changers = trajectories[trajectories["vehicle_id"].isin(set(events["vehicle_id"]))]
    by_vehicle = {vid: (g["time"].to_numpy(), g["d"].to_numpy())
                  for vid, g in changers.groupby("vehicle_id", sort=False)}
    columns = (events[c].to_numpy() for c in ("vehicle_id", "from_lane", "to_lane", "mid_time"))
    for i, (vid, from_lane, to_lane, mid_time) in enumerate(zip(*columns)):
        track = by_vehicle.get(vid)
        if track is None:
            continue
        t, d = track
        in_old = np.abs(d - road.lane_centre_d(from_lane)) <= CENTRED_TOL_M
        in_new = np.abs(d - road.lane_centre_d(to_lane)) <= CENTRED_TOL_M
        before = np.flatnonzero(in_old & (t <= mid_time + 1e-9))
        after = np.flatnonzero(in_new & (t >= mid_time - 1e-9))
        if len(before):
            starts[i] = t[before[-1]]
        if len(after):
            ends[i] = t[after[0]]
    events.insert(0, "event_id", np.arange(len(events), dtype=np.int64))
    events.insert(2, "start_time", starts)
    events.insert(4, "end_time", ends)
    return events[LANE_CHANGE_COLUMNS]
