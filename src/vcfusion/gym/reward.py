"""The Gymnasium environment's reward per V2C tick, from the metrics package's definitions.

reward = w.progress * progress - w.ttc * ttc_term - w.drac * drac_term - w.jerk * jerk_term
         - w.fuel * fuel_g - w.collision * collided

with the weights ``w`` of the scenario's ``reward:`` block (vcfusion.scenario.RewardConfig) and,
for the tick that just ended (the command's effect):

- ``progress``: metres the ego's front bumper moved along its route / (ego.desired_speed_mps *
  v2c.period_s): 1 per tick at the desired speed (default weight 1: about 160 over the accident
  scenario's 300 m trip);
- ``ttc_term``: (T - TTC) / T where the constant-velocity TTC to the radar leader
  (metrics.safety.ttc_series: gap / closing speed) is below T = metrics.ttc_threshold_s (1.5 s,
  SSAM), else 0; 0..1 (default weight 1: a tick in conflict costs up to one tick of progress);
- ``drac_term``: DRAC to the radar leader (closing^2 / (2 gap), the metrics' definition) / 3.35
  m/s^2, the DRAC above which Archer (2005) counts a conflict (default weight 0.5);
- ``jerk_term``: |change of the commanded acceleration| / v2c.period_s / 10 m/s^3 (a full
  braking swell is about 30 m/s^3, vcfusion.driver.params; default weight 0.05);
- ``fuel_g``: MOVESTAR fuel of the tick (metrics.movestar.fuel_rate_gps at the ego's speed and
  commanded acceleration, times the tick): about 0.08 g at 19 m/s cruise (default weight 1 per g);
- ``collided``: 1 at the tick the ego first touches another vehicle (the episode ends; default
  weight 100).

The reward reads the simulation (the ego's radar leader is SUMO's); the observation does not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vcfusion.metrics.movestar import fuel_rate_gps
from vcfusion.metrics.safety import ttc_series

# DRAC above which a following situation is a conflict (Archer, "Indicators for traffic safety
# assessment and prediction...", KTH 2005): the scale of the DRAC term.
DRAC_CONFLICT_MPS2 = 3.35
# Scale of the jerk term: a third of a full braking swell (vcfusion.driver.params, 30 m/s^3).
JERK_SCALE_MPS3 = 10.0


@dataclass(frozen=True)
class StepMetrics:
    """The tick's metrics (``info["metrics"]``) and reward terms."""

    progress_m: float
    ttc_s: float  # NaN: not closing in on a leader, or no leader
    drac_mps2: float  # 0 where TTC is undefined
    jerk_mps3: float
    fuel_g: float  # NaN: the ego's type has no MOVESTAR rates
    collided: bool

    def terms(self, desired_speed_mps: float, tick_s: float, ttc_threshold_s: float) -> dict[str, float]:
        ttc = self.ttc_s
        return {
            "progress": self.progress_m / (desired_speed_mps * tick_s),
            "ttc": (ttc_threshold_s - ttc) / ttc_threshold_s if ttc < ttc_threshold_s else 0.0,
            "drac": self.drac_mps2 / DRAC_CONFLICT_MPS2,
            "jerk": abs(self.jerk_mps3) / JERK_SCALE_MPS3,
            "fuel": 0.0 if math.isnan(self.fuel_g) else self.fuel_g,
            "collision": float(self.collided),
        }


def step_metrics(progress_m: float, speed: float, leader_gap_m: float | None, leader_speed: float | None,
                 accel: float, previous_accel: float, tick_s: float, movestar_type: int | None,
                 collided: bool) -> StepMetrics:
    ttc = drac = math.nan
    if leader_gap_m is not None and leader_speed is not None:
        ttc = float(ttc_series(np.array([leader_gap_m]), np.array([speed]), np.array([leader_speed]))[0])
        if not math.isnan(ttc):
            drac = (speed - leader_speed) ** 2 / (2.0 * leader_gap_m)
    fuel = fuel_rate_gps(max(speed, 0.0), accel, movestar_type) * tick_s if movestar_type else math.nan
    return StepMetrics(progress_m, ttc, 0.0 if math.isnan(drac) else drac, (accel - previous_accel) / tick_s, fuel,
                       collided)


def reward(terms: dict[str, float], weights) -> float:
    """The weighted sum of the module doc (progress adds, the others cost)."""
    return (weights.progress * terms["progress"] - weights.ttc * terms["ttc"] - weights.drac * terms["drac"]
            - weights.jerk * terms["jerk"] - weights.fuel * terms["fuel"] - weights.collision * terms["collision"])
