"""Axis maps: which joystick axis is steering, throttle and brake, their raw ranges and inversion.

A map is a small JSON file (`vcfusion drive --calibrate` writes one; `--axis-map FILE` reads it):

    {"device": "Logitech G29 Driving Force Racing Wheel",
     "steer":    {"axis": 0, "min": -1.0, "max": 1.0, "inverted": false, "deadzone": 0.0},
     "throttle": {"axis": 2, "min": -1.0, "max": 1.0, "inverted": true},
     "brake":    {"axis": 3, "min": -1.0, "max": 1.0, "inverted": true},
     "lane_left_button": 5, "lane_right_button": 4}

Raw values are SDL's, -1..1. A value is first scaled to t = (raw - min) / (max - min) in [0, 1].
Steering: not inverted means `min` is full LEFT (SDL's own convention: left is negative): +1 at
`min`, 0 at `centre` (the wheel at rest, from the calibration; default halfway), -1 at `max`, each
side linear; inverted swaps the sides. Pedals: not inverted
means `max` is fully pressed, so pedal = t; inverted (the Logitech pedals: +1 released, -1 floored)
means pedal = 1 - t.

Presets (by a substring of the SDL device name) are starting points for the Logitech G29 / G920 /
G923 (steering axis 0, throttle 2, brake 3, pedals inverted: the layout CARLA's wheel client and
most simulator configs use for these wheels) and for game pads (left stick, triggers). They have
not been checked on the hardware here: run `vcfusion drive --calibrate` once per wheel and station.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from vcfusion.errors import UsageError


class AxisRange(BaseModel):
    model_config = ConfigDict(extra="forbid")

    axis: int = Field(ge=0)
    min: float = Field(ge=-1.0, le=1.0)
    max: float = Field(ge=-1.0, le=1.0)
    inverted: bool = False
    deadzone: float = Field(default=0.0, ge=0.0, lt=1.0)
    # steering: the raw value of the wheel at rest (None: halfway between min and max). A wheel
    # that turns further one way than the other rests off that midpoint, and read linearly over
    # min..max its centre steered (-1.0 .. 0.8 read a centred wheel as 11 % right lock)
    centre: float | None = Field(default=None, ge=-1.0, le=1.0)

    @model_validator(mode="after")
    def _range(self):
        if not self.max > self.min:
            raise ValueError(f"max ({self.max}) must be above min ({self.min})")
        if self.centre is not None and not self.min < self.centre < self.max:
            raise ValueError(f"centre ({self.centre}) must lie between min ({self.min}) and max ({self.max})")
        return self

    def unit(self, raw: float) -> float:
        """The raw value scaled to [0, 1] over the calibrated range."""
        return min(1.0, max(0.0, (raw - self.min) / (self.max - self.min)))

    def steer(self, raw: float) -> float:
        # each side of the centre scaled on its own: full lock at min and max, 0 at the centre
        centre = (self.min + self.max) / 2 if self.centre is None else self.centre
        raw = min(self.max, max(self.min, raw))
        value = (centre - raw) / (centre - self.min) if raw <= centre else -(raw - centre) / (self.max - centre)
        value = -value if self.inverted else value
        if abs(value) <= self.deadzone:
            return 0.0
        # outside the dead zone the scale restarts at 0, so small corrections stay possible
        return (abs(value) - self.deadzone) / (1.0 - self.deadzone) * (1.0 if value > 0 else -1.0)

    def pedal(self, raw: float) -> float:
        t = self.unit(raw)
        t = 1.0 - t if self.inverted else t
        # a pedal resting slightly pressed (a worn spring, a foot on it) reads released
        return 0.0 if t <= self.deadzone else (t - self.deadzone) / (1.0 - self.deadzone)


class AxisMap(BaseModel):
    model_config = ConfigDict(extra="forbid")

    device: str = ""
    steer: AxisRange
    throttle: AxisRange
    brake: AxisRange
    lane_left_button: int | None = Field(default=None, ge=0)
    lane_right_button: int | None = Field(default=None, ge=0)

    @model_validator(mode="after")
    def _distinct(self):
        axes = [self.steer.axis, self.throttle.axis, self.brake.axis]
        if len(set(axes)) != 3:
            raise ValueError(f"steer, throttle and brake must be three different axes, got {axes}")
        return self

    def save(self, path: Path) -> None:
        from vcfusion.runio import atomic_write

        text = json.dumps(self.model_dump(), indent=2) + "\n"
        atomic_write(Path(path), lambda tmp: tmp.write_text(text))


def load_axis_map(path: Path) -> AxisMap:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise UsageError(f"{path}: axis-map file not found") from None
    except json.JSONDecodeError as exc:
        raise UsageError(f"{path}: not JSON ({exc})") from None
    try:
        return AxisMap.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = ".".join(str(p) for p in err["loc"]) or "(file)"
        raise UsageError(f"{path}: {field}: {err['msg']}") from None


def _logitech(name: str) -> AxisMap:
    pedal = dict(min=-1.0, max=1.0, inverted=True)
    return AxisMap(device=name, steer=AxisRange(axis=0, min=-1.0, max=1.0),
                   throttle=AxisRange(axis=2, **pedal), brake=AxisRange(axis=3, **pedal),
                   lane_left_button=5, lane_right_button=4)  # the paddles behind the wheel


PRESETS: dict[str, AxisMap] = {
    "G29": _logitech("Logitech G29"),
    "G920": _logitech("Logitech G920"),
    "G923": _logitech("Logitech G923"),
}
# SDL's joystick layout of common game pads: left stick x, left trigger 2, right trigger 5,
# triggers at -1 when released; shoulder buttons 4 / 5 change lanes.
GAMEPAD = AxisMap(device="game pad", steer=AxisRange(axis=0, min=-1.0, max=1.0, deadzone=0.05),
                  throttle=AxisRange(axis=5, min=-1.0, max=1.0), brake=AxisRange(axis=2, min=-1.0, max=1.0),
                  lane_left_button=4, lane_right_button=5)


def preset_for(device_name: str, num_axes: int) -> AxisMap | None:
    """The preset for an SDL device name, or the game-pad layout when the device has its axes;
    None when neither fits (then the device needs a calibration file)."""
    for key, preset in PRESETS.items():
        if key.lower() in device_name.lower():
            return preset
    return GAMEPAD if num_axes >= 6 else None


Control = Literal["steer_left", "steer_right", "throttle", "brake"]


def axis_map_from_phases(rest: list[float], held: dict[str, list[float]], device: str = "") -> AxisMap:
    """The axis map from a calibration: `rest` = every axis with hands and feet off; `held` =
    every axis while the person holds each of `steer_left`, `steer_right`, `throttle`, `brake`
    fully. Steering is the axis that differs most between left and right; each pedal the axis
    (not yet taken) that moved most from rest. Raises UsageError when a control moved nothing."""
    missing = [c for c in ("steer_left", "steer_right", "throttle", "brake") if c not in held]
    if missing:
        raise UsageError(f"calibration: no readings for {missing}")
    n = len(rest)

    def pick(delta: list[float], taken: set[int], what: str) -> int:
        best = max((i for i in range(n) if i not in taken), key=lambda i: delta[i], default=None)
        if best is None or delta[best] < 0.2:
            raise UsageError(f"calibration: no axis moved for {what} (largest change "
                             f"{0.0 if best is None else delta[best]:.2f}); was the device held fully?")
        return best

    left, right = held["steer_left"], held["steer_right"]
    steer = pick([abs(left[i] - right[i]) for i in range(n)], set(), "steering")
    lo, hi = min(left[steer], right[steer]), max(left[steer], right[steer])
    steer_range = AxisRange(axis=steer, min=lo, max=hi, inverted=left[steer] > right[steer],
                            centre=rest[steer] if lo < rest[steer] < hi else None)
    pedals = {}
    for name in ("throttle", "brake"):
        pressed = held[name]
        axis = pick([abs(pressed[i] - rest[i]) for i in range(n)], {steer, *(p.axis for p in pedals.values())}, name)
        pedals[name] = AxisRange(axis=axis, min=min(rest[axis], pressed[axis]), max=max(rest[axis], pressed[axis]),
                                 inverted=pressed[axis] < rest[axis])
    return AxisMap(device=device, steer=steer_range, **pedals)
