"""A stand-in for the lane-change predictor, for tests and for studies run before it is merged.

NOT the predictor: a geometric rule that knows where the accident is. A twin in a lane the
accident closes gets lc_prob rising linearly from 0 at `far_m` to 1 at `near_m` before the
accident (its distance measured to the accident's rear). Use it with
`vcfusion study guidance ... --process-model tests.support.standin_predictor:closed_lane_standin`.
"""

from __future__ import annotations

import numpy as np


def closed_lane_standin(scenario, far_m: float = 180.0, near_m: float = 100.0):
    from vcfusion.traffic.network import read_road, read_vehicle_types

    acc = scenario.accident
    road = read_road(scenario.network)
    truck_len = float(read_vehicle_types(scenario.vehicle_types)[acc.vtype].get("length", 12.0))
    accident_rear = acc.pos_m - truck_len
    closed = np.array(sorted(acc.lanes))

    def model(twins, store):
        if not len(twins):
            return {"lc_prob": np.zeros(0), "lc_decision": np.zeros(0, dtype=bool)}
        s, _ = road.to_road_frame(twins.x, twins.y)
        dist = accident_rear - (s + twins.length / 2)
        prob = np.clip((far_m - dist) / (far_m - near_m), 0.0, 1.0)
        prob = np.where(np.isin(twins.lane, closed) & (dist > 0) & (twins.speed > 0.5), prob, 0.0)
        return {"lc_prob": prob, "lc_decision": prob >= 0.5}

    return model
