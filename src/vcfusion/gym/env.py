"""``vcfusion/Highway-v0``: a Gymnasium environment on the co-simulation's own tick loop.

One ``step`` is one V2C tick (``v2c.period_s``, ten SUMO steps at the defaults): the action
becomes the ego's :class:`vcfusion.control.Command` for the tick, the loop of ``vcfusion run``
(vcfusion.cosim.CoSimulation, driven through CoSimulation.start / LiveRun) runs the SUMO steps,
the V2C channel, the cloud twins and their lane-change predictor, and the camera and fusion
stages where the observation needs them, and stops at the next tick. ``reset(seed=...)`` starts
a new run of the scenario with that seed: the same seed gives the same episode and byte-identical
observations.

Observation modes (``observation=``):

- ``kinematics``: float32 array (vehicles + 1, 6): row 0 the ego, rows 1.. the ``vehicles``
  received twins nearest along the road (by |dx|), in that order; columns KINEMATICS_FEATURES:
  presence (1 / 0 for an empty row), dx (m: a twin's GNSS point along the road minus the ego's
  centre; 0 for the ego), dy (m, across the road, left positive), speed (m/s, as the cloud has
  it), lane (track of the route, 0 = rightmost; -1 off the road) and lc_prob (the cloud's
  lane-change probability; 0 for the ego and where prediction is off). Twins are what the ego
  receives over V2C (GNSS error, latency, loss of the scenario); only the ego's row is its own
  state. Values are clipped to the space's bounds.
- ``camera``: the ego camera (camera block of the scenario: width_px x height_px): ``rgb``
  uint8 (H, W, 3), ``depth`` float32 (H, W, 1) camera Z in metres (sky = camera.far_m), or both
  as a dict (``camera="rgbd"``).
- ``fused``: dict of ``kinematics`` (as above) and ``boxes`` float32 (vehicles, 5): for each twin
  row, the AR overlay's box for that twin (shown flag, x1 / W, y1 / H, x2 / W, y2 / H; zeros
  when the overlay shows none).

Camera and fused modes switch on the scenario's vision (every tick) and, for fused, its fusion
stage (the scenario's detector and matcher).

Actions (``action=``): ``continuous``: Box([-1, 1], shape 2): [0] the acceleration, scaled to
+max_accel (3 m/s^2) above 0 and -max_decel (9 m/s^2) below (vcfusion.driver.params.CarLimits);
[1] a lane-change request: above 0.5 left, below -0.5 right. ``discrete``: Discrete(5),
DISCRETE_ACTIONS (idle, faster, slower, lane left, lane right).

Reward: vcfusion.gym.reward (weights from the scenario's ``reward:`` block). ``info``: the tick's
``time``, ``metrics`` (progress_m, ttc_s, drac_mps2, jerk_mps3, fuel_g, collided), the reward
``terms``, ``end_reason`` (None while the run goes on) and the run ``seed``.

With ``summary=True`` the info of an episode's last step also carries ``run_summary``: the run's
summary as ``vcfusion run`` writes it (its end-of-run tables computed, the scenario's metrics
block included: the project's TTC / DRAC / jerk / MOVESTAR figures of the ego and the traffic).

Episode end: terminated at trip completion (``ego.trip_distance_m``), at the ego's first
collision, or when the ego leaves its route; truncated at ``simulation.max_time_s`` (the
``max_time_s`` argument overrides it). At the end the observation is the last tick's.
"""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium
import numpy as np
from gymnasium import spaces

from vcfusion.control.api import Command
from vcfusion.driver.params import CarLimits
from vcfusion.gym.reward import reward, step_metrics
from vcfusion.records import EGO_ID
from vcfusion.scenario import Scenario, load_scenario

KINEMATICS_FEATURES = ("presence", "dx", "dy", "speed", "lane", "lc_prob")
# (acceleration m/s^2, lane change) of each discrete action
DISCRETE_ACTIONS = ((0.0, 0), (1.5, 0), (-3.0, 0), (0.0, 1), (0.0, -1))
DISCRETE_NAMES = ("idle", "faster", "slower", "lane_left", "lane_right")
OBSERVATIONS = ("kinematics", "camera", "fused")
CAMERA_CHANNELS = ("rgb", "depth", "rgbd")
LANE_CHANGE_AT = 0.5  # |action[1]| above this asks for a lane change
MAX_SPEED_MPS = 100.0  # bound of the speed feature


class _DecidedOutside:
    """The run's ego stage while the environment decides: it declares what the observation reads."""

    name = "gymnasium environment"

    def __init__(self, needs: tuple[str, ...]):
        self.needs = needs

    def acceleration(self, tick):  # the environment drives the loop (LiveRun): never called
        raise RuntimeError("the environment decides each tick through LiveRun.advance")


def _scenario_for(scenario: str | Path | Scenario | None, observation: str, max_time_s: float | None) -> Scenario:
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario or "accident")
    if sc.ego is None:
        raise ValueError(f"{sc.source or sc.name}: the environment drives the ego; expected an ego block")
    update: dict = {}
    if max_time_s is not None:
        update["simulation"] = sc.simulation.model_copy(update={"max_time_s": float(max_time_s)})
    if observation in ("camera", "fused"):
        from vcfusion.scenario import require_camera_world

        require_camera_world(sc)
        update["vision"] = sc.vision.model_copy(update={"enabled": True, "every_ticks": 1, "only_when_warning": False})
        update["ar"] = sc.ar.model_copy(update={"video": False})
    if observation == "fused":
        update["fusion"] = sc.fusion.model_copy(update={"enabled": True})
    return sc.model_copy(update=update) if update else sc


class HighwayEnv(gymnasium.Env):
    """See the module doc. ``scenario``: a scenario file or a loaded Scenario (default: the
    shipped accident scenario); ``vehicles``: twin rows of the kinematics array."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, scenario: str | Path | Scenario | None = None, observation: str = "kinematics",
                 action: str = "continuous", vehicles: int = 8, camera: str = "rgb", max_time_s: float | None = None,
                 summary: bool = False, render_mode: str | None = None):
        if observation not in OBSERVATIONS:
            raise ValueError(f"observation: expected one of {OBSERVATIONS}, got {observation!r}")
        if action not in ("continuous", "discrete"):
            raise ValueError(f"action: expected 'continuous' or 'discrete', got {action!r}")
        if camera not in CAMERA_CHANNELS:
            raise ValueError(f"camera: expected one of {CAMERA_CHANNELS}, got {camera!r}")
        if int(vehicles) < 1:
            raise ValueError(f"vehicles: expected at least 1 twin row, got {vehicles!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode: expected None or 'rgb_array', got {render_mode!r}")
        self.scenario = _scenario_for(scenario, observation, max_time_s)
        if render_mode == "rgb_array" and not self.scenario.vision.enabled:
            raise ValueError("render_mode 'rgb_array' shows the ego camera: expected observation 'camera' or 'fused', "
                             "or a scenario with vision.enabled")
        # rgb_array renders the ego camera: offered where the run renders it
        self.metadata = {**self.metadata, "render_modes": ["rgb_array"] if self.scenario.vision.enabled else []}
        self.observation_mode, self.action_mode, self.camera = observation, action, camera
        self.render_mode = render_mode
        self.vehicles = int(vehicles)
        self.summary = bool(summary)
        self.limits = CarLimits()
        sc = self.scenario
        self.tick_s = sc.v2c.period_s
        reach = float(sc.v2c.neighbour_range_m) + 50.0  # dx, dy bounds (GNSS error and road curvature margin)
        low = np.array([0.0, -reach, -reach, 0.0, -1.0, 0.0], np.float32)
        high = np.array([1.0, reach, reach, MAX_SPEED_MPS, 64.0, 1.0], np.float32)
        self._low, self._high = np.tile(low, (self.vehicles + 1, 1)), np.tile(high, (self.vehicles + 1, 1))
        kinematics = spaces.Box(self._low, self._high, dtype=np.float32)
        h, w = sc.camera.height_px, sc.camera.width_px
        rgb = spaces.Box(0, 255, (h, w, 3), np.uint8)
        depth = spaces.Box(0.0, float(sc.camera.far_m), (h, w, 1), np.float32)
        if observation == "kinematics":
            self.observation_space = kinematics
        elif observation == "camera":
            both = spaces.Dict({"rgb": rgb, "depth": depth})
            self.observation_space = {"rgb": rgb, "depth": depth, "rgbd": both}[camera]
        else:
            self.observation_space = spaces.Dict({"kinematics": kinematics,
                                                  "boxes": spaces.Box(0.0, 1.0, (self.vehicles, 5), np.float32)})
        self.action_space = (spaces.Box(-1.0, 1.0, (2,), np.float32) if action == "continuous"
                             else spaces.Discrete(len(DISCRETE_ACTIONS)))
        from vcfusion.metrics.traffic import movestar_type
        from vcfusion.traffic.network import read_vehicle_types

        vclass = read_vehicle_types(sc.vehicle_types)[sc.ego.vtype].get("vClass", "passenger")
        self._movestar_type = movestar_type(sc.metrics, sc.ego.vtype, vclass)
        self.live = None
        self._renderer = self._detector = None
        self.run_seed: int | None = None
        self._last_obs = None

    # -- episode --------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        from vcfusion.run import build_cosimulation

        self._close_run()
        self.run_seed = int(seed) if seed is not None else int(self.np_random.integers(2**31 - 1))
        if self.scenario.vision.enabled and self._renderer is None:  # kept across episodes (OpenGL set-up)
            from vcfusion.render.renderer import EgoCameraRenderer

            self._renderer = EgoCameraRenderer.for_scenario(self.scenario)
        if self.scenario.fusion.enabled and self._detector is None:  # the detector's weights, loaded once
            from vcfusion.fusion.stage import build_detector

            self._detector = build_detector(self.scenario, self.run_seed)
        cosim = build_cosimulation(self.scenario, self.run_seed, renderer=self._renderer, detector=self._detector)
        needs = {"kinematics": ("ego",), "camera": ("ego", "frame"), "fused": ("ego", "frame", "guidance")}
        cosim.controller = _DecidedOutside(needs[self.observation_mode])
        self.live = cosim.start()
        self._accel = 0.0
        self._ego_contacts = 0
        tick = self.live.tick
        if tick is None:
            raise RuntimeError(f"scenario {self.scenario.name}, seed {self.run_seed}: the run ended before its first "
                               f"tick ({self.live.end_reason})")
        self._s = tick.ego.s
        self._last_obs = self._observe(tick)
        return self._last_obs, {"time": tick.time, "seed": self.run_seed, "end_reason": None}

    def step(self, action):
        if self.live is None or self.live.tick is None:
            raise RuntimeError("step: the episode has ended (or was never started); expected reset() first")
        accel, change = self._command(action)
        previous, self._accel = self._accel, accel
        tick = self.live.advance(Command(accel, change))
        contacts = sum(EGO_ID in (c.collider, c.victim) for c in self.live.session.collisions)
        collided = contacts > self._ego_contacts
        self._ego_contacts = contacts
        sc = self.scenario
        if tick is not None:
            ego = tick.ego
            progress = ego.s - self._s
            self._s = ego.s
            metrics = step_metrics(progress, ego.speed, ego.leader_gap_m, ego.leader_speed, accel, previous,
                                   self.tick_s, self._movestar_type, collided)
            self._last_obs = self._observe(tick)
            now = tick.time
        else:  # the run ended between ticks: the trip's last metres
            end_s = sc.ego.depart_pos_m + sc.ego.trip_distance_m
            progress = max(0.0, end_s - self._s) if self.live.end_reason == "trip_complete" else 0.0
            metrics = step_metrics(progress, math.nan, None, None, accel, previous, self.tick_s, None, collided)
            now = math.nan
        terms = metrics.terms(sc.ego.desired_speed_mps, self.tick_s, sc.metrics.ttc_threshold_s)
        end = self.live.end_reason
        terminated = collided or end in ("trip_complete", "ego_left", "ego_off_route")
        truncated = not terminated and end is not None
        if collided and end is None:  # the episode ends at the collision; the run is stopped there
            end = "collision"
            self.live.stop(end)
        info = {"time": now, "seed": self.run_seed, "end_reason": end, "metrics": metrics.__dict__, "terms": terms}
        if terminated or truncated:
            if self.summary:  # the run's summary, as `vcfusion run` writes it (metrics included)
                info["run_summary"] = self.live.result().summary
            self._close_run()
        return self._last_obs, float(reward(terms, sc.reward)), bool(terminated), bool(truncated), info

    def _command(self, action) -> tuple[float, int]:
        if self.action_mode == "discrete":
            accel, change = DISCRETE_ACTIONS[int(action)]
            return accel, change
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(-1), -1.0, 1.0)
        accel = a[0] * (self.limits.max_accel_mps2 if a[0] >= 0 else self.limits.max_decel_mps2)
        change = 1 if a[1] > LANE_CHANGE_AT else -1 if a[1] < -LANE_CHANGE_AT else 0
        return float(accel), change

    # -- observations ---------------------------------------------------------------------
    def _kinematics(self, tick) -> tuple[np.ndarray, list[str]]:
        road = self.live.session.road
        i = tick.truth.index_of(EGO_ID)
        s_all, d_all = tick.truth.road_frame(road)  # the ego's own position only
        ego_s, ego_d = float(s_all[i]), float(d_all[i])
        out = np.zeros((self.vehicles + 1, len(KINEMATICS_FEATURES)), np.float32)
        out[0] = (1.0, 0.0, 0.0, tick.ego.speed, tick.ego.lane, 0.0)
        twins = tick.neighbours
        ids: list[str] = []
        if len(twins):
            s, d = twins.road_frame(road)
            dx, dy = s - ego_s, d - ego_d
            order = np.argsort(np.abs(dx), kind="stable")[:self.vehicles]
            prob = twins.outputs.get("lc_prob")
            n = len(order)
            out[1:n + 1, 0] = 1.0
            out[1:n + 1, 1] = dx[order]
            out[1:n + 1, 2] = dy[order]
            out[1:n + 1, 3] = twins.speed[order]
            out[1:n + 1, 4] = twins.lane[order]
            out[1:n + 1, 5] = np.asarray(prob)[order] if prob is not None else 0.0
            ids = [twins.ids[k] for k in order]
        return np.clip(out, self._low, self._high), ids

    def _camera(self, frame):
        if frame is None:
            raise RuntimeError(f"scenario {self.scenario.name}: no camera frame at a tick (camera mode renders "
                               "every tick)")
        rgb = np.ascontiguousarray(frame.rgb, dtype=np.uint8)
        far = float(self.scenario.camera.far_m)
        depth = np.nan_to_num(np.asarray(frame.depth, np.float32), nan=far, posinf=far)
        depth = np.clip(depth, 0.0, far)[..., None]
        return {"rgb": rgb, "depth": depth, "rgbd": {"rgb": rgb, "depth": depth}}[self.camera]

    def _observe(self, tick):
        if self.observation_mode == "camera":
            return self._camera(tick.frame)
        kinematics, ids = self._kinematics(tick)
        if self.observation_mode == "kinematics":
            return kinematics
        boxes = np.zeros((self.vehicles, 5), np.float32)
        frame = tick.frame
        items = tick.guidance.items if tick.guidance is not None else ()
        if frame is not None:
            w, h = float(frame.width), float(frame.height)
            shown = {g.vehicle_id: g.box for g in items if g.box is not None}
            for row, vid in enumerate(ids):
                box = shown.get(vid)
                if box is not None:
                    boxes[row] = (1.0, box[0] / w, box[1] / h, box[2] / w, box[3] / h)
        return {"kinematics": kinematics, "boxes": np.clip(boxes, 0.0, 1.0)}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        tick = self.live.tick if self.live is not None else None
        return None if tick is None or tick.frame is None else np.asarray(tick.frame.rgb)

    def _close_run(self) -> None:
        if self.live is not None:
            self.live.close()
            self.live = None

    def close(self) -> None:
        self._close_run()
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        super().close()
