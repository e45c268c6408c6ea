"""The cloud's lane-change predictor: a twin process model (paper Fig. 1, Section IV).

Every V2C tick the twin store calls :class:`LaneChangePredictor` with the snapshot of all
twins; it computes the features of all of them at once, runs the model once on the (N, F)
matrix (the MLP; or one step of the GRU sequence model, whose per-twin states
:class:`vcfusion.prediction.sequence.SequenceState` carries from tick to tick), thresholds the probabilities and smooths the decisions per twin (streaming Algorithm
3 or 4). It returns `lc_prob` (float) and `lc_decision` (0/1), which the store attaches to the
snapshot: they reach the ego in `Tick.neighbours` and are logged in the run's `twins` table.
At the end of a run with an ego it reports, for every lane change into the ego's lane, when the
cloud first flagged it (summary key `lane_change_flags`, :func:`first_flags`).

The per-twin memory the features need (smoothed speed, leaky maximum speed) is kept by the
predictor's FeatureExtractor from the snapshots themselves, not read from the store's raw
report history: that way a dataset rebuilt from the logged `twins` table (which holds exactly
these snapshots) gives the very same features as run time, whatever the channel did.
"""

from __future__ import annotations

import numpy as np

from vcfusion.runio import vehicle_tracks

from vcfusion.prediction.features import SEQUENCE_INPUT_SETS, FeatureExtractor
from vcfusion.prediction.model import LaneChangeModel, load_model
from vcfusion.prediction.sequence import SequenceModel, SequenceState
from vcfusion.prediction.smoothing import StreamingSmoother
from vcfusion.records import TwinStates
from vcfusion.traffic.network import Road


class LaneChangePredictor:
    """Twin process model; at the end of the run it adds `lane_change_flags` to the summary
    (`flag_end_after_mid_s`: a change's end when the trajectory does not show it, see first_flags)."""

    finish_needs = ("lane_changes", "twins")
    finish_summary = ("lane_change_flags",)

    def __init__(self, model: LaneChangeModel | SequenceModel, road: Road, period_s: float, smoothing: str | None = None,
                 threshold: float | None = None, tau_a_ticks: int | None = None, tau_c_ticks: int | None = None,
                 conservative_threshold: float | None = None, flag_end_after_mid_s: float = 1.5):
        self.model = model
        self.flag_end_after_mid_s = flag_end_after_mid_s
        self.extractor = FeatureExtractor(road, period_s)
        # the sequence model's per-twin hidden states (vcfusion.prediction.sequence.SequenceState)
        self.sequence = SequenceState(model) if model.kind == "gru" else None
        # a sequence model trained with the availability flags (and the lateral motion) also reads them
        names = tuple(model.feature_names)
        self.sway = model.kind == "gru" and names == SEQUENCE_INPUT_SETS["sway"]
        self.lateral = model.kind == "gru" and (self.sway or names == SEQUENCE_INPUT_SETS["lateral"])
        self.availability = model.kind == "gru" and (self.lateral or names == SEQUENCE_INPUT_SETS["availability"])
        smoothing = smoothing or model.smoothing
        self.threshold = model.threshold_for(smoothing) if threshold is None else threshold
        self.smoother = StreamingSmoother(
            smoothing,
            tau_a=model.tau_a_ticks if tau_a_ticks is None else tau_a_ticks,
            tau_c=model.tau_c_ticks if tau_c_ticks is None else tau_c_ticks,
            threshold=model.conservative_threshold if conservative_threshold is None else conservative_threshold)

    def __call__(self, twins: TwinStates, store=None) -> dict[str, np.ndarray]:
        if not len(twins):
            # no twin this tick (every report lost or timed out): nothing to predict, and every
            # twin's memory waits, as in the replay of the twins table, which has no rows here
            # (called, the extractor and the smoother forgot every twin)
            return {"lc_prob": np.zeros(0), "lc_decision": np.zeros(0, np.int8)}
        if self.sequence is not None:  # the GRU: one step per twin, its state carried to the next tick
            features = self.extractor.from_twins(twins, extras=True, availability=self.availability,
                                                 lateral=self.lateral, sway=self.sway)
            prob = self.sequence(twins.ids, twins.time, features)
        else:
            features = self.extractor.from_twins(twins)
            prob = self.model.predict_proba(features) if len(features) else np.zeros(0, np.float32)
        decision = self.smoother(twins.ids, (prob > self.threshold).astype(np.int8))
        return {"lc_prob": prob.astype(np.float64), "lc_decision": decision.astype(np.int8)}

    def finish(self, tables, summary: dict) -> None:
        """`lane_change_flags`: the cloud's first flags of the lane changes into the ego's lane
        (runs with an ego only: the lane_changes table then relates every change to the ego)."""
        changes = tables["lane_changes"]
        if "into_ego_lane" not in changes.columns or "lc_decision" not in tables.column_names("twins"):
            return
        lc = {name: changes[name].to_numpy() for name in changes.columns}
        into = lc["into_ego_lane"]
        into_ids = set(lc["vehicle_id"][into])
        # Only the columns and vehicles the flags need: the twins table is the largest one.
        twins = vehicle_tracks(tables.arrow("twins", ["vehicle_id", "time", "lc_decision"]), into_ids,
                               ["time", "lc_decision"])
        theirs = np.isin(lc["vehicle_id"], list(into_ids))
        flags = first_flags(twins, {k: v[theirs] for k, v in lc.items()}, self.flag_end_after_mid_s)
        ahead = dict(zip(lc["event_id"][into].tolist(), lc["ahead_of_ego"][into].tolist()))
        summary["lane_change_flags"] = [f | {"ahead_of_ego": bool(ahead[f["event_id"]])}
                                        for f in flags if f["event_id"] in ahead]


def predictor_for_scenario(scenario, road: Road) -> LaneChangePredictor | None:
    """The predictor a scenario's `prediction:` block asks for (None when disabled)."""
    from vcfusion.prediction.model import ModelFileError
    from vcfusion.scenario import ScenarioError

    cfg = scenario.prediction
    if not cfg.enabled:
        return None
    try:
        model = load_model(cfg.model)
    except ModelFileError as exc:
        raise ScenarioError(f"{scenario.source}: prediction.model: {exc}") from None
    # (load_scenario checked the model's V2C period against the scenario's)
    return LaneChangePredictor(model, road, scenario.v2c.period_s, cfg.smoothing, cfg.threshold,
                               cfg.tau_a_ticks, cfg.tau_c_ticks, cfg.conservative_threshold,
                               flag_end_after_mid_s=scenario.simulation.lanechange_duration_s / 2)


def first_flags(twins: dict[str, dict[str, np.ndarray]], events, end_after_mid_s: float = 1.5) -> list[dict]:
    """For each lane change in `events` (lane_changes columns): when the cloud first flagged it.

    `twins`: per vehicle, the time and lc_decision of its rows of the run's twins table, in time
    order (see :func:`vcfusion.runio.vehicle_tracks`). Looks at the vehicle's `lc_decision` at
    ticks after its previous lane change ended, up to this one's end. `final_run_*`: the first
    tick of the uninterrupted positive run holding the last positive decision; `first_*`: the
    first positive at all. Reported as seconds before the change's end and its midpoint
    (negative = after the midpoint); None when never flagged.
    """
    from vcfusion.prediction.labels import event_end_times

    out = []
    event_vids = np.asarray(events["vehicle_id"])
    if not len(event_vids):
        return out
    ends = np.asarray(event_end_times(events, end_after_mid_s), dtype=float)
    ends_of = {vid: ends[event_vids == vid] for vid in set(event_vids)}
    for vid, event_id, mid_time, end in zip(event_vids, np.asarray(events["event_id"]),
                                            np.asarray(events["mid_time"]), ends):
        row = {"vehicle_id": str(vid), "event_id": int(event_id), "mid_time": float(mid_time),
               "end_time": float(end), "final_run_before_end_s": None, "final_run_before_mid_s": None,
               "first_before_end_s": None, "first_before_mid_s": None}
        track = twins.get(vid)
        if track is not None:
            earlier = ends_of[vid]
            earlier = earlier[earlier < end - 1e-9]
            prev = float(earlier.max()) if len(earlier) else -np.inf
            t, d = track["time"], track["lc_decision"]
            region = np.flatnonzero((t > prev + 1e-9) & (t <= end + 1e-9))
            pos = region[d[region] == 1]
            if len(pos):
                k = pos[-1]
                while k - 1 >= region[0] and d[k - 1] == 1:
                    k -= 1
                for name, tick in (("final_run", t[k]), ("first", t[pos[0]])):
                    row[f"{name}_before_end_s"] = round(float(end - tick), 2)
                    row[f"{name}_before_mid_s"] = round(float(mid_time - tick), 2)
        out.append(row)
    return out
