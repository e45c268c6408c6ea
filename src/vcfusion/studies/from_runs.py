"""The guidance study of existing run folders (`vcfusion study guidance --from-runs DIR...`).

Any run folders with an ego driver: human trips (`vcfusion drive`, `vcfusion study hitl`), model
trips (`vcfusion run`, `vcfusion batch`), or both. Each folder is read back into the run dict the
model study's `arm_metrics` reads (its Parquet tables, the scenario it recorded), so both studies
compute every number with the same function.

- The scenario is the resolved one the manifest recorded (what the run really ran, whatever
  the scenario files say today, wherever they are now), not the file re-read.
- The condition (arm): without guidance, ``none``; with guidance, the source that produced it
  in that run, named as the model study names its arms: ``fusion`` (the camera, a detector and
  the overlay; ``oracle`` with ground-truth boxes) when the run's scenario had fusion on, else
  ``cloud``. Whether guidance was on: the `hitl` block of summary.json (human trips), the
  driver's `guidance_enabled` (model trips).
- The driver: ``driver_kind`` human or model; ``participant`` the person's id (empty for the
  model, whose draw is a function of the seed). A trip is (driver_kind, participant, seed) on one
  traffic scenario (`trip_key`: the resolved scenario without what the arms change); it is
  paired when it has a folder in every arm found. Folders of unpaired trips are reported and
  left out of the table (counted).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from vcfusion.errors import InputError
from vcfusion.runio import MANIFEST, SUMMARY, is_complete_run
from vcfusion.studies.guidance import ARM_TABLES, ARMS, REFERENCE_ARM, arm_metrics, choose_target, write_study

# what arm_metrics reads whatever the run was; `fusion` too when the run fused, `driver_events`
# when a driver model drove (a person's run has no such table)
REQUIRED_TABLES = ("ego", "vehicles", "trajectories", "lane_changes", "guidance")
PAIR_ON = ("driver_kind", "participant", "seed")
# scenario blocks the arms of one trip may differ in (the model study's arm_scenario changes
# vision, fusion and ar; a guidance-off model run needs driver.guidance false): the rest is the trip
ARM_BLOCKS = ("name", "description", "vision", "fusion", "ar")


class RunFolderError(InputError):
    """A folder given to --from-runs that the study cannot read (the message names it)."""


@dataclass(frozen=True)
class RunTrip:
    """One run folder, read back: the run dict of `arm_metrics` and who drove it in what condition."""
    folder: Path
    run: dict  # {"arm", "scenario", "tables", "summary", "process_models", "driver"}
    seed: int
    driver_kind: str  # "human" or "model"
    participant: str
    trip_key: str

    @property
    def arm(self) -> str:
        return self.run["arm"]

    @property
    def pair(self) -> tuple:
        return self.driver_kind, self.participant, self.trip_key, self.seed


def guided_arm(scenario) -> str:
    """The study arm whose highlights this scenario's guidance shows (vcfusion.studies.guidance.ARMS)."""
    if scenario.fusion.enabled:
        return "oracle" if scenario.fusion.detector == "oracle" else "fusion"
    return "cloud"


def trip_key(resolved: dict) -> str:
    """The traffic trip of a resolved scenario: everything but what the arms of a trip differ in."""
    trip = {k: v for k, v in resolved.items() if k not in ARM_BLOCKS}
    trip["driver"] = {k: v for k, v in trip.get("driver", {}).items() if k != "guidance"}
    return json.dumps(trip, sort_keys=True)


def _first_difference(a, b, path: str = "") -> str:
    """The dotted path of the first value in which two JSON values differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if a.get(k) != b.get(k):
                return _first_difference(a.get(k), b.get(k), f"{path}.{k}" if path else k)
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            if x != y:
                return _first_difference(x, y, f"{path}[{i}]")
    return path


def _read_json(folder: Path, name: str) -> dict:
    try:
        data = json.loads((folder / name).read_text())
    except FileNotFoundError:
        raise RunFolderError(f"{folder}: {name} is missing; expected a complete run folder") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RunFolderError(f"{folder / name}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise RunFolderError(f"{folder / name}: expected a JSON object")
    return data


def load_run_folder(folder: Path) -> RunTrip:
    """A complete run folder as the run dict the study's metrics read; RunFolderError (naming the
    folder, the file and what was expected) when it is not one the study can use."""
    from pydantic import ValidationError

    from vcfusion.scenario import Scenario

    folder = Path(folder)
    if not folder.is_dir():
        raise RunFolderError(f"{folder}: not a folder; expected a run folder")
    if not is_complete_run(folder):
        raise RunFolderError(f"{folder}: {MANIFEST} is missing; expected a complete run folder "
                             "(written by vcfusion run, batch, drive or study hitl)")
    manifest = _read_json(folder, MANIFEST)
    summary = _read_json(folder, SUMMARY)
    if not isinstance(manifest.get("scenario"), dict) or not isinstance(manifest.get("seed"), int):
        raise RunFolderError(f"{folder / MANIFEST}: expected the run's resolved 'scenario' and its 'seed'")
    try:
        scenario = Scenario.model_validate(manifest["scenario"])
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"])
        raise RunFolderError(f"{folder / MANIFEST}: scenario.{where}: {err['msg']} (a run of another vcfusion "
                             "version?)") from None
    if scenario.ego is None:
        raise RunFolderError(f"{folder}: the run has no ego (its scenario has no 'ego' block); the guidance "
                             "study compares the ego's trips")
    hitl, driver = summary.get("hitl"), summary.get("driver")
    if isinstance(hitl, dict):
        if hitl.get("guidance") not in ("on", "off"):
            raise RunFolderError(f"{folder / SUMMARY}: hitl.guidance: expected 'on' or 'off', "
                                 f"got {hitl.get('guidance')!r}")
        kind, guided, participant, params = "human", hitl["guidance"] == "on", str(hitl.get("participant") or ""), {}
    elif isinstance(driver, dict) and isinstance(driver.get("guidance_enabled"), bool):
        kind, guided, participant = "model", driver["guidance_enabled"], ""
        params = {k: v for k, v in driver.items() if k != "guidance_enabled"}
    else:
        raise RunFolderError(f"{folder / SUMMARY}: expected an 'hitl' block (a person's trip) or a 'driver' block "
                             "with 'guidance_enabled' (a driver model's trip); the run has neither")
    needed = list(REQUIRED_TABLES) + ["fusion"] * scenario.fusion.enabled + ["driver_events"] * (kind == "model")
    missing = [name for name in needed if not (folder / f"{name}.parquet").is_file()]
    if missing:
        raise RunFolderError(f"{folder}: {', '.join(m + '.parquet' for m in missing)} missing; the study's metrics "
                             "need " + ", ".join(needed))
    tables = {}
    for name in ARM_TABLES:
        path = folder / f"{name}.parquet"
        if path.is_file():
            try:
                tables[name] = pd.read_parquet(path)
            except Exception as exc:  # a truncated or foreign file: name it
                raise RunFolderError(f"{path}: cannot be read as Parquet ({type(exc).__name__}: {exc})") from None
    # as the model study names them (simulate_arm); "(not recorded)": a run written before the
    # summary listed its process models
    names = summary.get("process_models")
    models = "(not recorded)" if names is None else (",".join(names) or "(none)")
    run = {"arm": guided_arm(scenario) if guided else REFERENCE_ARM, "scenario": scenario, "tables": tables,
           "summary": summary, "process_models": models, "driver": params}
    return RunTrip(folder, run, manifest["seed"], kind, participant, trip_key(manifest["scenario"]))


def find_run_folders(paths: list[Path]) -> tuple[list[Path], list[Path]]:
    """(run folders, skipped sub-folders) of the folders given: each is a run folder, an hitl
    session (its protocol.json's trips; the practice drive is not a study trip) or a folder of
    run folders and sessions (a batch's seed_NNNN, a folder of sessions); sub-folders that are
    none of these (e.g. a batch's unfinished seed) are skipped and reported."""
    runs, skipped = [], []

    def session(folder: Path) -> list[Path]:
        protocol = _read_json(folder, "protocol.json")
        trips = [folder / t["run"] for t in protocol.get("trips", []) if isinstance(t, dict) and "run" in t]
        skipped.extend(t for t in trips if not is_complete_run(t))
        return [t for t in trips if is_complete_run(t)]

    for path in map(Path, paths):
        if is_complete_run(path):
            runs.append(path)
            continue
        if not path.is_dir():
            raise RunFolderError(f"{path}: no such folder; expected a run folder or a folder of run folders")
        if (path / "protocol.json").is_file():
            runs += session(path)
            continue
        found = []
        for child in sorted(p for p in path.iterdir() if p.is_dir()):
            if is_complete_run(child):
                found.append(child)
            elif (child / "protocol.json").is_file():
                found += session(child)
            else:
                skipped.append(child)
        if not found:
            raise RunFolderError(f"{path}: expected a run folder (with {MANIFEST}) or a folder of run folders "
                                 "(a batch, an hitl session); found none")
        runs += found
    unique = list(dict.fromkeys(p.resolve() for p in runs))  # a folder named twice counts once
    return unique, skipped


def study_of_runs(paths: list[Path], out: Path, renders: Path) -> dict:
    """The guidance study's table, summary and figures from run folders (module doc); writes what
    `run_guidance_study` writes. Every folder is read and checked before anything is written."""
    folders, skipped = find_run_folders(paths)
    trips = [load_run_folder(f) for f in folders]
    # every folder, paired or not: a folder of another scenario is a mistake to say, not a trip to leave out
    scenarios: dict[str, RunTrip] = {}
    for trip in trips:
        scenarios.setdefault(trip.trip_key, trip)
    if len(scenarios) > 1:
        first, other = list(scenarios.values())[:2]
        raise RunFolderError(f"{other.folder}: a trip of another scenario than {first.folder} (scenario."
                             f"{_first_difference(json.loads(first.trip_key), json.loads(other.trip_key))} differs; "
                             f"{len(scenarios)} scenarios in all): a study compares trips of one scenario; "
                             "give the folders of one")
    by_pair: dict[tuple, dict[str, RunTrip]] = {}
    for trip in trips:
        slots = by_pair.setdefault(trip.pair, {})
        if trip.arm in slots:
            driver = f"participant {trip.participant!r}" if trip.driver_kind == "human" else "the driver model"
            raise RunFolderError(f"{trip.folder}: the same trip (seed {trip.seed}, {driver}) in the same arm "
                                 f"{trip.arm!r} as {slots[trip.arm].folder}; give one folder per trip and arm")
        slots[trip.arm] = trip
    found = {t.arm for t in trips}
    arms = tuple(a for a in ARMS if a in found)
    if REFERENCE_ARM not in found or len(arms) < 2:
        raise InputError(f"--from-runs: the {len(trips)} run folders are all in arm(s) {', '.join(arms)}; the study "
                         f"compares trips without guidance ('{REFERENCE_ARM}') with guided ones: give folders of both")
    paired = {k: v for k, v in by_pair.items() if set(v) == set(arms)}
    unpaired = sorted((t.folder, sorted(v)) for v in by_pair.values() if set(v) != set(arms) for t in v.values())
    if not paired:
        raise InputError(f"--from-runs: no trip (driver and seed) has a run folder in every arm ({', '.join(arms)}); "
                         f"{len(unpaired)} unpaired folders, e.g. {unpaired[0][0]}")
    rows = []
    for key in sorted(paired, key=lambda k: (k[0], k[1], k[3])):
        runs = [paired[key][a].run for a in arms]
        target = choose_target(runs)  # the seed's vehicle, per driver: each drove their own trip
        for arm in arms:
            trip = paired[key][arm]
            rows.append({"seed": trip.seed, "arm": arm, "driver_kind": trip.driver_kind,
                         "participant": trip.participant, **arm_metrics(trip.run, target),
                         "run_folder": str(trip.folder)})
    table = pd.DataFrame(rows)
    kinds = table.drop_duplicates(["driver_kind", "participant"])
    people = kinds[kinds["driver_kind"] == "human"]
    drivers = ", ".join(([f"{len(people)} participant(s)"] if len(people) else [])
                        + (["the driver model"] if (kinds["driver_kind"] == "model").any() else []))
    names = sorted({t.run["scenario"].name for v in paired.values() for t in v.values()})
    info = {"scenario": ", ".join(names), "run_folders": len(folders),
            "paired_folders": len(table), "unpaired_folders": len(unpaired), "drivers": drivers,
            "unpaired": [{"folder": str(f), "arms_of_its_trip": a} for f, a in unpaired],
            "skipped_folders": [str(p) for p in skipped], "seeds": sorted(set(table["seed"].tolist())),
            "trips_failed": 0}
    result = write_study(table, arms, info, out, renders, PAIR_ON)
    return result | {"unpaired": unpaired, "skipped": skipped}

