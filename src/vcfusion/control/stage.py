"""A controller of the API (vcfusion.control.api) as the tick loop's ego stage, and loading one
by the import path a scenario names."""

from __future__ import annotations

import importlib
import inspect

from vcfusion.control.api import Command, Controller, ControllerContext, Observation

# Tick fields a controller may ask for beyond the ego's own (vcfusion.stages checks that a stage
# of the run provides them).
OPTIONAL_FIELDS = ("frame", "detections", "guidance")


class ControllerError(ValueError):
    """A controller that cannot be loaded or built; the message names the import path."""


def resolve(path: str):
    """The object an import path ``package.module:Name`` names (``Name`` may be dotted: a nested
    attribute). Raises :class:`ControllerError` naming what failed."""
    if not isinstance(path, str) or path.count(":") != 1 or not all(path.split(":")):
        raise ControllerError(f"expected an import path 'package.module:Name', got {path!r}")
    module_name, attribute = path.split(":")
    try:
        target = importlib.import_module(module_name)
    except ImportError as exc:
        raise ControllerError(f"{path}: cannot import module {module_name!r} ({exc})") from None
    for part in attribute.split("."):
        if not hasattr(target, part):
            raise ControllerError(f"{path}: module {module_name!r} has no attribute {attribute!r}")
        target = getattr(target, part)
    if not callable(target):
        raise ControllerError(f"{path}: {attribute!r} is not callable; expected a controller class or factory")
    return target


def check_params(path: str, params: dict) -> None:
    """ControllerError unless the factory at `path` accepts `params` as keyword arguments."""
    factory = resolve(path)
    try:
        inspect.signature(factory).bind(**params)
    except TypeError as exc:
        raise ControllerError(f"{path}: controller_params {sorted(params)} do not fit its arguments ({exc})") from None
    except ValueError:  # a builtin without a signature: checked when it is called
        pass


def load_controller(path: str, params: dict | None = None):
    """Build the controller the import path names, with `params` as keyword arguments."""
    factory = resolve(path)
    try:
        controller = factory(**(params or {}))
    except TypeError as exc:
        raise ControllerError(f"{path}: cannot build the controller with controller_params "
                              f"{sorted(params or {})} ({exc})") from None
    if not callable(getattr(controller, "act", None)):
        raise ControllerError(f"{path}: built a {type(controller).__name__}, which has no act(observation) method; "
                              "expected a vcfusion.control.Controller")
    return controller


class ControllerStage:
    """The tick loop's ego stage for a :class:`Controller`: builds the Observation from the tick
    and returns the controller's Command (the loop applies its acceleration and lane change).

    It declares what the controller declares (``needs``, ``finish`` and its tables / summary
    keys) and forwards a per-step controller's ``step``."""

    def __init__(self, controller: Controller, context: ControllerContext | None = None):
        self.controller = controller
        self.name = type(controller).__name__
        if context is not None and callable(getattr(controller, "start", None)):
            controller.start(context)
        wanted = tuple(getattr(controller, "needs", ()) or ())
        unknown = [f for f in wanted if f not in OPTIONAL_FIELDS + ("ego", "neighbours")]
        if unknown:
            raise ControllerError(f"controller {self.name}: needs {unknown[0]!r}; expected some of {OPTIONAL_FIELDS}")
        self.needs = ("ego",) + tuple(f for f in wanted if f in OPTIONAL_FIELDS)
        self.perceives = bool(getattr(controller, "perceives", False))
        for attribute in ("finish_tables", "finish_summary", "finish_needs"):
            if hasattr(controller, attribute):
                setattr(self, attribute, getattr(controller, attribute))
        if callable(getattr(controller, "finish", None)):
            self.finish = controller.finish
        if callable(getattr(controller, "step", None)):
            self.step = controller.step

    def observe(self, tick) -> Observation:
        return Observation(time=tick.time, ego=tick.ego, neighbours=tick.neighbours, frame=tick.frame,
                           detections=tick.detections, guidance=tick.guidance,
                           scene=tick.truth if self.perceives else None)

    def acceleration(self, tick) -> Command:
        command = self.controller.act(self.observe(tick))
        if not isinstance(command, Command):
            raise ControllerError(f"controller {self.name}: act() returned a {type(command).__name__}; "
                                  "expected a vcfusion.control.Command")
        return command
