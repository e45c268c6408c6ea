"""Intelligent Driver Model (Treiber, Hennecke & Helbing 2000) car following.

Used as the ego's longitudinal controller: acceleration from own speed and the gap and speed
of the leader. Default parameters are the highway values of Treiber & Kesting, "Traffic Flow
Dynamics" (2013), Table 11.2: T = 1.5 s, s0 = 2 m, a = 1.0 m/s^2 (we use 1.5 for a car
with a driver who keeps the set speed), b = 2.0 m/s^2, delta = 4.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class IDMParams:
    desired_speed_mps: float = 19.0
    time_headway_s: float = 1.5
    min_gap_m: float = 2.0
    max_accel_mps2: float = 1.5
    comfort_decel_mps2: float = 2.0
    delta: float = 4.0
    # Physical braking limit of a passenger car on dry asphalt (about 0.9 g).
    max_decel_mps2: float = 9.0


def idm_acceleration(p: IDMParams, speed: float, gap: float | None = None, leader_speed: float | None = None) -> float:
    """IDM acceleration; `gap` is bumper to bumper, None when there is no leader."""
    free = 1.0 - (speed / p.desired_speed_mps) ** p.delta
    interaction = 0.0
    if gap is not None and leader_speed is not None:
        dv = speed - leader_speed
        s_star = p.min_gap_m + max(0.0, speed * p.time_headway_s
                                   + speed * dv / (2.0 * math.sqrt(p.max_accel_mps2 * p.comfort_decel_mps2)))
        interaction = (s_star / max(gap, 0.1)) ** 2
    acc = p.max_accel_mps2 * (free - interaction)
    return max(acc, -p.max_decel_mps2)


class IdmController:
    """Ego controller without a human in it: IDM on the radar leader in the ego's lane (SUMO's
    leader of the ego). For runs that need the ego to drive but not the driver model (camera
    renders, the identification study); `vcfusion run` uses the driver model."""

    needs = ("ego",)

    def __init__(self, params: IDMParams):
        self.params = params

    @classmethod
    def for_scenario(cls, scenario) -> "IdmController":
        return cls(IDMParams(desired_speed_mps=scenario.ego.desired_speed_mps))

    def acceleration(self, tick) -> float:
        ego = tick.ego
        return idm_acceleration(self.params, ego.speed, ego.leader_gap_m, ego.leader_speed)
