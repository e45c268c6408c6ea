"""The guidance log of a run, and the cloud guidance where a run has no vision fusion.

With vision fusion (``camera=True``: the AR overlay sets ``tick.guidance``, source ``fusion``)
this stage only logs what is shown; a tick where the camera gave no frame keeps
``tick.guidance = None`` (nothing is drawn, nothing stands in for it) and is logged with source
``no_frame``, so a study counts it. Without vision fusion it fills ``tick.guidance`` at every tick
straight from the cloud's predictions:
every neighbour twin ahead of the ego (the run's :class:`~vcfusion.guidance.GuidancePolicy`:
rear bumper beyond the ego's front bumper, within ``driver.guidance_view_range_m``) gets an item
with its ``lc_prob`` (from the twins' process-model outputs) and the policy's level: highlighted
only while the cloud's smoothed ``lc_decision`` is positive, coloured by the probability
thresholds (``box`` is None: nothing was matched in an image). It declares ``fills =
("guidance",)``, so the run refuses to put it before a stage that provides guidance. It logs the
items shown and their source to the ``guidance`` table: ``fusion`` (items from the AR overlay),
``cloud`` (this stage), or ``none`` (no process model writes ``lc_prob``: no guidance can be shown).
"""

from __future__ import annotations

import numpy as np

from vcfusion.guidance import GuidancePolicy
from vcfusion.records import Guidance, GuidanceSet
from vcfusion.traffic.network import Road


class CloudGuidanceFallback:
    """Tick hook: logs the guidance shown (``box_vehicle_id``: the vehicle the driver sees
    highlighted); without a camera it makes that guidance from the cloud predictions."""

    table = "guidance"
    columns = ("time", "vehicle_id", "box_vehicle_id", "lc_prob", "level", "source")

    def __init__(self, road: Road, policy: GuidancePolicy, camera: bool = False):
        self.road = road
        self.policy = policy
        self.camera = camera
        if camera:  # the overlay provides the guidance: log it, never replace it
            self.needs = ("ego", "neighbours", "guidance")
        else:
            self.needs = ("ego", "neighbours")
            self.fills = ("guidance",)

    def __call__(self, tick) -> list[dict]:
        if tick.guidance is None and not self.camera:
            items = self._from_cloud(tick)
            tick.guidance = GuidanceSet(tuple(items or ()), "cloud" if items is not None else "none")
        t = round(tick.time, 6)
        if tick.guidance is None:
            return [{"time": t, "vehicle_id": "", "box_vehicle_id": "", "lc_prob": np.nan, "level": "",
                     "source": "no_frame"}]
        source = tick.guidance.source
        return [{"time": t, "vehicle_id": g.vehicle_id, "box_vehicle_id": g.shown_vehicle_id or "",
                 "lc_prob": float(g.lc_prob), "level": g.level, "source": source} for g in tick.guidance.items] or [
            {"time": t, "vehicle_id": "", "box_vehicle_id": "", "lc_prob": np.nan, "level": "", "source": source}]

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
        shown = self.policy.ahead(s - near.length / 2, tick.ego.s) & np.isfinite(prob)
        decisions = [None] * len(near) if decision is None else np.asarray(decision).tolist()
        return [Guidance(tick.time, vid, p, self.policy.level(p, dec), None)
                for vid, p, dec, show in zip(near.ids, prob.tolist(), decisions, shown.tolist()) if show]
