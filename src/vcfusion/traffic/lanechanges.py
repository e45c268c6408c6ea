"""Lane-change events: SUMO's lanechange-output joined with the lateral trajectory.

SUMO reports one record per change at the moment the vehicle's centre line enters the new
lane (the manoeuvre's midpoint), with the reason. With continuous lane changing the
manoeuvre starts earlier and ends later: start is the last sample before the midpoint at
which the vehicle was still centred in its old lane, end the first sample after it at which
it is centred in the new one (to `CENTRED_TOL_M`), at the trajectory's sampling period.

Lanes are tracks of the scenario's route (index from the right, stable across edges): SUMO's
lane ids map to them with the road frame's `track_of`, so a ramp vehicle's merge from the
acceleration lane is track 0 -> 1 whatever SUMO's index on that edge; a change on an edge off the
route has lanes -1 (and no start or end).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from vcfusion.records import EGO_ID
from vcfusion.traffic.roadframe import RoadFrame

CENTRED_TOL_M = 0.05
# a person never centres a car to 5 cm: a person's change starts where the car was last wholly in
# its old lane and ends where it is first wholly in the new one (a 1.8 m car)
PERSON_CAR_WIDTH_M = 1.8

# "Lateral motion settled": a change starts at the last sample before its midpoint, and ends at the
# first one from it on, at which the lateral speed towards the new lane (of d smoothed over
# LATERAL_SMOOTH_S, centred) is at most LATERAL_SETTLED_MPS. Recorded drivers keep their own offset in
# a lane, and so do SUMO's sublane-model vehicles (lcSigma): for them "centred to 5 cm" may never
# happen near the change (in the sublane model it found starts ~10 s before the midpoint). Imports
# of recordings and sublane runs use this rule; SUMO's lanes-as-units runs keep CENTRED_TOL_M.
LATERAL_SMOOTH_S = 1.0
LATERAL_SETTLED_MPS = 0.2

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


def read_sumo_lanechanges(path: str | Path, road: RoadFrame | None = None) -> dict[str, np.ndarray]:
    """SUMO's lanechange-output as columns (one element per change, at its midpoint). With a
    road frame, lanes are the tracks of its route and pos_m the position along it (-1 and NaN on
    lanes off the route); without one, SUMO's lane indices and lane positions."""
    path = Path(path)
    if road is None:
        lane_of, pos_of = _lane_index, lambda lane_id, pos: pos
    else:
        track_of, edge_start = road.track_of, road.edge_start_s

        def lane_of(lane_id: str) -> int:
            return track_of.get(lane_id, -1)

        def pos_of(lane_id: str, pos: float) -> float:
            start = edge_start.get(lane_id.rsplit("_", 1)[0])
            return start + pos if start is not None else np.nan
    rows = []
    if path.exists() and path.stat().st_size:
        for c in ET.parse(path).getroot().iter("change"):
            rows.append((c.get("id"), float(c.get("time")), lane_of(c.get("from")), lane_of(c.get("to")),
                         int(c.get("dir")), c.get("reason"), pos_of(c.get("from"), float(c.get("pos"))),
                         float(c.get("speed")),
                         _gap(c.get("leaderGap")), _gap(c.get("followerGap"))))
    values = list(zip(*rows)) if rows else [()] * len(SUMO_CHANGE_DTYPES)
    return {name: np.array(v, dtype=dtype) for (name, dtype), v in zip(SUMO_CHANGE_DTYPES.items(), values)}


PERSON_REASON = "person"  # the ego's lane changes when a person steers it (vcfusion.hitl)


def ego_lane_changes(track: dict[str, np.ndarray] | None, road: Road, ego_length_m: float) -> dict[str, np.ndarray]:
    """The ego's own lane changes as SUMO would report them (one row per change, columns of
    SUMO_CHANGE_DTYPES), from its trajectory: SUMO's lanechange-output does not see a vehicle
    placed with moveToXY. The midpoint is the first sample with the centre line in the new lane
    (at the trajectory's period); pos_m the front bumper there, speed from the neighbouring
    samples; reason `person`; the gaps are not known (NaN). A model-driven ego never changes
    lanes: no rows."""
    empty = {name: np.array([], dtype=dtype) for name, dtype in SUMO_CHANGE_DTYPES.items()}
    if track is None or len(track["time"]) < 2:
        return empty
    t, d, s = track["time"], track["d"], track["s"]
    lane = road.lane_of(s, d)
    k = np.flatnonzero((lane[1:] != lane[:-1]) & (lane[1:] >= 0) & (lane[:-1] >= 0)) + 1
    if not len(k):
        return empty
    lo, hi = np.maximum(k - 1, 0), np.minimum(k + 1, len(t) - 1)
    return {
        "vehicle_id": np.full(len(k), EGO_ID).astype(str), "mid_time": t[k].astype(float),
        "from_lane": lane[k - 1].astype(np.int64), "to_lane": lane[k].astype(np.int64),
        "direction": np.sign(lane[k].astype(np.int64) - lane[k - 1]),  # SUMO: +1 = to the left
        "reason": np.full(len(k), PERSON_REASON).astype(str), "pos_m": s[k] + ego_length_m / 2,
        "speed_mps": (s[hi] - s[lo]) / (t[hi] - t[lo]), "leader_gap_m": np.full(len(k), np.nan),
        "follower_gap_m": np.full(len(k), np.nan),
    }


def merge_changes(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {name: np.concatenate([a[name], b[name]]).astype(dtype) for name, dtype in SUMO_CHANGE_DTYPES.items()}


def lateral_speed(d: np.ndarray, period_s: float) -> np.ndarray:
    """Rate of change of d smoothed over LATERAL_SMOOTH_S (centred); NaN where d is unknown."""
    import pandas as pd

    n = max(1, int(round(LATERAL_SMOOTH_S / period_s))) | 1  # odd, so the window is centred
    if len(d) < max(n, 2):
        return np.full(len(d), np.nan)
    smooth = pd.Series(np.asarray(d, dtype=float)).rolling(n, center=True, min_periods=n).mean().to_numpy()
    return np.gradient(smooth, period_s)


def settled_bounds(t: np.ndarray, d: np.ndarray, mid_time: float, direction: int) -> tuple[float, float]:
    """(start, end) of a change by the settled rule (see LATERAL_SETTLED_MPS), NaN where the track
    does not show it (it ends first, or d is unknown)."""
    if len(t) < 2:
        return np.nan, np.nan
    toward = direction * lateral_speed(d, float(np.median(np.diff(t))))
    k = int(np.searchsorted(t, mid_time - 1e-9))
    start = end = np.nan
    for j in range(min(k, len(t)) - 1, -1, -1):
        if np.isnan(toward[j]):
            break
        if toward[j] <= LATERAL_SETTLED_MPS:
            start = float(t[j])
            break
    for j in range(k, len(t)):
        if np.isnan(toward[j]):
            break
        if toward[j] <= LATERAL_SETTLED_MPS:
            end = float(t[j])
            break
    return start, end


def lane_change_events(sumo_changes: dict[str, np.ndarray], tracks: dict[str, dict[str, np.ndarray]],
                       road: RoadFrame, rule: str = "centred") -> dict[str, np.ndarray]:
    """Add start and end times from the lateral trajectory; one element per lane change, in
    LANE_CHANGE_COLUMNS order, sorted by midpoint then vehicle. `tracks`: time, d and s of each
    changer's trajectory samples, in time order (see runio.vehicle_tracks); lane centres are
    taken at each sample's s (a lane's d range may change along the route). `rule`: "centred"
    (to CENTRED_TOL_M; a person's changes to PERSON_CAR_WIDTH_M) or "settled" (the lateral-speed
    rule, for SUMO's sublane model)."""
    order = np.lexsort((sumo_changes["vehicle_id"], sumo_changes["mid_time"]))  # stable
    events = {name: values[order] for name, values in sumo_changes.items()}
    starts = np.full(len(order), np.nan)
    ends = np.full(len(order), np.nan)
    person_tol = max(CENTRED_TOL_M, (road.lane_width_m - PERSON_CAR_WIDTH_M) / 2)
    columns = (events[c] for c in ("vehicle_id", "from_lane", "to_lane", "mid_time", "reason"))
    for i, (vid, from_lane, to_lane, mid_time, reason) in enumerate(zip(*columns)):
        track = tracks.get(vid)
        if track is None or from_lane < 0 or to_lane < 0:
            continue
        t, d = track["time"], track["d"]
        if rule == "settled" and reason != PERSON_REASON:
            starts[i], ends[i] = settled_bounds(t, d, mid_time, 1 if to_lane > from_lane else -1)
            continue
        s = track["s"] if "s" in track else 0.0
        tol = person_tol if reason == PERSON_REASON else CENTRED_TOL_M
        in_old = np.abs(d - road.lane_centre_d(from_lane, s)) <= tol
        in_new = np.abs(d - road.lane_centre_d(to_lane, s)) <= tol
        before = np.flatnonzero(in_old & (t <= mid_time + 1e-9))
        after = np.flatnonzero(in_new & (t >= mid_time - 1e-9))
        if len(before):
            starts[i] = t[before[-1]]
        if len(after):
            ends[i] = t[after[0]]
    events |= {"event_id": np.arange(len(order), dtype=np.int64), "start_time": starts, "end_time": ends}
    return {name: events[name] for name in LANE_CHANGE_COLUMNS}


def relate_to_ego(events: dict[str, np.ndarray], tracks: dict[str, dict[str, np.ndarray]],
                  lengths: dict[str, float], ego_lane: int | np.ndarray) -> dict[str, np.ndarray]:
    """Mark lane changes into the ego's lane and where they happened relative to the ego.
    `ego_lane`: the ego's lane, or per event the ego's lane at the change's midpoint.

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
        gaps[vids == EGO_ID] = np.nan  # the ego's own changes (a person drives it) have no gap to it
    return events | {"into_ego_lane": (events["to_lane"] == ego_lane) & (vids != EGO_ID),
                     "gap_to_ego_m": gaps, "ahead_of_ego": gaps > 0}
