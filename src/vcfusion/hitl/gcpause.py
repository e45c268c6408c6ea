"""Python's garbage collector during a paced drive: its pauses timed, and the heap built before the
trip kept out of its collections.

A full (generation-2) collection walks every container object of the process: after the imports
(torch, pandas, pyrender, SUMO's bindings) and the drive's set-up that is 110-180 ms of CPU time on
the 2-core VM (three at the start of a drive, `tools/hitl_frame_profile.py`), five frame periods
at 30 frames/s; one falling inside a drive would drop a burst of frames. :func:`frozen_heap`
collects once before the trip's clock starts and moves every object then alive to the permanent
generation (:func:`gc.freeze`), so the collections during the trip walk only the objects the trip
made. :class:`GcPauses` times each collection (:data:`gc.callbacks`) for the per-frame figures
(`frames.gc_ms`, the summary's `gc_collections`, `gc_pause_ms_max`).
"""

from __future__ import annotations

import gc
import time
from contextlib import contextmanager


class GcPauses:
    """The garbage collections made while entered: (generation, start perf_counter s, pause s)."""

    def __init__(self):
        self.pauses: list[tuple[int, float, float]] = []
        self.total_s = 0.0  # the pauses' sum, for a running difference per frame
        self._start: float | None = None

    def _callback(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._start = time.perf_counter()
        elif self._start is not None:
            now = time.perf_counter()
            self.pauses.append((int(info["generation"]), self._start, now - self._start))
            self.total_s += now - self._start
            self._start = None

    def since(self, wall_s: float) -> list[tuple[int, float, float]]:
        """The collections that started at or after `wall_s` (perf_counter)."""
        return [p for p in self.pauses if p[1] >= wall_s]

    def __enter__(self) -> "GcPauses":
        gc.callbacks.append(self._callback)
        return self

    def __exit__(self, *exc) -> None:
        gc.callbacks.remove(self._callback)
        self._start = None


@contextmanager
def frozen_heap():
    """Collect, then freeze every object alive (gc.freeze) for the block; unfrozen on every exit.
    Objects made in the block are collected as usual. Entered while objects are frozen already
    (by whoever froze them), it freezes the new ones too and leaves all frozen on exit."""
    outer = gc.get_freeze_count() > 0
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        if not outer:
            gc.unfreeze()
