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

from vcfusion.records import EGO_ID
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


# SUMO's lanechange-output as read: one row per change, at its midpoint
SUMO_CHANGE_DTYPES = {
    "vehicle_id": str, "mid_time": float, "from_lane": np.int64, "to_lane": np.int64, "direction": np.int64,
    "reason": str, "pos_m": float, "speed_mps": float, "leader_gap_m": float, "follower_gap_m": float,
}


def read_sumo_lanechanges(path: str | Path) -> dict[str, np.ndarray]:
    """SUMO's lanechange-output as columns (one element per change, at its midpoint)."""
    path = Path(path)
    rows = []
    if path.exists() and path.stat().st_size:
        for c in ET.parse(path).getroot().iter("change"):
            rows.append((c.get("id"), float(c.get("time")), _lane_index(c.get("from")), _lane_index(c.get("to")),
                         int(c.get("dir")), c.get("reason"), float(c.get("pos")), float(c.get("speed")),
                         _gap(c.get("leaderGap")), _gap(c.get("followerGap"))))
    values = list(zip(*rows)) if rows else [()] * len(SUMO_CHANGE_DTYPES)
    return {name: np.array(v, dtype=dtype) for (name, dtype), v in zip(SUMO_CHANGE_DTYPES.items(), values)}


def lane_change_events(sumo_changes: dict[str, np.ndarray], tracks: dict[str, dict[str, np.ndarray]],
                       road: Road) -> dict[str, np.ndarray]:
    """Add start and end times from the lateral trajectory; one element per lane change, in
    LANE_CHANGE_COLUMNS order, sorted by midpoint then vehicle. `tracks`: time and d of each
    changer's trajectory samples, in time order (see runio.vehicle_tracks)."""
    order = np.lexsort((sumo_changes["vehicle_id"], sumo_changes["mid_time"]))  # stable
    events = {name: values[order] for name, values in sumo_changes.items()}
    starts = np.full(len(order), np.nan)
    ends = np.full(len(order), np.nan)
    columns = (events[c] for c in ("vehicle_id", "from_lane", "to_lane", "mid_time"))
    for i, (vid, from_lane, to_lane, mid_time) in enumerate(zip(*columns)):
        track = tracks.get(vid)
        if track is None:
            continue
        t, d = track["time"], track["d"]
        in_old = np.abs(d - road.lane_centre_d(from_lane)) <= CENTRED_TOL_M
        in_new = np.abs(d - road.lane_centre_d(to_lane)) <= CENTRED_TOL_M
        before = np.flatnonzero(in_old & (t <= mid_time + 1e-9))
        after = np.flatnonzero(in_new & (t >= mid_time - 1e-9))
        if len(before):
            starts[i] = t[before[-1]]
        if len(after):
            ends[i] = t[after[0]]
    events |= {"event_id": np.arange(len(order), dtype=np.int64), "start_time": starts, "end_time": ends}
    return {name: events[name] for name in LANE_CHANGE_COLUMNS}


def relate_to_ego(events: dict[str, np.ndarray], tracks: dict[str, dict[str, np.ndarray]],
                  lengths: dict[str, float], ego_lane: int) -> dict[str, np.ndarray]:
    """Mark lane changes into the ego's lane and where they happened relative to the ego.

    `gap_to_ego_m`: bumper to bumper along the road, the changer's rear minus the ego's front,
    at the trajectory sample nearest the change's midpoint. `tracks`: time and s of the ego's
    and the changers' trajectory samples (see runio.vehicle_tracks; others are ignored).
    """
    vids, mid = events["vehicle_id"], events["mid_time"]
    gaps = np.full(len(vids), np.nan)
    ego = tracks.get(EGO_ID)
    if ego is not None and len(ego["time"]) and len(vids):
        ego_t, ego_s = ego["time"], ego["s"]
        at = np.abs(ego_t[None, :] - mid[:, None]).argmin(axis=1)
        changer_s = np.full(len(vids), np.nan)
        for i, (vid, t) in enumerate(zip(vids, ego_t[at])):
            track = tracks.get(vid)
            hit = np.flatnonzero(track["time"] == t) if track is not None else ()
            if len(hit):
                changer_s[i] = track["s"][hit[-1]]
        changer_length = np.array([lengths.get(v, np.nan) for v in vids], dtype=float)
        gaps = changer_s - ego_s[at] - 0.5 * (changer_length + lengths[EGO_ID])
    return events | {"into_ego_lane": (events["to_lane"] == ego_lane) & (vids != EGO_ID),
                     "gap_to_ego_m": gaps, "ahead_of_ego": gaps > 0}
