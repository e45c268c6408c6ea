"""What the driver can see: a forward field of view, the left mirror, and occlusion.

A geometric test on the road plane, the same in every arm of a study (the instance map of a
rendered frame exists only in the camera arms; using it there would give the arms different
drivers). Every vehicle is a rectangle aligned with the road in the road frame (s along, d
across), the driver's eye a point (the camera mount: ``camera.forward_m`` ahead of the ego's
footprint centre, at ``camera.height_m``).

- **Forward view**: the part of a vehicle's horizontal bearing interval (seen from the eye)
  within +-``hfov / 2`` of the road direction. ``hfov`` is the camera's (the AR shows the
  camera's view), or ``driver.field_of_view_deg`` when the scenario sets it.
- **Occlusion**: a nearer vehicle hides the part of a farther one's bearing interval that it
  covers, when its top is higher in the driver's view: (h_o - eye) / r_o,far >= (h - eye) /
  r_near (a car hides a car behind it; a truck behind a car stays visible over it until it is
  about (h_truck - eye) / (h_car - eye) times farther away). A vehicle is seen when at least
  ``min_visible_fraction`` of its in-view bearing interval is uncovered.
- **Left mirror**: vehicles in the adjacent lane to the left whose front is behind the eye,
  within ``mirror_range_m`` (no occlusion test in the mirror).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vcfusion.guidance import GuidancePolicy


@dataclass(frozen=True)
class DriverView:
    hfov_deg: float = 70.0
    eye_forward_m: float = 0.6  # ahead of the ego's footprint centre
    eye_height_m: float = 1.4
    mirror_range_m: float = 50.0  # assumption: a car is recognisable in a flat mirror up to ~50 m
    # assumption: a vehicle is recognised from a quarter of its outline
    min_visible_fraction: float = 0.25

    @classmethod
    def from_scenario(cls, scenario) -> "DriverView":
        cam = scenario.camera
        fov = getattr(scenario.driver, "field_of_view_deg", None)
        return cls(hfov_deg=float(fov if fov is not None else cam.hfov_deg), eye_forward_m=float(cam.forward_m),
                   eye_height_m=float(cam.height_m))


def _uncovered_fraction(lo: float, hi: float, covers: list[tuple[float, float]]) -> float:
    """Share of [lo, hi] not covered by the union of the intervals `covers`."""
    if hi <= lo:
        return 0.0
    covered, reach = 0.0, lo
    for a, b in sorted(covers):
        a, b = max(a, reach), min(b, hi)
        if b > a:
            covered += b - a
            reach = b
    return max(0.0, 1.0 - covered / (hi - lo))


def visible_vehicles(s: np.ndarray, d: np.ndarray, length: np.ndarray, width: np.ndarray, height: np.ndarray,
                     ego: int, policy: GuidancePolicy, view: DriverView) -> np.ndarray:
    """Boolean mask: which vehicles (road-frame centres `s`, `d`; the ego at index `ego`, never
    seen) the driver sees. See the module doc."""
    n = len(s)
    seen = np.zeros(n, dtype=bool)
    eye_s, eye_d = float(s[ego] + view.eye_forward_m), float(d[ego])
    half = math.radians(view.hfov_deg) / 2
    near_s = s - length / 2 - eye_s  # relative rear and front
    far_s = s + length / 2 - eye_s
    lo_d, hi_d = d - width / 2 - eye_d, d + width / 2 - eye_d
    # mirror: the adjacent lane on the left (larger d), behind the eye
    lateral = d - policy.ego_lane_centre_d
    w = policy.lane_width_m
    mirror = (lateral >= w / 2) & (lateral < 1.5 * w) & (far_s < 0) & (far_s > -view.mirror_range_m)
    # forward: bearing interval, nearest and farthest distance of each rectangle from the eye
    intervals: list[tuple[float, float] | None] = [None] * n
    r_near = np.full(n, np.inf)
    r_far = np.full(n, np.inf)
    for i in range(n):
        if i == ego or far_s[i] <= 0:
            continue
        xs = (max(near_s[i], 1e-3), far_s[i])
        ang = [math.atan2(y, x) for x in xs for y in (lo_d[i], hi_d[i])]
        lo, hi = max(min(ang), -half), min(max(ang), half)
        if hi <= lo:
            continue
        intervals[i] = (lo, hi)
        cx = min(max(0.0, near_s[i]), far_s[i])
        cy = min(max(0.0, lo_d[i]), hi_d[i])
        r_near[i] = max(math.hypot(cx, cy), 0.1)
        r_far[i] = math.hypot(far_s[i], max(abs(lo_d[i]), abs(hi_d[i])))
    top = (height - view.eye_height_m)
    for i in range(n):
        if intervals[i] is None:
            continue
        lo, hi = intervals[i]
        covers = [intervals[k] for k in range(n)
                  if k != i and intervals[k] is not None and r_near[k] < r_near[i]
                  and top[k] / r_far[k] >= top[i] / r_near[i]]
        seen[i] = _uncovered_fraction(lo, hi, covers) >= view.min_visible_fraction
    seen |= mirror
    seen[ego] = False
    return seen
