"""The cloud Digital Twin store and its process models.

Each vehicle has a twin: its latest reported state and a bounded history (a ring buffer of
at least `history_s` seconds), stamped with measurement time. Every V2C tick the store runs
its process models on all twins at once; a process model is any callable
``model(twins: TwinStates, store: TwinStore) -> dict[str, np.ndarray]`` whose columns are
attached to the snapshot the ego receives (e.g. ``lc_prob``).
"""

from __future__ import annotations

import math
from typing import Callable, Protocol

import numpy as np

from vcfusion.records import GnssReports, TwinStates
from vcfusion.scenario import V2CConfig
from vcfusion.traffic.network import Road

# Ring-buffer columns of a twin's history.
HISTORY_FIELDS = ("measured_time", "x", "y", "z", "heading", "speed", "accel")
_STATIC_FIELDS = ("length", "width", "height")


class ProcessModel(Protocol):
    def __call__(self, twins: TwinStates, store: "TwinStore") -> dict[str, np.ndarray]: ...


class _History:
    """Fixed-capacity ring buffer of one twin's reports (oldest overwritten)."""

    __slots__ = ("data", "count", "head")

    def __init__(self, capacity: int):
        self.data = np.full((capacity, len(HISTORY_FIELDS)), np.nan)
        self.count = 0
        self.head = 0  # next write position

    def push(self, row: np.ndarray) -> None:
        self.data[self.head] = row
        self.head = (self.head + 1) % len(self.data)
        self.count = min(self.count + 1, len(self.data))

    def latest(self) -> np.ndarray:
        return self.data[(self.head - 1) % len(self.data)]

    def ordered(self) -> np.ndarray:
        """Rows oldest to newest."""
        cap = len(self.data)
        idx = (self.head - self.count + np.arange(self.count)) % cap
        return self.data[idx]


class TwinStore:
    def __init__(self, config: V2CConfig, road: Road):
        self.config = config
        self.road = road
        # Twice the nominal number of reports, so jittered or duplicated arrivals never cut history short.
        self.capacity = 2 * math.ceil(config.history_s / config.period_s) + 1
        self._history: dict[str, _History] = {}
        self._static: dict[str, tuple[float, float, float]] = {}
        self.process_models: list[tuple[str, Callable]] = []
        self.received = 0

    def add_process_model(self, name: str, model: ProcessModel) -> None:
        self.process_models.append((name, model))

    def ingest(self, reports: GnssReports) -> None:
        rows = np.stack([getattr(reports, f) for f in HISTORY_FIELDS], axis=-1)
        for i, vid in enumerate(reports.ids):
            hist = self._history.get(vid)
            if hist is None:
                hist = self._history[vid] = _History(self.capacity)
                self._static[vid] = (reports.length[i], reports.width[i], reports.height[i])
            # Out-of-order arrivals (jitter) never replace a newer measurement.
            if hist.count and rows[i, 0] <= hist.latest()[0]:
                continue
            hist.push(rows[i])
            self.received += 1

    def forget_stale(self, now: float) -> None:
        limit = now - self.config.twin_timeout_s
        for vid in [v for v, h in self._history.items() if h.latest()[0] < limit]:
            del self._history[vid]
            del self._static[vid]

    def __contains__(self, vehicle_id: str) -> bool:
        return vehicle_id in self._history

    def history(self, vehicle_id: str) -> np.ndarray:
        """(k, len(HISTORY_FIELDS)) rows of one twin, oldest first."""
        return self._history[vehicle_id].ordered()

    def snapshot(self, now: float) -> TwinStates:
        """Latest state of every twin, with process-model outputs."""
        ids = tuple(sorted(self._history))
        latest = np.array([self._history[v].latest() for v in ids]).reshape(len(ids), len(HISTORY_FIELDS))
        static = np.array([self._static[v] for v in ids], dtype=float).reshape(len(ids), 3)
        cols = {f: latest[:, k].copy() for k, f in enumerate(HISTORY_FIELDS)}
        _, d = self.road.to_road_frame(cols["x"], cols["y"])
        twins = TwinStates(
            time=now, ids=ids, lane=self.road.lane_of(d), outputs={},
            **cols, **{f: static[:, k].copy() for k, f in enumerate(_STATIC_FIELDS)},
        )
        for name, model in self.process_models:
            out = model(twins, self)
            for key, value in out.items():
                value = np.asarray(value)
                if value.shape[:1] != (len(ids),):
                    raise ValueError(f"process model {name!r} returned {key!r} of shape {value.shape} for {len(ids)} twins")
                twins.outputs[key] = value
        return twins


def neighbours(twins: TwinStates, ego_xy: tuple[float, float], range_m: float, exclude: str | None) -> TwinStates:
    """The twins within range_m (horizontal) of the ego, the ego's own twin excluded."""
    if not len(twins):
        return twins
    dist = np.hypot(twins.x - ego_xy[0], twins.y - ego_xy[1])
    keep = (dist <= range_m) & np.array([vid != exclude for vid in twins.ids])
    return twins.select(np.flatnonzero(keep))
