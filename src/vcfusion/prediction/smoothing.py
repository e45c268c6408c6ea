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

import numba
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


_METHODS = ("none", "aggressive", "conservative")


@numba.njit(cache=True)
def _stream_step(lc: np.ndarray, previous: np.ndarray, memory: np.ndarray, method: int, tau_a: int,
                 threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """One tick of every twin: (smoothed decisions, new memory rows). Memory row: [positive steps
    still owed by earlier positives (aggressive), the last tau_c + 1 raw decisions, newest last
    (conservative)]; `previous[i]` is twin i's row in `memory`, -1 for a new twin (all zeros).
    Compiled: on the tens of twins of a tick NumPy's per-call overhead was the cost."""
    n, width = lc.shape[0], memory.shape[1]
    out = np.zeros(n, dtype=np.int8)
    state = np.zeros((n, width), dtype=np.int64)
    for i in range(n):
        if previous[i] >= 0:
            state[i] = memory[previous[i]]
        if method == 0:
            out[i] = lc[i]
        elif method == 1:
            out[i] = lc[i] == 1 or state[i, 0] > 0
            state[i, 0] = tau_a if lc[i] == 1 else max(state[i, 0] - 1, 0)
        else:
            total = 0
            for c in range(1, width - 1):
                state[i, c] = state[i, c + 1]
                total += state[i, c]
            state[i, width - 1] = lc[i]
            total += lc[i]
            out[i] = total / (width - 1) > threshold
    return out, state


class StreamingSmoother:
    """Online Algorithm 3 / 4 for many twins: feed each tick's raw decisions of all twins.

    State per twin: for aggressive, the steps left of the current positive hold; for
    conservative, the last tau_c + 1 raw decisions (a new twin starts with zeros, as in the
    batch form). Twins absent from a tick are forgotten.
    """

    def __init__(self, method: str, tau_a: int = 0, tau_c: int = 0, threshold: float = 0.5):
        if method not in _METHODS:
            raise ValueError(f"smoothing: expected none, aggressive or conservative, got {method!r}")
        self.method, self.tau_a, self.tau_c, self.threshold = method, int(tau_a), int(tau_c), threshold
        self._memory = TwinMemory(2 + self.tau_c, dtype=np.int64)

    def __call__(self, ids, decisions: np.ndarray) -> np.ndarray:
        lc = np.asarray(decisions).astype(np.int8)
        out, state = _stream_step(lc, self._memory.previous_rows(ids), self._memory.state,
                                  _METHODS.index(self.method), self.tau_a, float(self.threshold))
        self._memory.keep(ids, state)
        return out
