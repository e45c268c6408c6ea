"""Per-twin memory carried from one V2C tick to the next, keyed by twin id."""

from __future__ import annotations

import numpy as np


class TwinMemory:
    """One row of state per twin. Each tick: :meth:`carried` gives the previous rows aligned to
    the tick's ids (new twins get their ``fresh`` row), :meth:`keep` stores the updated rows; a
    twin absent from a tick is forgotten.

    A dict lookup per twin: a tick holds tens to hundreds of twins, where this is several times
    cheaper than sorting and searching string arrays.
    """

    def __init__(self, width: int, dtype=np.float64):
        self._row: dict[str, int] = {}
        self._state = np.zeros((0, width), dtype=dtype)

    @property
    def state(self) -> np.ndarray:
        """The rows kept at the last tick."""
        return self._state

    def previous_rows(self, ids) -> np.ndarray:
        """For each id, its row in :attr:`state`, or -1 for a twin not seen at the last tick."""
        row = self._row
        return np.array([row.get(v, -1) for v in ids], dtype=np.int64)

    def carried(self, ids, fresh: np.ndarray) -> np.ndarray:
        state = fresh.copy()
        row = self._row
        pairs = [(i, row[v]) for i, v in enumerate(ids) if v in row]
        if pairs:
            dst, src = np.array(pairs).T
            state[dst] = self._state[src]
        return state

    def keep(self, ids, state: np.ndarray) -> None:
        self._row = dict(zip(ids, range(len(state))))
        self._state = state
