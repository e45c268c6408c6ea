"""The ego's vehicle model under a person's pedals and steering wheel.

Longitudinal (per SUMO step dt, documented in docs/components/hitl.md, "How a trip runs"):
    a_wanted = throttle * max_accel - brake * max_decel - coast(v)
    coast(v) = ROLLING_MPS2 + DRAG_PER_M * v^2      (rolling resistance + air drag, no pedal)
then the acceleration moves toward a_wanted no faster than the car's jerk limits (braking jerk
when it falls, throttle jerk when it rises), and speed >= 0 (no reverse). The limits are the
driver model's car (`driver.params.CarLimits`: +3 / -9 m/s^2, 30 / 10 m/s^3), so a person and the
driver model drive the same car. The coast coefficients give 0.25 m/s^2 at 19 m/s, the coasting
deceleration of a mid-size car in gear (an assumption, stated as such).

Lateral: a heading-command model. The wheel (steer in [-1, 1], left positive) asks for a yaw
relative to the road, steer * MAX_YAW_RAD, reached with a first-order lag (YAW_TIME_CONSTANT_S);
the front bumper's lateral position moves at v * sin(yaw). A centred wheel drives straight along
the road, so a lane change is "turn, hold, return", without the counter-steering a bicycle model
would ask of a keyboard. At 19 m/s full lock crosses a 3.5 m lane in about 2 s. The car stays on
the road: its lateral position is clamped to the edges of the lanes present where its front
bumper is, less half the car's width (the barrier), and the yaw drops to zero there. Where a lane
ends ahead (an acceleration lane, a lane drop) the barrier closes in on it before its end, at
BARRIER_SLOPE (the drawn taper's: 3.5 m over 60 m): a car left in that lane is pushed into the
next one gradually, and is out of it where SUMO's lane ends (SUMO cannot place a vehicle past the
end of a lane, and the trip was lost as "off route"). Speed stops at the vehicle type's maxSpeed
(a limiter: the acceleration drops to what reaches it).

A discrete lane change (keyboard key, or `lane_change` in a replay file) sets a target lane; the
model then steers itself toward that lane's centre (wanted lateral speed 0.8 /s x the distance,
at most 1.2 m/s, so about 4 s per lane) and releases when the front bumper is within 5 cm of it;
any steering input cancels it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vcfusion.driver.params import CarLimits
from vcfusion.traffic.network import Road

ROLLING_MPS2 = 0.1
DRAG_PER_M = 0.1 / 240.0  # 0.15 m/s^2 of drag at 19 m/s
MAX_YAW_RAD = 0.1
YAW_TIME_CONSTANT_S = 0.3
LANE_CHANGE_GAIN = 0.8  # 1/s: wanted lateral speed per metre from the target lane's centre
LANE_CHANGE_MAX_LATERAL_MPS = 1.2
LANE_CHANGE_DONE_M = 0.05
STEER_TAKES_OVER = 0.05  # |steer| above this cancels an automatic lane change
BARRIER_SLOPE = 3.5 / 60.0  # m across per m along: how fast the barrier closes in where a lane ends
BARRIER_LOOKAHEAD_M = 300.0  # narrowings this far ahead shape it (17.5 m of road width at the slope)


@dataclass(frozen=True)
class ControlSample:
    """The driver's controls for one SUMO step (mapped from any device)."""

    steer: float  # -1 full right .. +1 full left
    throttle: float  # 0 released .. 1 floored
    brake: float  # 0 released .. 1 full
    lane_change: int = 0  # -1 right / +1 left: a discrete lane change asked for at this step


@dataclass
class VehicleState:
    speed: float
    accel: float
    d: float  # front bumper, m left of the right road edge
    yaw: float  # rad relative to the road, left positive
    target_lane: int | None = None


class VehicleModel:
    def __init__(self, road: Road, speed: float, d: float, car_width_m: float, limits: CarLimits = CarLimits(),
                 max_speed_mps: float = math.inf):
        self.road = road
        self.limits = limits
        self.state = VehicleState(speed=speed, accel=0.0, d=d, yaw=0.0)
        self.half_width = car_width_m / 2
        self.max_speed = max_speed_mps

    def bounds(self, s: float) -> tuple[float, float]:
        """The lateral range of the front bumper's centre at s: the edges of the lanes present there,
        less half the car, closing in at BARRIER_SLOPE towards where the road narrows ahead (the
        edges at each place x m ahead where the lanes present change, less x times the slope)."""
        starts = self.road.piece_starts_s
        x = np.r_[0.0, starts[(starts > s) & (starts <= s + BARRIER_LOOKAHEAD_M)] - s]
        right, left = self.road.road_bounds(s + x)
        right = float(np.max(np.asarray(right) - BARRIER_SLOPE * x))
        left = float(np.min(np.asarray(left) + BARRIER_SLOPE * x))
        return right + self.half_width, left - self.half_width

    def wanted_accel(self, c: ControlSample, speed: float) -> float:
        coast = ROLLING_MPS2 + DRAG_PER_M * speed * speed if speed > 0 else 0.0
        return c.throttle * self.limits.max_accel_mps2 - c.brake * self.limits.max_decel_mps2 - coast

    def update(self, c: ControlSample, dt: float, s_front: float = 0.0) -> VehicleState:
        """Advance the controls by one step with the front bumper at `s_front` along the road;
        returns the state commanded for the next step (the acceleration to apply and where to put
        the front bumper laterally)."""
        st = self.state
        lim = self.limits
        wanted = self.wanted_accel(c, st.speed)
        step_up, step_down = lim.max_throttle_jerk_mps3 * dt, lim.max_brake_jerk_mps3 * dt
        accel = min(max(wanted, st.accel - step_down), st.accel + step_up)
        accel = min(max(accel, -lim.max_decel_mps2), lim.max_accel_mps2)
        if st.speed <= 0.0 and accel < 0.0:
            accel = 0.0  # standing still: brakes hold, no reverse
        accel = min(accel, max(0.0, (self.max_speed - st.speed) / dt))  # the limiter
        st.accel = accel
        st.speed = max(0.0, st.speed + accel * dt)  # the loop integrates the same way

        steer = c.steer
        if c.lane_change:
            current = int(self.road.lane_of(s_front, st.d))
            base = st.target_lane if st.target_lane is not None else current
            target = base + int(c.lane_change)
            if base >= 0 and self.road.lane_exists(target, s_front):
                st.target_lane = target  # a lane present here; else (the road's edge) the key does nothing
        if st.target_lane is not None and not self.road.lane_exists(st.target_lane, s_front):
            st.target_lane = None  # the lane ended (the barrier took the car out of it)
        if st.target_lane is not None:
            if abs(steer) > STEER_TAKES_OVER:
                st.target_lane = None  # the driver steers: the automatic change stops
            else:
                error = float(self.road.lane_centre_d(st.target_lane, s_front)) - st.d
                if abs(error) < LANE_CHANGE_DONE_M and abs(st.yaw) < 0.01:
                    st.target_lane = None
                lateral = max(-LANE_CHANGE_MAX_LATERAL_MPS, min(LANE_CHANGE_MAX_LATERAL_MPS, LANE_CHANGE_GAIN * error))
                speed = max(st.speed, 1.0)
                steer = math.asin(max(-1.0, min(1.0, lateral / speed))) / MAX_YAW_RAD
        wanted_yaw = max(-1.0, min(1.0, steer)) * MAX_YAW_RAD
        st.yaw += (wanted_yaw - st.yaw) * min(1.0, dt / YAW_TIME_CONSTANT_S)
        st.d += st.speed * math.sin(st.yaw) * dt
        d_min, d_max = self.bounds(s_front + st.speed * dt)  # where the step puts the front bumper
        if st.d <= d_min or st.d >= d_max:
            st.d = min(max(st.d, d_min), d_max)
            st.yaw = 0.0  # against the barrier: along the road
        return st
