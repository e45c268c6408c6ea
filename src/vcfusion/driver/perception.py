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
- Nothing whose rear is more than ``sight_range_m`` ahead of the eye is seen.

The test runs every tick as a compiled kernel (`_visible`); tests/driver/test_driver_model.py checks it
against a plain-Python transcription of the rules above on random scenes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
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
    # assumption: beyond 200 m ahead (its rear) a vehicle is not judged (the driver watches the
    # adjacent lanes up to 100 m, guidance covers 150 m)
    sight_range_m: float = 200.0

    @classmethod
    def from_scenario(cls, scenario) -> "DriverView":
        cam = scenario.camera
        fov = getattr(scenario.driver, "field_of_view_deg", None)
        return cls(hfov_deg=float(fov if fov is not None else cam.hfov_deg), eye_forward_m=float(cam.forward_m),
                   eye_height_m=float(cam.height_m))


@numba.njit(cache=True)
def _visible(s, d, length, width, height, ego, eye_forward, eye_height, half_fov, mirror_range, min_fraction,
             ego_lane_centre_d, lane_width, sight_range):
    """The test of the module doc over all vehicles at once (compiled: it runs every tick, and in
    Python over ten vehicles it cost ~0.3 ms, most of a tick's budget). float64 / int64 inputs."""
    n = s.shape[0]
    seen = np.zeros(n, dtype=np.bool_)
    eye_s = s[ego] + eye_forward
    eye_d = d[ego]
    lo = np.zeros(n)
    hi = np.zeros(n)
    r_near = np.full(n, np.inf)
    slope = np.zeros(n)  # top of the vehicle in view: (height - eye) / distance
    occluder_slope = np.zeros(n)  # ... at its far end (what it hides behind it)
    valid = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        if i == ego:
            continue
        near_s = s[i] - length[i] / 2 - eye_s
        far_s = s[i] + length[i] / 2 - eye_s
        lo_d = d[i] - width[i] / 2 - eye_d
        hi_d = d[i] + width[i] / 2 - eye_d
        lateral = abs(d[i] - ego_lane_centre_d)
        # the left mirror: the adjacent lane on the left (larger d), behind the eye
        if (d[i] > ego_lane_centre_d and lateral >= lane_width / 2 and lateral < 1.5 * lane_width
                and far_s < 0 and far_s > -mirror_range):
            seen[i] = True
            continue
        if far_s <= 0 or near_s > sight_range:
            continue
        x0 = max(near_s, 1e-3)
        b_lo, b_hi = np.inf, -np.inf
        for x in (x0, far_s):
            for y in (lo_d, hi_d):
                b = np.arctan2(y, x)
                b_lo = min(b_lo, b)
                b_hi = max(b_hi, b)
        b_lo = max(b_lo, -half_fov)
        b_hi = min(b_hi, half_fov)
        if b_hi <= b_lo:
            continue
        valid[i] = True
        lo[i], hi[i] = b_lo, b_hi
        cx = min(max(0.0, near_s), far_s)
        cy = min(max(0.0, lo_d), hi_d)
        r_near[i] = max(np.hypot(cx, cy), 0.1)
        r_far = np.hypot(far_s, max(abs(lo_d), abs(hi_d)))
        slope[i] = (height[i] - eye_height) / r_near[i]
        occluder_slope[i] = (height[i] - eye_height) / r_far
    order = np.argsort(lo)
    for i in range(n):
        if not valid[i]:
            continue
        # union of the nearer, higher-in-view vehicles' intervals over [lo_i, hi_i], in order of lo
        covered, reach = 0.0, lo[i]
        for k in order:
            if k == i or not valid[k] or r_near[k] >= r_near[i] or occluder_slope[k] < slope[i]:
                continue
            a = max(lo[k], reach)
            b = min(hi[k], hi[i])
            if b > a:
                covered += b - a
                reach = b
        seen[i] = 1.0 - covered / (hi[i] - lo[i]) >= min_fraction
    return seen


def visible_vehicles(s: np.ndarray, d: np.ndarray, length: np.ndarray, width: np.ndarray, height: np.ndarray,
                     ego: int, policy: GuidancePolicy, view: DriverView) -> np.ndarray:
    """Boolean mask: which vehicles (road-frame centres `s`, `d`; the ego at index `ego`, never
    seen) the driver sees. See the module doc."""
    f = np.ascontiguousarray
    return _visible(f(s, dtype=np.float64), f(d, dtype=np.float64), f(length, dtype=np.float64),
                    f(width, dtype=np.float64), f(height, dtype=np.float64), int(ego), float(view.eye_forward_m),
                    float(view.eye_height_m), math.radians(view.hfov_deg) / 2, float(view.mirror_range_m),
                    float(view.min_visible_fraction), float(policy.ego_lane_centre_d), float(policy.lane_width_m),
                    float(view.sight_range_m))
