"""tools/matched_curves.py --agreement: how far decision curves lie apart, on a known case."""


import pandas as pd
import pytest

from support.tool_modules import load_tool





def _curve(thresholds, predicted, fa):
    return pd.DataFrame({"threshold": thresholds, "all_predicted": predicted, "all_fa_per_veh_h": fa})


def test_agreement_over_the_common_thresholds_and_the_mean_over_pairs():
    curves = {"a": _curve([0.3, 0.4, 0.5], [0.80, 0.70, 0.60], [9.0, 5.0, 2.0]),
              "b": _curve([0.3, 0.4, 0.5, 0.6], [0.80, 0.60, 0.60, 0.5], [8.0, 5.0, 4.0, 1.0]),
              "c": _curve([0.3, 0.4, 0.5], [0.80, 0.70, 0.60], [9.0, 5.0, 2.0])}
    table = load_tool("matched_curves").agreement(curves).set_index("pair")
    ab = table.loc["a / b"]
    assert ab["thresholds"] == 3  # 0.6 is in b only
    assert ab["predicted: mean abs. difference (points)"] == pytest.approx(10 / 3)
    assert ab["predicted: largest (points)"] == pytest.approx(10.0)
    assert ab["false alarms / veh-h: mean abs. difference"] == pytest.approx(1.0)
    assert ab["false alarms / veh-h: largest"] == pytest.approx(2.0)
    assert table.loc["a / c", "false alarms / veh-h: largest"] == 0.0
    mean = table.loc["mean over 3 pairs"]
    assert mean["false alarms / veh-h: mean abs. difference"] == pytest.approx((1.0 + 1.0 + 0.0) / 3)
