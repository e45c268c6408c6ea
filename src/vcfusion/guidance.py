"""The guidance policy of a run: which level a neighbour's warning has, and which neighbours matter.

One :class:`GuidancePolicy` is built per run from the scenario (:meth:`GuidancePolicy.from_scenario`,
called by ``run.build_cosimulation``) and handed to the three stages that use it: the AR overlay
(``fusion/overlay.py``: the colour of a box), the cloud guidance (``driver/cloud_guidance.py``:
which neighbours get an item) and the driver model (``driver/model.py``: which items and lateral
cues it responds to). It sits beside ``records.py`` rather than in ``driver/`` or ``fusion/``
because both use it and neither should import the other.

**Levels** (:meth:`GuidancePolicy.level`). A neighbour is highlighted only while the cloud's
smoothed decision ``lc_decision`` is positive (the paper's Algorithm 3/4 output); its level then
follows the lane-change probability: ``high`` (red) at ``lc_prob >= ar.high_threshold``,
``medium`` (yellow) at ``>= ar.medium_threshold``, else ``none``. The scenario's ``ar:`` block is
the only place the thresholds are set; the defaults, 0.3 and 0.6, are chosen as follows.
``lc_prob`` is calibrated (docs/components/prediction.md, "Calibration"): it is the probability that the
vehicle's lane change ends within tau = 5 s, and its mean, the base rate, is 11 %. The shipped
GRU's decision (aggressive smoothing) switches on at ``lc_prob > 0.78`` (the MLP's at 0.86) and
holds for 5 s after the last such tick, so every warning starts red with any thresholds up to that;
the thresholds colour a warning while it is held and the probability moves. The hold exists to keep warnings
steady (the paper's reason for Algorithms 3 and 4: a warning that goes dark and comes back
confuses the driver), so a held warning should go dark only once the probability is back near
ordinary levels: medium = 0.3, about three times the base rate. High = 0.6: a change within 5 s
is clearly more likely than not. With 0.5 / 0.8 instead a held
warning would be dark in 40 % of the held twin-ticks instead of 34 % and red in 47 % instead of
58 % (scenarios/accident.yaml, seeds 0-7: 3,636 twin-ticks with ``lc_decision = 1``). A process
model that writes ``lc_prob`` but no ``lc_decision`` is levelled by the thresholds alone.

**Ahead** (:meth:`GuidancePolicy.ahead`): a vehicle's rear bumper is beyond the ego's front bumper,
by at most a range (``driver.guidance_view_range_m`` for what guidance shows; the driver model
watches the adjacent lanes up to its own ``notice_range_m``).

**Lanes** (:meth:`GuidancePolicy.in_ego_lane`, :meth:`GuidancePolicy.in_adjacent_lane`), from the
lateral distance of a vehicle's centre to the ego lane's centre line, w the lane width: in the
ego lane below w / 2; in an adjacent lane from w / 2 up to (not including) 1.5 w.

The ego's id is :data:`vcfusion.records.EGO_ID`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vcfusion.records import EGO_ID

GUIDANCE_LEVELS = ("none", "medium", "high")
# The levels that warn: the overlay draws them with a label, the driver responds to them.
WARNING_LEVELS = ("medium", "high")


@dataclass(frozen=True)
class GuidancePolicy:
    medium: float  # lc_prob at or above which a flagged neighbour is medium (yellow)
    high: float  # ... and high (red)
    view_range_m: float  # guidance items are made for neighbours ahead within this range
    ego_lane: int
    lane_width_m: float
    ego_lane_centre_d: float  # d of the ego lane's centre line (from the road's right edge)
    ego_id: str = EGO_ID

    def __post_init__(self):
        if not 0.0 <= self.medium <= self.high <= 1.0:
            raise ValueError(f"guidance thresholds: expected 0 <= medium <= high <= 1, got {self.medium}, {self.high}")
        if not (self.view_range_m > 0 and self.lane_width_m > 0):
            raise ValueError(f"guidance policy: expected a positive view range and lane width, got "
                             f"{self.view_range_m}, {self.lane_width_m}")

    @classmethod
    def on_road(cls, road, ego_lane: int, medium: float, high: float, view_range_m: float,
                ego_s: float = 0.0) -> "GuidancePolicy":
        """The policy on a road frame; the ego lane's centre is taken at s = ego_s (a track keeps
        its d range along a route whose lanes keep their widths)."""
        return cls(medium=float(medium), high=float(high), view_range_m=float(view_range_m), ego_lane=int(ego_lane),
                   lane_width_m=float(road.lane_width_m),
                   ego_lane_centre_d=float(road.lane_centre_d(ego_lane, ego_s)))

    @classmethod
    def from_scenario(cls, scenario, road) -> "GuidancePolicy":
        """The policy of a scenario with an ego: ``ar`` thresholds, ``driver.guidance_view_range_m``."""
        if scenario.ego is None:
            raise ValueError(f"{scenario.source or scenario.name}: guidance needs an ego; expected an ego block")
        return cls.on_road(road, scenario.ego.lane, scenario.ar.medium_threshold, scenario.ar.high_threshold,
                           scenario.driver.guidance_view_range_m, ego_s=scenario.ego.depart_pos_m)

    def level(self, prob: float, decision: int | None = None) -> str:
        """The level of a neighbour with lane-change probability `prob` and, when the predictor
        gives one, the cloud's smoothed decision `decision` (0/1); see the module doc."""
        if (decision is not None and not decision) or not math.isfinite(prob):
            return "none"
        if prob >= self.high:
            return "high"
        if prob >= self.medium:
            return "medium"
        return "none"

    @staticmethod
    def warns(level: str) -> bool:
        return level in WARNING_LEVELS

    def any_warning(self, twins) -> bool:
        """Whether any of `twins` (e.g. the ego's neighbours) has a warning level."""
        if twins is None or not len(twins) or "lc_prob" not in twins.outputs:
            return False
        prob = np.asarray(twins.outputs["lc_prob"], dtype=float)
        decision = twins.outputs.get("lc_decision")
        decisions = [None] * len(prob) if decision is None else np.asarray(decision).tolist()
        return any(self.warns(self.level(float(p), d)) for p, d in zip(prob.tolist(), decisions))

    def ahead(self, rear_s, ego_front_s, range_m: float | None = None):
        """Rear bumper(s) `rear_s` beyond the ego's front bumper by at most `range_m` (default:
        the view range). Scalars or arrays."""
        r = self.view_range_m if range_m is None else range_m
        gap = rear_s - ego_front_s
        return (gap > 0) & (gap <= r)

    def lateral_m(self, d):
        """Distance of lateral position(s) `d` (road frame) from the ego lane's centre line."""
        return np.abs(d - self.ego_lane_centre_d)

    def in_ego_lane(self, lateral_m):
        return lateral_m < self.lane_width_m / 2

    def in_adjacent_lane(self, lateral_m):
        w = self.lane_width_m
        return (w / 2 <= lateral_m) & (lateral_m < 1.5 * w)
