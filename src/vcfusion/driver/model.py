"""The human driver model that stands in for the paper's participants (longitudinal only).

Every V2C tick (0.1 s) the driver:
1. **sees** the traffic it can see (``driver/perception.py``: forward field of view, the left
   mirror, occlusion by nearer vehicles; ground truth of those vehicles), and remembers it, so
   that car following can use a delayed view;
2. **notices cues** (each logged to ``driver_events``):
   - *lateral*: a seen neighbour ahead (within ``notice_range_m``) in an adjacent lane whose
     centre has moved ``lateral_notice_m`` toward the ego lane and is still moving toward it (not
     a car leaving the ego lane; the cue ends when the car is back at its lane centre, in the ego
     lane or further away, so its next move over is a new cue); response ``cutin_reaction_s``
     later (an unexpected event), or ``guidance_reaction_s`` later (an expected event, Green
     2000) when the driver was already attending to that vehicle: it is highlighted, or the
     driver *anticipates* its merge;
   - *anticipation* (every arm: a fair human baseline): a seen neighbour ahead in an adjacent
     lane with a seen stopped vehicle ahead of it in its own lane (the accident): the driver
     expects it to merge and attends to it; while such a vehicle is still in the adjacent lane,
     slower than the ego and nearer than the desired gap s0 + v T, the driver releases the
     throttle and covers the brake as for a warning (step 3);
   - *guidance* (when enabled): a warning item (level medium/high) of ``tick.guidance``; the
     driver responds to the vehicle it sees highlighted (:attr:`Guidance.shown_vehicle_id`: the
     vehicle inside the box, whichever twin the cloud meant). The warning is *active* while
     shown and for ``warning_hold_s`` after (hysteresis: a one-tick gap does not end it, and a
     one-tick warning ends before any response starts);
3. **responds to a warning** ``guidance_reaction_s`` after first seeing it, for as long as it
   stays active: releases the throttle and covers the brake (acceleration at most
   ``-cover_decel_mps2``); it brakes toward a gap (the vehicle becomes a prospective leader)
   only when the highlighted vehicle starts to move over (the lateral cue) or the gap to it
   closes (closing in and nearer than the driver's desired gap s0 + v T). The response ends with
   the warning;
4. **chooses leaders**: every seen vehicle whose centre is in the ego lane ahead, plus the
   prospective leaders: vehicles responded to after a lateral cue while still displaced toward
   the ego lane, and highlighted vehicles whose gap closes while their warning is active;
5. **computes the IDM acceleration** for each leader from the view ``follow_reaction_s`` ago,
   with the gap extrapolated over the delay at the then closing speed (the anticipation of the
   Human Driver Model; over the view's age in a trip's first ``follow_reaction_s``), and takes
   the smallest. A prospective leader not yet in the lane asks for up to the comfortable
   deceleration ``b``, or, once it moves into the path, for what stopping ``s0`` behind it needs;
6. **moves the pedal**: the applied acceleration follows the desired one with a first-order
   lag (``pedal_time_constant_s``), bounded by the car's acceleration and jerk limits.

With guidance enabled and no warning shown, every step is the unguided driver's (tested: the
ego trace is byte-identical).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from vcfusion.driver.idm import IDMParams, idm_acceleration
from vcfusion.driver.params import CarLimits, DriverParams
from vcfusion.driver.perception import DriverView, visible_vehicles
from vcfusion.guidance import GuidancePolicy
from vcfusion.traffic.network import Road

# A vehicle slower than this is "stopped" for the anticipation cue (the accident's trucks).
STOPPED_MPS = 0.5
# A neighbour whose centre is off its lane's centre toward the ego lane by more than this is still
# moving over (a prospective leader once responded to); back within it, its lateral cue has ended.
DISPLACED_M = 0.1


def stopping_decel(gap_m: float, closing_mps: float) -> float:
    """The constant deceleration (m/s^2) that ends a closing speed `closing_mps` within `gap_m`
    (v^2 / 2 s; 0 when not closing): what a prospective leader that moves into the ego's path asks
    for beyond the comfortable deceleration, so the driver never keeps closing on it at a rate it
    cannot stop from (curved.yaml seed 16: a truck sliding over from two lanes across, 19 m ahead
    at 11 m/s closing, needs 3.2 m/s^2; the comfortable b of 1.5-2.5 m/s^2 hit it)."""
    if closing_mps <= 0:
        return 0.0
    return closing_mps * closing_mps / (2.0 * max(gap_m, 0.1))


@dataclass
class _Seen:
    time: float
    ego_front: float
    ego_speed: float
    rear: dict  # vehicle id -> rear bumper s (seen vehicles only)
    speed: dict  # vehicle id -> speed


@dataclass
class _Warning:
    noticed: float  # first tick shown (of this episode)
    last_shown: float
    level: str
    lc_prob: float
    twin_id: str  # the twin the cloud meant (differs from the vehicle when the box is wrong)


class DriverModel:
    """Ego controller (see the module doc). `acceleration(tick)` is called every V2C tick; at the
    end of the run `finish` adds its tables (``driver``, ``driver_events``) and its summary."""

    finish_tables = ("driver", "driver_events")
    finish_summary = ("driver",)

    def __init__(self, params: DriverParams, road: Road, policy: GuidancePolicy, guidance_enabled: bool,
                 limits: CarLimits = CarLimits(), view: DriverView = DriverView()):
        self.p = params
        self.limits = limits
        self.road = road
        self.policy = policy
        self.view = view
        self.ego_id = policy.ego_id
        self.guidance_enabled = guidance_enabled
        # with guidance on it reads what the driver is shown; it sees the traffic either way
        self.needs = ("ego", "guidance") if guidance_enabled else ("ego",)
        self.idm = IDMParams(desired_speed_mps=params.desired_speed_mps, time_headway_s=params.time_headway_s,
                             min_gap_m=params.min_gap_m, max_accel_mps2=params.max_accel_mps2,
                             comfort_decel_mps2=params.comfort_decel_mps2, max_decel_mps2=limits.max_decel_mps2)
        self._memory: deque[_Seen] = deque(maxlen=64)
        self.applied = 0.0
        self._last_time: float | None = None
        self.visual_response: dict[str, float] = {}  # vid -> time the driver responds (lateral cue)
        self._lateral_before: dict[str, float] = {}  # vid -> distance from the ego lane's centre, last tick
        # vid -> distance from the ego lane's centre where its present move toward the ego lane began
        # (where it was first seen, or last stood still or moved away)
        self._lateral_start: dict[str, float] = {}
        self._toward: set[str] = set()  # seen vehicles moving toward the ego lane at this tick
        self.anticipated: set[str] = set()  # vehicles the driver expects to merge
        self.warnings: dict[str, _Warning] = {}  # active warnings by the vehicle seen highlighted
        self.events: list[dict] = []
        self.log_rows: list[dict] = []

    def summary(self) -> dict:
        """The trip's driver draw, for the run summary."""
        return self.p.to_dict() | {"guidance_enabled": self.guidance_enabled}

    def finish(self, tables, summary: dict) -> None:
        tables.update(self.tables())
        summary["driver"] = self.summary()

    def tables(self) -> dict:
        """Run-folder tables: the driver's per-tick decisions and the cues it noticed."""
        import pandas as pd

        events = pd.DataFrame(self.events, columns=["time", "vehicle_id", "cue", "twin_id", "level", "lc_prob",
                                                    "response_time"])
        rows = self.log_rows  # one dict per tick: built column by column (cheaper than from records)
        log = pd.DataFrame({k: [r[k] for r in rows] for k in rows[0]}) if rows else pd.DataFrame()
        return {"driver": log, "driver_events": events}

    # -- perception -------------------------------------------------------------------
    def _see(self, tick):
        truth = tick.truth
        i = truth.index_of(self.ego_id)
        s, d = truth.road_frame(self.road)
        seen_mask = visible_vehicles(s, d, truth.length, truth.width, truth.height, i, self.policy, self.view)
        ego_front = float(s[i] + truth.length[i] / 2)
        idx = seen_mask.nonzero()[0]  # an index array: each selection below converts no list
        ids = [truth.ids[k] for k in idx.tolist()]
        d_seen = d[idx]
        # plain dicts of plain floats, seen vehicles only (the loops below run over ~10 vehicles)
        rear = dict(zip(ids, (s[idx] - truth.length[idx] / 2).tolist()))
        speed = dict(zip(ids, truth.speed[idx].tolist()))
        lateral = dict(zip(ids, self.policy.lateral_m(d_seen).tolist()))
        lane = dict(zip(ids, np.rint((d_seen - self.policy.ego_lane_centre_d) / self.policy.lane_width_m).tolist()))
        seen = _Seen(tick.time, ego_front, float(truth.speed[i]), rear, speed)
        self._memory.append(seen)
        return seen, lateral, lane

    def _delayed(self, now: float) -> _Seen:
        """The newest memory at least follow_reaction_s old (the oldest if none is)."""
        target = now - self.p.follow_reaction_s + 1e-6
        for m in reversed(self._memory):  # time order: the newest old-enough one is near the end
            if m.time <= target:
                return m
        return self._memory[0]

    def _event(self, time, vid, cue, response_time, twin_id="", level="", lc_prob=math.nan):
        self.events.append({"time": time, "vehicle_id": vid, "cue": cue, "twin_id": twin_id, "level": level,
                            "lc_prob": lc_prob, "response_time": response_time})

    def _update_warnings(self, now: float, items) -> None:
        """Warnings by the vehicle seen highlighted, with the hold (hysteresis) of the module doc."""
        for item in items:
            vid = item.shown_vehicle_id
            if vid is None or vid == self.ego_id:  # a box around no vehicle highlights nothing
                continue
            w = self.warnings.get(vid)
            if w is None:
                self.warnings[vid] = _Warning(now, now, item.level, float(item.lc_prob), item.vehicle_id)
                self._event(now, vid, "guidance", now + self.p.guidance_reaction_s, item.vehicle_id, item.level,
                            float(item.lc_prob))
            else:
                w.last_shown = now
        for vid in [v for v, w in self.warnings.items() if now - w.last_shown > self.p.warning_hold_s + 1e-9]:
            del self.warnings[vid]  # the warning has ended, and with it the response

    def _notice(self, now: float, seen: _Seen, lateral: dict, lane: dict) -> None:
        policy, w = self.policy, self.policy.lane_width_m
        # a list in the tick's vehicle order (a set's order would follow the process's string hashing,
        # and the events table must be the same in every process)
        ahead = [vid for vid in lateral if policy.ahead(seen.rear[vid], seen.ego_front, self.p.notice_range_m)]
        # anticipation: a moving neighbour with a stopped vehicle ahead of it in its own lane
        stopped = [(lane[v], seen.rear[v]) for v in lateral if seen.speed[v] < STOPPED_MPS and lane[v] != 0]
        for vid in ahead:
            if vid in self.anticipated or not policy.in_adjacent_lane(lateral[vid]) or seen.speed[vid] < STOPPED_MPS:
                continue
            if any(ln == lane[vid] and rear > seen.rear[vid] for ln, rear in stopped):
                self.anticipated.add(vid)
                self._event(now, vid, "anticipation", math.nan)
        # where each seen vehicle's move toward the ego lane began, and which move toward it now
        start, self._toward = {}, set()
        for vid, lat in lateral.items():
            toward = lat < self._lateral_before.get(vid, -math.inf)
            start[vid] = self._lateral_start.get(vid, lat) if toward else lat
            if toward:
                self._toward.add(vid)
        self._lateral_start = start
        # a lateral cue ends once its vehicle is back at its lane centre (an aborted move), in the
        # ego lane (a leader now) or beyond the adjacent lane, and not moving toward the ego lane
        # (crossing the adjacent lane from the next one over): its next move over is a new cue
        for vid in [v for v, due in self.visual_response.items() if due <= now and v in lateral
                    and not (policy.in_adjacent_lane(lateral[v])
                             and (lateral[v] < w - DISPLACED_M or v in self._toward))]:
            del self.visual_response[vid]
        for vid in ahead:
            if vid in self.visual_response:
                continue
            # an adjacent-lane neighbour that has moved toward the ego lane by the noticed amount (from
            # its lane's centre, or from where its move began: a vehicle crossing the adjacent lane
            # from the next one over) and is still moving toward it (a car leaving the ego lane
            # crosses the same band moving away)
            toward = vid in self._toward
            moved = lateral[vid] <= w - self.p.lateral_notice_m or start[vid] - lateral[vid] >= self.p.lateral_notice_m
            if toward and policy.in_adjacent_lane(lateral[vid]) and moved:
                expected = vid in self.anticipated or vid in self.warnings
                delay = self.p.guidance_reaction_s if expected else self.p.cutin_reaction_s
                self.visual_response[vid] = now + delay
                self._event(now, vid, "lateral", now + delay)
        self._lateral_before = lateral

    # -- control ----------------------------------------------------------------------
    def acceleration(self, tick) -> float:
        now = tick.time
        seen, lateral, lane = self._see(tick)
        # the warnings shown at this tick (none reach a driver who does not use the guidance)
        shown = tick.guidance.items if self.guidance_enabled and tick.guidance is not None else ()
        self._update_warnings(now, [g for g in shown if self.policy.warns(g.level)])
        self._notice(now, seen, lateral, lane)
        policy, w = self.policy, self.policy.lane_width_m
        past = self._delayed(now)
        ego_speed = seen.ego_speed
        desired = idm_acceleration(self.idm, ego_speed)  # free road
        leader, kind, leader_gap = "", "", math.nan
        # responding to a warning: throttle released, foot over the brake
        responding = {vid for vid, wr in self.warnings.items() if now + 1e-9 >= wr.noticed + self.p.guidance_reaction_s}
        # neighbours in an adjacent lane ahead, nearer than the desired gap and slower: the gap to them closes
        desired_gap = self.idm.min_gap_m + ego_speed * self.idm.time_headway_s
        closing = {vid for vid, dist in lateral.items() if policy.in_adjacent_lane(dist)
                   and 0.0 < seen.rear[vid] - seen.ego_front < desired_gap and seen.speed[vid] < ego_speed}
        # a merge it expects close ahead (an anticipated neighbour the gap to which closes) makes it
        # cover the brake as a warning does (curved.yaml seed 1011: a queued car 10 m ahead started
        # into the ego's lane while the ego sped up from 4 to 5.4 m/s past it, and the lateral cue
        # came too late to stop)
        cover = bool(responding) or not closing.isdisjoint(self.anticipated)
        if cover and -self.p.cover_decel_mps2 < desired:
            desired, kind = -self.p.cover_decel_mps2, "cover"
        for vid, dist in lateral.items():
            if seen.rear[vid] <= seen.ego_front:
                continue
            in_lane = policy.in_ego_lane(dist)
            gap_now = seen.rear[vid] - seen.ego_front
            # prospective: responded to after it moved over (still displaced toward the lane or
            # still moving toward it), or highlighted, responded to, and the gap to it closes
            moved_over = (self.visual_response.get(vid, math.inf) <= now
                          and (dist < w - DISPLACED_M or (vid in self._toward and policy.in_adjacent_lane(dist))))
            gap_closes = vid in responding and vid in closing
            prospective = not in_lane and (moved_over or gap_closes)
            if not (in_lane or prospective):
                continue
            if vid in past.rear:
                dv = past.ego_speed - past.speed[vid]
                # over the delay, or over the view's age where the trip is younger than the delay
                gap = past.rear[vid] - past.ego_front - min(self.p.follow_reaction_s, now - past.time) * dv
                v_lead = past.speed[vid]
            else:  # not seen as long ago as the delay: the first look
                gap, v_lead = gap_now, seen.speed[vid]
            acc = idm_acceleration(self.idm, ego_speed, max(gap, 0.1), v_lead)
            if prospective:
                # b at most; for a vehicle moving into the path, what stopping s0 behind it needs
                # where that is more (a stop planned at its rear ends past it with the pedal lag:
                # curved.yaml seed 1038); a highlighted vehicle that only stands close by asks for b
                need = stopping_decel(gap - self.idm.min_gap_m, ego_speed - v_lead) if moved_over else 0.0
                acc = max(acc, -max(self.p.comfort_decel_mps2, need))
            if acc < desired:
                desired, leader, kind, leader_gap = acc, vid, "lane" if in_lane else "prospective", gap
        desired = min(max(float(desired), -self.limits.max_decel_mps2), self.limits.max_accel_mps2)
        dt = now - self._last_time if self._last_time is not None else 0.0
        self._last_time = now
        if dt > 0:
            step = (desired - self.applied) * min(1.0, dt / self.p.pedal_time_constant_s)
            # Releasing the brake is as quick as pressing it; the throttle side is slower.
            rise = self.limits.max_throttle_jerk_mps3 if self.applied >= 0 else self.limits.max_brake_jerk_mps3
            step = min(max(step, -self.limits.max_brake_jerk_mps3 * dt), rise * dt)
            self.applied += step
        self.log_rows.append({"time": round(now, 6), "leader_id": leader, "leader_kind": kind,
                              "perceived_gap_m": leader_gap, "desired_accel": desired,
                              "applied_accel": self.applied, "guidance_enabled": self.guidance_enabled,
                              "guidance_shown": len(shown), "warnings_active": len(self.warnings),
                              "covering": cover, "vehicles_seen": len(lateral)})
        return self.applied
