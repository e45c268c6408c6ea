"""Per-twin memory carried from one V2C tick to the next, keyed by twin id."""

from __future__ import annotations

import numpy as np


class TwinMemory:
    """One row of state per twin. Each tick: :meth:`previous_rows` finds each twin's row of the
    last tick in :attr:`state` (-1 for a new twin), the tick's compiled update reads them, and
    :meth:`keep` stores the updated rows; a twin absent from a tick is forgotten.

    A dict lookup per twin: a tick holds tens to hundreds of twins, where this is several times
    cheaper than sorting and searching string arrays.
    """

    def __init__(self, width: int, dtype=np.float64):
        self._row: dict[str, int] = {}
        self._ids: tuple | None = None  # the last tick's ids when given as a tuple (the run-time path)
        self._state = np.zeros((0, width), dtype=dtype)

    @property
    def state(self) -> np.ndarray:
        """The rows kept at the last tick."""
        return self._state

    def previous_rows(self, ids) -> np.ndarray:
        """For each id, its row in :attr:`state`, or -1 for a twin not seen at the last tick."""
        if isinstance(ids, tuple) and ids == self._ids:  # the twins of the last tick, in its order
            return np.arange(len(ids), dtype=np.int64)
        row = self._row
        return np.array([row.get(v, -1) for v in ids], dtype=np.int64)

    def keep(self, ids, state: np.ndarray) -> None:
        if not (isinstance(ids, tuple) and ids == self._ids):
            self._row = dict(zip(ids, range(len(state))))
            self._ids = ids if isinstance(ids, tuple) else None
        self._state = state
