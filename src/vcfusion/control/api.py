"""The ego controller API: what an ego controller receives every V2C tick and what it returns.

A controller is any object with ``act(observation) -> Command`` (:class:`Controller`). The tick
loop (vcfusion.cosim) calls it once per V2C tick, after the tick's stages (cloud twins, camera,
fusion, guidance), and holds the command's acceleration for the SUMO steps until the next tick.

What a controller receives (:class:`Observation`) is what the ego has at that tick:

- ``ego``: its own state (speed, acceleration, front bumper along its route, lane) and its radar
  leader in its lane (id, bumper-to-bumper gap, speed);
- ``neighbours``: the cloud Digital Twins it receives over V2C (within
  ``v2c.neighbour_range_m``), as the cloud has them: GNSS positions with the scenario's error and
  latency, and each twin process model's outputs (``lc_prob``, the lane-change probability, when
  ``prediction.enabled``);
- ``frame``, ``detections``, ``guidance``: the ego camera's image, the detector's boxes and the
  guidance shown to the driver, where the scenario runs those stages (else None).

Nothing in it is the simulated ground truth of other vehicles. A controller that models a
person's eyes (the built-in driver model, vcfusion.driver.perception: field of view, mirror,
occlusion) declares ``perceives = True`` and receives ``scene``: the simulated world, which it
must pass through its own perception model. ADAS logic and learned policies leave it off.

Optional members of a controller (all read once, when the run is built):

- ``needs``: further Tick fields it reads (``"guidance"``, ``"frame"``, ``"detections"``;
  vcfusion.stages checks that a stage of the run provides them);
- ``start(context)``: called with the run's :class:`ControllerContext` before the first tick;
- ``finish(tables, summary)`` with ``finish_tables`` / ``finish_summary``: its end-of-run tables
  and summary keys (vcfusion.stages);
- ``step(EgoStep) -> EgoCommand``: a per-step controller (a person at the wheel, vcfusion.hitl),
  called before every SUMO step; it sets the ego's acceleration and may place it across the road.

A scenario names its controller by import path (``ego.controller: "mypkg.mod:MyController"``,
with ``ego.controller_params`` passed as keyword arguments); without one the ego is driven by
the built-in driver model (vcfusion.driver.model).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    from vcfusion.cosim import EgoView
    from vcfusion.detection.detectors import Detections
    from vcfusion.records import GuidanceSet, TwinStates, VehicleStates
    from vcfusion.scenario import Scenario

# Lane-change requests of a Command: toward the left (higher lane index) or the right lane.
LEFT, KEEP, RIGHT = 1, 0, -1


@dataclass(frozen=True)
class Command:
    """A controller's command for the steps until the next tick.

    ``accel``: the ego's longitudinal acceleration, m/s^2 (the loop integrates the speed every
    SUMO step and holds it at or above 0). ``lane_change``: +1 asks for the lane to the left, -1
    for the lane to the right, 0 keeps the lane. A request starts a lane change of
    ``simulation.lanechange_duration_s`` (SUMO's continuous lane change) toward the adjacent lane;
    a request toward a lane that is absent there is refused by SUMO and the ego keeps its lane
    (the observation's ``ego.lane`` shows which lane it is in). Lateral safety is the controller's:
    SUMO does not check the target lane's gaps for the ego.
    """

    accel: float
    lane_change: int = KEEP

    def __post_init__(self):
        if self.lane_change not in (LEFT, KEEP, RIGHT):
            raise ValueError(f"Command.lane_change: expected -1, 0 or 1, got {self.lane_change!r}")


@dataclass(frozen=True)
class Observation:
    """What the ego has at one V2C tick (see the module doc). Times in s, SI units."""

    time: float
    ego: EgoView
    neighbours: TwinStates
    frame: Any = None  # render.renderer.Frame or fusion.fuse.CameraFrame: RGB + metric depth
    detections: Detections | None = None
    guidance: GuidanceSet | None = None
    # the simulated world, only for a controller with `perceives = True` (a model of a person's eyes)
    scene: VehicleStates | None = None

    def lane_change_probability(self) -> dict[str, float]:
        """Each received twin's lane-change probability (``lc_prob``) by vehicle id; empty when no
        process model of the run writes it."""
        prob = self.neighbours.outputs.get("lc_prob")
        if prob is None:
            return {}
        return dict(zip(self.neighbours.ids, (float(p) for p in prob)))


@dataclass(frozen=True)
class ControllerContext:
    """What a controller may read once, before the first tick (``start(context)``)."""

    scenario: Scenario
    seed: int
    road: Any  # the scenario's road frame (vcfusion.traffic.roadframe): lanes, (s, d) of a point
    guidance_enabled: bool  # whether the ego's driver uses the guidance (driver.guidance)


@runtime_checkable
class Controller(Protocol):
    """An ego controller: ``act`` is called every V2C tick (see the module doc)."""

    def act(self, observation: Observation) -> Command: ...
