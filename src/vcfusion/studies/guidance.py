"""The guidance study (paper Section V, Fig. 8 and 9): paired trips in several arms.

Trip k runs the scenario with seed k once per arm, with the same traffic seed and the same
driver draw (`vcfusion.driver.params.draw_driver(seed)`). Arms (`ARMS`):
- ``none``: the driver without AR (a "legacy vehicle"); nothing is rendered;
- ``cloud``: highlights from the cloud's predictions alone, no camera (source ``cloud``);
- ``fusion``: the paper's system: the ego camera is rendered every tick, the scenario's
  detector (the shipped CNN unless the scenario's ``fusion`` block names another), the
  scenario's matcher (joint by default), the AR overlay (source ``fusion``); turned on by the
  arm whatever the scenario's ``vision`` / ``fusion`` blocks say;
- ``oracle``: as fusion with the ground-truth boxes of the rendered frame as detections.
Every arm runs the cloud twins with their process models (the lane-change predictor writes
`lc_prob`). An arm says what produced its highlights (`guidance_source`); a camera-arm tick
without a frame is counted (`ticks_without_frame`), never filled from another source.

Per trip and arm (`arm_metrics`, the one place the study's metrics are computed): TTC, gaps,
acceleration and jerk (`vcfusion.metrics.safety`), MOVESTAR fuel and emissions per km
(`vcfusion.metrics.movestar`), the highlight episodes judged by the one definition of
`vcfusion.metrics.highlights` (`highlight_tallies`: right, wrong, missed, unseen, and the wrong ones
by the vehicle in the box), and each ego collision described (`vcfusion.metrics.collisions`). TTC
and gaps are measured in every arm against the same vehicle: the first cut-in ahead of the ego in
the reference arm (``none``; the first arm with one where it has none), chosen once per seed;
because SUMO's vehicles react to the ego, an arm's own first cut-in can be another vehicle
(`first_cut_in_differs`).

The effect of an arm is its paired difference to ``none`` per trip, over the trips where every
arm has the metric (so the table and the figures' bars and annotations are the same numbers):
mean with a t-based 95% confidence interval, the paired t-test p-value and the relative change
of the arm means, next to the paper's values.

libsumo holds one simulation per process: trips run in worker processes (vcfusion.workers), each
running its arms one after the other; a worker keeps its renderer and detector loaded across
trips (`_worker_resources`).
"""

from __future__ import annotations

import importlib
import json
import math
import time as wallclock
import traceback
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from vcfusion.runio import differing_keys, package_code_sha256, package_versions, write_json, write_table
from vcfusion.workers import JobFailed, run_jobs

# none: no AR (a "legacy vehicle"); cloud: highlights from the cloud alone, no camera; fusion:
# camera render + the scenario's detector (the shipped CNN by default) + matcher + overlay (the
# paper's system); oracle: the same with ground-truth boxes.
ARMS = ("none", "cloud", "fusion", "oracle")
CAMERA_ARMS = ("fusion", "oracle")
DEFAULT_ARMS = ("none", "fusion")
REFERENCE_ARM = "none"
# what produced each arm's highlights (the guidance table's source), for the check that no arm
# silently fell back to another source
ARM_SOURCES = {"none": None, "cloud": "cloud", "fusion": "fusion", "oracle": "fusion"}

# (column, label, unit, paper baseline, paper with guidance, paper relative change %)
SAFETY_METRICS = [
    ("avg_ttc_s", "average TTC to the lane-change vehicle", "s", None, None, 30.31),
    ("avg_ttc_clipped_s", "average TTC, clipped at 20 s", "s", None, None, None),
    ("min_ttc_s", "minimum TTC to the lane-change vehicle", "s", None, None, None),
    ("tet_s", "TET (TTC < metrics.ttc_threshold_s)", "s", None, None, None),
    ("tit_s2", "TIT (TTC < metrics.ttc_threshold_s)", "s^2", None, None, None),
    ("avg_abs_accel_mps2", "average |acceleration|", "m/s^2", 2.57, 2.07, None),
    ("max_abs_jerk_mps3", "maximum |jerk|", "m/s^3", 40.14, 35.91, None),
    ("max_decel_mps2", "maximum deceleration", "m/s^2", None, None, None),
    ("min_gap_to_target_m", "minimum gap to the lane-change vehicle, metrics.cut_in_window_s from its cut-in",
     "m", None, None, None),
    ("min_gap_stay_m", "minimum gap to the lane-change vehicle over its whole stay", "m", None, None, None),
    ("collisions", "collisions of the ego", "", None, None, None),
]
EMISSION_METRICS = [
    ("fuel_g_per_km", "fuel", "g/km", 53.82, 51.37, None),
    ("co_g_per_km", "CO", "g/km", None, None, -38.32),
    ("hc_g_per_km", "HC", "g/km", None, None, None),
    ("nox_g_per_km", "NOx", "g/km", None, None, None),
    ("pm25_g_per_km", "PM2.5 (elemental + organic)", "g/km", None, None, None),
    ("co2_g_per_km", "CO2", "g/km", None, None, None),
]
# The raw mean TTC is dominated by near-zero closing speeds (unbounded): the figure shows the
# mean of TTC clipped at 20 s; both are in the tables and the summary.
FIG8 = ["avg_ttc_clipped_s", "avg_abs_accel_mps2", "max_abs_jerk_mps3"]
FIG9 = ["fuel_g_per_km", "co_g_per_km", "hc_g_per_km", "nox_g_per_km", "pm25_g_per_km", "co2_g_per_km"]


class StudyError(RuntimeError):
    """The study cannot give a meaningful result (message for the user)."""


def load_process_model(spec: str, scenario):
    """'module:factory' -> (name, model); factory(scenario) returns a ProcessModel."""
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise ValueError(f"--process-model: expected 'module:factory', got {spec!r}")
    try:
        factory = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"--process-model: cannot load {spec!r}: {exc}") from None
    try:
        model = factory(scenario)
    except Exception as exc:  # the user's factory: say which one and what it raised, in one line
        raise ValueError(f"--process-model: {spec}(scenario {scenario.name!r}) raised {type(exc).__name__}: "
                         f"{exc}") from None
    if not callable(model):
        raise ValueError(f"--process-model: {spec}(scenario) returned a {type(model).__name__}; expected a process "
                         "model, a callable model(twins, store) -> {column: values}")
    return (f"{module_name}:{attr}", model)


def arm_scenario(scenario, arm: str):
    """The scenario as arm `arm` runs it: guidance on in every arm but `none`; the camera and
    fusion stages on for the camera arms (with the scenario's own fusion settings where it has
    them, the shipped CNN otherwise), off for the others (they never render); no video."""
    if arm not in ARMS:
        raise ValueError(f"--arms: expected arms among {', '.join(ARMS)}, got {arm!r}")
    camera = arm in CAMERA_ARMS
    fusion = scenario.fusion.model_copy(update={"enabled": camera})
    if arm == "oracle":
        fusion = fusion.model_copy(update={"detector": "oracle"})
    elif arm == "fusion" and not scenario.fusion.enabled:
        fusion = fusion.model_copy(update={"detector": "cnn"})
    return scenario.model_copy(update={
        "driver": scenario.driver.model_copy(update={"guidance": arm != "none"}),
        # every tick renders and fuses unless the scenario itself asks for vision.only_when_warning:
        # skipping ticks starves the joint matcher's position filter, so it is not the default path
        "vision": scenario.vision.model_copy(update={"enabled": camera}),
        "fusion": fusion,
        "ar": scenario.ar.model_copy(update={"video": False}),
    })


def arm_run_scenario(scenario, arm: str):
    """The scenario of `arm_scenario` as one run folder holds it (`vcfusion run --arm`): the camera
    arms record their AR frames (`ar.video`), which `vcfusion explain-highlights` shows; recording
    changes no result (curved seeds 5020, 5123, 5030: every highlight count the study's)."""
    sc = arm_scenario(scenario, arm)
    return sc.model_copy(update={"ar": sc.ar.model_copy(update={"video": arm in CAMERA_ARMS})})


# One per worker process (run_jobs workers are persistent): the renderer (its GL context and
# scene) and the CNN detector are built once and reused by every trip the worker runs.
_WORKER = {}


def renderer_key(scenario) -> str:
    """What `EgoCameraRenderer.for_scenario` builds from (the network, the road the camera draws:
    the ego's route or the scenario's, the camera), as canonical JSON: a hashable key, equal for
    two scenarios exactly when their renderers are the same."""
    from vcfusion.render.renderer import camera_road

    road = camera_road(scenario)
    return json.dumps({"network": str(scenario.network), "route": [str(e) for e in road.route],
                       "camera": scenario.camera.model_dump(mode="json")}, sort_keys=True)


def _worker_resources(scenario):
    """(renderer, detector) for a camera arm of `scenario`, built once per worker process."""
    from vcfusion.fusion.stage import build_detector

    key = ("renderer", renderer_key(scenario))
    renderer = _WORKER.get(key)
    if renderer is None:
        from vcfusion.render.renderer import EgoCameraRenderer

        for old in [k for k in _WORKER if k[0] == "renderer"]:  # one GL context per worker
            _WORKER.pop(old).close()
        renderer = _WORKER[key] = EgoCameraRenderer.for_scenario(scenario)
    f = scenario.fusion
    if f.detector == "oracle":
        return renderer, None  # cheap and stateful per frame: a fresh one per run
    dkey = ("detector", f.detector, str(f.weights))
    if dkey not in _WORKER:  # its threads: the worker's share of the cores (workers.worker_threads)
        _WORKER[dkey] = build_detector(scenario, 0)
    return renderer, _WORKER[dkey]


ARM_TABLES = ("ego", "trajectories", "vehicles", "lane_changes", "collisions", "guidance", "fusion",
              "driver", "driver_events", "display")


def simulate_arm(scenario, seed: int, arm: str, process_model_specs: tuple[str, ...] = ()) -> dict:
    """Run one arm of one trip; the tables the metrics need, and what the run was."""
    from vcfusion.run import build_cosimulation

    sc = arm_scenario(scenario, arm)
    extra = [load_process_model(s, sc) for s in process_model_specs]
    renderer = detector = None
    if arm in CAMERA_ARMS:
        renderer, detector = _worker_resources(sc)
    cosim = build_cosimulation(sc, seed, extra_process_models=extra,
                               renderer=renderer, detector=detector)
    result = cosim.run()
    tables = {name: result.tables[name] for name in ARM_TABLES if name in result.tables}
    return {"arm": arm, "scenario": sc, "tables": tables, "summary": result.summary,
            "process_models": ",".join(name for name, _ in cosim.process_models) or "(none)",
            "driver": cosim.controller.p.to_dict()}


# The study's trip log, OUT/trips.jsonl: a header line naming what the trips depend on besides their
# seeds (`study_identity`), then one line per finished trip (its rows). A study stopped part way
# (Ctrl-C, a machine taken back) continues from it when run again into the same folder; the 200
# paired trips of a matrix scenario take hours on two cores (docs/components/guidance-loop.md).
TRIP_LOG = "trips.jsonl"
# what each part of the identity is, for the error that names what differs
_IDENTITY_PARTS = {"arm_order": "the arms", "arms": "an arm's resolved scenario or the files it reads",
                   "process_models": "--process-model", "versions": "the package versions",
                   "code_sha256": "the package's code"}


def study_identity(scenario, arms: tuple[str, ...], process_model_specs: tuple[str, ...]) -> dict:
    """What a study's trips depend on besides their seeds: each arm's resolved scenario and the
    files it reads by content (`run.manifest_for`), the arms in their order (the seed's vehicle is
    the first arm's cut-in where the reference has none), the process models, the package
    versions and the package's code. As JSON reads it back, to compare with a log's header."""
    from vcfusion.run import manifest_for

    per_arm = {}
    for arm in arms:
        manifest = manifest_for(arm_scenario(scenario, arm), 0)
        per_arm[arm] = {"scenario": manifest["scenario"], "files_sha256": manifest["files_sha256"]}
    identity = {"arm_order": list(arms), "arms": per_arm, "process_models": list(process_model_specs),
                "versions": package_versions(), "code_sha256": package_code_sha256()}
    return json.loads(json.dumps(identity, sort_keys=True, default=str))


def _json_plain(value):
    """json's fallback for the numpy scalars in a trip's rows: their Python value."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"a trip row holds a {type(value).__name__}, which the trip log cannot write")


def trip_line(seed: int, rows: list[dict]) -> str:
    """One trip's record of the log (NaN and infinities as JSON's extensions: read back the same)."""
    return json.dumps({"seed": seed, "rows": rows}, default=_json_plain) + "\n"


def read_trip_log(path: Path, identity: dict) -> dict[int, list[dict]]:
    """The finished trips of the log at `path` by seed ({} where there is none). UsageError when the
    log is another study's, or when a line before the last is no trip record; a last line cut short
    (the study stopped while writing it) is left out, and `open_trip_log` writes the log without it."""
    from vcfusion.errors import UsageError

    if not path.exists():
        return {}
    lines = path.read_text().split("\n")
    try:
        header = json.loads(lines[0])
    except ValueError:
        header = None
    if not isinstance(header, dict) or not isinstance(header.get("study"), dict):
        raise UsageError(f"{path}: line 1: expected a guidance study's trip log (a JSON object with 'study'); "
                         f"choose another --out, or remove {path}")
    differs = differing_keys(identity, header["study"])
    if differs:
        what = ", ".join(_IDENTITY_PARTS.get(k, k) for k in differs)
        raise UsageError(f"{path}: holds the trips of another study (it differs in: {what}); a study continues "
                         f"only its own trips: choose another --out, or remove {path} to start over")
    trips = {}
    last = len(lines)  # the piece after the final newline: empty unless a record was cut short
    for number, line in enumerate(lines[1:], start=2):
        if not line and number == last:
            break
        try:
            record = json.loads(line)
            trips[int(record["seed"])] = list(record["rows"])
        except (ValueError, KeyError, TypeError):
            if number == last:
                break
            raise UsageError(f"{path}: line {number}: expected a trip record {{\"seed\": ..., \"rows\": [...]}}; "
                             f"remove {path} to start the study over") from None
    return trips


def open_trip_log(path: Path, identity: dict, trips: dict[int, list[dict]]):
    """The log at `path` rewritten (the header and `trips`) and opened for appending."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        f.write(json.dumps({"study": identity}, sort_keys=True) + "\n")
        for seed in sorted(trips):
            f.write(trip_line(seed, trips[seed]))
    tmp.replace(path)
    return open(path, "a")


def highlight_episodes(rows: pd.DataFrame, period_s: float, by=("vehicle_id", "box_vehicle_id")) -> list[tuple]:
    """(*values of the `by` columns, start time) of each episode in the rows of a guidance or
    fusion table (one row per item and tick): runs of ticks with the same values of `by` (the
    twin, the vehicle shown), a gap of more than 1.5 periods starting a new episode."""
    out = []
    for key, g in rows.groupby(list(by), sort=True):
        key = key if isinstance(key, tuple) else (key,)
        t = np.sort(g["time"].to_numpy(dtype=float))
        starts = np.concatenate([[0], np.flatnonzero(np.diff(t) > 1.5 * period_s + 1e-9) + 1])
        out += [(*(str(k) for k in key), float(t[k])) for k in starts]
    return out


HIGHLIGHT_COUNTS = ("highlights_right", "highlights_wrong", "missed_warnings", "unseen_warnings")
# the same judgements per AR update (warned twins in view), without episodes
HIGHLIGHT_UPDATES = ("updates_right", "updates_wrong", "updates_missed", "updates_unseen")


# the wrong episodes by the vehicle in the box (`box_vehicle_id`: the one whose visible box the
# drawn box overlaps most, what the driver model responds to): the meant vehicle, at an IoU with its
# visible box below RIGHT_IOU (a box too large, too small or off: the driver still responds to the
# right vehicle; only a camera's judged rows have it), another vehicle (the driver responds to that
# one), or none
WRONG_KINDS = ("wrong_on_meant_vehicle", "wrong_on_other_vehicle", "wrong_on_no_vehicle")


def _wrong_kind(twin: str, shown: str) -> str:
    return f"wrong_on_{'meant' if shown == twin else 'other' if shown else 'no'}_vehicle"


def highlight_update_counts(fusion: pd.DataFrame | None) -> dict:
    """Warned twin-updates of a camera run's ``fusion`` table by outcome (HIGHLIGHT_UPDATES);
    NaN without one (no camera: nothing judged per frame)."""
    from vcfusion.guidance import WARNING_LEVELS

    if fusion is None or not len(fusion) or "outcome" not in fusion:
        return dict.fromkeys(HIGHLIGHT_UPDATES, math.nan)
    warned = fusion[fusion["level"].isin(WARNING_LEVELS)]
    return {f"updates_{o}": int((warned["outcome"] == o).sum()) for o in ("right", "wrong", "missed", "unseen")}


def highlight_counts(guidance: pd.DataFrame | None, fusion: pd.DataFrame | None, period_s: float) -> dict:
    """The HIGHLIGHT_COUNTS of :func:`highlight_tallies`."""
    tallies = highlight_tallies(guidance, fusion, period_s)
    return {k: tallies[k] for k in HIGHLIGHT_COUNTS}


def highlight_tallies(guidance: pd.DataFrame | None, fusion: pd.DataFrame | None, period_s: float) -> dict:
    """Highlight episodes of one run, judged by the one definition (vcfusion.metrics.highlights):
    runs of frames in which a warned twin has the same outcome and the same vehicle in its box, a
    flicker of a right box bridged (vcfusion.metrics.highlights.warning_episodes).

    With a camera (a ``fusion`` table: one judged row per twin in view and AR update):
    ``highlights_right`` / ``highlights_wrong`` (a box drawn for the twin, on its vehicle or not),
    ``missed_warnings`` (the twin's vehicle visible, nothing drawn), ``unseen_warnings`` (its
    vehicle not visible, nothing drawn: behind another vehicle or too small; not a miss). Without
    one (the cloud arm, a person's display), from the ``guidance`` table: every item marks the twin
    it means (right unless it names another vehicle); nothing is missed or unseen. Also the wrong
    episodes by WRONG_KINDS, from the same episodes (their sum is ``highlights_wrong``; NaN where
    neither table has a row)."""
    from vcfusion.guidance import WARNING_LEVELS

    out = dict.fromkeys(HIGHLIGHT_COUNTS, 0) | dict.fromkeys(WRONG_KINDS, 0)
    if fusion is not None and len(fusion):
        if "outcome" not in fusion:
            from vcfusion.errors import InputError

            raise InputError("fusion table: no 'outcome' column (the judged highlight of each twin); expected a "
                             "run written by a version that judges highlights (vcfusion.metrics.highlights)")
        from vcfusion.metrics.highlights import warning_episodes

        warned = fusion[fusion["level"].isin(WARNING_LEVELS)]
        for ep in warning_episodes(warned, period_s):
            key = {"right": "highlights_right", "wrong": "highlights_wrong", "missed": "missed_warnings",
                   "unseen": "unseen_warnings"}[ep.outcome]
            out[key] += 1
            if ep.outcome == "wrong":
                out[_wrong_kind(ep.twin, ep.box_vehicle_id)] += 1
        return out
    if guidance is not None and len(guidance):
        for twin, shown, _ in highlight_episodes(guidance[guidance["level"].isin(WARNING_LEVELS)], period_s):
            out["highlights_right" if twin == shown else "highlights_wrong"] += 1
            if twin != shown:
                out[_wrong_kind(twin, shown)] += 1
        return out
    return out | dict.fromkeys(WRONG_KINDS, math.nan)


def arm_metrics(run: dict, target_id: str | None) -> dict:
    """Every metric of one arm of one trip (the study's one metric computation), TTC and gaps
    against the seed's `target_id`."""
    from vcfusion.metrics.collisions import describe as describe_collision
    from vcfusion.metrics.movestar import trip_emissions
    from vcfusion.metrics.safety import cut_in_target, trip_metrics
    from vcfusion.metrics.traffic import ego_movestar_type

    sc, tables, arm = run["scenario"], dict(run["tables"]), run["arm"]
    own = cut_in_target(tables.get("lane_changes"), sc.metrics.leader_range_m)
    if target_id is not None:  # the seed's vehicle, whichever cut in first in this arm
        lc = tables["lane_changes"]
        tables["lane_changes"] = lc[lc["vehicle_id"] == target_id]
    row = {"end_reason": run["summary"]["end_reason"],
           "cut_ins_ahead_of_ego": run["summary"].get("cut_ins_ahead_of_ego", 0)}
    m = sc.metrics  # the same thresholds and definitions as the runs' metrics tables
    row.update(trip_metrics(tables, sc.ego.lane, sc.simulation.step_s, m.leader_range_m, m.ttc_threshold_s,
                            m.jerk_window_s, m.ttc_clip_s, m.cut_in_window_s))
    row["ttc_threshold_s"] = m.ttc_threshold_s
    row["target_id"] = target_id
    # whether the seed's vehicle cut in ahead of the ego in this arm (else its TTC / gap are NaN)
    row["target_cut_in_here"] = bool(target_id is not None and not math.isnan(row["target_mid_time_s"]))
    row["own_first_cut_in_id"] = None if own is None else str(own["vehicle_id"])
    row["first_cut_in_differs"] = row["own_first_cut_in_id"] != target_id
    ego = tables["ego"]
    em = trip_emissions(ego["time"].to_numpy(), ego["speed"].to_numpy(), ego_movestar_type(sc, tables["vehicles"]))
    pk = em["per_km"]
    row.update({
        "fuel_g_per_km": pk["Fuel"], "co_g_per_km": pk["CO"], "hc_g_per_km": pk["HC"], "nox_g_per_km": pk["NOx"],
        "pm25_g_per_km": (pk["PM2.5_Ele"] + pk["PM2.5_Org"]) if pk["CO"] is not None else None,
        "co2_g_per_km": pk["CO2"], "fuel_g": em["totals"]["Fuel"], "movestar_tt_s": em["TT_s"],
    })
    # what produced the highlights, and how good they were
    guidance = tables.get("guidance")
    sources = sorted(set(guidance["source"])) if guidance is not None and len(guidance) else ["none"]
    row["guidance_source"] = "+".join(sources)
    row["ticks_without_frame"] = int((guidance["source"] == "no_frame").sum()) if guidance is not None else 0
    nan = math.nan
    counts = highlight_tallies(guidance, tables.get("fusion"), sc.v2c.period_s) if arm != REFERENCE_ARM else {}
    display = tables.get("display")
    if counts and display is not None and len(display):
        # a person's trip: right and wrong (and the wrong ones' kinds) are what its display drew
        # (vcfusion.hitl.driver's display table, each box judged by the one definition when drawn);
        # missed / unseen stay the fusion's
        drawn = highlight_tallies(display, None, sc.v2c.period_s)
        counts.update({k: drawn[k] for k in ("highlights_right", "highlights_wrong", *WRONG_KINDS)})
    for key in HIGHLIGHT_COUNTS:
        row[key] = counts.get(key, nan)
    row.update(highlight_update_counts(tables.get("fusion")) if arm != REFERENCE_ARM
               else dict.fromkeys(HIGHLIGHT_UPDATES, nan))
    row.update({k: counts.get(k, nan) for k in WRONG_KINDS})
    # the driver's first response to the seed's vehicle (any cue)
    events = tables.get("driver_events")
    row["response_time_s"], row["response_cue"] = nan, ""
    if target_id is not None and events is not None and len(events):
        mine = events[(events["vehicle_id"] == target_id) & events["response_time"].notna()]
        if len(mine):
            first = mine.sort_values("response_time").iloc[0]
            row["response_time_s"], row["response_cue"] = float(first["response_time"]), str(first["cue"])
    # every ego collision, described (vcfusion.metrics.collisions; the records are in the run summary)
    records = run["summary"].get("ego_collisions", [])
    row["ego_collision_detail"] = " | ".join(describe_collision(r) for r in records)
    row["process_models"] = run["process_models"]
    for k, v in run["driver"].items():
        row[f"driver_{k}"] = v
    return row


def choose_target(runs: list[dict]) -> str | None:
    """The seed's vehicle for TTC and gaps: the reference arm's first cut-in ahead of the ego, else
    the first arm's (in `runs` order, the reference first) that has one."""
    from vcfusion.metrics.safety import cut_in_target

    ordered = sorted(runs, key=lambda r: r["arm"] != REFERENCE_ARM)
    for run in ordered:
        first = cut_in_target(run["tables"].get("lane_changes"), run["scenario"].metrics.leader_range_m)
        if first is not None:
            return str(first["vehicle_id"])
    return None


def run_trip(scenario_path: str, seed: int, process_model_specs: tuple[str, ...],
             arms: tuple[str, ...] = DEFAULT_ARMS) -> tuple[int, list[dict] | None, str | None]:
    """Every arm of trip `seed` (worker entry point): one metrics row per arm."""
    from vcfusion.scenario import load_scenario

    try:
        scenario = load_scenario(scenario_path)
        runs = []
        for arm in arms:
            started = wallclock.perf_counter()
            run = simulate_arm(scenario, seed, arm, process_model_specs)
            run["wall_s"] = wallclock.perf_counter() - started
            runs.append(run)
        target = choose_target(runs)
        rows = []
        for run in runs:
            rows.append({"seed": seed, "arm": run["arm"], **arm_metrics(run, target), "arm_wall_s": run["wall_s"]})
        return seed, rows, None
    except Exception as exc:  # one failing trip must not stop the study
        return seed, None, f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}"


def paired_summary(trips: pd.DataFrame, metrics=SAFETY_METRICS + EMISSION_METRICS,
                   reference: str = REFERENCE_ARM, pair_on: tuple[str, ...] = ("seed",)) -> pd.DataFrame:
    """Per metric and arm (other than `reference`): the mean of both arms, the mean paired
    difference (arm - reference) with a t-based 95% CI, the paired t-test p-value, over the trips
    where every arm has the metric (the figures use the same numbers). A trip is one value of the
    `pair_on` columns (the seed; for run folders also the driver: participant or model)."""
    from scipy import stats

    arms = [a for a in ARMS if a in set(trips["arm"])] + sorted(set(trips["arm"]) - set(ARMS))
    if reference not in arms:
        raise StudyError(f"paired summary: the reference arm {reference!r} is not among the arms {arms}")
    rows = []
    for col, label, unit, paper_off, paper_on, paper_rel in metrics:
        wide = trips.pivot(index=list(pair_on), columns="arm", values=col).astype(float)[arms].dropna()
        n = len(wide)
        if paper_rel is None and paper_off is not None:
            paper_rel = 100.0 * (paper_on - paper_off) / paper_off
        for arm in arms:
            if arm == reference:
                continue
            diff = wide[arm] - wide[reference]
            mean_ref, mean_arm = wide[reference].mean(), wide[arm].mean()
            if n >= 2 and diff.std(ddof=1) > 0:
                half = stats.t.ppf(0.975, n - 1) * diff.std(ddof=1) / math.sqrt(n)
                p = float(stats.ttest_rel(wide[arm], wide[reference]).pvalue)
            elif n >= 2:  # every pair differs by the same amount: no spread, so p is 0 unless that is 0
                half, p = 0.0, (1.0 if diff.iloc[0] == 0 else 0.0)
            else:
                half, p = math.nan, math.nan
            rows.append({
                "metric": col, "label": label, "unit": unit, "arm": arm, "reference": reference, "n_pairs": n,
                "mean_ref": mean_ref, "mean_arm": mean_arm,
                "mean_diff": diff.mean() if n else math.nan, "ci95_low": diff.mean() - half if n else math.nan,
                "ci95_high": diff.mean() + half if n else math.nan, "p_value": p,
                "rel_change_pct": 100.0 * (mean_arm - mean_ref) / mean_ref if n and mean_ref else math.nan,
                "paper_off": paper_off, "paper_on": paper_on, "paper_rel_change_pct": paper_rel,
            })
    return pd.DataFrame(rows)


def _verdict(r) -> str:
    if not r.n_pairs or math.isnan(r.ci95_low):
        return "no data"
    if r.ci95_low > 0:
        return "higher"
    if r.ci95_high < 0:
        return "lower"
    return "no significant difference"


def _given(x) -> bool:
    return x is not None and not (isinstance(x, float) and math.isnan(x))


def format_summary(summary: pd.DataFrame, info: dict) -> str:
    if "run_folders" in info:  # the study of existing run folders (vcfusion.studies.from_runs)
        head = (f"guidance study of run folders ({info['scenario']}): {info['trips_ok']} paired trips from "
                f"{info['run_folders']} run folders ({info['drivers']}), {info['unpaired_folders']} unpaired "
                f"folders left out, arms {', '.join(info['arms'])}")
    else:
        head = (f"guidance study {info['scenario']}: {info['trips_ok']} paired trips "
                f"({info['trips_failed']} failed), arms {', '.join(info['arms'])}, in {info['wall_s']:.0f} s wall "
                f"with {info['workers']} workers"
                + (f" ({info['trips_from_log']} trips taken from the trip log)" if info.get("trips_from_log") else ""))
    lines = [head,
             f"  process models: {info['process_models']}",
             f"  trips with a cut-in ahead of the ego (TTC/gap vehicle chosen once per seed): "
             f"{info['trips_with_target']} of {info['trips_ok']}"]
    for arm, a in info["per_arm"].items():
        line = f"  {arm}: " + ("no highlights shown" if arm == REFERENCE_ARM
                                else f"highlights from {a['guidance_source']}")
        if arm != REFERENCE_ARM:
            drawn = a["highlights_right"] + a["highlights_wrong"]
            share = (f" (of the {drawn} drawn: wrong {100 * a['highlights_wrong'] / drawn:.1f} %, missed "
                     f"{100 * a['missed_warnings'] / drawn:.1f} %)") if drawn else ""
            line += (f"; highlight episodes right {a['highlights_right']}, wrong {a['highlights_wrong']}, "
                     f"missed warnings {a['missed_warnings']} (vehicle visible, nothing drawn){share}, warnings "
                     f"on a vehicle the camera does not show {a['unseen_warnings']}; ticks without a camera frame "
                     f"{a['ticks_without_frame']}")
        line += f"; own first cut-in differs from the seed's vehicle in {a['first_cut_in_differs']} trips"
        if arm != REFERENCE_ARM:
            line += (f"; responds to that vehicle {a['response_gain_s']:.2f} s earlier than {REFERENCE_ARM} "
                     f"(mean over {a['response_pairs']} trips)")
        hit = a.get("collision_trips", [])
        line += (f"; ego collisions in {len(hit)} trips" + (" (" + ", ".join(
            "seed " + str(k[-1] if isinstance(k, (list, tuple)) else k) for k in hit) + ")" if hit else ""))
        if a.get("mean_wall_s") is not None:
            line += f"; {a['mean_wall_s']:.1f} s wall per trip"
        lines.append(line)
    for arm in summary["arm"].unique():
        part = summary[summary["arm"] == arm]
        lines += ["", f"  {arm} vs {REFERENCE_ARM} (paired over trips where every arm has the metric)",
                  f"  {'metric':<46} {'n':>4} {REFERENCE_ARM:>9} {arm:>9} {'diff [95% CI]':>32} {'rel':>8} "
                  f"{'p':>7}  paper (off -> on, rel)  verdict"]
        for r in part.itertuples(index=False):
            paper = f"{r.paper_off:g} -> {r.paper_on:g}" if _given(r.paper_off) else ""
            if _given(r.paper_rel_change_pct):
                paper += f" ({r.paper_rel_change_pct:+.2f}%)"
            unit = f" [{r.unit}]" if r.unit else ""
            lines.append(
                f"  {(r.label + unit)[:46]:<46} {r.n_pairs:4d} {r.mean_ref:9.4g} {r.mean_arm:9.4g} "
                f"{r.mean_diff:+9.3g} [{r.ci95_low:+9.3g}, {r.ci95_high:+9.3g}] {r.rel_change_pct:+7.2f}% "
                f"{r.p_value:7.3g}  {paper:<22}  {_verdict(r)}")
    return "\n".join(lines)


ARM_COLOURS = {"none": "#999999", "cloud": "#6a9fd4", "fusion": "#d9a400", "oracle": "#5aa05a"}


def plot_figures(summary: pd.DataFrame, renders: Path) -> list[Path]:
    """Fig. 8 (TTC, |accel|, jerk) and Fig. 9 (fuel and emissions) like the paper's, every arm:
    bars = arm means over the paired trips, error bars and annotations = the paired difference to
    the reference arm with its 95% CI (the summary's numbers, nothing recomputed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    renders.mkdir(parents=True, exist_ok=True)
    paths = []
    arms = [REFERENCE_ARM] + list(summary["arm"].unique())
    for name, cols, title in (("guidance_fig8_safety_comfort.png", FIG8, "Safety and comfort (cf. paper Fig. 8)"),
                              ("guidance_fig9_fuel_emissions.png", FIG9, "Fuel and emissions (cf. paper Fig. 9)")):
        fig, axes = plt.subplots(1, len(cols), figsize=((0.6 + 0.6 * len(arms)) * len(cols), 4.4))
        for ax, col in zip(np.atleast_1d(axes), cols):
            part = summary[summary["metric"] == col].set_index("arm")
            first = part.iloc[0]
            means = [first["mean_ref"]] + [part.loc[a, "mean_arm"] for a in arms[1:]]
            errs = [0.0] + [(part.loc[a, "ci95_high"] - part.loc[a, "ci95_low"]) / 2 for a in arms[1:]]
            ax.bar(arms, means, yerr=errs, capsize=4, color=[ARM_COLOURS.get(a, "#777777") for a in arms])
            ax.set_title(f"{first['label']}\n[{first['unit']}], n = {first['n_pairs']}", fontsize=8)
            notes = [f"{a}: {part.loc[a, 'mean_diff']:+.3g} [{part.loc[a, 'ci95_low']:+.3g}, "
                     f"{part.loc[a, 'ci95_high']:+.3g}]" for a in arms[1:]]
            if _given(first["paper_rel_change_pct"]):
                notes.append(f"paper {first['paper_rel_change_pct']:+.1f}%")
            ax.set_xlabel("diff to " + REFERENCE_ARM + " [95% CI]\n" + "\n".join(notes), fontsize=6)
            ax.tick_params(labelsize=7)
        fig.suptitle(f"{title}: paired differences to '{REFERENCE_ARM}' (95% CI)", fontsize=9)
        fig.tight_layout()
        path = renders / name
        tmp = path.with_suffix(".tmp.png")
        fig.savefig(tmp, dpi=120)
        plt.close(fig)
        tmp.replace(path)
        paths.append(path)
    return paths


def parse_arms(text: str) -> tuple[str, ...]:
    arms = tuple(a.strip() for a in text.split(",") if a.strip())
    bad = [a for a in arms if a not in ARMS]
    if bad or not arms:
        raise ValueError(f"--arms: expected a comma-separated list of {', '.join(ARMS)}, got {text!r}")
    if len(set(arms)) != len(arms):
        raise ValueError(f"--arms: an arm is named twice in {text!r}")
    if REFERENCE_ARM not in arms:
        raise ValueError(f"--arms: expected '{REFERENCE_ARM}' among the arms (every arm is compared with it), "
                         f"got {text!r}")
    if len(arms) < 2:
        raise ValueError(f"--arms: expected at least one arm besides '{REFERENCE_ARM}', got {text!r}")
    return arms


def run_guidance_study(scenario_path: Path, trips: int, workers: int, out: Path, renders: Path,
                       first_seed: int = 0, process_model_specs: tuple[str, ...] = (),
                       progress: bool = True, arms: tuple[str, ...] = DEFAULT_ARMS) -> dict:
    """Run the paired trips, write OUT/trips.parquet|csv, summary.csv|json|txt and the figures.
    Each finished trip is logged to OUT/trips.jsonl as it ends; trips of this study already there
    (the same scenario, arms and code: `study_identity`) are taken from it, not run again."""
    from vcfusion.scenario import ScenarioError, load_scenario, require_camera_world

    arms = parse_arms(",".join(arms))
    scenario = load_scenario(scenario_path)
    if scenario.ego is None:
        raise ScenarioError(f"{scenario_path}: ego: the guidance study needs an ego; the scenario has no ego block")
    for spec in process_model_specs:  # fail fast, before any worker starts
        load_process_model(spec, scenario)
    if not scenario.prediction.enabled and not process_model_specs:
        raise StudyError(f"{scenario_path}: prediction.enabled is false and no --process-model is given, so no "
                         "process model writes 'lc_prob' to the cloud twins, nothing ever warns and every arm is "
                         "the same driver: set prediction: {enabled: true} or pass --process-model module:factory")
    if any(arm in CAMERA_ARMS for arm in arms):
        from vcfusion.fusion.stage import require_matching_range

        require_camera_world(scenario)  # what the camera arms render
        require_matching_range(arm_scenario(scenario, "fusion"))
    started = wallclock.perf_counter()
    seeds = list(range(first_seed, first_seed + trips))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    identity = study_identity(scenario, arms, tuple(process_model_specs))
    log_path = out / TRIP_LOG
    logged = read_trip_log(log_path, identity)
    from_log = [s for s in seeds if s in logged]
    todo = [s for s in seeds if s not in logged]
    rows: list[dict] = [row for s in from_log for row in logged[s]]
    failed: list[tuple[int, str]] = []
    bar = tqdm(total=len(seeds), initial=len(from_log), unit="trip", desc=f"guidance study {scenario.name}",
               disable=not progress)
    if from_log and progress:
        bar.write(f"{len(from_log)} of {len(seeds)} trips taken from {log_path} (this study's own: the same "
                  "scenario, arms and code)")
    jobs = [(str(scenario_path), s, tuple(process_model_specs), tuple(arms)) for s in todo]
    try:
        with open_trip_log(log_path, identity, logged) as log:
            for index, outcome in run_jobs(run_trip, jobs, workers):
                # a JobFailed: the trip's worker process died (its other trips go on in a new one)
                seed, result, error = (todo[index], None, outcome.cause) if isinstance(outcome, JobFailed) else outcome
                if error:  # not logged: the same command tries it again
                    failed.append((seed, error))
                    bar.write(f"trip {seed} failed: {error.splitlines()[0]}")
                else:
                    rows.extend(result)
                    log.write(trip_line(seed, result))
                    log.flush()
                bar.update(1)
    finally:
        bar.close()
    failed.sort()
    # as a batch's: the failed trips and their causes (the command then exits with 1)
    if failed:
        write_json(out / "failures.json", {str(s): e for s, e in failed})
    else:
        (out / "failures.json").unlink(missing_ok=True)
    if not rows:
        raise StudyError(f"all {len(seeds)} trips failed; first error: {failed[0][1] if failed else '?'}")
    table = pd.DataFrame(rows)
    info = {
        "scenario": scenario.name, "scenario_file": str(scenario_path), "seeds": [seeds[0], seeds[-1]],
        "trips_failed": len(failed), "trips_from_log": len(from_log), "workers": workers,
        "wall_s": wallclock.perf_counter() - started,  # this sitting's: trips taken from the log cost none
    }
    result = write_study(table, arms, info, out, renders, ("seed",), failed)
    return result | {"failed": failed}


def write_study(table: pd.DataFrame, arms: tuple[str, ...], info: dict, out: Path, renders: Path,
                pair_on: tuple[str, ...], failed: list[tuple[int, str]] = ()) -> dict:
    """From the trips table (one row per trip and arm, `arm_metrics` columns): the checks on the
    arms' sources, the paired summary, OUT/trips.parquet|csv, summary.csv|json|txt and the
    figures. A trip is one value of the `pair_on` columns. `info` is completed and returned."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    table = table.copy()
    table["arm"] = pd.Categorical(table["arm"], categories=list(arms))
    table = table.sort_values([*pair_on, "arm"]).reset_index(drop=True)
    table["arm"] = table["arm"].astype(str)
    guided = table[table["arm"] != REFERENCE_ARM]
    sources = sorted(set("+".join(guided["guidance_source"]).split("+")))
    if sources == ["none"]:
        raise StudyError("no process model writes 'lc_prob' to the cloud twins, so no guidance was ever shown "
                         "and every arm is the same driver: wire the lane-change predictor in "
                         "run.build_cosimulation or pass --process-model module:factory")
    # no silent fallback: an arm's highlights come from its own source (no_frame ticks are counted)
    for arm in arms:
        expected = ARM_SOURCES[arm]
        got = set("+".join(table.loc[table["arm"] == arm, "guidance_source"]).split("+")) - {"no_frame"}
        if expected is not None and not got <= {expected, "none"}:
            raise StudyError(f"arm {arm}: highlights came from {sorted(got)}, expected only {expected!r}")
    summary = paired_summary(table, pair_on=pair_on)
    per_arm = {}
    ref_response = table[table["arm"] == REFERENCE_ARM].set_index(list(pair_on))["response_time_s"]
    for arm in arms:
        t = table[table["arm"] == arm]
        resp = t["response_time_s"].dropna()
        gain = (ref_response - t.set_index(list(pair_on))["response_time_s"]).dropna()
        per_arm[arm] = {
            "guidance_source": "+".join(sorted(set("+".join(t["guidance_source"]).split("+")))),
            "highlights_right": int(t["highlights_right"].sum()) if arm != REFERENCE_ARM else None,
            "highlights_wrong": int(t["highlights_wrong"].sum()) if arm != REFERENCE_ARM else None,
            "missed_warnings": int(t["missed_warnings"].sum()) if arm != REFERENCE_ARM else None,
            "unseen_warnings": int(t["unseen_warnings"].sum()) if arm != REFERENCE_ARM else None,
            "ticks_without_frame": int(t["ticks_without_frame"].sum()),
            # never hidden: the trips in which the ego collided, by their pair key (the seed)
            "collision_trips": [list(k) if isinstance(k, tuple) else k
                                for k in t.loc[t["collisions"].fillna(0) > 0, list(pair_on)].itertuples(index=False, name=None)],
            "first_cut_in_differs": int(t["first_cut_in_differs"].sum()),
            "target_cut_in_here": int(t["target_cut_in_here"].sum()),
            "mean_response_time_s": float(resp.mean()) if len(resp) else math.nan, "responses": int(len(resp)),
            # paired: how much earlier the driver responds to the seed's vehicle than in the reference arm
            "response_gain_s": float(gain.mean()) if len(gain) else math.nan, "response_pairs": int(len(gain)),
            # the run folders record no wall time per trip
            "mean_wall_s": float(t["arm_wall_s"].mean()) if "arm_wall_s" in t else None,
        }
    trips = table.groupby(list(pair_on))
    info = info | {
        "arms": list(arms), "reference_arm": REFERENCE_ARM, "trips_ok": int(trips.ngroups),
        "process_models": ", ".join(sorted(set(table["process_models"]))),
        "trips_with_target": int(trips["target_id"].first().notna().sum()),
        "per_arm": per_arm,
    }
    write_table(out / "trips.parquet", table)
    # the collisions, one row each, with their trip (never left out of the study's outputs)
    hits = table[table["collisions"].fillna(0) > 0]
    tmp = out / "collisions.csv.tmp"
    hits.reindex(columns=[*pair_on, "arm", "collisions", "ego_collision_detail"]).to_csv(tmp, index=False)
    tmp.replace(out / "collisions.csv")
    tmp = out / "trips.csv.tmp"
    table.to_csv(tmp, index=False)
    tmp.replace(out / "trips.csv")
    tmp = out / "summary.csv.tmp"
    summary.to_csv(tmp, index=False)
    tmp.replace(out / "summary.csv")
    text = format_summary(summary, info)
    write_json(out / "summary.json", info | {"metrics": json.loads(summary.to_json(orient="records")),
                                             "failed": {str(s): e for s, e in failed}})
    (out / "summary.txt").write_text(text + "\n")
    figures = plot_figures(summary, Path(renders))
    return {"info": info, "summary": summary, "text": text, "figures": figures, "trips": table}
