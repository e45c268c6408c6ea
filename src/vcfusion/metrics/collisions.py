"""A record of every ego collision of a run: who, where, how fast, and what the driver saw, was
shown and did in the seconds before (the run summary's ``ego_collisions``; the guidance study
lists them per trip and arm).

One record per pair in contact with the ego (SUMO's first report of the contact):
- ``time``, ``other`` (the other vehicle), ``ego_role`` (``collider``: the ego ran into it;
  ``victim``: it ran into the ego), SUMO's ``kind``, ``lane`` and ``pos``;
- ``ego_speed_mps`` / ``other_speed_mps`` at the contact and ``closing_speed_mps`` (the
  collider's speed minus the victim's); ``ego_d_m`` / ``other_d_m`` (road-frame lateral
  positions) and ``body_clearance_m``, the distance between the two footprints (rectangles of
  their length and width at their position and heading) at SUMO's first report of the contact
  (> 0: the bodies did not touch: SUMO counts a vehicle in its target lane from the start of a lane
  change and compares positions along the lane, whatever the bodies' headings; < 0: they overlap
  by that much), and ``least_body_clearance_m``, the least of it until SUMO's last report of the
  contact (the bodies can meet after SUMO has counted the contact);
- ``other_lane_changes``: the other vehicle's lane changes in the window (start, mid, from lane,
  to lane, into the ego lane);
- ``driver``: the driver model's state in the window (one sample per ``sample_s``: its leader and
  the leader's kind, the perceived gap, the desired and applied acceleration, whether it covers
  the brake, active warnings, vehicles seen); ``driver_cues``: the cues it noticed about the
  other vehicle (lateral, anticipation, guidance) and when it responds; ``other_was_leader_s``:
  the first time in the window the other vehicle was its leader (None: never);
- ``shown``: the warnings guidance made in the window (twin, vehicle highlighted, level, first
  and last time; the driver saw them only when ``guidance_on``), and ``other_highlighted`` /
  ``other_warned_twin``: whether the other vehicle was highlighted, whether the cloud warned
  about its twin.

Ground truth throughout: this is the scoring side, nothing here reaches the driver.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from vcfusion.records import EGO_ID

WINDOW_S = 5.0  # how far before the contact the record looks (s)
SAMPLE_S = 0.5  # the driver's state every this many seconds in the window


def _f(x) -> float | None:
    x = float(x)
    return None if math.isnan(x) else round(x, 3)


def _window(table: pd.DataFrame | None, t0: float, t1: float) -> pd.DataFrame:
    if table is None or not len(table) or "time" not in table:
        return pd.DataFrame()
    return table[(table["time"] >= t0 - 1e-9) & (table["time"] <= t1 + 1e-9)]


# corners of a footprint in order around it, as fractions of length and width (for body_points)
_FOOTPRINT = (np.array([0.5, -0.5, -0.5, 0.5]), np.array([0.5, 0.5, -0.5, -0.5]), np.zeros(4))


def footprints(x, y, heading, length, width) -> np.ndarray:
    """(N, 4, 2) corners, in order around each, of N vehicles' footprints: `length` x `width`
    rectangles centred on (`x`, `y`), the long side along `heading` (rad, counter-clockwise from +x;
    records.py)."""
    from vcfusion.fusion.matching import body_points

    n = len(np.atleast_1d(x))
    return body_points(np.atleast_1d(x), np.atleast_1d(y), np.zeros(n), np.atleast_1d(heading),
                       np.atleast_1d(length), np.atleast_1d(width), np.zeros(n), *_FOOTPRINT)[..., :2]


def _point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    k = min(max(float(np.dot(p - a, ab)) / max(float(np.dot(ab, ab)), 1e-12), 0.0), 1.0)
    return float(np.hypot(*(a + k * ab - p)))


def footprint_clearance(a: np.ndarray, b: np.ndarray) -> float:
    """Distance (m) between two convex footprints given by their corners in order (:func:`footprints`):
    the least corner-to-side distance where they are apart, minus the least overlap along the
    footprints' side normals (separating axes) where they overlap."""
    overlap = math.inf
    for poly in (a, b):
        for k in range(len(poly)):
            side = poly[(k + 1) % len(poly)] - poly[k]
            axis = np.array([-side[1], side[0]]) / max(float(np.hypot(*side)), 1e-12)
            pa, pb = a @ axis, b @ axis
            gap = max(pb.min() - pa.max(), pa.min() - pb.max())
            if gap > 0:  # a separating axis: apart; the nearest points are a corner and a side
                return min(_point_segment(p, q[m], q[(m + 1) % len(q)])
                           for pts, q in ((a, b), (b, a)) for p in pts for m in range(len(q)))
            overlap = min(overlap, -gap)
    return -overlap


def _body_geometry(tables, t: float, t_end: float, other: str) -> dict:
    """Lateral positions (road frame d) of the ego and the other vehicle and the distance between
    their footprints (:func:`footprint_clearance`; m, < 0: the bodies overlap) at the trajectory
    sample nearest `t`, and the least such distance over the samples from there to `t_end` (SUMO's
    last report of the contact)."""
    traj, veh = tables.get("trajectories"), tables.get("vehicles")
    none = {"ego_d_m": None, "other_d_m": None, "body_clearance_m": None, "least_body_clearance_m": None}
    if traj is None or veh is None or not len(traj):
        return none
    size = veh.set_index("vehicle_id")[["length", "width"]]
    if EGO_ID not in size.index or other not in size.index:
        return none
    # the samples holding both vehicles, one row each: the ego's columns, then the other's
    pair = [traj.loc[traj["vehicle_id"] == v, ["time", "x", "y", "heading", "d"]] for v in (EGO_ID, other)]
    both = pair[0].merge(pair[1], on="time", suffixes=("_ego", "_other")).sort_values("time")
    if not len(both):
        return none
    first = both["time"].to_numpy()[np.abs(both["time"].to_numpy() - t).argmin()]
    span = both[(both["time"] >= first) & (both["time"] <= max(first, t_end) + 1e-9)]
    ego, them = (footprints(span[f"x_{k}"].to_numpy(), span[f"y_{k}"].to_numpy(), span[f"heading_{k}"].to_numpy(),
                            np.full(len(span), size.loc[v, "length"]), np.full(len(span), size.loc[v, "width"]))
                 for k, v in (("ego", EGO_ID), ("other", other)))
    clearances = [footprint_clearance(a, b) for a, b in zip(ego, them)]
    return {"ego_d_m": _f(span["d_ego"].iloc[0]), "other_d_m": _f(span["d_other"].iloc[0]),
            "body_clearance_m": _f(clearances[0]), "least_body_clearance_m": _f(min(clearances))}


def ego_collision_records(tables, window_s: float = WINDOW_S, sample_s: float = SAMPLE_S) -> list[dict]:
    """The records of the ego's collisions in a run's `tables` (see the module doc)."""
    from vcfusion.guidance import WARNING_LEVELS

    col = tables.get("collisions") if hasattr(tables, "get") else None
    if col is None or not len(col):
        return []
    mine = col[(col["collider"] == EGO_ID) | (col["victim"] == EGO_ID)].sort_values("time")
    mine = mine.drop_duplicates(["collider", "victim"], keep="first")
    records = []
    for c in mine.itertuples(index=False):
        t, t0 = float(c.time), float(c.time) - window_s
        ego_collider = c.collider == EGO_ID
        other = str(c.victim if ego_collider else c.collider)
        rec = {"time": round(t, 3), "other": other, "ego_role": "collider" if ego_collider else "victim",
               "kind": str(c.kind), "lane": str(c.lane), "pos": _f(c.pos),
               "ego_speed_mps": _f(c.collider_speed if ego_collider else c.victim_speed),
               "other_speed_mps": _f(c.victim_speed if ego_collider else c.collider_speed),
               "closing_speed_mps": _f(float(c.collider_speed) - float(c.victim_speed))}
        rec.update(_body_geometry(tables, t, float(c.end_time), other))
        lc = tables.get("lane_changes")
        if lc is not None and len(lc):
            theirs = lc[(lc["vehicle_id"] == other) & (lc["end_time"] >= t0) & (lc["start_time"] <= t)]
            rec["other_lane_changes"] = [
                {"start": _f(r.start_time), "mid": _f(r.mid_time), "from_lane": int(r.from_lane),
                 "to_lane": int(r.to_lane), "into_ego_lane": bool(getattr(r, "into_ego_lane", False))}
                for r in theirs.itertuples(index=False)]
        else:
            rec["other_lane_changes"] = []
        drv = _window(tables.get("driver"), t0, t)
        if len(drv):
            picks = drv.iloc[np.unique(np.searchsorted(drv["time"].to_numpy(), np.arange(t0, t + 1e-9, sample_s)).clip(
                0, len(drv) - 1))]
            rec["driver"] = [{"time": _f(r.time), "leader": r.leader_id, "leader_kind": r.leader_kind,
                              "perceived_gap_m": _f(r.perceived_gap_m), "desired_accel": _f(r.desired_accel),
                              "applied_accel": _f(r.applied_accel), "covering": bool(r.covering),
                              "warnings_active": int(r.warnings_active), "vehicles_seen": int(r.vehicles_seen)}
                             for r in picks.itertuples(index=False)]
            led = drv[drv["leader_id"] == other]
            rec["other_was_leader_s"] = _f(led["time"].iloc[0]) if len(led) else None
        else:  # a person drove (no driver model)
            rec["driver"], rec["other_was_leader_s"] = [], None
        ev = _window(tables.get("driver_events"), t0, t)
        rec["driver_cues"] = [] if not len(ev) else [
            {"time": _f(r.time), "cue": r.cue, "twin": r.twin_id, "level": r.level, "response_time": _f(r.response_time)}
            for r in ev[ev["vehicle_id"] == other].itertuples(index=False)]
        shown = _window(tables.get("guidance"), t0, t)
        shown = shown[shown["level"].isin(WARNING_LEVELS)] if len(shown) else shown
        rec["shown"] = [] if not len(shown) else [
            {"twin": twin, "highlighted": box, "level": "high" if (g["level"] == "high").any() else "medium",
             "first": _f(g["time"].min()), "last": _f(g["time"].max())}
            for (twin, box), g in shown.groupby(["vehicle_id", "box_vehicle_id"], sort=True)]
        # the guidance log records what guidance made in every arm; the driver saw it only with guidance on
        rec["guidance_on"] = bool(drv["guidance_enabled"].iloc[0]) if "guidance_enabled" in drv else None
        rec["other_highlighted"] = any(s["highlighted"] == other for s in rec["shown"])
        rec["other_warned_twin"] = any(s["twin"] == other for s in rec["shown"])
        records.append(rec)
    return records


def describe(rec: dict) -> str:
    """One line of a record, for a study's table and the run's summary text."""
    who = (f"ego ran into {rec['other']}" if rec["ego_role"] == "collider" else f"{rec['other']} ran into the ego")
    into = [c for c in rec.get("other_lane_changes", []) if c["into_ego_lane"]]
    cut = f", {rec['other']} cut in (mid {into[0]['mid']:.1f} s)" if into else ""
    shown = ("; it was highlighted" if rec["other_highlighted"] else
             "; its twin was warned about but another vehicle highlighted" if rec["other_warned_twin"] else
             "; not highlighted")
    if rec.get("guidance_on") is False:
        shown = "; guidance off" + (" (the cloud warned about it)" if rec["other_warned_twin"] else "")
    leader = (f"; the driver's leader from {rec['other_was_leader_s']:.1f} s" if rec.get("other_was_leader_s") is not None
              else "; never the driver's leader")
    gap, least = rec.get("body_clearance_m"), rec.get("least_body_clearance_m")
    side = (f"; no body contact: {gap:.2f} m between their bodies (SUMO counts a lane change's target lane from "
            f"its start and positions along the lane whatever the headings)" if gap is not None and gap > 0 else "")
    if side and least is not None and least < 0:
        side += f"; the bodies met before SUMO's last report of it ({-least:.2f} m overlap)"
    return (f"{rec['time']:.1f} s: {who} at {rec['closing_speed_mps']:.1f} m/s closing (ego {rec['ego_speed_mps']:.1f} m/s)"
            f"{side}{cut}{shown}{leader}")
