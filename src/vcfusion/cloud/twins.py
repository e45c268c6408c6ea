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

import numba
import numpy as np

from vcfusion.records import GnssReports, TwinStates, keep_road_frame
from vcfusion.scenario import V2CConfig
from vcfusion.traffic.roadframe import RoadFrame

# Ring-buffer columns of a twin's history.
HISTORY_FIELDS = ("measured_time", "x", "y", "z", "heading", "speed", "accel")
_STATIC_FIELDS = ("length", "width", "height")


class ProcessModel(Protocol):
    def __call__(self, twins: TwinStates, store: "TwinStore") -> dict[str, np.ndarray]: ...


@numba.njit(cache=True)
def _store_reports(data: np.ndarray, head: np.ndarray, count: np.ndarray, newest: np.ndarray, slots: np.ndarray,
                   fields: np.ndarray) -> int:
    """Write report i (column i of `fields`, HISTORY_FIELDS order) into the ring buffer of slot
    slots[i] unless its twin already has a newer measurement (out-of-order arrivals under
    jitter never replace it); returns how many were stored. Compiled: it runs every tick, where
    a handful of fancy-indexing calls cost more than the copying."""
    capacity = data.shape[1]
    stored = 0
    for i in range(slots.shape[0]):
        slot = slots[i]
        if fields[0, i] > newest[slot]:
            newest[slot] = fields[0, i]
            for k in range(fields.shape[0]):
                data[slot, head[slot], k] = fields[k, i]
            head[slot] = (head[slot] + 1) % capacity
            count[slot] = min(count[slot] + 1, capacity)
            stored += 1
    return stored


class TwinStore:
    """Twins in fixed slots of preallocated arrays: a ring buffer of reports per slot.

    Slots of forgotten twins are reused; the arrays double when full. Every tick touches all
    twins, so ingest and snapshot are array operations over slots, not Python loops over twins.
    """

    def __init__(self, config: V2CConfig, road: RoadFrame, run_s: float = math.inf):
        """`run_s`: the run's length; a twin never holds more history than that."""
        self.config = config
        self.road = road
        # Twice the nominal number of reports, so jittered or duplicated arrivals never cut history short.
        self.capacity = 2 * math.ceil(min(config.history_s, run_s) / config.period_s) + 1
        self._slot: dict[str, int] = {}  # twin id -> slot
        self._free: list[int] = []
        self._data = np.full((0, self.capacity, len(HISTORY_FIELDS)), np.nan)  # (slots, ring, fields)
        self._head = np.zeros(0, dtype=np.int64)  # next write position per slot
        self._count = np.zeros(0, dtype=np.int64)
        self._static = np.zeros((0, len(_STATIC_FIELDS)))
        # measurement time of each slot's latest report (+inf: free slot, never stale), kept beside
        # the ring buffer because every tick compares against it
        self._newest = np.zeros(0)
        self._id_of: list[str | None] = []  # twin id of each slot
        self.process_models: list[tuple[str, Callable]] = []
        self.received = 0
        self._order: tuple[tuple[str, ...], np.ndarray] | None = None  # sorted ids and their slots, until a twin comes or goes
        # the last ingested batch's ids and their slots, until a twin goes (a new one makes a new batch's ids)
        self._slots_of: tuple[tuple[str, ...], np.ndarray] | None = None

    def add_process_model(self, name: str, model: ProcessModel) -> None:
        self.process_models.append((name, model))

    def _new_slot(self) -> int:
        if not self._free:
            old = len(self._head)
            grow = max(old, 16)
            self._data = np.concatenate([self._data, np.full((grow, *self._data.shape[1:]), np.nan)])
            self._head = np.concatenate([self._head, np.zeros(grow, dtype=np.int64)])
            self._count = np.concatenate([self._count, np.zeros(grow, dtype=np.int64)])
            self._static = np.concatenate([self._static, np.zeros((grow, len(_STATIC_FIELDS)))])
            self._newest = np.concatenate([self._newest, np.full(grow, np.inf)])
            self._id_of += [None] * grow
            self._free = list(range(old + grow - 1, old - 1, -1))  # lowest slot first
        return self._free.pop()

    def _latest(self, slots: np.ndarray) -> np.ndarray:
        return self._data[slots, (self._head[slots] - 1) % self.capacity]

    def ingest(self, reports: GnssReports) -> None:
        if not len(reports):
            return
        fields = np.array([getattr(reports, f) for f in HISTORY_FIELDS], dtype=float)  # (fields, reports)
        if self._slots_of is not None and reports.ids == self._slots_of[0]:
            # the vehicles of the last batch, in its order (the common tick): the same slots
            self.received += _store_reports(self._data, self._head, self._count, self._newest, self._slots_of[1],
                                            fields)
            return
        slots = np.empty(len(reports), dtype=np.int64)
        for i, vid in enumerate(reports.ids):
            slot = self._slot.get(vid)
            if slot is None:
                slot = self._slot[vid] = self._new_slot()
                self._order = None
                self._head[slot] = self._count[slot] = 0
                self._newest[slot] = -np.inf  # any first report is newer
                self._id_of[slot] = vid
                self._static[slot] = (reports.length[i], reports.width[i], reports.height[i])
            slots[i] = slot
        self._slots_of = reports.ids, slots
        self.received += _store_reports(self._data, self._head, self._count, self._newest, slots, fields)

    def forget_stale(self, now: float) -> None:
        for slot in (self._newest < now - self.config.twin_timeout_s).nonzero()[0]:
            del self._slot[self._id_of[slot]]
            self._order = self._slots_of = None
            self._id_of[slot] = None
            self._newest[slot] = np.inf
            self._free.append(int(slot))

    def __contains__(self, vehicle_id: str) -> bool:
        return vehicle_id in self._slot

    def history(self, vehicle_id: str) -> np.ndarray:
        """(k, len(HISTORY_FIELDS)) rows of one twin, oldest first."""
        slot = self._slot[vehicle_id]
        count, head = self._count[slot], self._head[slot]
        return self._data[slot, (head - count + np.arange(count)) % self.capacity]

    def snapshot(self, now: float) -> TwinStates:
        """Latest state of every twin, with process-model outputs."""
        if self._order is None:
            ids = tuple(sorted(self._slot))
            self._order = ids, np.array([self._slot[v] for v in ids], dtype=np.int64)
        ids, slots = self._order
        latest = self._latest(slots)
        static = self._static[slots]
        cols = {f: latest[:, k] for k, f in enumerate(HISTORY_FIELDS)}
        # map matching: (s, d) and the lane (track) from the GNSS position, on any route's frame
        s, d, lane = self.road.locate(cols["x"], cols["y"])
        twins = TwinStates(
            time=now, ids=ids, lane=lane, outputs={},
            **cols, **{f: static[:, k] for k, f in enumerate(_STATIC_FIELDS)},
        )
        keep_road_frame(twins, self.road, s, d)  # the process models and the ego's stages reuse them
        written: dict[str, str] = {}  # output -> the process model that wrote it
        for name, model in self.process_models:
            out = model(twins, self)
            for key, value in out.items():
                value = np.asarray(value)
                if value.shape[:1] != (len(ids),):
                    raise ValueError(f"process model {name!r} returned {key!r} of shape {value.shape} for {len(ids)} twins")
                if key in written:
                    # the later one would replace it silently (a stand-in's lc_prob beside the
                    # predictor's lc_decision: one model's probability, the other's highlights)
                    raise ValueError(f"process models {written[key]!r} and {name!r} both write {key!r}; expected "
                                     "one writer per output (turn the other off, e.g. prediction.enabled: false)")
                written[key] = name
                twins.outputs[key] = value
        return twins


def neighbours(twins: TwinStates, ego_xy: tuple[float, float], range_m: float, exclude: str | None) -> TwinStates:
    """The twins within range_m (horizontal) of the ego, the ego's own twin excluded."""
    if not len(twins):
        return twins
    keep = np.hypot(twins.x - ego_xy[0], twins.y - ego_xy[1]) <= range_m
    if exclude in twins.ids:
        keep[twins.ids.index(exclude)] = False
    return twins.select(keep.nonzero()[0])
