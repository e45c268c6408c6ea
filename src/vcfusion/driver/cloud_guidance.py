"""Guidance items for the driver when the vision-fusion stage does not provide them.

The AR overlay (vision fusion) puts ``Guidance`` items into ``tick.annotations['guidance']``.
When it is not wired, this hook makes the items straight from the cloud's predictions: every
neighbour twin whose centre is ahead of the ego's front bumper within ``view_range_m`` gets
an item with its ``lc_prob`` (from the twins' process-model outputs) and a level from
``records.guidance_level``: highlighted only while the cloud's smoothed ``lc_decision`` is
positive, coloured by the probability thresholds (``box`` is None: nothing was matched in an image). It runs after the other hooks
and never overwrites items the fusion stage made; it records which source was used in
``tick.annotations['guidance_source']`` and in the ``guidance`` table:
``fusion`` (items from the AR overlay), ``cloud`` (this fallback), or ``none`` (no process
model writes ``lc_prob``: no guidance can be shown).
"""

from __future__ import annotations

import numpy as np

from vcfusion.records import Guidance, guidance_level
from vcfusion.traffic.network import Road


class CloudGuidanceFallback:
    """Tick hook: guidance from the cloud predictions when no overlay made any."""

    table = "guidance"

    def __init__(self, road: Road, medium: float = 0.5, high: float = 0.8, view_range_m: float = 150.0):
        if not 0.0 <= medium <= high <= 1.0:
            raise ValueError(f"guidance thresholds: expected 0 <= medium <= high <= 1, got {medium}, {high}")
        self.road = road
        self.medium, self.high, self.view_range_m = medium, high, view_range_m

    def __call__(self, tick) -> list[dict]:
        if "guidance" in tick.annotations:
            source, items = "fusion", list(tick.annotations["guidance"])
        else:
            items = self._from_cloud(tick)
            source = "cloud" if items is not None else "none"
            items = items or []
            tick.annotations["guidance"] = items
        tick.annotations["guidance_source"] = source
        return [{"time": round(tick.time, 6), "vehicle_id": g.vehicle_id, "lc_prob": float(g.lc_prob),
                 "level": g.level, "source": source} for g in items] or [
            {"time": round(tick.time, 6), "vehicle_id": "", "lc_prob": np.nan, "level": "", "source": source}]

    def _from_cloud(self, tick) -> list[Guidance] | None:
        near = tick.neighbours
        if near is None or tick.ego is None:
            return []
        if "lc_prob" not in near.outputs:
            return None
        if not len(near):
            return []
        s, _ = near.road_frame(self.road)
        prob = np.asarray(near.outputs["lc_prob"], dtype=float)
        decision = near.outputs.get("lc_decision")
        ahead = (s > tick.ego.s) & (s - tick.ego.s <= self.view_range_m) & np.isfinite(prob)
        decisions = [None] * len(near) if decision is None else np.asarray(decision).tolist()
        return [Guidance(tick.time, vid, p, guidance_level(p, self.medium, self.high, dec), None)
                for vid, p, dec, show in zip(near.ids, prob.tolist(), decisions, ahead.tolist()) if show]
