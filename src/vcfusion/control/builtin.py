"""Controllers that ship with vcfusion, as implementations of vcfusion.control.Controller.

- :class:`DriverModelController`: the built-in driver model (vcfusion.driver.model). A scenario
  without ``ego.controller`` runs the driver model itself; naming this class gives the same run
  (tested: byte-identical tables).
- :class:`IdmController`: IDM on the radar leader (vcfusion.driver.idm), no person in it.
- :class:`ScriptedController`: a fixed acceleration over a time window, then IDM; a baseline
  and a test fixture.

The human driver (vcfusion.hitl.driver.HumanDriver) is the per-step kind: ``act`` takes the
tick's guidance and camera frame for its display, and ``step`` reads the wheel and pedals before
every SUMO step (see vcfusion.control.api).
"""

from __future__ import annotations

from types import SimpleNamespace

from vcfusion.control.api import Command, ControllerContext, Observation
from vcfusion.driver.idm import IDMParams, idm_acceleration


class DriverModelController:
    """The driver model of vcfusion.driver.model behind the controller API. Its perception model
    (field of view, mirror, occlusion) reads the scene (``perceives``); the driver is drawn from
    the run's seed as in ``vcfusion run``. Tables ``driver`` and ``driver_events`` and the summary's
    ``driver`` block as there."""

    perceives = True
    finish_tables = ("driver", "driver_events")
    finish_summary = ("driver",)

    def __init__(self, guidance: bool | None = None):
        self.guidance = guidance  # None: the scenario's driver.guidance
        self.model = None
        self.needs: tuple[str, ...] = ()

    def start(self, context: ControllerContext) -> None:
        from vcfusion.driver.model import DriverModel
        from vcfusion.driver.params import draw_driver
        from vcfusion.driver.perception import DriverView
        from vcfusion.guidance import GuidancePolicy

        sc = context.scenario
        enabled = context.guidance_enabled if self.guidance is None else self.guidance
        self.model = DriverModel(draw_driver(context.seed, sc.ego.desired_speed_mps), context.road,
                                 GuidancePolicy.from_scenario(sc, context.road), enabled,
                                 view=DriverView.from_scenario(sc))
        self.needs = tuple(f for f in self.model.needs if f != "ego")

    def act(self, observation: Observation) -> Command:
        if self.model is None:
            raise RuntimeError("DriverModelController: start(context) was not called (the run builds it)")
        # the driver model reads the tick's time, guidance and the scene it perceives
        tick = SimpleNamespace(time=observation.time, truth=observation.scene, guidance=observation.guidance)
        return Command(self.model.acceleration(tick))

    def finish(self, tables, summary: dict) -> None:
        self.model.finish(tables, summary)


class IdmController:
    """IDM (Treiber et al. 2000) on the radar leader in the ego's lane. ``desired_speed_mps``
    None: the scenario's ``ego.desired_speed_mps``; the other parameters are IDMParams'."""

    def __init__(self, desired_speed_mps: float | None = None, **idm):
        self.desired = desired_speed_mps
        self.idm = idm
        self.params = IDMParams(**idm) if desired_speed_mps is None else IDMParams(desired_speed_mps, **idm)

    def start(self, context: ControllerContext) -> None:
        if self.desired is None:
            self.params = IDMParams(desired_speed_mps=context.scenario.ego.desired_speed_mps, **self.idm)

    def act(self, observation: Observation) -> Command:
        ego = observation.ego
        return Command(idm_acceleration(self.params, ego.speed, ego.leader_gap_m, ego.leader_speed))


class ScriptedController(IdmController):
    """``accel_mps2`` from ``from_s`` to ``until_s`` (simulated time, s), IDM outside the window;
    ``lane_change`` (+1 left, -1 right) requested once at ``lane_change_at_s`` when given."""

    def __init__(self, accel_mps2: float, from_s: float = 0.0, until_s: float = float("inf"),
                 lane_change: int = 0, lane_change_at_s: float | None = None, desired_speed_mps: float | None = None):
        super().__init__(desired_speed_mps)
        self.accel = float(accel_mps2)
        self.window = (float(from_s), float(until_s))
        self.lane_change = int(lane_change)
        self.lane_change_at = lane_change_at_s
        self._asked = False

    def act(self, observation: Observation) -> Command:
        now = observation.time
        change = 0
        due = self.lane_change_at is not None and now >= self.lane_change_at - 1e-9
        if self.lane_change and due and not self._asked:
            change, self._asked = self.lane_change, True
        if self.window[0] - 1e-9 <= now < self.window[1] - 1e-9:
            return Command(self.accel, change)
        return Command(super().act(observation).accel, change)
