"""The early-warning weighting of the GRU's positive window (SequenceConfig.early_weight)."""

import numpy as np
import pandas as pd
import pytest

from vcfusion.prediction.train_sequence import loss_weights

TAU, TAU_G = 5.0, 2.0


def _stream():
    # one change ending at t = 20 s: positives 15.1-20 s (ttl 4.9 .. 0), gap, negatives, far ticks
    t = np.round(np.arange(0.0, 20.05, 0.1), 1)
    ttl = 20.0 - t
    negative = (ttl >= TAU + TAU_G - 1e-6) & (ttl < 2 * TAU + TAU_G - 1e-6)
    window = np.where(ttl < TAU - 1e-6, 1, np.where(negative, 0, -1))
    return pd.DataFrame({"time": t, "time_to_lc": ttl, "window_label": window})


def test_zero_early_weight_is_the_plain_recipe():
    s = _stream()
    y0, w0 = loss_weights(s, TAU, TAU_G, 3.0)
    y1, w1 = loss_weights(s, TAU, TAU_G, 3.0, early_weight=0.0)
    assert np.array_equal(y0, y1) and np.array_equal(w0, w1)
    assert np.ptp(w0[y0 == 1]) == 0.0  # all positives alike


def test_early_positives_weigh_more_and_the_balance_holds():
    s = _stream()
    y, w = loss_weights(s, TAU, TAU_G, 3.0, early_weight=2.0)
    pos = y == 1
    ttl = s["time_to_lc"].to_numpy()
    # weight grows linearly with the time to the end: 1 + 2 * ttl / tau, up to a common factor
    ratio = w[pos] / (1.0 + 2.0 * ttl[pos] / TAU)
    assert np.allclose(ratio, ratio[0], rtol=1e-5)
    assert w[pos][np.argmax(ttl[pos])] > 2.5 * w[pos][np.argmin(ttl[pos])]
    # positives still balance all negatives; negatives and gap ticks unchanged
    assert w[pos].sum() == pytest.approx(w[~pos].sum(), rel=1e-5)
    _, w_plain = loss_weights(s, TAU, TAU_G, 3.0)
    assert np.array_equal(w[~pos], w_plain[~pos])
    gap = (s["window_label"] == -1).to_numpy() & (ttl <= 2 * TAU + TAU_G)
    assert (w[gap] == 0).all()


@pytest.mark.parametrize("extra", [["--kind", "gru", "--early-weight", "-1"],
                                   ["--kind", "gru", "--early-weight", "nan"],
                                   ["--kind", "mlp", "--early-weight", "2"]])
def test_the_command_refuses_a_bad_early_weight(tmp_path, capsys, extra):
    from vcfusion.commands import main

    assert main(["train", str(tmp_path / "no-dataset"), "--out", str(tmp_path / "m.npz"), *extra]) == 2
    assert "--early-weight" in capsys.readouterr().err
    assert not (tmp_path / "m.npz").exists()
