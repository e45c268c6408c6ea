"""tools/sway_strata.py: a vehicle's lane-keeping sway leaves out the ticks around its lane change
and those without a lateral position, and caps the squares."""


import numpy as np
import pandas as pd
import pytest

from support.tool_modules import load_tool





def test_vehicle_sway_is_the_lane_keeping_rms():
    t = np.round(np.arange(0.0, 60.0, 0.1), 1)
    n = len(t)
    # vehicle a: +-0.2 m/s of sway, a change ending at 40 s with 2 m/s around it (ticks 28-45 s are
    # not lane keeping); vehicle b: 3 m/s (capped at 0.5) until 30 s, then no lateral position (reads 0)
    va = np.where((t > 28.0) & (t < 45.0), 2.0, np.where(np.arange(n) % 2 == 0, 0.2, -0.2))
    stream = pd.DataFrame({"seed": np.r_[np.zeros(n), np.zeros(n)].astype(int), "original_seed": 0,
                           "vehicle_id": ["a"] * n + ["b"] * n, "time": np.r_[t, t],
                           "lateral_speed_mps": np.r_[va, np.where(t < 30.0, 3.0, 0.0)],
                           "lateral_known": np.r_[np.ones(n), (t < 30.0).astype(float)]})
    events = pd.DataFrame({"seed": [0], "event_id": [0], "vehicle_id": ["a"], "end": [40.0], "mid": [38.0]})
    sway = load_tool("sway_strata").vehicle_sway(stream, events)
    assert sway[(0, "a")] == pytest.approx(0.2)
    assert sway[(0, "b")] == pytest.approx(0.5)
