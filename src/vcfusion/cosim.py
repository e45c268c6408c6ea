"""The co-simulation tick loop.

SUMO advances in steps of `simulation.step_s`. Every V2C period (a tick):
1. every vehicle's GNSS report goes into the V2C channel; reports that have arrived reach the
   cloud twin store, which runs its process models over all twins at once;
2. the ego receives its neighbours' twins (within `v2c.neighbour_range_m`);
3. tick hooks run in order (camera, fusion + overlay, guidance; each may log rows to a table)
   and fill the tick's typed fields (frame, detections, guidance);
4. the ego controller sets the ego's acceleration for the steps until the next tick.
What each stage reads and sets is declared and checked when the run is built (vcfusion.stages).
The ego's speed is integrated here and imposed on SUMO every step (speed mode 0), so the
ego's motion is exactly what the controller asked for. `CoSimulation.start()` runs the same loop
one ego tick at a time for a caller that decides each tick (LiveRun: the Gymnasium environment).
"""

from __future__ import annotations

import tempfile
import time as wallclock
from contextlib import ExitStack
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np
import pandas as pd
import pyarrow.compute as pc
from tqdm import tqdm

from vcfusion.cloud.channel import V2CChannel
from vcfusion.cloud.twins import ProcessModel, TwinStore, neighbours
from vcfusion.control.api import Command
from vcfusion.interrupts import raise_if_received
from vcfusion.metrics.collisions import describe as describe_collision, ego_collision_records
from vcfusion.metrics.run_metrics import add_run_metrics
from vcfusion.metrics.safety import colliding_pairs, cut_ins
from vcfusion.metrics.traffic import sumo_model_rates
from vcfusion.records import EGO_ID, GuidanceSet, TwinStates, VehicleStates
from vcfusion.runio import RunTables, TableSink, vehicle_tracks
from vcfusion.scenario import Scenario
from vcfusion.stages import WiringError, check_wiring, declared, stage_name
from vcfusion.threads import one_blas_thread
from vcfusion.traffic.lanechanges import (ego_lane_changes, lane_change_events, merge_changes, read_sumo_lanechanges,
                                          relate_to_ego)
from vcfusion.traffic.network import FLAT_WITHIN_M, network_elevation
from vcfusion.traffic.roadframe import RoadFrame
from vcfusion.traffic.session import Collision, SumoSession

if TYPE_CHECKING:  # the camera and detector types only: traffic-only runs never import OpenGL or torch
    from vcfusion.detection.detectors import Detections
    from vcfusion.fusion.fuse import CameraFrame
    from vcfusion.render.renderer import Frame


@dataclass(frozen=True)
class EgoView:
    """What the ego knows at a tick: its own state and its radar leader in its lane."""

    speed: float
    accel: float
    s: float  # front bumper along the road
    lane: int
    leader_id: str | None
    leader_gap_m: float | None  # bumper to bumper
    leader_speed: float | None


@dataclass
class Tick:
    """What the stages of one tick see. The loop sets the first five fields (`ego` and
    `neighbours` only when the scenario has an ego); each later field is set by the one stage that
    declares it in `provides` (or `fills`), and may be None at ticks where that stage has nothing."""

    time: float
    truth: VehicleStates
    twins: TwinStates
    ego: EgoView | None
    neighbours: TwinStates | None
    # The ego camera's image: a rendered Frame (render/hook.py), or a CameraFrame from a frame
    # source that stands in for the renderer.
    frame: Frame | CameraFrame | None = None
    detections: Detections | None = None  # the detector's boxes on that frame (fusion stage)
    guidance: GuidanceSet | None = None  # what the driver is shown, with its source (fusion / cloud guidance)


class EgoController(Protocol):
    """Sets the ego's acceleration every tick (a float, m/s^2, or a vcfusion.control.Command with
    a lane-change request: a controller of the API runs through vcfusion.control.ControllerStage);
    may declare `needs` and `finish` (vcfusion.stages).

    A controller may also have ``step(EgoStep) -> EgoCommand``, called every SUMO step after the
    tick's stages: a person at the wheel (vcfusion.hitl) acts between ticks, and steers."""

    def acceleration(self, tick: Tick) -> float | Command: ...


@dataclass(frozen=True)
class EgoStep:
    """What a per-step ego controller sees before each SUMO step."""

    time: float
    s_front: float  # front bumper along the road
    speed: float
    states: Callable[[], VehicleStates]  # the ground truth now, read on demand (e.g. a display frame)


@dataclass(frozen=True)
class EgoCommand:
    """A per-step controller's command for the next step: the acceleration, and optionally where the
    ego's front bumper centre is across the road (`d`, m left of the right road edge) and its yaw
    relative to the road (rad, left positive). With `d` set the ego is placed (SUMO moveToXY,
    keepRoute=2: it stays on its edge, in the lane under its centre, and SUMO's followers and
    collision check see it there); without, it keeps its lane as SUMO drives it."""

    accel: float
    d: float | None = None
    yaw: float = 0.0


@dataclass(frozen=True)
class StopRun:
    """A decision that ends a live run at the tick it answers, with `reason` as its end reason
    (LiveRun.stop: e.g. a Gymnasium episode that ends at the ego's collision)."""

    reason: str


class TickHook(Protocol):
    """Runs every V2C tick; may return rows for its table of the run folder; declares what it
    needs from and provides to the tick (vcfusion.stages)."""

    table: str

    def __call__(self, tick: Tick) -> list[dict] | None: ...


@dataclass
class RunResult:
    scenario: Scenario
    seed: int
    tables: RunTables  # name -> DataFrame (streamed tables are read from Parquet on access)
    summary: dict
    wall_s: float  # the whole run: SUMO start-up, tick loop, end-of-run tables and summary
    loop_wall_s: float = float("nan")  # the tick loop alone


STREAMED_TABLES = ("trajectories", "twins", "ego")
EGO_COLUMNS = ["time", "s", "speed", "accel", "command_accel", "leader_id", "leader_gap_m"]
TRAJECTORY_COLUMNS = ["time", "vehicle_id", "x", "y", "z", "heading", "speed", "accel",
                      "lane", "lateral_offset", "s", "d"]


EMPTY_COLUMNS = {"trajectories": TRAJECTORY_COLUMNS, "ego": EGO_COLUMNS}


def _truth_rows(truth: VehicleStates, road: RoadFrame) -> dict[str, np.ndarray]:
    s, d = truth.road_frame(road)
    return {
        "time": np.full(len(truth), round(truth.time, 6)),
        "vehicle_id": np.array(truth.ids, dtype=object),
        "x": truth.x, "y": truth.y, "z": truth.z, "heading": truth.heading,
        "speed": truth.speed, "accel": truth.accel, "lane": truth.lane,
        "lateral_offset": truth.lateral_offset, "s": s, "d": d,
    }


def _ego_columns(rows: list[tuple]) -> dict[str, np.ndarray]:
    return {name: np.array(values) for name, values in zip(EGO_COLUMNS, zip(*rows))}


def _twin_rows(twins: TwinStates) -> dict[str, np.ndarray]:
    rows = {
        "time": np.full(len(twins), round(twins.time, 6)),
        "vehicle_id": np.array(twins.ids, dtype=object),
        "measured_time": twins.measured_time.round(6),
        "x": twins.x, "y": twins.y, "z": twins.z, "heading": twins.heading,
        "speed": twins.speed, "accel": twins.accel, "lane": twins.lane,
    }
    # copies: the table sink keeps what it is given, and a process model may reuse its output arrays
    rows.update({k: np.array(v) for k, v in twins.outputs.items()})
    return rows


class CoSimulation:
    def __init__(
        self,
        scenario: Scenario,
        seed: int,
        controller: EgoController | None = None,
        process_models: list[tuple[str, ProcessModel]] | None = None,
        hooks: list[TickHook] | None = None,
        extra_sumo_args: list[str] | None = None,
    ):
        self.scenario = scenario
        self.seed = seed
        # One generator per run: placements, V2C loss/jitter/noise all follow from the seed.
        self.rng = np.random.default_rng(seed)
        if scenario.ego is not None and controller is None:
            raise WiringError(f"scenario {scenario.name}: it has an ego, so the run needs the ego's controller "
                              "(run.build_cosimulation wires the driver model; driver.idm.IdmController follows "
                              "the radar leader)")
        if scenario.ego is None and controller is not None:
            raise WiringError(f"scenario {scenario.name}: controller {stage_name(controller)} given, but the "
                              "scenario has no ego block")
        self.controller = controller
        self.process_models = process_models or []
        self.hooks = hooks or []
        # Further SUMO options (e.g. --fcd-output for cross-checks, SSM devices).
        self.extra_sumo_args = extra_sumo_args or []
        self.check_wiring()

    def check_wiring(self) -> None:
        """Refuse stages in an order that cannot work (raises WiringError; see vcfusion.stages).
        Run again by run(): callers may change `hooks` after building."""
        check_wiring(self.process_models, self.hooks, self.controller, self.scenario.ego is not None)

    def stages(self) -> list:
        """Every stage of the run in the order it runs: process models, hooks, controller."""
        return [m for _, m in self.process_models] + list(self.hooks) + (
            [self.controller] if self.controller is not None else [])

    def run(self, progress: bool = False) -> RunResult:
        self.check_wiring()
        started = wallclock.perf_counter()
        workdir, sinks, lc_file, session = self._open()
        try:
            loop_started = wallclock.perf_counter()
            with one_blas_thread():  # small per-tick arrays: BLAS threads only cost hand-offs
                out = self._loop(session, sinks, progress)
            loop_wall = wallclock.perf_counter() - loop_started
            session.finish()
        finally:
            session.close()
        return self._results(session, workdir, sinks, lc_file, out, started, loop_wall)

    def _open(self) -> tuple[tempfile.TemporaryDirectory, dict[str, TableSink], Path, SumoSession]:
        """The run's working folder, its table sinks, SUMO's lane-change file and the started SUMO."""
        sc = self.scenario
        # Tables that grow with simulated time are streamed to Parquet here (flat memory).
        workdir = tempfile.TemporaryDirectory(prefix="vcfusion-run-")
        sinks = {name: TableSink(Path(workdir.name) / f"{name}.parquet") for name in STREAMED_TABLES}
        sinks.update({hook.table: TableSink(Path(workdir.name) / f"{hook.table}.parquet") for hook in self.hooks})
        lc_file = Path(workdir.name) / "lanechanges.xml"
        tripinfo = Path(workdir.name) / "tripinfo.xml"  # SUMO's emission totals (metrics)
        session = SumoSession(sc, self.seed, lc_file, np.random.default_rng(self.rng.integers(2**63)),
                              self.extra_sumo_args, (tripinfo, partial(sumo_model_rates, sc.metrics))
                              if sc.metrics.enabled else None)
        return workdir, sinks, lc_file, session

    def start(self, progress: bool = False) -> "LiveRun":
        """Start the run and stop at its first ego tick: the caller decides each tick
        (:class:`LiveRun`), on the same loop as :meth:`run` (the Gymnasium environment)."""
        return LiveRun(self, progress)

    def _results(self, session: SumoSession, workdir, sinks: dict[str, TableSink], lc_file: Path, out: dict,
                 started: float, loop_wall: float) -> RunResult:
        """The run's tables and summary from its streamed tables and the closed SUMO session."""
        sc = self.scenario
        sumo_changes = read_sumo_lanechanges(lc_file, session.road)
        lc_file.unlink(missing_ok=True)
        stored = {name: sink.close() for name, sink in sinks.items()}
        # a table without rows keeps its columns (a hook names them: a reader's table["time"] works)
        empty = EMPTY_COLUMNS | {h.table: list(h.columns) for h in self.hooks if getattr(h, "columns", None)}
        frames = {name: pd.DataFrame(columns=empty.get(name, [])) for name, f in stored.items() if f is None}
        vehicles = session.vehicle_table()
        frames["vehicles"] = vehicles
        frames["collisions"] = pd.DataFrame([c.__dict__ for c in out["collisions"]],
                                            columns=list(Collision.__dataclass_fields__))
        tables = RunTables(frames, {k: f for k, f in stored.items() if f is not None}, keepalive=workdir)
        lateral = tables.arrow("trajectories", ["vehicle_id", "time", "d", "s"])
        # the changers' and the ego's samples as plain arrays, selected once for both lane-change steps
        tracks = vehicle_tracks(lateral, set(sumo_changes["vehicle_id"]) | {EGO_ID}, ["time", "d", "s"])
        if sc.ego is not None:
            lengths = dict(zip(vehicles["vehicle_id"], vehicles["length"]))
            # a person steers the ego across lanes; SUMO does not report those changes (it reports
            # those a controller's Command asked for: they are not counted twice)
            if not (sumo_changes["vehicle_id"] == EGO_ID).any():
                sumo_changes = merge_changes(sumo_changes, ego_lane_changes(tracks.get(EGO_ID), session.road,
                                                                            lengths[EGO_ID]))
        sublane = sc.lane_change_model is not None and sc.lane_change_model.model == "SL2015"
        events = lane_change_events(sumo_changes, tracks, session.road, "settled" if sublane else "centred")
        if sc.ego is not None:
            events = relate_to_ego(events, tracks, lengths, _ego_lane_at(tracks, events["mid_time"], session.road,
                                                                         sc.ego.lane))
        tables["lane_changes"] = pd.DataFrame(events)
        summary = summarize(sc, self.seed, tables, events, out["channel"], out["end_reason"], lateral)
        # what wrote the twins' predictions (a study reading run folders reports it, as for its own trips)
        summary["process_models"] = [name for name, _ in self.process_models]
        for stage in self.stages():
            _finish(stage, tables, summary)
        if sc.ego is not None:  # who hit whom and what the driver saw and was shown before (vcfusion.metrics.collisions)
            summary["ego_collisions"] = ego_collision_records(tables)
        if sc.metrics.enabled:  # per-vehicle safety, comfort and emissions (vcfusion.metrics)
            summary["metrics"] = add_run_metrics(sc, tables, session)
            highest, _ = network_elevation(sc.network)
            if highest > FLAT_WITHIN_M:  # MOVESTAR's rates are for zero grade: say so where the road climbs
                summary["network_max_height_m"] = round(highest, 2)
        return RunResult(sc, self.seed, tables, summary, wallclock.perf_counter() - started, loop_wall)

    def _loop(self, session: SumoSession, sinks: dict[str, TableSink], progress: bool) -> dict:
        """The tick loop with the run's own controller deciding at each ego tick."""
        ticks = self._ticks(session, sinks, progress)
        try:
            tick = next(ticks)
            while True:
                tick = ticks.send(self.controller.acceleration(tick))
        except StopIteration as stop:
            return stop.value

    def _ticks(self, session: SumoSession, sinks: dict[str, TableSink], progress: bool):
        """The tick loop as a generator: it yields each ego tick, after the tick's stages, and
        takes the ego's decision for it (an acceleration, m/s^2, or a vcfusion.control.Command);
        returns the loop's outcome (collisions, end reason, channel)."""
        sc = self.scenario
        dt = sc.simulation.step_s
        tick_every = sc.steps(sc.v2c.period_s)
        traj_every = sc.steps(sc.simulation.trajectory_period_s)
        channel = V2CChannel(sc.v2c, self.rng)
        store = TwinStore(sc.v2c, session.road, sc.simulation.max_time_s)
        for name, model in self.process_models:
            store.add_process_model(name, model)

        out = {"channel": channel}
        # the ego's 0.01-s rows as plain tuples in EGO_COLUMNS order, converted every 1,000 steps
        ego_rows: list[tuple] = []
        ego_cfg = sc.ego
        ego_speed = ego_cfg.speed_mps if ego_cfg else 0.0
        ego_accel = 0.0
        stepper = getattr(self.controller, "step", None)  # a per-step controller (a person driving)
        command = None
        if ego_cfg is not None:
            trip_end_s = ego_cfg.depart_pos_m + ego_cfg.trip_distance_m
        end_reason = "max_time"
        max_steps = int(round(sc.simulation.max_time_s / dt))
        bar = tqdm(total=max_steps, unit="step", desc=f"{sc.name} seed {self.seed}", disable=not progress,
                   leave=False, mininterval=0.5)
        k = int(round(session.time / dt))
        # the session's per-step calls bound once (the loop runs 100 times per simulated second)
        ego_state, set_ego_speed, sumo_step = session.ego_state, session.set_ego_speed, session.step
        no_leader = ("", np.nan)
        while k < max_steps:
            is_tick = k % tick_every == 0
            is_traj = k % traj_every == 0
            if is_tick or is_traj:
                truth = session.states()
                if is_traj:
                    sinks["trajectories"].append(_truth_rows(truth, session.road))
            if ego_cfg is not None:
                state = ego_state()
                if state is None:
                    end_reason = "ego_off_route" if session.ego_off_route else "ego_left"
                    break
                s_front, ego_speed_now, sumo_acc, leader = state
                if s_front >= trip_end_s:
                    end_reason = "trip_complete"
                    break
            if is_tick:
                raise_if_received()  # a Ctrl-C that numba swallowed while compiling (vcfusion.interrupts)
                now = truth.time
                channel.send(channel.measure(truth))
                for batch in channel.deliver(now):
                    store.ingest(batch)
                store.forget_stale(now)
                twins = store.snapshot(now)
                sinks["twins"].append(_twin_rows(twins))
                ego_view = near = None
                if ego_cfg is not None:
                    i = truth.index_of(EGO_ID)
                    ego_view = self._ego_view(session, truth, i, leader)
                    near = neighbours(twins, (truth.x[i], truth.y[i]), sc.v2c.neighbour_range_m, EGO_ID)
                tick = Tick(now, truth, twins, ego_view, near)
                for hook in self.hooks:
                    sinks[hook.table].append_rows(hook(tick) or [])
                if ego_cfg is not None:
                    decision = yield tick
                    if isinstance(decision, StopRun):  # the caller ends the run here (LiveRun.stop)
                        end_reason = decision.reason
                        break
                    if isinstance(decision, Command):
                        ego_accel = float(decision.accel)
                        if decision.lane_change:
                            session.change_ego_lane(decision.lane_change)
                    else:
                        ego_accel = float(decision)
            if stepper is not None:
                command = stepper(EgoStep(session.time, s_front, ego_speed_now, session.states))
                ego_accel = float(command.accel)
            if ego_cfg is not None:
                # session.time is the nearest double to a whole number of milliseconds: its own round(.., 6)
                ego_rows.append((session.time, s_front, ego_speed_now, sumo_acc, ego_accel, *(leader or no_leader)))
                if len(ego_rows) >= 1000:
                    sinks["ego"].append(_ego_columns(ego_rows))
                    ego_rows = []
                ego_speed = max(0.0, ego_speed + ego_accel * dt)
                set_ego_speed(ego_speed)
                if command is not None and command.d is not None:
                    # SUMO moves its vehicles s += v dt with the new speed; the placed ego does the same
                    session.place_ego(s_front + ego_speed * dt * np.cos(command.yaw), command.d, command.yaw)
            sumo_step()
            k += 1
            if k % tick_every == 0:
                if progress:
                    bar.update(tick_every)
                if not sc.flows and session.vehicle_count() == 0:
                    end_reason = "no_vehicles"
                    break
        bar.close()
        if ego_rows:
            sinks["ego"].append(_ego_columns(ego_rows))
        out["collisions"] = session.collisions
        out["end_reason"] = end_reason
        return out

    def _ego_view(self, session: SumoSession, truth: VehicleStates, i: int,
                  leader: tuple[str, float] | None) -> EgoView:
        s = truth.road_frame(session.road)[0][i]
        leader_speed = None
        if leader:
            # the truth was read at this step (SumoSession.states: SUMO's getSpeed of every vehicle), so
            # the leader's speed there is SUMO's getSpeed(leader) without another libsumo call
            ids = truth.ids
            leader_speed = float(truth.speed[ids.index(leader[0])]) if leader[0] in ids else session.speed_of(leader[0])
        return EgoView(
            speed=float(truth.speed[i]), accel=float(truth.accel[i]),
            s=float(s + truth.length[i] / 2), lane=int(truth.lane[i]),
            leader_id=leader[0] if leader else None,
            leader_gap_m=leader[1] if leader else None,
            leader_speed=leader_speed,
        )


class LiveRun:
    """A run driven from outside its loop, one ego tick at a time: the loop of
    :meth:`CoSimulation.run` (the same stages, tables and SUMO session), with each tick's ego
    decision (an acceleration or a vcfusion.control.Command) given by the caller instead of the
    run's controller. ``tick`` is the tick waiting for a decision (None once the run has ended);
    ``advance(decision)`` applies it and runs to the next ego tick; ``result()`` gives the run's
    tables and summary once it has ended; ``close()`` stops it and frees SUMO (libsumo: one
    simulation per process, so one live run at a time)."""

    def __init__(self, cosim: CoSimulation, progress: bool = False):
        if cosim.scenario.ego is None:
            raise WiringError(f"scenario {cosim.scenario.name}: a live run decides for the ego; expected an ego block")
        cosim.check_wiring()
        self.cosim = cosim
        self._started = wallclock.perf_counter()
        self._workdir, self._sinks, self._lc_file, self.session = cosim._open()
        self._blas = ExitStack()
        self._blas.enter_context(one_blas_thread())  # as run() holds it around its loop
        self._ticks = cosim._ticks(self.session, self._sinks, progress)
        self.tick: Tick | None = None
        self.out: dict | None = None
        self._closed = False
        self._advance(None)

    @property
    def ended(self) -> bool:
        return self.out is not None

    @property
    def end_reason(self) -> str | None:
        return self.out["end_reason"] if self.out is not None else None

    def _advance(self, decision) -> Tick | None:
        try:
            self.tick = next(self._ticks) if decision is None else self._ticks.send(decision)
        except StopIteration as stop:
            self.tick, self.out = None, stop.value
            self._loop_wall = wallclock.perf_counter() - self._started
        except BaseException:
            self.close()
            raise
        return self.tick

    def advance(self, decision: float | Command) -> Tick | None:
        """Apply the decision for the waiting tick and run to the next ego tick (None: the run ended)."""
        if self.tick is None:
            raise RuntimeError("LiveRun.advance: the run has ended (end_reason: "
                               f"{self.end_reason}); expected a new run")
        return self._advance(decision)

    def stop(self, reason: str) -> None:
        """End the run at the waiting tick (its tables end there; `reason` is the summary's end_reason)."""
        if self.tick is not None:
            self._advance(StopRun(reason))

    def result(self) -> RunResult:
        """The run's tables and summary, as run() returns them (the run must have ended)."""
        if self.out is None:
            raise RuntimeError("LiveRun.result: the run has not ended; advance it to its end first")
        try:
            self.session.finish()
        finally:
            self._stop()
        return self.cosim._results(self.session, self._workdir, self._sinks, self._lc_file, self.out, self._started,
                                   self._loop_wall)

    def _stop(self) -> None:
        if not self._closed:
            self._closed = True
            self._ticks.close()
            self.session.close()
            self._blas.close()

    def close(self) -> None:
        """Stop the run, free SUMO and remove its working folder (nothing is kept)."""
        was_open = not self._closed
        self._stop()
        if was_open:
            for sink in self._sinks.values():
                sink.close()
            self._workdir.cleanup()


def _ego_lane_at(tracks: dict, times: np.ndarray, road: RoadFrame, start_lane: int) -> np.ndarray:
    """The ego's lane at each of `times` (its nearest trajectory sample): a person may change
    lanes (vcfusion.hitl), so "into the ego's lane" means the lane it drives in then."""
    ego = tracks.get(EGO_ID)
    if ego is None or not len(ego["time"]) or not len(times):
        return np.full(len(times), start_lane)
    at = np.abs(ego["time"][None, :] - np.asarray(times)[:, None]).argmin(axis=1)
    return road.lane_of(ego["s"][at], ego["d"][at])


def _finish(stage, tables: RunTables, summary: dict) -> None:
    """A stage's end-of-run step, held to what it declared (vcfusion.stages): it may add its
    tables and summary keys, never replace another's."""
    finish = getattr(stage, "finish", None)
    if finish is None:
        return
    tables_before, keys_before = set(tables), set(summary)
    finish(tables, summary)
    for kind, before, after, allowed in (("table", tables_before, set(tables), declared(stage, "finish_tables")),
                                         ("summary key", keys_before, set(summary), declared(stage, "finish_summary"))):
        extra = sorted((after - before) - set(allowed)) or sorted(set(allowed) & before)
        if extra:
            raise WiringError(f"{stage_name(stage)}.finish wrote {kind} {extra[0]!r}, which it does not declare "
                              f"or which an earlier step wrote")


def summarize(sc: Scenario, seed: int, tables, lc: dict[str, np.ndarray], channel: V2CChannel, end_reason: str,
              traj) -> dict:
    """The run summary. `lc`: the lane_changes table as columns; `traj`: an Arrow table with at
    least the vehicle_id and time columns of the trajectories."""
    to_lanes, per_lane = np.unique(lc["to_lane"], return_counts=True)
    reasons, per_reason = np.unique(lc["reason"], return_counts=True)
    summary: dict = {
        "scenario": sc.name,
        "seed": seed,
        "end_reason": end_reason,
        "simulated_s": float(pc.max(traj["time"]).as_py()) if traj.num_rows else 0.0,
        "vehicles": int(pc.count_distinct(traj["vehicle_id"]).as_py()) if traj.num_rows else 0,
        "lane_changes": int(len(lc["event_id"])),
        "lane_changes_by_target_lane": {int(k): int(v) for k, v in zip(to_lanes, per_lane)},
        "lane_changes_by_reason": {str(k): int(v) for k, v in zip(reasons, per_reason)},
        "collisions": len(colliding_pairs(tables["collisions"])),
        "v2c_reports_sent": channel.sent,
        "v2c_reports_lost": channel.lost,
    }
    if sc.ego is not None and "into_ego_lane" in lc:
        cut = cut_ins(lc, sc.metrics.leader_range_m)
        ego = tables.arrow("ego", ["s", "speed", "leader_gap_m"])
        s, speed, gap = (ego.column(c).to_numpy() for c in ("s", "speed", "leader_gap_m"))
        summary.update({
            "ego_lane": sc.ego.lane,
            "cut_ins_ahead_of_ego": int(cut.sum()),
            "cut_ins": [
                {"vehicle_id": str(vid), "mid_time": float(mid), "gap_to_ego_m": round(float(gap_m), 2)}
                for vid, mid, gap_m in zip(lc["vehicle_id"][cut], lc["mid_time"][cut], lc["gap_to_ego_m"][cut])
            ],
            "ego_distance_m": float(s[-1] - s[0]) if len(s) else 0.0,
            "ego_mean_speed_mps": float(speed.mean()) if len(speed) else 0.0,
            "ego_min_leader_gap_m": float(np.nanmin(gap)) if (~np.isnan(gap)).any() else None,
        })
    return summary


def format_summary(summary: dict, wall_s: float | None = None) -> str:
    lines = [f"scenario {summary['scenario']}, seed {summary['seed']}: "
             f"{summary['simulated_s']:.1f} s simulated ({summary['end_reason']})"
             + (f" in {wall_s:.1f} s wall" if wall_s is not None else "")]
    lines.append(f"  vehicles: {summary['vehicles']}, collisions: {summary['collisions']} (vehicle pairs)")
    by_lane = ", ".join(f"into lane {k}: {v}" for k, v in summary["lane_changes_by_target_lane"].items()) or "none"
    lines.append(f"  lane changes: {summary['lane_changes']} ({by_lane})")
    if summary["lane_changes_by_reason"]:
        lines.append("  reasons: " + ", ".join(f"{k} {v}" for k, v in summary["lane_changes_by_reason"].items()))
    if "ego_lane" in summary:
        lines.append(f"  ego (departed in lane {summary['ego_lane']}): {summary['ego_distance_m']:.0f} m at "
                     f"{summary['ego_mean_speed_mps']:.1f} m/s mean; cut-ins ahead of the ego: "
                     f"{summary['cut_ins_ahead_of_ego']}")
        for c in summary["cut_ins"]:
            lines.append(f"    {c['vehicle_id']} at t = {c['mid_time']:.2f} s, {c['gap_to_ego_m']:.1f} m ahead")
        for rec in summary.get("ego_collisions", []):
            lines.append(f"  ego collision: {describe_collision(rec)}")
    if "lane_change_flags" in summary:
        lines.append("  cloud lane-change flags, changes into the ego lane (s before end / before mid):")
        for f in summary["lane_change_flags"]:
            if f["final_run_before_end_s"] is None:
                lines.append(f"    {f['vehicle_id']} (ends t = {f['end_time']:.1f} s): not flagged")
            else:
                lines.append(f"    {f['vehicle_id']} (ends t = {f['end_time']:.1f} s): final run from "
                             f"{f['final_run_before_end_s']:.1f} / {f['final_run_before_mid_s']:.1f} s, first positive "
                             f"{f['first_before_end_s']:.1f} / {f['first_before_mid_s']:.1f} s")
    lost = summary["v2c_reports_lost"]
    lines.append(f"  V2C: {summary['v2c_reports_sent']} reports sent, {lost} lost")
    return "\n".join(lines)
