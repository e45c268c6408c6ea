"""The libsumo session: start SUMO, place vehicles, step, read states, drive the ego.

This module is the only place that talks to SUMO. It converts SUMO's conventions once:
SUMO's position is the front-bumper centre and its angle is degrees clockwise from north;
records carry the footprint centre and a yaw in radians counter-clockwise from +x.

libsumo holds one simulation per process and is not thread-safe: parallel runs are processes.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from itertools import chain
from pathlib import Path
from typing import Callable

import libsumo
import numpy as np
from libsumo import _libsumo
from traci import constants as tc

from vcfusion.records import EGO_ID, VehicleStates
from vcfusion.scenario import Scenario
from vcfusion.traffic.network import (Road, accident_s, closed_lanes, read_road, read_vehicle_types, sumo_lane_id,
                                      sumo_place)
from vcfusion.traffic.roadframe import RoadFrame

# A stop longer than any run: the accident vehicles never leave.
ACCIDENT_STOP_S = 1.0e6
# How far ahead SUMO looks for the ego's leader (m): the ego table's leader columns see no farther.
LEADER_HORIZON_M = 250.0
# the TraCI variables of the ego's subscription (ids from SUMO's TraCI constants)
_LANE_POSITION, _SPEED, _ACCELERATION, _LEADER, _LANE_ID = (tc.VAR_LANEPOSITION, tc.VAR_SPEED, tc.VAR_ACCELERATION,
                                                             tc.VAR_LEADER, tc.VAR_LANE_ID)
_EGO_VARS = (_LANE_POSITION, _SPEED, _ACCELERATION, _LEADER)
# libsumo's compiled functions, called without the Python wrapper each of them has in libsumo.py
# (a function frame per call; the calls below run every step or for every vehicle every tick)
_ego_results = _libsumo.vehicle_getSubscriptionResults
_set_speed = _libsumo.vehicle_setSpeed
_getters = (_libsumo.vehicle_getIDList, _libsumo.vehicle_getPosition3D, _libsumo.vehicle_getAngle,
            _libsumo.vehicle_getSpeed, _libsumo.vehicle_getAcceleration, _libsumo.vehicle_getLaneIndex,
            _libsumo.vehicle_getLateralLanePosition, _libsumo.vehicle_getLaneID)


class RunError(RuntimeError):
    """A run that cannot proceed for this seed (e.g. an impossible departure)."""


LANE_END_NOTE_M = 500.0  # a refused departure this close to the end of its lane may be refused for it


@dataclass(frozen=True)
class Collision:
    """One contact of a pair: SUMO's record of it at its first step (while a contact lasts SUMO
    reports that same record every step: speeds, lane and position at the impact), and the last
    step the pair was still in contact."""

    time: float
    collider: str
    victim: str
    kind: str
    collider_speed: float
    victim_speed: float
    lane: str
    pos: float
    end_time: float


@dataclass(frozen=True)
class Placement:
    vehicle_id: str
    group: str
    vtype: str
    lane: int  # track of its route (index from the right)
    pos_m: float  # front bumper, along its route
    speed_mps: float
    desired_speed_mps: float | None
    depart_s: float = 0.0
    # where SUMO inserts it: the route's edges from the insertion edge on, the lane index and the
    # lane position there (on a single edge: the route, the lane and pos_m)
    edges: tuple[str, ...] = ()
    sumo_lane: int = 0
    sumo_pos_m: float = 0.0


def sumo_angle_to_yaw(angle_deg: np.ndarray) -> np.ndarray:
    """SUMO angle (deg clockwise from north) to yaw (rad counter-clockwise from +x)."""
    return np.radians(90.0 - np.asarray(angle_deg, dtype=float))


def frame_of(scenario: Scenario, road: RoadFrame, route: list[str] | None) -> RoadFrame:
    """The frame of an item's own route (the scenario's when it names none)."""
    if route is None or tuple(route) == road.route:
        return road
    return read_road(scenario.network, route)


# metres to spare, beyond the stopping distance, between a vehicle's departure and the end of its lane
STOP_MARGIN_M = 5.0


def lane_slot(road: RoadFrame, place: tuple[tuple[str, ...], int, float]) -> tuple[tuple, float]:
    """(lane key, front position) of a SUMO placement (edges, lane index, lane position): a track of
    the scenario's route with the position along it (so vehicles on other routes through the same
    lane compare), or a SUMO lane off that route with its lane position."""
    edges, _, pos = place
    lane_id = sumo_lane_id(place)
    track = road.track_of.get(lane_id)
    if track is None:
        return ("lane", lane_id), pos
    return ("track", track), road.edge_start_s[edges[0]] + pos


def vtype_length(vtypes: dict, vtype: str) -> float:
    return float(vtypes[vtype].get("length", 5.0))  # SUMO's default


def fixed_vehicles(scenario: Scenario, road: RoadFrame) -> list[tuple[str, str, str, tuple, float]]:
    """The vehicles whose place the scenario fixes, before any drawn: (id, what it is in the scenario,
    vType, SUMO placement, departure speed) of the parked accident vehicles and the ego."""
    out = []
    if scenario.accident is not None:
        acc = scenario.accident
        s = accident_s(acc, road)
        out += [(f"accident{i}", "accident", acc.vtype, sumo_place(road, lane, s), 0.0)
                for i, lane in enumerate(acc.lanes)]
    if scenario.ego is not None:
        ego = scenario.ego
        out.append((EGO_ID, "ego", ego.vtype, sumo_place(frame_of(scenario, road, ego.route), ego.lane,
                                                          ego.depart_pos_m), ego.speed_mps))
    return out


def plan_placements(scenario: Scenario, road: RoadFrame, vtypes: dict, rng: np.random.Generator) -> list[Placement]:
    """Draw the initial vehicles and flow arrivals of one seed. A draw of a lane absent at the
    drawn position (an acceleration lane, a lane drop) is drawn again, like one too close to
    another vehicle."""
    placements: list[Placement] = []
    # lane -> [(rear, front)]: a track of the scenario's route with positions along it (so spacing
    # holds across its edges, whatever route a vehicle follows), or a SUMO lane off that route with
    # lane positions
    occupied: dict[tuple, list[tuple[float, float]]] = {}

    def free(place, length: float, spacing: float) -> bool:
        lane, front = lane_slot(road, place)
        return all(front + spacing <= rear or front - length - spacing >= other_front
                   for rear, other_front in occupied.get(lane, []))

    def occupy(place, length: float) -> None:
        lane, front = lane_slot(road, place)
        occupied.setdefault(lane, []).append((front - length, front))

    for _, _, vtype, place, _ in fixed_vehicles(scenario, road):
        occupy(place, vtype_length(vtypes, vtype))

    for group in scenario.vehicles:
        length = vtype_length(vtypes, group.vtype)
        frame = frame_of(scenario, road, group.route)
        # a lane closed to the group's class (a shoulder, a bus lane) is drawn again too
        closed = closed_lanes(scenario.network, vtypes[group.vtype].get("vClass", "passenger"))
        # SUMO refuses a departure on a lane that ends (an acceleration lane, a lane drop) closer
        # than the vehicle can stop from its departure speed: such a draw is drawn again
        stopping_m = group.speed_mps ** 2 / (2.0 * float(vtypes[group.vtype].get("decel", 4.5))) + STOP_MARGIN_M
        for k in range(group.count):
            for _attempt in range(200):
                lane = int(rng.choice(group.lanes))
                front = float(rng.uniform(*group.pos_m))
                place = sumo_place(frame, lane, front)
                if (place is not None and free(place, length, group.min_spacing_m)
                        and not frame.lane_end_ahead(lane, front) - front < stopping_m
                        and sumo_lane_id(place) not in closed):
                    break
            else:
                raise RunError(
                    f"vehicles.{group.name}: could not place vehicle {k + 1} of {group.count} in lanes "
                    f"{group.lanes} within {list(group.pos_m)} m with {group.min_spacing_m} m spacing (and "
                    f"{stopping_m:.0f} m of its lane ahead, to stop from {group.speed_mps:g} m/s)")
            if front - length < 0 or front > frame.length_m:
                raise RunError(
                    f"vehicles.{group.name}: vehicle {k + 1} drawn at {front:.1f} m, outside the road "
                    f"[{length:.1f}, {frame.length_m:.1f}] m: impossible departure")
            occupy(place, length)
            placements.append(Placement(f"{group.name}{k}", group.name, group.vtype, lane, front,
                                        group.speed_mps, group.desired_speed_mps, 0.0, *place))

    for f_idx, flow in enumerate(scenario.flows):
        rate = flow.vehs_per_hour / 3600.0
        frame = frame_of(scenario, road, flow.route)
        length = vtype_length(vtypes, flow.vtype)
        t = float(rng.exponential(1.0 / rate))
        n = 0
        while t < scenario.simulation.max_time_s:
            lane = int(rng.choice(flow.lanes))
            placements.append(Placement(f"f{f_idx}.{n}", f"flow{f_idx}", flow.vtype, lane, length, flow.speed_mps,
                                        None, t, *sumo_place(frame, lane, length)))
            n += 1
            t += float(rng.exponential(1.0 / rate))
    return placements


def traffic_vtypes(scenario: Scenario) -> list[str]:
    """The vehicle types of a scenario's vehicle groups and flows (not the ego's, not the accident's)."""
    return sorted({g.vtype for g in scenario.vehicles} | {f.vtype for f in scenario.flows})


def lane_change_vtypes(scenario: Scenario, out: Path) -> Path:
    """The scenario's vehicle types file with its lane_change_model's attributes set on the
    chosen types, written to `out`."""
    import xml.etree.ElementTree as ET

    lcm = scenario.lane_change_model
    chosen = set(lcm.vtypes or traffic_vtypes(scenario))
    tree = ET.parse(scenario.vehicle_types)
    for vt in tree.getroot().iter("vType"):
        if vt.get("id") in chosen:
            for name, value in lcm.vtype_attributes().items():
                vt.set(name, value)
    tree.write(out, encoding="UTF-8", xml_declaration=True)
    return out


def draw_lane_change_duration(cfg, rng: np.random.Generator) -> float:
    """One vehicle's lane-change duration, s (scenario.LaneChangeDurationConfig)."""
    if cfg.distribution == "fixed":
        value = cfg.median_s
    elif cfg.distribution == "lognormal":
        value = cfg.median_s * float(np.exp(cfg.sigma * rng.standard_normal()))
    else:
        value = float(rng.uniform(cfg.min_s, cfg.max_s))
    return float(min(max(value, cfg.min_s), cfg.max_s))


class SumoSession:
    """One running SUMO simulation of a scenario."""

    def __init__(self, scenario: Scenario, seed: int, lanechange_file: Path, rng: np.random.Generator,
                 extra_sumo_args: list[str] | None = None,
                 emissions: tuple[Path, Callable[[str, str], bool]] | None = None):
        """`emissions`: (tripinfo file, rated(vtype, vclass)): SUMO's emission model on the vehicles
        whose type `rated` names (the metrics). Moving vehicles carry SUMO's emissions device, their
        trip totals written to the tripinfo file (`tripinfo_file`; None when no moving vehicle is
        rated); the parked accident vehicles are rated without it (`parked_emissions`, by finish())."""
        self.scenario = scenario
        self.seed = seed
        self.road = read_road(scenario.network, scenario.route)
        # the ego's own route (its s: the ego table, the trip), and whether positions need its edge
        self.ego_frame = frame_of(scenario, self.road, scenario.ego.route) if scenario.ego is not None else None
        self._ego_single_edge = self.ego_frame is not None and len(self.ego_frame.route) == 1
        # a vehicle's lane is its track: on a network of one straight edge (a Road) SUMO's lane index,
        # elsewhere from its lane id (a route of one edge of a larger network has vehicles off it)
        self._lane_by_index = isinstance(self.road, Road)
        self.vtypes = read_vehicle_types(scenario.vehicle_types)
        self.step_s = scenario.simulation.step_s
        # (load_scenario checked the vehicle types, lanes and positions against these files)
        self.placements = plan_placements(scenario, self.road, self.vtypes, rng)
        self._emission_types: list[str] = []
        self._untracked_types: list[str] = []  # vTypes without a tripinfo device (see _emission_args)
        self.tripinfo_file: Path | None = None
        # parked accident vehicles SUMO's model rates: id -> (vtype, rates at their insertion step)
        self._parked_rated: dict[str, tuple[str, tuple[float, ...]]] = {}
        self._steps = 0  # SUMO steps taken (a parked vehicle is on the road from the first)
        # their rows of the sumo_emissions table (SUMO's units), filled by finish()
        self.parked_emissions: list[tuple] = []
        lcm = scenario.lane_change_model
        # the scenario's lane-change model: its vehicle types rewritten beside the lane-change output
        vtypes_file = scenario.vehicle_types if lcm is None else lane_change_vtypes(
            scenario, lanechange_file.with_name(lanechange_file.stem + ".vtypes.add.xml"))
        self._lc_types = set(lcm.vtypes or traffic_vtypes(scenario)) if lcm is not None else set()
        self._lc_duration = lcm.duration if lcm is not None else None
        # per-vehicle durations from a generator of their own (the placements' draws stay as they were)
        self._lc_rng = np.random.default_rng(rng.integers(2**63)) if self._lc_duration is not None else None
        self.lane_change_durations: dict[str, float] = {}  # vehicle -> drawn duration, s
        lateral = (["--lateral-resolution", repr(lcm.lateral_resolution_m)] if lcm is not None
                   and lcm.lateral_resolution_m is not None  # SUMO refuses it with --lanechange.duration
                   else ["--lanechange.duration", repr(scenario.simulation.lanechange_duration_s)])
        self.sumo_args = [
            "sumo",
            "--net-file", str(scenario.network),
            "--additional-files", str(vtypes_file),
            "--step-length", repr(self.step_s),
            "--seed", str(seed),
            *lateral,
            "--collision.action", "warn",
            # contact only: SUMO's default also calls a gap under the vType's minGap (2.5 m) a
            # collision, which the ego's driver (IDM s0 = 2 m, or a person) keeps when stopping
            "--collision.mingap-factor", "0",
            "--collision.check-junctions", "true",
            "--lanechange-output", str(lanechange_file),
            "--no-step-log", "true",
            "--no-warnings", "true",
            "--duration-log.disable", "true",
            *(self._emission_args(*emissions) if emissions else []),
            *(extra_sumo_args or []),
        ]
        try:
            libsumo.start(self.sumo_args)
        except libsumo.TraCIException as exc:  # SUMO printed its reason ("Error: ...") just before
            raise RunError(f"SUMO did not start ({exc}; SUMO's own message is the line above)") from None
        self._open = True
        self.time = 0.0
        # SUMO counts time in whole milliseconds (simulation.step_s is a whole number of them): the
        # step's start time is counted here, as SUMO counts it, instead of asked every step
        self._step_ms = int(round(self.step_s * 1000.0))
        self._begin_ms = int(round(libsumo.simulation.getTime() * 1000.0))  # when the next step begins
        self._static: dict[str, tuple] = {}
        # (ids, their static columns) of the last states(): reused while the same vehicles are there
        self._static_of: tuple[tuple, tuple] = ((), ((), (), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)))
        self.collisions: list[Collision] = []  # every contact SUMO reported, in the order they began
        self._contact: dict[tuple[str, str], int] = {}  # (collider, victim) -> its latest contact
        self._ego_min_gap: float | None = None
        self.ego_off_route = False  # the trip ended because the ego left its route (ego_state)
        try:
            # SUMO's emission model of each vehicle type (HBEFA/PHEMlight; SUMO's default where the type names none)
            self.emission_classes = {vt: libsumo.vehicletype.getEmissionClass(vt) for vt in self.vtypes}
            self._populate()
        except libsumo.TraCIException as exc:  # e.g. a departure speed above the vehicle type's maxSpeed
            self.close()
            raise RunError(f"SUMO refused the scenario's vehicles: {exc}") from None
        except Exception:
            self.close()
            raise

    def _emission_args(self, tripinfo: Path, rated: Callable[[str, str], bool]) -> list[str]:
        # The device goes on the rated types only (_populate): it rates its vehicles every step, which
        # costs more than the rest of the metrics when every vehicle has it. Not by
        # --device.emissions.explicit: libsumo keeps the first run's list for the process's later runs.
        sc = self.scenario
        moving = {g.vtype for g in sc.vehicles} | {f.vtype for f in sc.flows}
        moving |= {sc.ego.vtype} if sc.ego else set()

        def rates(vt: str) -> bool:
            return rated(vt, self.vtypes[vt].get("vClass", "passenger"))

        self._emission_types = sorted(vt for vt in moving if rates(vt))
        if sc.accident is not None and rates(sc.accident.vtype) and sc.accident.vtype not in moving:
            # Parked from their insertion to the run's end: SUMO rates a stopped vehicle the same every
            # step, so two reads give its totals; the device and the tripinfo output would cost every
            # step (SUMO looks the output up by option name and flushes it each step: ~10,000
            # instructions, ~2.5 % of a 0.01-s step of the accident scenario). (A type that also moves
            # carries the device; its parked vehicles then come from the tripinfo file as well.)
            self._parked_rated = {f"accident{i}": (sc.accident.vtype, ()) for i in range(len(sc.accident.lanes))}
        if not self._emission_types:
            return []  # no moving vehicle rated: no device, no tripinfo output
        self.tripinfo_file = tripinfo
        # the tripinfo device only where the emissions device is: the file is read for their totals
        # alone, and a device on every vehicle costs SUMO every step
        self._untracked_types = sorted(self.vtypes.keys() - set(self._emission_types))
        return ["--tripinfo-output", str(tripinfo), "--tripinfo-output.write-unfinished", "true"]

    # -- set-up -------------------------------------------------------------------------
    def _route_id(self, edges: tuple[str, ...]) -> str:
        """A SUMO route of these edges (added once)."""
        rid = self._routes.get(edges)
        if rid is None:
            rid = self._routes[edges] = f"r{len(self._routes)}"
            libsumo.route.add(rid, list(edges))
        return rid

    def _populate(self) -> None:
        sc = self.scenario
        for vt in self._emission_types:  # before any vehicle of the type is built
            libsumo.vehicletype.setParameter(vt, "has.emissions.device", "true")
        for vt in self._untracked_types:
            libsumo.vehicletype.setParameter(vt, "has.tripinfo.device", "false")
        self._routes: dict[tuple[str, ...], str] = {}
        for vid, what, vtype, (edges, index, pos), speed in fixed_vehicles(sc, self.road):
            libsumo.vehicle.add(vid, self._route_id(edges), vtype, depart="0", departLane=str(index),
                                departPos=repr(pos), departSpeed=repr(speed))
            if what == "accident":
                libsumo.vehicle.setStop(vid, edges[0], pos=pos, laneIndex=index, duration=ACCIDENT_STOP_S, flags=0)
        for p in self.placements:
            depart_speed = repr(p.speed_mps) if p.depart_s == 0.0 else "desired"
            libsumo.vehicle.add(p.vehicle_id, self._route_id(p.edges), p.vtype, depart=repr(round(p.depart_s, 2)),
                                departLane=str(p.sumo_lane), departPos=repr(p.sumo_pos_m), departSpeed=depart_speed)
            if p.desired_speed_mps is not None:
                libsumo.vehicle.setMaxSpeed(p.vehicle_id, p.desired_speed_mps)
        self.step()
        if self._parked_rated:  # their insertion step's rates (the sum below counts from this step)
            on_road = set(libsumo.vehicle.getIDList())
            for vid, (vtype, _) in self._parked_rated.items():
                if vid not in on_road:
                    raise RunError(f"SUMO could not insert the accident vehicle {vid} at its position")
                self._parked_rated[vid] = (vtype, _emission_rates(vid))
        if sc.ego is not None:
            if EGO_ID not in libsumo.vehicle.getIDList():
                raise RunError("the ego could not be inserted at its departure position")
            # Our code drives the ego: no SUMO safety checks, no SUMO lane changes.
            libsumo.vehicle.setSpeedMode(EGO_ID, 0)
            libsumo.vehicle.setLaneChangeMode(EGO_ID, 0)
            # what ego_state reads every step, gathered by SUMO in its step: one call instead of four
            # (the same values as the getters; its results are empty once the ego has left)
            libsumo.vehicle.subscribe(EGO_ID, list(_EGO_VARS) if self._ego_single_edge else [*_EGO_VARS, _LANE_ID],
                                      parameters={_LEADER: LEADER_HORIZON_M})
        on_road = set(libsumo.vehicle.getIDList())
        missing = [p for p in self.placements if p.depart_s == 0.0 and p.vehicle_id not in on_road]
        if missing:
            raise RunError(self._insertion_problem(missing))

    def _insertion_problem(self, missing: list[Placement]) -> str:
        """Why SUMO refused the first vehicle it could not insert: its nearest neighbours in its lane
        at t = 0 (SUMO says nothing itself), and the others it held back."""
        first = missing[0]
        # every vehicle placed at t = 0: (id, group, lane key, front, length, speed)
        placed = [(p.vehicle_id, f"vehicles.{p.group}", *lane_slot(self.road, (p.edges, p.sumo_lane, p.sumo_pos_m)),
                   vtype_length(self.vtypes, p.vtype), p.speed_mps) for p in self.placements if p.depart_s == 0.0]
        placed += [(vid, what, *lane_slot(self.road, place), vtype_length(self.vtypes, vtype), speed)
                   for vid, what, vtype, place, speed in fixed_vehicles(self.scenario, self.road)]
        me = next(v for v in placed if v[0] == first.vehicle_id)
        _, group, lane, front, length, speed = me
        near = []
        ahead = [v for v in placed if v[2] == lane and v[3] > front]
        behind = [v for v in placed if v[2] == lane and v[3] < front and v[0] != me[0]]
        if ahead:
            v = min(ahead, key=lambda v: v[3])
            near.append(f"{v[3] - v[4] - front:.1f} m behind {v[0]!r} ({v[1]}, {v[5]:g} m/s)")
        if behind:
            v = max(behind, key=lambda v: v[3])
            near.append(f"{front - length - v[3]:.1f} m ahead of {v[0]!r} ({v[1]}, {v[5]:g} m/s)")
        where = "; ".join(near) if near else "no other vehicle in its lane"
        held = [p.vehicle_id for p in missing[1:]]
        spacing = ("SUMO refuses a departure whose gap to the vehicle ahead or behind is below the gap the follower "
                   "needs to brake safely at their departure speeds: raise "
                   f"{group}.min_spacing_m (a group keeps it to every vehicle placed before it) or lower its speed_mps")
        # a lane that ends ahead (a lane drop): SUMO also refuses a departure that leaves too little road
        # for the lane changes needed before the end ("too many lane changes required"), which this
        # message blamed on the spacing even with the nearest vehicle 360 m away
        to_end = float(self.road.lane_end_ahead(first.lane, first.pos_m)) - first.pos_m
        if to_end < LANE_END_NOTE_M:  # inf where the lane runs to the route's end
            reason = (f"; its lane ends {to_end:.0f} m ahead. SUMO refuses a departure that leaves too little road "
                      "for the lane changes it needs before the end of its lane: place the group where its lane "
                      f"goes on, farther from the end, or slower. Else: {spacing}")
        else:
            reason = f". {spacing}"
        return (f"SUMO could not insert {first.vehicle_id!r} ({group}, lane {first.lane} at {first.pos_m:.1f} m, "
                f"{first.speed_mps:g} m/s): {where}{reason}"
                + (f". Also not inserted: {held} (SUMO holds back the vehicles that depart after a refused one "
                   "in its lane)" if held else ""))

    # -- stepping -----------------------------------------------------------------------
    def step(self) -> None:
        libsumo.simulationStep()
        self._steps += 1
        # SUMO's outputs (fcd, lanechange, collisions) label the state after a step with the time
        # the step began; getTime() already returns the next one. Stamp like the outputs: the
        # nearest double to the step's start in seconds (round(getTime() - step_s, 9), one libsumo
        # call and a rounding fewer per step)
        self.time = self._begin_ms / 1000.0
        self._begin_ms += self._step_ms
        for c in libsumo.simulation.getCollisions():
            # a pair reported again one step after its last report is the same contact going on
            k = self._contact.get((c.collider, c.victim))
            if k is not None and self.collisions[k].end_time >= self.time - 1.5 * self.step_s:
                self.collisions[k] = replace(self.collisions[k], end_time=self.time)
            else:
                self._contact[(c.collider, c.victim)] = len(self.collisions)
                self.collisions.append(Collision(self.time, c.collider, c.victim, c.type, c.colliderSpeed,
                                                 c.victimSpeed, c.lane, c.pos, self.time))
        if self._lc_rng is not None:  # the configured duration of each vehicle that has just departed
            for vid in libsumo.simulation.getDepartedIDList():
                if libsumo.vehicle.getTypeID(vid) in self._lc_types:
                    duration = draw_lane_change_duration(self._lc_duration, self._lc_rng)
                    self.lane_change_durations[vid] = duration
                    libsumo.vehicle.setMaxSpeedLat(vid, self.road.lane_width_m / duration)

    def set_ego_speed(self, speed_mps: float) -> None:
        _set_speed(EGO_ID, max(0.0, speed_mps))

    def change_ego_lane(self, direction: int) -> None:
        """Start the ego's change to the adjacent lane on its left (+1) or right (-1), taking
        simulation.lanechange_duration_s (SUMO's continuous lane change; the ego's lane-change mode
        0 makes SUMO follow the request without checking the target lane's gaps). SUMO drops a
        request toward a lane that is absent there."""
        libsumo.vehicle.changeLaneRelative(EGO_ID, int(direction), self.scenario.simulation.lanechange_duration_s)

    def place_ego(self, s_front: float, d: float, yaw: float) -> None:
        """Put the ego's front bumper centre at position (`s_front`, `d`) of its route (d: m left of
        the right road edge), yawed `yaw` rad (left positive) from the road, for the next step.
        keepRoute=2: the ego stays on its edge, in the lane under its front bumper, so SUMO's
        followers and lane changers see it there and its collision check includes it."""
        # s_front is along the ego's own route (ego_state), which may be a part of the scenario's
        x, y = self.ego_frame.to_world(s_front, d)
        angle = 90.0 - np.degrees(float(self.ego_frame.heading(s_front, d)) + yaw)
        libsumo.vehicle.moveToXY(EGO_ID, "", -1, float(x), float(y), angle=float(angle), keepRoute=2)

    def vehicle_count(self) -> int:
        return libsumo.vehicle.getIDCount()

    def ego_state(self) -> tuple[float, float, float, tuple[str, float] | None] | None:
        """The ego now: (front-bumper position along its route, speed, acceleration, leader), where
        leader is SUMO's (id, bumper-to-bumper gap) within LEADER_HORIZON_M or None; None once the
        ego left. One call per SUMO step (it runs 100 times per simulated second): the values of
        the ego's subscription (_populate)."""
        found = _ego_results(EGO_ID)
        if not found:  # the ego has left the simulation, and its subscription with it
            return None
        pos, speed, accel = found[_LANE_POSITION], found[_SPEED], found[_ACCELERATION]
        if not self._ego_single_edge:
            try:
                pos = float(self.ego_frame.route_position(found[_LANE_ID], pos))
            except KeyError:  # SUMO put the ego on an edge off its route (a person steered it onto a ramp)
                self.ego_off_route = True
                return None
        leader = found[_LEADER]  # ("", -1) when there is none within the horizon
        if not leader or not leader[0]:
            return pos, speed, accel, None
        # the leader's distance excludes the follower's minGap; add it back for the true gap.
        if self._ego_min_gap is None:
            self._ego_min_gap = libsumo.vehicle.getMinGap(EGO_ID)
        return pos, speed, accel, (leader[0], leader[1] + self._ego_min_gap)

    def speed_of(self, vehicle_id: str) -> float:
        return libsumo.vehicle.getSpeed(vehicle_id)

    def states(self) -> VehicleStates:
        """Ground truth of every vehicle in the network now.

        Plain per-vehicle getters, one row per vehicle: libsumo subscriptions would gather the
        values at every SUMO step (+13 us per step for 10 vehicles, measured) while we read them
        only every V2C tick (10 steps).
        """
        v = libsumo.vehicle
        id_list, position, angle, speed, accel, lane_index, lateral, lane_id = _getters
        ids = tuple(id_list())
        n = len(ids)
        if not self._lane_by_index:  # the track of the lane (-1 off the route: a ramp, another road)
            track_of = self.road.track_of
            lane_index = lambda vid: track_of.get(lane_id(vid), -1)  # noqa: E731
        # every vehicle's plain floats in one flat buffer (no list of rows to convert)
        cols = np.fromiter(chain.from_iterable(
            (*position(vid), angle(vid), speed(vid), accel(vid), lane_index(vid), lateral(vid)) for vid in ids),
            dtype=float, count=8 * n).reshape(n, 8).T.copy()
        front_x, front_y, front_z, angle, speed, accel, lane, lat = cols
        lane = lane.astype(np.int16)
        if ids != self._static_of[0]:
            for vid in ids:
                if vid not in self._static:
                    self._static[vid] = (v.getTypeID(vid), v.getVehicleClass(vid), v.getLength(vid),
                                         v.getWidth(vid), v.getHeight(vid))
            vtype, vclass, *sizes = zip(*[self._static[vid] for vid in ids]) if n else ((),) * 5
            sizes = [np.array(x, dtype=float) for x in sizes]
            # half lengths kept: (c * length) / 2 is c * (length / 2) exactly (a power of two)
            self._static_of = ids, (vtype, vclass, *sizes, sizes[0] / 2)
        vtype, vclass, length, width, height, half_length = self._static_of[1]
        heading = sumo_angle_to_yaw(angle)
        # Footprint centre: half a length behind the front bumper along the heading.
        cx = front_x - np.cos(heading) * half_length
        cy = front_y - np.sin(heading) * half_length
        return VehicleStates(
            time=self.time,
            ids=ids,
            vtype=vtype,
            vclass=vclass,
            x=cx, y=cy, z=front_z,
            heading=heading, speed=speed, accel=accel, lane=lane, lateral_offset=lat,
            length=length.copy(), width=width.copy(), height=height.copy(),  # records own their arrays
        )

    def vehicle_table(self):
        """Static facts of every vehicle seen in the run: type, class, size and placement group."""
        import pandas as pd

        groups = {p.vehicle_id: p.group for p in self.placements}
        groups[EGO_ID] = "ego"
        names = ["vehicle_id", "vtype", "vclass", "length", "width", "height"]
        rows = [(vid, *s) for vid, s in sorted(self._static.items())]
        columns = {name: list(values) for name, values in zip(names, zip(*rows))} if rows else {n: [] for n in names}
        columns["group"] = [groups.get(vid, "accident" if vid.startswith("accident") else "")
                            for vid in columns["vehicle_id"]]
        return pd.DataFrame(columns, columns=[*names, "group"])

    def finish(self) -> None:
        """The run went to its end: rate the parked accident vehicles (`parked_emissions`) while
        SUMO still holds them. Not part of close(), which also runs on the way up from an error
        that a rating error must not replace."""
        if self._open and self._parked_rated and all(rates for _, rates in self._parked_rated.values()):
            self.parked_emissions = self._parked_totals()

    def close(self) -> None:
        if self._open:
            libsumo.close()
            self._open = False

    def _parked_totals(self) -> list[tuple]:
        """The parked rated vehicles' rows of the sumo_emissions table: SUMO's per-step values (what
        its --emission-output writes) summed over the run, in SUMO's units (mg, Wh). A stopped
        vehicle's values are the same every step after its insertion step, so the sum is the
        insertion step's plus the steps since times now (SUMO rates it 0 while stopped)."""
        v = libsumo.vehicle
        on_road = set(v.getIDList())
        end = libsumo.simulation.getTime()  # the time after the last step, as tripinfo's duration
        rows = []
        for vid, (vtype, first) in self._parked_rated.items():
            if vid not in on_road or not v.isStopped(vid):
                raise RunError(f"the accident vehicle {vid} left its stop: its emissions were rated as parked")
            now = _emission_rates(vid)
            totals = [(a + b * (self._steps - 1)) * self.step_s for a, b in zip(first, now)]
            rows.append((vid, vtype, 0.0, end, v.getDistance(vid), *totals))
        return rows

    def __enter__(self) -> "SumoSession":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _emission_rates(vid: str) -> tuple[float, ...]:
    """SUMO's emission model on a vehicle in the last step: CO, CO2, HC, NOx, PMx, fuel (mg/s) and
    electricity (Wh/s), the order of the sumo_emissions table's columns."""
    v = libsumo.vehicle
    return (v.getCOEmission(vid), v.getCO2Emission(vid), v.getHCEmission(vid), v.getNOxEmission(vid),
            v.getPMxEmission(vid), v.getFuelConsumption(vid), v.getElectricityConsumption(vid))


def sumo_version() -> str:
    from importlib.metadata import version

    return version("libsumo")

