"""The human driver model that stands in for the paper's participants (longitudinal only).

Every V2C tick (0.1 s) the driver:
1. **sees** the traffic (ground truth ``tick.truth`` stands for what the driver sees through
   the windscreen), and remembers it, so that car following can use a delayed view;
2. **notices cut-ins**. Without guidance, a neighbour ahead (within ``notice_range_m``) in an
   adjacent lane is noticed when its centre has moved ``lateral_notice_m`` from its lane centre
   toward the ego lane; the driver responds ``cutin_reaction_s`` later (an unexpected event).
   With guidance (when enabled for this trip), a warning item (level medium/high) of
   ``tick.guidance`` for a vehicle ahead in an adjacent lane is noticed when first shown, and the
   driver responds ``guidance_reaction_s`` later (an expected event). The earliest response wins;
   the visual cue works in both arms. "Ahead", "adjacent lane", the warning levels and the ego's
   id are the run's :class:`~vcfusion.guidance.GuidancePolicy`;
3. **chooses leaders**: every vehicle whose centre is in the ego lane ahead, plus every
   vehicle it has responded to as a prospective leader while that vehicle is still ahead
   displaced toward the ego lane (or, for guidance, while its warning is still shown);
4. **computes the IDM acceleration** for each leader from the view ``follow_reaction_s`` ago,
   with the gap extrapolated over the delay at the then closing speed (the anticipation of the
   Human Driver Model), and takes the smallest. A prospective leader not yet in the lane only
   asks for up to the comfortable deceleration ``b`` (the driver opens the gap smoothly; he
   does not emergency-brake for a car that is still in its own lane); the free-road term
   applies as usual;
5. **moves the pedal**: the applied acceleration follows the desired one with a first-order
   lag (``pedal_time_constant_s``), bounded by the car's acceleration and jerk limits.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from vcfusion.driver.idm import IDMParams, idm_acceleration
from vcfusion.driver.params import CarLimits, DriverParams
from vcfusion.guidance import GuidancePolicy
from vcfusion.traffic.network import Road


@dataclass
class _Seen:
    time: float
    ego_front: float
    ego_speed: float
    rear: dict  # vehicle id -> rear bumper s
    speed: dict  # vehicle id -> speed


class DriverModel:
    """Ego controller (see the module doc). `acceleration(tick)` is called every V2C tick; at the
    end of the run `finish` adds its tables (``driver``, ``driver_events``) and its summary."""

    finish_tables = ("driver", "driver_events")
    finish_summary = ("driver",)

    def __init__(self, params: DriverParams, road: Road, policy: GuidancePolicy, guidance_enabled: bool,
                 limits: CarLimits = CarLimits()):
        self.p = params
        self.limits = limits
        self.road = road
        self.policy = policy
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
        self.guidance_response: dict[str, float] = {}  # vid -> time the driver responds (AR cue)
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

        events = pd.DataFrame(self.events, columns=["time", "vehicle_id", "cue", "level", "lc_prob", "response_time"])
        rows = self.log_rows  # one dict per tick: built column by column (cheaper than from records)
        log = pd.DataFrame({k: [r[k] for r in rows] for k in rows[0]}) if rows else pd.DataFrame()
        return {"driver": log, "driver_events": events}

    # -- perception -------------------------------------------------------------------
    def _see(self, tick):
        truth = tick.truth
        i = truth.index_of(self.ego_id)
        s, d = truth.road_frame(self.road)
        ego_front = float(s[i] + truth.length[i] / 2)
        # plain dicts of plain floats, everyone but the ego (the loops below run over ~10 vehicles)
        rear = dict(zip(truth.ids, (s - truth.length / 2).tolist()))
        speed = dict(zip(truth.ids, truth.speed.tolist()))
        lateral = dict(zip(truth.ids, self.policy.lateral_m(d).tolist()))
        for others in (rear, speed, lateral):
            del others[self.ego_id]
        seen = _Seen(tick.time, ego_front, float(truth.speed[i]), rear, speed)
        self._memory.append(seen)
        return seen, lateral

    def _delayed(self, now: float) -> _Seen:
        """The newest memory at least follow_reaction_s old (the oldest if none is)."""
        target = now - self.p.follow_reaction_s + 1e-6
        for m in reversed(self._memory):  # time order: the newest old-enough one is near the end
            if m.time <= target:
                return m
        return self._memory[0]

    def _notice(self, tick, seen: _Seen, lateral: dict, shown: list) -> None:
        policy, w = self.policy, self.policy.lane_width_m
        for vid, dist in lateral.items():
            if vid in self.visual_response or not policy.ahead(seen.rear[vid], seen.ego_front, self.p.notice_range_m):
                continue
            # An adjacent-lane neighbour that has moved toward the ego lane by the noticed amount.
            if policy.in_adjacent_lane(dist) and dist <= w - self.p.lateral_notice_m:
                self.visual_response[vid] = tick.time + self.p.cutin_reaction_s
                self.events.append({"time": tick.time, "vehicle_id": vid, "cue": "lateral",
                                    "response_time": self.visual_response[vid]})
        for item in shown:
            vid = item.vehicle_id
            if vid in self.guidance_response or vid not in lateral:
                continue
            if (policy.ahead(seen.rear[vid], seen.ego_front, self.p.notice_range_m)
                    and policy.in_adjacent_lane(lateral[vid])):
                self.guidance_response[vid] = tick.time + self.p.guidance_reaction_s
                self.events.append({"time": tick.time, "vehicle_id": vid, "cue": "guidance",
                                    "level": item.level, "lc_prob": float(item.lc_prob),
                                    "response_time": self.guidance_response[vid]})

    # -- control ----------------------------------------------------------------------
    def acceleration(self, tick) -> float:
        now = tick.time
        seen, lateral = self._see(tick)
        # the warnings shown at this tick (none reach a driver who does not use the guidance)
        shown_items = tick.guidance.items if self.guidance_enabled and tick.guidance is not None else ()
        warnings = [g for g in shown_items if self.policy.warns(g.level)]
        self._notice(tick, seen, lateral, warnings)
        policy, w = self.policy, self.policy.lane_width_m
        shown = {g.vehicle_id for g in warnings}
        past = self._delayed(now)
        ego_speed = seen.ego_speed
        desired = idm_acceleration(self.idm, ego_speed)  # free road
        leader, kind, leader_gap = "", "", math.nan
        for vid, dist in lateral.items():
            if seen.rear[vid] <= seen.ego_front:
                continue
            in_lane = policy.in_ego_lane(dist)
            responded = min(self.visual_response.get(vid, math.inf), self.guidance_response.get(vid, math.inf))
            # Responded to, not yet in the lane, and still a candidate: an adjacent-lane car that
            # is still displaced toward the ego lane, or whose warning is still shown.
            prospective = (not in_lane and responded <= now
                           and ((vid in shown and policy.in_adjacent_lane(dist)) or dist < w - 0.1))
            if not (in_lane or prospective):
                continue
            if vid in past.rear:
                dv = past.ego_speed - past.speed[vid]
                gap = past.rear[vid] - past.ego_front - self.p.follow_reaction_s * dv
                v_lead = past.speed[vid]
            else:  # not seen as long ago as the delay: the first look
                gap, v_lead = seen.rear[vid] - seen.ego_front, seen.speed[vid]
            acc = idm_acceleration(self.idm, ego_speed, max(gap, 0.1), v_lead)
            if prospective:
                acc = max(acc, -self.p.comfort_decel_mps2)
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
                              "guidance_shown": len(shown)})
        return self.applied
