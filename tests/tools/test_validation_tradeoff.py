"""tools/validation_tradeoff.py: each false alarm is found by the same rule as the event scores and
given the right kinds (censored, late, after a change); a run confirmed by a change is none."""


import numpy as np
import pandas as pd

from vcfusion.prediction.events import event_scores

from support.tool_modules import load_tool





def test_false_alarm_kinds_one_vehicle():
    t = np.round(np.arange(0.0, 30.0, 0.1), 1)  # one vehicle, 0 .. 29.9 s
    stream = pd.DataFrame({"seed": 0, "vehicle_id": "v", "time": t})
    events = pd.DataFrame({"seed": [0], "event_id": [0], "vehicle_id": ["v"], "end": [25.0], "mid": [23.0]})
    runs = [(1.0, 2.0),    # false alarm; the change ends 13 s after its window: no kind
            (13.0, 14.0),  # false alarm; the change ends 1 s after its window (24 s): late
            (20.0, 21.0),  # the change ends in [20, 31]: confirmed, no false alarm
            (26.0, 27.0)]  # 1 s after the change; its window runs past the track's end: censored
    d = np.zeros(len(t), dtype=np.int8)
    for a, b in runs:
        d[(t >= a) & (t <= b)] = 1
    fa = load_tool("validation_tradeoff").false_alarm_kinds(stream, d, events)
    summary = event_scores(stream, d, events, 0.1, 10.0)[0]
    assert len(fa) == summary["false_alarms"] == 3
    assert fa["censored"].tolist() == [False, False, True]
    assert fa["late"].tolist() == [False, True, False]
    assert fa["after_change"].tolist() == [False, False, True]
    assert int(fa["censored"].sum()) == summary["false_alarms_censored"]
