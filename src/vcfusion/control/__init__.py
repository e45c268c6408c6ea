"""Bring your own ego: the controller API (see vcfusion.control.api for the contract).

    from vcfusion.control import Command, Observation

    class Brake:
        def act(self, obs: Observation) -> Command:
            return Command(accel=-2.0 if obs.ego.speed > 10.0 else 0.0)

A scenario names it with ``ego.controller: "mymodule:Brake"`` (and ``ego.controller_params``).
"""

from vcfusion.control.api import KEEP, LEFT, RIGHT, Command, Controller, ControllerContext, Observation
from vcfusion.control.stage import ControllerError, ControllerStage, load_controller

__all__ = ["Command", "Controller", "ControllerContext", "ControllerError", "ControllerStage", "KEEP", "LEFT",
           "Observation", "RIGHT", "load_controller"]
