"""The privileged ceiling: SUMO's own lane-change state, logged per tick, as extra model inputs.

How predictable are SUMO's lane changes at all? The cloud sees positions and speeds; SUMO's
lane-change model (LC2013) decides from its own state: per direction whether it wants to change
and why (strategic, cooperative, speedGain, keepRight; urgent), whether the change is blocked,
the driver's desired speed and the speedGain / keepRight urges it accumulates over seconds.
A predictor that may read these each tick (a *privileged* one, impossible to deploy) through the
same labels and evaluation gives the ceiling: what it misses, no observer could know.

- :class:`LaneChangeStateHook`: a tick hook (table `lc_state`) reading every vehicle's state from
  libsumo at each V2C tick. Only `vcfusion dataset --privileged` adds it: traffic-only runs do
  not query SUMO for it and stay byte-identical.
- :func:`add_privileged`: the PRIVILEGED_NAMES columns joined onto a run's samples by
  (time, vehicle_id); `sumo_state_known` = 0 (and every other column 0) where SUMO had no state
  (a stale twin of a vehicle that left, a state SUMO had not computed yet).
- `vcfusion train --privileged` trains the MLP on FEATURE_NAMES + PRIVILEGED_NAMES (the ceiling
  model); `vcfusion evaluate` scores such a model, and on a dataset with these columns also the
  rule "SUMO wants to change lanes" (:class:`SumoWantsRule`).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

# libsumo's LaneChangeAction bits (traci.constants LCA_*)
LCA_LEFT, LCA_RIGHT = 1 << 1, 1 << 2
LCA_STRATEGIC, LCA_COOPERATIVE, LCA_SPEEDGAIN, LCA_KEEPRIGHT = 1 << 3, 1 << 4, 1 << 5, 1 << 6
LCA_URGENT = 1 << 8
LCA_BLOCKED = (1 << 9) | (1 << 10) | (1 << 11) | (1 << 12) | (1 << 14) | (1 << 28)  # traci's LCA_BLOCKED
LCA_UNKNOWN = 1 << 30
_BITS = (("wants", None), ("blocked", LCA_BLOCKED), ("urgent", LCA_URGENT), ("strategic", LCA_STRATEGIC),
         ("cooperative", LCA_COOPERATIVE), ("speedgain", LCA_SPEEDGAIN), ("keepright", LCA_KEEPRIGHT))
# LC2013's accumulated urges (vehicle.getParameter 'laneChangeModel.<key>')
_URGES = (("sumo_speedgain_urge_left", "speedGainProbabilityLeft"),
          ("sumo_speedgain_urge_right", "speedGainProbabilityRight"),
          ("sumo_keepright_urge", "keepRightProbability"))

PRIVILEGED_NAMES: tuple[str, ...] = (
    "sumo_state_known",
    *[f"sumo_{bit}_{side}" for side in ("left", "right") for bit, _ in _BITS],
    "sumo_desired_speed", "sumo_desired_minus_speed",
    *[name for name, _ in _URGES],
)
LC_STATE_TABLE = "lc_state"


def state_columns(state_left: np.ndarray, state_right: np.ndarray) -> dict[str, np.ndarray]:
    """The bit columns of PRIVILEGED_NAMES from getLaneChangeState's first value per direction."""
    out = {}
    for side, state, want in (("left", state_left, LCA_LEFT), ("right", state_right, LCA_RIGHT)):
        state = np.asarray(state, dtype=np.int64)
        known = (state & LCA_UNKNOWN) == 0
        for bit, mask in _BITS:
            out[f"sumo_{bit}_{side}"] = (known & ((state & (want if mask is None else mask)) != 0)).astype(np.float32)
    return out


class LaneChangeStateHook:
    """Tick hook: every vehicle's lane-change state from libsumo (see the module docstring).

    Rows: time, vehicle_id, state_left, state_right (getLaneChangeState's first value, the lane-change
    model's own wish before TraCI), desired_speed (getAllowedSpeed: the lane's limit x the driver's
    speed factor, capped by the vehicle's maximum), speed (SUMO's) and LC2013's urges.
    """

    table = LC_STATE_TABLE
    needs = ("truth",)  # vcfusion.stages: it reads the tick's ground truth (the vehicle ids)

    def __call__(self, tick) -> list[dict]:
        import libsumo

        vehicle = libsumo.vehicle
        truth = tick.truth
        time = round(truth.time, 6)
        rows = []
        for vid, speed in zip(truth.ids, truth.speed):
            row = {"time": time, "vehicle_id": vid,
                   "state_left": int(vehicle.getLaneChangeState(vid, 1)[0]),
                   "state_right": int(vehicle.getLaneChangeState(vid, -1)[0]),
                   "desired_speed": min(vehicle.getAllowedSpeed(vid), vehicle.getMaxSpeed(vid)),
                   "speed": float(speed)}
            for name, key in _URGES:
                row[name] = float(vehicle.getParameter(vid, f"laneChangeModel.{key}"))
            rows.append(row)
        return rows


def privileged_frame(lc_state: pd.DataFrame) -> pd.DataFrame:
    """time, vehicle_id and the PRIVILEGED_NAMES columns of a run's `lc_state` table."""
    left = lc_state["state_left"].to_numpy(np.int64)
    right = lc_state["state_right"].to_numpy(np.int64)
    known = ((left & LCA_UNKNOWN) == 0) | ((right & LCA_UNKNOWN) == 0)
    desired = lc_state["desired_speed"].to_numpy(float)
    out = {"time": lc_state["time"].to_numpy(float), "vehicle_id": lc_state["vehicle_id"].astype(str).to_numpy(),
           "sumo_state_known": known.astype(np.float32), **state_columns(left, right),
           "sumo_desired_speed": desired, "sumo_desired_minus_speed": desired - lc_state["speed"].to_numpy(float)}
    for name, _ in _URGES:
        out[name] = lc_state[name].to_numpy(float)
    frame = pd.DataFrame(out)
    return frame[["time", "vehicle_id", *PRIVILEGED_NAMES]]


def add_privileged(samples: pd.DataFrame, lc_state: pd.DataFrame) -> pd.DataFrame:
    """samples with the PRIVILEGED_NAMES columns (float32) joined by (time, vehicle_id), 0 where
    SUMO had no state for that twin at that tick; row order kept."""
    frame = privileged_frame(lc_state)
    key = lambda t: np.round(np.asarray(t, dtype=float), 6)  # noqa: E731 (both sides on the 1e-6 grid)
    frame = frame.assign(time=key(frame["time"]))
    merged = pd.DataFrame({"time": key(samples["time"]), "vehicle_id": samples["vehicle_id"].astype(str).to_numpy()})
    merged = merged.merge(frame, on=["time", "vehicle_id"], how="left", sort=False, validate="many_to_one")
    out = samples.copy()
    for name in PRIVILEGED_NAMES:
        out[name] = merged[name].fillna(0.0).to_numpy(np.float32)
    return out


class SumoWantsRule:
    """Privileged rule: 1 while SUMO's lane-change model wants to change lanes (either side,
    blocked or not), else 0."""

    def __init__(self, names: list[str]):
        self.left = names.index("sumo_wants_left")
        self.right = names.index("sumo_wants_right")

    def predict_proba(self, x: np.ndarray) -> np.ndarray:
        return ((x[:, self.left] > 0) | (x[:, self.right] > 0)).astype(np.float32)
