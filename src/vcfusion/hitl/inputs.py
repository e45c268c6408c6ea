"""Control devices: each turns what the person does into one ControlSample per SUMO step.

All devices share one interface: the driver loop hands every SDL event to `handle(event)`, then
asks `sample(time, dt)` for the step's controls and the raw readings to record. A replayed file
is a device like the others, so a replay runs exactly the code a live trip runs.

- Keyboard: arrows or WASD. SDL's key-state array does not see events posted by software (tests,
  automation), and a held key must keep working whatever posts it, so the device keeps its own
  set of held keys from KEYDOWN / KEYUP events. Pedals and wheel move at fixed rates while a key
  is held (THROTTLE_RATE ...), in simulated time, so a replay reproduces them. Q / E ask for a
  discrete lane change left / right.
- Joystick / wheel: an AxisMap (calibration.py) maps raw SDL axes. A pedal axis reads as released
  until it has reported a value other than the one SDL gave when the device was opened: SDL (and
  the Linux driver under it) reports 0 for an axis that has sent nothing yet, which on Logitech
  pedals (+1 released, -1 floored) would read as half pressed.
- Replay: a CSV or Parquet file with time_s, throttle, brake, steer and optional lane_change
  (-1 / 0 / +1), or a previous trip's inputs.parquet (sim_time and the mapped columns). The value
  at a step is the last row at or before it (sample and hold); each row with a lane change fires
  it once.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vcfusion.errors import UsageError
from vcfusion.hitl.calibration import AxisMap
from vcfusion.hitl.vehicle import ControlSample

THROTTLE_RATE = 2.0  # per second while held (0 -> 1 in 0.5 s)
THROTTLE_RELEASE_RATE = 5.0
BRAKE_RATE = 2.0
BRAKE_RELEASE_RATE = 5.0
STEER_RATE = 1.5  # toward full lock while held
STEER_RETURN_RATE = 3.0  # back to centre when released (a self-centring wheel)
# a changing axis value must move this far from the value it had when opened to count as touched
TOUCH_EPS = 1e-3


def _toward(value: float, target: float, rate: float, dt: float) -> float:
    step = rate * dt
    return min(target, value + step) if target > value else max(target, value - step)


class KeyboardInput:
    """Arrows / WASD with its own key state (see the module doc)."""

    name = "keyboard"

    def __init__(self):
        import pygame

        self.pg = pygame
        self.held: set[int] = set()
        self._lane_change = 0
        self.steer = self.throttle = self.brake = 0.0
        k = pygame
        self.keys = {"throttle": {k.K_UP, k.K_w}, "brake": {k.K_DOWN, k.K_s},
                     "left": {k.K_LEFT, k.K_a}, "right": {k.K_RIGHT, k.K_d}}
        self.lane_keys = {k.K_q: +1, k.K_e: -1}

    def handle(self, event) -> None:
        if event.type == self.pg.KEYDOWN:
            self.held.add(event.key)
            self._lane_change = self.lane_keys.get(event.key, self._lane_change)
        elif event.type == self.pg.KEYUP:
            self.held.discard(event.key)

    def _down(self, control: str) -> bool:
        return bool(self.held & self.keys[control])

    def sample(self, time: float, dt: float) -> tuple[ControlSample, dict]:
        self.throttle = _toward(self.throttle, 1.0 if self._down("throttle") else 0.0,
                                THROTTLE_RATE if self._down("throttle") else THROTTLE_RELEASE_RATE, dt)
        self.brake = _toward(self.brake, 1.0 if self._down("brake") else 0.0,
                             BRAKE_RATE if self._down("brake") else BRAKE_RELEASE_RATE, dt)
        wanted = float(self._down("left")) - float(self._down("right"))
        self.steer = _toward(self.steer, wanted, STEER_RATE if wanted else STEER_RETURN_RATE, dt)
        lane_change, self._lane_change = self._lane_change, 0
        keys = ",".join(sorted(self.pg.key.name(k) for k in self.held))
        return ControlSample(self.steer, self.throttle, self.brake, lane_change), {"keys": keys}


class JoystickInput:
    """An SDL joystick (wheel, pedals, game pad) through an AxisMap."""

    def __init__(self, joystick, axis_map: AxisMap, map_source: str = ""):
        """`map_source`: the axis-map file the map was read from, named in errors ("" for a preset)."""
        import pygame

        self.pg = pygame
        self.joystick = joystick
        self.joystick.init()
        self.instance_id = joystick.get_instance_id()
        self.map = axis_map
        self.device_name = joystick.get_name()
        self.name = f"joystick:{self.device_name}"
        n = joystick.get_numaxes()
        used = max(axis_map.steer.axis, axis_map.throttle.axis, axis_map.brake.axis)
        if used >= n:
            source = f"{map_source}: " if map_source else f"axis map of {axis_map.device or 'the preset'}: "
            raise UsageError(f"{source}axis {used} used, but {joystick.get_name()!r} "
                             f"has {n} axes (axes 0..{n - 1}); run `vcfusion drive --calibrate`")
        self.opened = [joystick.get_axis(i) for i in range(n)]
        self.touched = [False] * n
        self._lane_change = 0
        self.connected = True
        self._loss_recorded = False
        self.disconnects: list[float] = []  # simulated times the device was found unplugged (summary)

    def _adopt(self, joystick) -> None:
        """Read `joystick` from now on (the same device plugged back in): its axes count as untouched
        again, so pedals read released until they move."""
        joystick.init()
        self.joystick = joystick
        self.instance_id = joystick.get_instance_id()
        self.opened = [joystick.get_axis(i) for i in range(joystick.get_numaxes())]
        self.touched = [False] * len(self.opened)
        self.connected = True
        self._loss_recorded = False

    def handle(self, event) -> None:
        if event.type == self.pg.JOYDEVICEADDED and not self.connected:
            js = self.pg.joystick.Joystick(event.device_index)
            # (the unplugged joystick object must not be asked anything: pygame crashes on it)
            if js.get_name() == self.device_name and js.get_numaxes() == len(self.opened):
                self._adopt(js)
            return
        if getattr(event, "instance_id", None) != self.instance_id:
            return
        if event.type == self.pg.JOYDEVICEREMOVED:
            self.connected = False
            return
        if event.type == self.pg.JOYAXISMOTION:
            if abs(event.value - self.opened[event.axis]) > TOUCH_EPS:
                self.touched[event.axis] = True
        elif event.type == self.pg.JOYBUTTONDOWN:
            if event.button == self.map.lane_left_button:
                self._lane_change = 1
            elif event.button == self.map.lane_right_button:
                self._lane_change = -1

    def sample(self, time: float, dt: float) -> tuple[ControlSample, dict]:
        if not self.connected:
            # unplugged: SDL would read its axes as 0 (both Logitech pedals half pressed); the car
            # coasts with the wheel centred until the device is back, and the trip records when
            if not self._loss_recorded:
                self.disconnects.append(round(time, 6))
                self._loss_recorded = True
            return ControlSample(0.0, 0.0, 0.0, 0), {"axes": [], "buttons": []}
        js, m = self.joystick, self.map
        axes = [float(js.get_axis(i)) for i in range(js.get_numaxes())]
        buttons = [int(js.get_button(i)) for i in range(js.get_numbuttons())]
        # never-touched axes: pedals released, wheel centred
        steer = m.steer.steer(axes[m.steer.axis]) if self.touched[m.steer.axis] else 0.0
        throttle = m.throttle.pedal(axes[m.throttle.axis]) if self.touched[m.throttle.axis] else 0.0
        brake = m.brake.pedal(axes[m.brake.axis]) if self.touched[m.brake.axis] else 0.0
        lane_change, self._lane_change = self._lane_change, 0
        return ControlSample(steer, throttle, brake, lane_change), {"axes": axes, "buttons": buttons}


REPLAY_COLUMNS = ("time_s", "throttle", "brake", "steer")


class ReplayInput:
    """Controls read from a file (see the module doc)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.name = f"replay:{self.path.name}"
        table = _read_table(self.path)
        if "time_s" not in table and "sim_time" in table:  # a previous trip's inputs.parquet
            table = table.rename(columns={"sim_time": "time_s"})
        missing = [c for c in REPLAY_COLUMNS if c not in table]
        if missing:
            raise UsageError(f"{self.path}: missing column {missing[0]!r}; expected columns "
                             f"{', '.join(REPLAY_COLUMNS)} (and optionally lane_change)")
        if len(table) == 0:
            raise UsageError(f"{self.path}: no rows")
        cols = {}
        for name, lo, hi in (("time_s", 0.0, np.inf), ("throttle", 0.0, 1.0), ("brake", 0.0, 1.0),
                             ("steer", -1.0, 1.0), ("lane_change", -1.0, 1.0)):
            if name not in table:
                cols[name] = np.zeros(len(table))
                continue
            try:
                values = table[name].to_numpy(dtype=float)
            except (TypeError, ValueError):
                raise UsageError(f"{self.path}: column {name!r}: expected numbers") from None
            bad = ~np.isfinite(values) | (values < lo) | (values > hi)
            if bad.any():
                row = int(np.flatnonzero(bad)[0])
                raise UsageError(f"{self.path}: column {name!r}, row {row + 1}: {float(values[row]):g} is outside "
                                 f"[{lo:g}, {hi:g}]")
            cols[name] = values
        if (np.diff(cols["time_s"]) < 0).any():
            row = int(np.flatnonzero(np.diff(cols["time_s"]) < 0)[0]) + 1
            raise UsageError(f"{self.path}: column 'time_s', row {row + 1}: times must not decrease")
        if not np.isin(cols["lane_change"], (-1.0, 0.0, 1.0)).all():
            raise UsageError(f"{self.path}: column 'lane_change': expected -1, 0 or +1")
        self.time, self.throttle, self.brake, self.steer = (cols[c] for c in REPLAY_COLUMNS)
        self.lane_change = cols["lane_change"].astype(int)
        self.end_s = float(self.time[-1])
        self._next_row = 0

    def handle(self, event) -> None:
        pass

    def sample(self, time: float, dt: float) -> tuple[ControlSample, dict]:
        last = int(np.searchsorted(self.time, time + 1e-9, side="right")) - 1
        if last < 0:
            return ControlSample(0.0, 0.0, 0.0, 0), {}
        lane_change = int(np.sign(self.lane_change[self._next_row:last + 1].sum()))
        self._next_row = max(self._next_row, last + 1)
        return ControlSample(float(self.steer[last]), float(self.throttle[last]), float(self.brake[last]),
                             lane_change), {}


def _read_table(path: Path):
    import pandas as pd

    if not path.is_file():
        raise UsageError(f"--input replay:{path}: file not found")
    try:
        if path.suffix.lower() == ".parquet":
            return pd.read_parquet(path)
        if path.suffix.lower() == ".csv":
            return pd.read_csv(path)
    except Exception as exc:  # the reader's own message names what is wrong in the file
        raise UsageError(f"{path}: cannot be read ({exc})") from None
    raise UsageError(f"--input replay:{path}: expected a .csv or .parquet file")


def open_input(spec: str, axis_map_file: Path | None = None):
    """`keyboard`, `joystick` (the first SDL joystick; axis map from the file, else a preset by
    device name) or `replay:FILE`. Needs SDL started (sdl.init_sdl) for the first two."""
    if spec == "keyboard":
        return KeyboardInput()
    if spec == "joystick":
        import pygame

        from vcfusion.hitl.calibration import load_axis_map, preset_for

        pygame.event.pump()
        if pygame.joystick.get_count() == 0:
            raise UsageError("--input joystick: SDL sees no joystick or wheel; is it plugged in?")
        js = pygame.joystick.Joystick(0)
        js.init()
        axis_map = load_axis_map(axis_map_file) if axis_map_file else preset_for(js.get_name(), js.get_numaxes())
        if axis_map is None:
            raise UsageError(f"--input joystick: no preset for {js.get_name()!r} ({js.get_numaxes()} axes); "
                             "run `vcfusion drive --calibrate --axis-map FILE` and pass --axis-map FILE")
        return JoystickInput(js, axis_map, map_source=str(axis_map_file) if axis_map_file else "")
    return check_input_spec(spec)  # replay:FILE, read and checked; anything else is refused


def check_input_spec(spec: str) -> "ReplayInput | None":
    """UsageError unless `spec` is keyboard, joystick or replay:FILE with a readable replay file,
    before anything is opened or written; the replay's input when it names one."""
    if spec.startswith("replay:"):
        return ReplayInput(Path(spec[len("replay:"):]))
    if spec not in ("keyboard", "joystick"):
        raise UsageError(f"--input: expected keyboard, joystick or replay:FILE, got {spec!r}")
