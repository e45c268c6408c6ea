"""Driver and car parameters of the ego, drawn per trip from documented distributions.

Sources (see docs/components/driver.md, "The model"):
- IDM parameter ranges: Treiber & Kesting, "Traffic Flow Dynamics" (Springer 2013), Table 11.2
  (highway: desired time gap T 1.0 s within 0.8-2.0 s, minimum gap s0 2 m, acceleration a
  1.0 m/s^2 within 0.8-2.5 m/s^2, comfortable deceleration b 1.5 m/s^2 within 1-2 m/s^2).
- Car-following reaction time with anticipation: Treiber, Kesting & Helbing, "Delays,
  inaccuracies and anticipation in microscopic traffic models", Physica A 360 (2006) 71-88
  (Human Driver Model; reaction times 0.6-1.2 s).
- Brake reaction times: Green, "How long does it take to stop? Methodological analysis of
  driver perception-brake times", Transportation Human Factors 2(3) (2000) 195-216: about
  0.7-0.75 s when the driver is fully aware / expects the event, about 1.25 s for an
  unexpected but common signal, about 1.5 s for a surprise. A neighbour cutting in without a
  warning is "unexpected"; an AR warning that is already shown turns it into an "expected"
  event.
- Car limits: braking up to about 0.9 g on dry asphalt (9 m/s^2, the ego vtype's
  emergencyDecel); full braking builds up within the brake "swell" time of 0.2-0.4 s used
  in accident reconstruction, so the braking jerk is bounded by about 9 / 0.3 = 30 m/s^3;
  a mid-size car reaches about 3 m/s^2 at 70 km/h (the ego vtype's accel); the throttle
  side is slower (we bound it at 10 m/s^3, an assumption).
- Warning response (driver/model.py): on a warning the driver releases the throttle and covers
  the brake, the "prepared" state in which Green (2000) measures the ~0.75 s expected-event
  times. Released throttle in gear decelerates a mid-size car at 19 m/s by about 0.4-0.6 m/s^2
  (air drag 0.5 * 1.2 kg/m^3 * 0.65 m^2 * (19 m/s)^2 = 140 N, rolling resistance 0.01 * 1500 kg
  * g = 150 N, engine drag torque at the wheels 300-600 N, over 1500 kg): ``cover_decel_mps2``
  is drawn from 0.3-0.7 m/s^2 (a physics estimate; the drag values are assumptions).
- Hysteresis of a warning (``warning_hold_s`` 0.3 s): a warning stays active this long after it
  was last shown. About one fixation (fixations while driving last ~0.2-0.4 s, an assumption
  stated as such): a warning missing for one 0.1 s frame is not seen to go away, and one shown for
  a single frame is gone long before the 0.4-1.5 s reaction would start a response.
- Perception (driver/perception.py): forward field of view = the camera's horizontal field of
  view (70 deg, configurable in the scenario as ``driver.field_of_view_deg``), left mirror up to
  50 m behind, a vehicle seen when a quarter of its outline is visible: assumptions.
- The lateral displacement a driver notices (0.3-0.5 m from the lane centre toward the ego
  lane) and the pedal time constant (0.2-0.4 s, the movement-time share of Green's
  perception-response time) are modelling assumptions, stated as such.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

# Fixed sub-stream of the trip seed for the driver draw: the driver does not depend on how
# many random numbers the traffic consumed, so both arms of a paired trip get the same driver.
DRIVER_STREAM = 0x0D7


@dataclass(frozen=True)
class CarLimits:
    max_accel_mps2: float = 3.0
    max_decel_mps2: float = 9.0
    max_brake_jerk_mps3: float = 30.0  # how fast the deceleration can build up
    max_throttle_jerk_mps3: float = 10.0


@dataclass(frozen=True)
class DriverParams:
    desired_speed_mps: float
    time_headway_s: float  # IDM T
    min_gap_m: float  # IDM s0
    max_accel_mps2: float  # IDM a
    comfort_decel_mps2: float  # IDM b
    follow_reaction_s: float  # delay of the leader's perception in car following (HDM T')
    cutin_reaction_s: float  # from seeing a neighbour drift toward the lane to responding
    guidance_reaction_s: float  # from the AR overlay's warning to responding
    lateral_notice_m: float  # lateral displacement toward the ego lane that is noticed
    notice_range_m: float  # how far ahead the driver watches the adjacent lanes
    pedal_time_constant_s: float  # first-order lag of the applied acceleration
    cover_decel_mps2: float = 0.5  # released throttle, foot over the brake (warning response)
    warning_hold_s: float = 0.3  # a warning stays active this long after last shown (hysteresis)

    def to_dict(self) -> dict:
        return asdict(self)


def _lognormal(rng: np.random.Generator, median: float, sigma: float, lo: float, hi: float) -> float:
    return float(np.clip(median * np.exp(sigma * rng.standard_normal()), lo, hi))


def draw_driver(seed: int, desired_speed_mps: float) -> DriverParams:
    """One driver for trip `seed` (the same for both arms of a paired trip)."""
    rng = np.random.default_rng([int(seed), DRIVER_STREAM])
    return DriverParams(
        desired_speed_mps=desired_speed_mps,
        time_headway_s=float(rng.uniform(1.0, 1.8)),
        min_gap_m=2.0,
        max_accel_mps2=float(rng.uniform(1.0, 2.0)),
        comfort_decel_mps2=float(rng.uniform(1.5, 2.5)),
        follow_reaction_s=float(rng.uniform(0.6, 1.2)),
        # Green (2000): ~1.25 s unexpected; ~0.75 s expected. Log-normal spread, clipped.
        cutin_reaction_s=_lognormal(rng, 1.25, 0.2, 0.7, 2.5),
        guidance_reaction_s=_lognormal(rng, 0.75, 0.2, 0.4, 1.5),
        lateral_notice_m=float(rng.uniform(0.3, 0.5)),
        notice_range_m=100.0,
        pedal_time_constant_s=float(rng.uniform(0.2, 0.4)),
        # drawn after the draws above, so adding these parameters left those draws unchanged
        cover_decel_mps2=float(rng.uniform(0.3, 0.7)),
        warning_hold_s=0.3,
    )
