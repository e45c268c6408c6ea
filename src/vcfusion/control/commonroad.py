"""A run folder as a CommonRoad scenario (commonroad-io): the road as lanelets, every vehicle's
trajectory as a dynamic obstacle, and the ego's trip as a planning problem.

- Time: CommonRoad's time step is the run's ``simulation.trajectory_period_s``; a sample at time
  t is time step round(t / dt).
- Road: one lanelet per lane (track) of the scenario's route and per stretch where the lane
  exists (RoadFrame.lane_spans), with its left, centre and right lines sampled every
  LANELET_STEP_M along the road (the ends included) in SUMO's world frame; lanelets of neighbouring
  tracks that cover the same stretch are adjacent (same direction).
- Vehicles: a DynamicObstacle per vehicle of ``vehicles.parquet`` (the parked accident vehicles
  too, with their standing trajectory), a rectangle of its length and width; states at every
  trajectory sample: position = the footprint centre (the trajectories' x, y), orientation = the
  heading (rad, counter-clockwise from the x axis, as CommonRoad's), velocity, acceleration.
  Obstacle ids: OBSTACLE_ID0 + the vehicle's row in ``vehicles.parquet``; the ego is one of them
  (``ego_obstacle_id`` in the id table written beside the file).
- Ego: also the planning problem (its first state; goal: the run's remaining time steps).

Needs commonroad-io (the ``commonroad`` extra). commonroad-io pins protobuf 3.20.2, which
onnx >= 1.17 (the ``dev`` extra's ONNX export) refuses: install it in an environment of its own.
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.errors import InputError

LANELET_STEP_M = 5.0  # sampling of the lanelets' lines along the road
LANELET_ID0 = 100
OBSTACLE_ID0 = 10_000
PLANNING_PROBLEM_ID = 1
OBSTACLE_TYPES = {"truck": "TRUCK", "trailer": "TRUCK", "bus": "BUS", "coach": "BUS", "motorcycle": "MOTORCYCLE",
                  "bicycle": "BICYCLE"}  # SUMO vClass -> CommonRoad ObstacleType (others: CAR)


def use_pure_python_protobuf() -> None:
    """commonroad-io's generated protobuf modules predate protobuf 4's runtime ("Descriptors cannot
    be created directly"); protobuf's pure-Python runtime still accepts them, and onnx works on it
    too. The runtime is chosen when google.protobuf is first imported, so this takes effect only
    before that (a fresh `vcfusion export-commonroad` process, the test session's conftest); where
    protobuf was loaded first, commonroad_problem() says why the export cannot run."""
    if "google.protobuf" not in sys.modules:
        os.environ.setdefault("PROTOCOL_BUFFERS_PYTHON_IMPLEMENTATION", "python")


def commonroad_problem() -> str | None:
    """Why commonroad-io cannot be used here (None when it loads)."""
    use_pure_python_protobuf()
    try:
        import commonroad.common.file_reader  # noqa: F401
        import commonroad.common.file_writer  # noqa: F401
    except ImportError:
        return ("needs commonroad-io: pip install 'vcfusion[commonroad]' (an environment of its own: it pins "
                "protobuf 3.20.2)")
    except TypeError as exc:  # its generated protobuf modules under protobuf's compiled runtime
        return (f"commonroad-io does not load with this process's protobuf runtime ({' '.join(str(exc).split()[:6])}"
                "...): set PROTOCOL_BUFFERS_PYTHON_IMPLEMENTATION=python before anything imports protobuf")
    return None


def _rectangle(length: float, width: float):
    """A rectangle obstacle shape: commonroad-io 2025+ (obstacle_shapes) or 2024 (geometry.shape), which
    commonroad-crime 0.4 pins."""
    try:
        from commonroad.geometry.obstacle_shapes.rect_obstacle_shape import RectObstacleShape
    except ImportError:
        from commonroad.geometry.shape import Rectangle

        return Rectangle(float(length), float(width))
    return RectObstacleShape(width=float(width), length=float(length))


def _scenario_id(**fields):
    try:
        from commonroad.common.common_scenario import ScenarioID
    except ImportError:  # commonroad-io 2024
        from commonroad.scenario.scenario import ScenarioID
    return ScenarioID(**fields)


def _planning_problem(pid: int, state, goal, ego_id: int):
    import inspect

    from commonroad.planning.planning_problem import PlanningProblem

    takes_ego = "ego_id" in inspect.signature(PlanningProblem).parameters  # commonroad-io 2025+
    return PlanningProblem(pid, state, goal, ego_id=ego_id) if takes_ego else PlanningProblem(pid, state, goal)


class ExportError(InputError):
    """A run folder that cannot be exported; the message names the file and what was expected."""


def _read_run(folder: Path, scenario_path: Path | None):
    from vcfusion.run import _sha256
    from vcfusion.scenario import load_scenario

    folder = Path(folder)
    manifest_file = folder / "manifest.json"
    if not manifest_file.is_file():
        raise ExportError(f"{folder}: no manifest.json; expected a run folder of `vcfusion run` or `vcfusion drive`")
    manifest = json.loads(manifest_file.read_text())
    for name in ("trajectories.parquet", "vehicles.parquet"):
        if not (folder / name).is_file():
            raise ExportError(f"{folder}: no {name}; expected a complete run folder")
    source = scenario_path or (Path(manifest["scenario_file"]) if manifest.get("scenario_file") else None)
    if source is None or not source.is_file():
        raise ExportError(f"{folder}: the run's scenario file {source} is not found from here; expected --scenario "
                          "with the scenario the run was made from (its network gives the lanelets)")
    scenario = load_scenario(source)
    recorded = manifest.get("files_sha256", {}).get("network")
    if recorded is not None and _sha256(scenario.network) != recorded:
        raise ExportError(f"{source}: network {scenario.network.name} differs from the one the run in {folder} used "
                          "(files_sha256.network); expected the run's own scenario")
    return manifest, scenario


def _lanelets(road):
    from commonroad.common.common_lanelet import LaneletType
    from commonroad.scenario.lanelet import Lanelet

    out, by_span = [], {}
    for track in range(road.num_tracks):
        for k, (s0, s1) in enumerate(np.asarray(road.lane_spans(track), dtype=float)):
            n = max(2, int(math.ceil((s1 - s0) / LANELET_STEP_M)) + 1)
            s = np.linspace(s0, s1, n)
            right, left = (np.asarray(b, dtype=float) for b in road.lane_bounds(track, s))
            lines = [np.column_stack(road.to_world(s, d)) for d in (left, (left + right) / 2.0, right)]
            lid = LANELET_ID0 + 100 * track + k
            by_span[(track, round(s0, 3), round(s1, 3))] = lid
            out.append((lid, track, (round(s0, 3), round(s1, 3)), lines))
    lanelets = []
    for lid, track, span, (left, centre, right) in out:
        kw = {}
        if (track + 1, *span) in by_span:
            kw.update(adjacent_left=by_span[(track + 1, *span)], adjacent_left_same_direction=True)
        if (track - 1, *span) in by_span:
            kw.update(adjacent_right=by_span[(track - 1, *span)], adjacent_right_same_direction=True)
        lanelets.append(Lanelet(left, centre, right, lid, lanelet_type={LaneletType.HIGHWAY}, **kw))
    return lanelets


def _states(rows: pd.DataFrame, dt: float):
    from commonroad.scenario.state import CustomState, InitialState

    steps = np.rint(rows["time"].to_numpy() / dt).astype(int)
    cols = (rows[c].to_numpy(dtype=float) for c in ("x", "y", "heading", "speed", "accel"))
    states = []
    for k, (step, x, y, h, v, a) in enumerate(zip(steps, *cols)):
        kind = InitialState if k == 0 else CustomState
        states.append(kind(time_step=int(step), position=np.array([x, y]), orientation=float(h), velocity=float(v),
                           acceleration=float(a), yaw_rate=0.0, slip_angle=0.0))
    return states


def build_commonroad(folder: Path, scenario_path: Path | None = None):
    """(CommonRoad Scenario, PlanningProblemSet, id table) of a run folder (see the module doc)."""
    from commonroad.common.util import Interval
    from commonroad.planning.goal import GoalRegion
    from commonroad.planning.planning_problem import PlanningProblemSet
    from commonroad.prediction.prediction import TrajectoryPrediction
    from commonroad.scenario.obstacle import DynamicObstacle, ObstacleType
    from commonroad.scenario.scenario import Scenario as CrScenario
    from commonroad.scenario.state import CustomState
    from commonroad.scenario.trajectory import Trajectory

    from vcfusion.records import EGO_ID
    from vcfusion.traffic.network import read_road

    folder = Path(folder)
    manifest, sc = _read_run(folder, scenario_path)
    dt = float(sc.simulation.trajectory_period_s)
    road = read_road(sc.network, sc.route)
    scenario_id = _scenario_id(country_id="ZAM", map_name=f"vcfusion-{sc.name}", map_id=1, configuration_id=1,
                             obstacle_behavior="T", prediction_id=int(manifest["seed"]))
    scenario = CrScenario(dt, scenario_id)
    for lanelet in _lanelets(road):
        scenario.lanelet_network.add_lanelet(lanelet)
    vehicles = pd.read_parquet(folder / "vehicles.parquet")
    traj = pd.read_parquet(folder / "trajectories.parquet", columns=["time", "vehicle_id", "x", "y", "heading",
                                                                      "speed", "accel"])
    traj = traj.sort_values(["vehicle_id", "time"], kind="stable")
    by_vehicle = dict(tuple(traj.groupby("vehicle_id", sort=False)))
    ids, problems = {}, []
    for row, (vid, vclass, length, width) in enumerate(zip(vehicles["vehicle_id"], vehicles["vclass"],
                                                            vehicles["length"], vehicles["width"])):
        rows = by_vehicle.get(vid)
        if rows is None or not len(rows):
            continue
        oid = OBSTACLE_ID0 + row
        ids[str(vid)] = oid
        shape = _rectangle(length, width)
        states = _states(rows, dt)
        prediction = None
        if len(states) > 1:
            prediction = TrajectoryPrediction(Trajectory(states[1].time_step, states[1:]), shape)
        kind = ObstacleType[OBSTACLE_TYPES.get(str(vclass), "CAR")]
        scenario.add_objects(DynamicObstacle(oid, kind, shape, states[0], prediction))
        if vid == EGO_ID:
            last = states[-1].time_step
            goal = GoalRegion([CustomState(time_step=Interval(states[0].time_step, last))])
            problems.append(_planning_problem(PLANNING_PROBLEM_ID, states[0], goal, oid))
    table = {"dt": dt, "obstacle_ids": ids, "ego_obstacle_id": ids.get(EGO_ID), "run": str(folder)}
    return scenario, PlanningProblemSet(problems), table


def export_commonroad(folder: Path, out: Path, scenario_path: Path | None = None) -> dict:
    """Write the run folder as CommonRoad XML at `out` (whole or not at all) and its id table
    (vehicle id -> obstacle id) as `out` with suffix .ids.json; returns the table."""
    from commonroad.common.file_writer import CommonRoadFileWriter, FileFormat, OverwriteExistingFile
    from commonroad.scenario.scenario import Tag

    from vcfusion.runio import atomic_write

    out = Path(out)
    if out.suffix != ".xml":
        raise ExportError(f"--out {out}: expected a .xml file (CommonRoad XML)")
    scenario, problems, table = build_commonroad(folder, scenario_path)
    # XML (commonroad-io's default is protobuf), positions to 0.1 mm (4 decimals)
    writer = CommonRoadFileWriter(scenario, problems, author="vcfusion", affiliation="vcfusion",
                                  source=f"vcfusion run folder {Path(folder).name}", tags={Tag.HIGHWAY},
                                  decimal_precision=4, file_format=FileFormat.XML)

    def write(tmp: Path) -> None:
        tmp.unlink()  # the writer makes its own file (it reports replacing one)
        writer.write_to_file(str(tmp), OverwriteExistingFile.SKIP)

    atomic_write(out, write)
    ids_file = out.with_suffix(".ids.json")
    atomic_write(ids_file, lambda tmp: tmp.write_text(json.dumps(table, indent=1) + "\n"))
    return table
