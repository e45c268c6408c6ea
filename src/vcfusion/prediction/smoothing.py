"""Smoothing of per-tick lane-change decisions: the paper's Algorithms 3 and 4.

Both take and return 1-D arrays of 0/1 decisions of one vehicle in time order; one element
per step (a V2C tick at run time, a second in the paper's Table I).

- :func:`aggressive` (Algorithm 3): each positive lasts tau_a more steps.
- :func:`conservative` (Algorithm 4): step t is positive when the mean of steps
  t - tau_c .. t exceeds the threshold (strictly).

First tau_c steps. Algorithm 4 starts at t = tau_c (1-based), where the window t - tau_c .. t
would reach before the first step. We treat steps before the start of the stream as 0
(stay put) and keep the denominator tau_c + 1: a vehicle only just seen must show tau_c + 1
steps' worth of evidence like any other. With threshold 0.5 this means no positive in the
first ceil(0.5 (tau_c + 1)) - 1 steps. It is also what the streaming form does for a new twin.

:class:`StreamingSmoother` is the online form used by the cloud: per-twin state, one call per
tick for all twins, equal to the batch functions step by step (tested).
"""

from __future__ import annotations

import numpy as np

from vcfusion.prediction.memory import TwinMemory


def _as_decisions(predictions) -> np.ndarray:
    arr = np.asarray(predictions)
    if arr.ndim != 1:
        raise ValueError(f"expected a 1-D array of 0/1 predictions, got shape {arr.shape}")
    if arr.size and not np.isin(arr, (0, 1)).all():
        raise ValueError("expected predictions of 0 or 1 only")
    return arr.astype(np.int8)


def aggressive(predictions, tau_a: int) -> np.ndarray:
    """Algorithm 3: a positive at t makes t .. t + tau_a positive (within the array)."""
    if tau_a < 0:
        raise ValueError(f"tau_a: expected >= 0, got {tau_a}")
    lc = _as_decisions(predictions)
    out = np.zeros_like(lc)
    for shift in range(min(int(tau_a), len(lc) - 1) + 1):
        out[shift:] |= lc[: len(lc) - shift] if shift else lc
    return out


def conservative(predictions, tau_c: int, threshold: float = 0.5) -> np.ndarray:
    """Algorithm 4: positive where mean(lc[t - tau_c .. t]) > threshold; steps before the stream count 0."""
    if tau_c < 0:
        raise ValueError(f"tau_c: expected >= 0, got {tau_c}")
    lc = _as_decisions(predictions)
    window = int(tau_c) + 1
    csum = np.concatenate([[0], np.cumsum(lc, dtype=np.int64)])
    idx = np.arange(len(lc))
    sums = csum[idx + 1] - csum[np.maximum(idx + 1 - window, 0)]
    return (sums / window > threshold).astype(np.int8)


def smooth(predictions, method: str, tau_a: int = 0, tau_c: int = 0, threshold: float = 0.5) -> np.ndarray:
    if method == "none":
        return _as_decisions(predictions).copy()
    if method == "aggressive":
        return aggressive(predictions, tau_a)
    if method == "conservative":
        return conservative(predictions, tau_c, threshold)
    raise ValueError(f"smoothing: expected none, aggressive or conservative, got {method!r}")


class StreamingSmoother:
    """Online Algorithm 3 / 4 for many twins: feed each tick's raw decisions of all twins.

    State per twin: for aggressive, the steps left of the current positive hold; for
    conservative, the last tau_c + 1 raw decisions (a new twin starts with zeros, as in the
    batch form). Twins absent from a tick are forgotten.
    """

    def __init__(self, method: str, tau_a: int = 0, tau_c: int = 0, threshold: float = 0.5):
        if method not in ("none", "aggressive", "conservative"):
            raise ValueError(f"smoothing: expected none, aggressive or conservative, got {method!r}")
        self.method, self.tau_a, self.tau_c, self.threshold = method, int(tau_a), int(tau_c), threshold
        # one row per twin: [ticks still positive after this one (aggressive), the last tau_c + 1
        # raw decisions, newest last (conservative)]
        self._memory = TwinMemory(2 + self.tau_c, dtype=np.int64)

    def __call__(self, ids, decisions: np.ndarray) -> np.ndarray:
        lc = np.asarray(decisions).astype(np.int8)
        state = self._memory.carried(ids, np.zeros((len(lc), 2 + self.tau_c), dtype=np.int64))
        hold, recent = state[:, 0], state[:, 1:]
        if self.method == "none":
            out = lc.copy()
        elif self.method == "aggressive":
            # hold = extra positive steps still owed by earlier positives, before this step
            out = ((lc == 1) | (hold > 0)).astype(np.int8)
            hold = np.where(lc == 1, self.tau_a, np.maximum(hold - 1, 0))
        else:
            recent = np.concatenate([recent[:, 1:], lc[:, None]], axis=1)
            out = (recent.sum(axis=1) / (self.tau_c + 1) > self.threshold).astype(np.int8)
        self._memory.keep(ids, np.concatenate([hold[:, None], recent], axis=1))
        return out
