"""Lane-change datasets: simulate many seeds, compute features and labels, split by seed.

Layout of a dataset folder DIR:
- DIR/runs/seed_NNNN/  a complete run folder per seed (twins, lane_changes, vehicles, ...)
  plus `samples.parquet`: one row per twin per V2C tick (the every-tick stream), with the
  features, the labels of :mod:`vcfusion.prediction.labels` and the ids. Written atomically
  by the batch runner, so an interrupted build resumes where it stopped.
- DIR/dataset.json  parameters (scenario, tau, tau_g, feature names, splits by seed) and counts.
- DIR/README.md     the schema of samples.parquet.
Training uses the rows with window_label >= 0 (the balanced Fig. 5 windows); evaluation on
the stream uses every row of the test seeds.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.errors import InputError
from vcfusion.prediction.features import (FEATURE_NAMES, LATERAL_NAMES, SEQUENCE_EXTRA_NAMES,
                                          features_from_twins_table)
from vcfusion.prediction.labels import label_samples
from vcfusion.studies.batch import SeedOutcome, check_kept_runs, complete_seeds, run_batch, seed_folder
from vcfusion.traffic.network import read_road
from vcfusion.workers import JobFailed, run_jobs

DATASET_JSON = "dataset.json"
SAMPLES = "samples.parquet"
ID_COLUMNS = ["seed", "time", "vehicle_id", "event_id", "lc_reason", "time_to_lc", "time_since_lc",
              "window_label", "stream_label"]
SPLIT_FRACTIONS = (0.7, 0.15, 0.15)  # train, validation, test, in seed order
# What the samples mean beyond their column names: raised when the labels or the features change
# meaning under the same names, so that a dataset built before is refused instead of training or
# scoring a model on what the cloud no longer computes. 1 (absent in dataset.json): the negative
# window one tick later than the paper's, lane histories averaging the absent lane's sentinel;
# 2: the paper's negative window, lane histories that start afresh when the twin has the lane.
SAMPLES_VERSION = 2


class DatasetError(InputError):
    """A dataset folder that cannot be used; the message is for the user."""


def build_samples(tables: dict[str, pd.DataFrame], road, period_s: float, seed: int, tau: float, tau_g: float,
                  end_after_mid_s: float) -> pd.DataFrame:
    """The every-tick sample table of one run (features from its twins table + labels)."""
    feats = features_from_twins_table(tables["twins"], tables["vehicles"], road, period_s)
    events = tables["lane_changes"]
    labels = label_samples(feats["time"].to_numpy(), feats["vehicle_id"].to_numpy(), events, tau, tau_g,
                           end_after_mid_s)
    reason = dict(zip(events["event_id"], events["reason"])) if len(events) else {}
    out = pd.DataFrame({
        "seed": np.full(len(feats), seed, dtype=np.int32),
        "time": feats["time"].to_numpy(),
        "vehicle_id": feats["vehicle_id"].to_numpy(),
        "event_id": labels["event_id"].to_numpy(),
        "lc_reason": [reason.get(e, "") for e in labels["event_id"].to_numpy()],
        "time_to_lc": labels["time_to_lc"].to_numpy(),
        "time_since_lc": labels["time_since_lc"].to_numpy(),
        "window_label": labels["window_label"].to_numpy(),
        "stream_label": labels["stream_label"].to_numpy(),
    })
    for name in (*FEATURE_NAMES, *SEQUENCE_EXTRA_NAMES, *LATERAL_NAMES):
        out[name] = feats[name].to_numpy(dtype=np.float32)
    return out


def _dataset_seed(scenario_path: str, seed: int, out: str, tau: float, tau_g: float,
                  privileged: bool = False) -> SeedOutcome:
    """Batch-runner task: simulate one seed and write its run folder with samples.parquet
    (privileged: also log SUMO's lane-change state, table `lc_state`, and join it to the samples)."""
    import traceback

    from vcfusion.run import build_cosimulation, manifest_for
    from vcfusion.runio import write_run_folder
    from vcfusion.scenario import load_scenario

    try:
        scenario = load_scenario(scenario_path)
        cosim = build_cosimulation(scenario, seed)
        if privileged:
            from vcfusion.prediction.privileged import LaneChangeStateHook

            cosim.hooks.append(LaneChangeStateHook())
        result = cosim.run()
        road = read_road(scenario.network, scenario.route)
        samples = build_samples(result.tables, road, scenario.v2c.period_s, seed, tau, tau_g,
                                scenario.simulation.lanechange_duration_s / 2)
        if privileged:
            from vcfusion.prediction.privileged import LC_STATE_TABLE, add_privileged

            samples = add_privileged(samples, result.tables[LC_STATE_TABLE])
        tables = {k: v for k, v in result.tables.items() if k != "ego"} | {"samples": samples}
        manifest = manifest_for(scenario, seed) | {"dataset": {"tau": tau, "tau_g": tau_g}}
        write_run_folder(seed_folder(Path(out), seed), tables, manifest, result.summary)
        return SeedOutcome(seed, True, result.summary, None)
    except Exception as exc:  # one failing seed must not stop the others
        return SeedOutcome(seed, False, None, f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}")


def _refeature_seed(folder: str, scenario_path: str, seed: int, tau: float, tau_g: float) -> int:
    """Recompute one run folder's samples.parquet from its twins / vehicles / lane_changes tables
    (no simulation: the twins table holds exactly the snapshots the cloud saw). Atomic."""
    from vcfusion.runio import atomic_write, write_table
    from vcfusion.scenario import load_scenario

    scenario = load_scenario(scenario_path)
    folder = Path(folder)
    tables = {k: pd.read_parquet(folder / f"{k}.parquet") for k in ("twins", "vehicles", "lane_changes")}
    road = read_road(scenario.network, scenario.route)
    samples = build_samples(tables, road, scenario.v2c.period_s, seed, tau, tau_g,
                            scenario.simulation.lanechange_duration_s / 2)
    from vcfusion.prediction.privileged import LC_STATE_TABLE, add_privileged

    if (folder / f"{LC_STATE_TABLE}.parquet").is_file():  # a privileged dataset keeps its SUMO columns
        samples = add_privileged(samples, pd.read_parquet(folder / f"{LC_STATE_TABLE}.parquet"))
    atomic_write(folder / SAMPLES, lambda tmp: write_table(tmp, samples))
    return seed


def refeature_runs(scenario_path: Path, seeds: list[int], runs: Path, workers: int, tau: float, tau_g: float,
                   progress: bool = True) -> tuple[list[int], list[tuple[int, str]]]:
    """Recompute samples.parquet of every complete run folder among `seeds` (parallel).

    Returns the seeds recomputed and the (seed, cause) of those that failed (their worker died
    or the recomputation raised): their samples are of the old features and must not be used.
    """
    from tqdm import tqdm

    from vcfusion.runio import is_complete_run

    todo = [s for s in seeds if is_complete_run(seed_folder(runs, s))]
    args = [(str(seed_folder(runs, s)), str(scenario_path), s, tau, tau_g) for s in todo]
    done, failed = [], []
    with tqdm(total=len(todo), desc="features", unit="seed", disable=not progress) as bar:
        for index, result in run_jobs(_refeature_seed, args, workers):
            if isinstance(result, JobFailed):
                failed.append((todo[index], result.cause))
                bar.write(f"features of seed {todo[index]} failed: {result.cause.splitlines()[0]}")
            else:
                done.append(todo[index])
            bar.update()
    return sorted(done), sorted(failed)


def split_seeds(seeds: list[int]) -> dict[str, list[int]]:
    """Train / validation / test by seed order (runs never shared); each split non-empty from 3 seeds."""
    seeds = sorted(seeds)
    n = len(seeds)
    n_test = max(1, round(n * SPLIT_FRACTIONS[2])) if n >= 3 else 0
    n_val = max(1, round(n * SPLIT_FRACTIONS[1])) if n >= 3 else 0
    n_train = n - n_val - n_test
    return {"train": seeds[:n_train], "validation": seeds[n_train:n_train + n_val],
            "test": seeds[n_train + n_val:]}


@dataclass(frozen=True)
class DatasetInfo:
    root: Path
    tau: float
    tau_g: float
    period_s: float
    feature_names: tuple[str, ...]
    splits: dict[str, list[int]]
    meta: dict

    def seeds(self, split: str) -> list[int]:
        """The seeds of a split; 'all' = every seed (for an imported recording: every vehicle)."""
        if split == "all":
            return sorted({s for seeds in self.splits.values() for s in seeds})
        return list(self.splits.get(split, []))

    def samples_file(self, seed: int) -> Path:
        return seed_folder(self.root / "runs", seed) / SAMPLES

    def run_folder(self, seed: int) -> Path:
        return seed_folder(self.root / "runs", seed)


def read_dataset_json(meta_file: Path) -> dict:
    try:
        meta = json.loads(meta_file.read_text())
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{meta_file}: cannot read: {exc}") from None
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{meta_file}: line {exc.lineno}, column {exc.colno}: not valid JSON ({exc.msg}); "
                           "expected the dataset.json `vcfusion dataset` writes") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{meta_file}: expected a JSON object of dataset parameters, got {type(meta).__name__}")
    return meta


def load_dataset(root: str | Path) -> DatasetInfo:
    """A dataset folder's parameters; every samples file of its splits is checked for the columns
    training and evaluation read (Parquet footers only), so a bad folder stops a command before it
    computes or writes anything."""
    root = Path(root)
    meta_file = root / DATASET_JSON
    if not meta_file.is_file():
        raise DatasetError(f"{root}: not a dataset folder (no {DATASET_JSON}); build one with `vcfusion dataset`")
    meta = read_dataset_json(meta_file)
    if "splits" not in meta:
        raise DatasetError(f"{meta_file}: the dataset build did not finish (no splits); run `vcfusion dataset` again")
    for key, kind, expected in (("tau", (int, float), "a number"), ("tau_g", (int, float), "a number"),
                                ("period_s", (int, float), "a number"), ("feature_names", list, "a list of names"),
                                ("splits", dict, "{split: [seeds]}")):
        if not isinstance(meta.get(key), kind) or isinstance(meta.get(key), bool):
            raise DatasetError(f"{meta_file}: {key}: expected {expected}, got {meta.get(key)!r}")
    version = meta.get("samples_version", 1)
    if version != SAMPLES_VERSION:
        raise DatasetError(f"{meta_file}: samples_version: {version!r}, this vcfusion computes version "
                           f"{SAMPLES_VERSION} (labels and features changed meaning); bring the folder up to date "
                           "without simulating: the `vcfusion dataset` command that built it, with --refeature "
                           "(an imported recording: import it again)")
    splits = meta["splits"]
    for split, seeds in splits.items():
        if not (isinstance(seeds, list) and all(isinstance(x, int) and x >= 0 for x in seeds)):
            raise DatasetError(f"{meta_file}: splits.{split}: expected a list of seeds, got {seeds!r}")
    info = DatasetInfo(root, float(meta["tau"]), float(meta["tau_g"]), float(meta["period_s"]),
                       tuple(meta["feature_names"]), {k: list(v) for k, v in splits.items()}, meta)
    needed = set(ID_COLUMNS) | set(info.feature_names)
    for split, seeds in info.splits.items():
        for seed in seeds:
            _check_samples_file(info.samples_file(seed), seed, split, needed)
    return info


def _check_samples_file(f: Path, seed: int, split: str, needed: set[str]) -> None:
    import pyarrow.parquet as pq

    if not f.is_file():
        raise DatasetError(f"{f}: missing samples of seed {seed} (split {split})")
    try:
        names = set(pq.read_schema(f).names)
    except Exception as exc:  # noqa: BLE001 - any unreadable file gets the same message
        raise DatasetError(f"{f}: not a readable Parquet file ({type(exc).__name__}); rebuild seed {seed} with "
                           "`vcfusion dataset`") from None
    missing = sorted(needed - names)
    if missing:
        raise DatasetError(f"{f}: missing columns {missing[:5]}{' ...' if len(missing) > 5 else ''}; expected "
                           "the samples table `vcfusion dataset` writes")


def load_samples(info: DatasetInfo, split: str, window_only: bool = False, columns: list[str] | None = None) -> pd.DataFrame:
    frames = []
    for seed in info.seeds(split):
        f = info.samples_file(seed)
        if not f.is_file():
            raise DatasetError(f"{f}: missing samples of seed {seed} (split {split})")
        try:
            df = pd.read_parquet(f, columns=columns)
        except Exception as exc:  # noqa: BLE001 - a file that passed the footer check but not the read
            raise DatasetError(f"{f}: cannot read the samples ({type(exc).__name__}: {exc})") from None
        if window_only:
            df = df[df["window_label"] >= 0]
        frames.append(df)
    if not frames:
        raise DatasetError(f"{info.root}: split {split!r} has no seeds")
    return pd.concat(frames, ignore_index=True)


README = """# Lane-change prediction dataset

Built by `vcfusion dataset` (vcfusion.prediction.dataset). Parameters, feature names, the
version of what labels and features mean (`samples_version`) and the split of seeds into
train / validation / test are in `dataset.json`.

`runs/seed_NNNN/` is the complete run folder of one seed (see the run-folder tables:
`twins.parquet` is what the cloud saw, `lane_changes.parquet` the ground-truth events).
`runs/seed_NNNN/samples.parquet` has one row per cloud twin per V2C tick:

| column | meaning |
|---|---|
| seed | simulation seed (the split unit) |
| time | cloud time of the snapshot, s |
| vehicle_id | the twin |
| event_id | the vehicle's next lane change (`lane_changes.event_id` of the same run), -1 if none |
| lc_reason | SUMO's reason of that change ('' if none) |
| time_to_lc | end time of that change minus time, s (NaN if none) |
| time_since_lc | time since the end of the vehicle's previous change, s (NaN if none) |
| window_label | Fig. 5 time windows: 1 positive (0 <= time_to_lc < tau), 0 negative (tau + tau_g <= time_to_lc < 2 tau + tau_g), -1 neither (not used in training) |
| stream_label | every-tick truth: 1 when 0 <= time_to_lc < tau, else 0 |
| FEATURES... | float32, see vcfusion/prediction/features.py: longitudinal only, no lateral position/speed, heading, steering, blinker or SUMO lane-change state |
| lane_end_ahead_m | float32: distance to where the own lane ends ahead (400 m when it does not end within that); an input of the sequence model only |
| lateral_known, lateral_speed_mps, lateral_drift_m | float32: lateral motion across the road (left positive; 0 with lateral_known = 0 where the source had no lateral position); inputs of a sequence model of the `lateral` input set only |

Features: {features}

Sentinels: a lane that does not exist gives gap 0 m and speed difference 0 (with
`right_lane_exists` / `left_lane_exists` = 0); no vehicle within 150 m gives gap 150 m and
difference 0; no stopped vehicle within 400 m ahead gives `stopped_ahead_*` = 400 m.
`*_trend` / `*_mean`: short-history features (fast 0.5 s minus slow 2 s moving average, and the
slow average), kept per absolute lane; a side lane that does not exist gives 0 for both.
After a feature change, `vcfusion dataset ... --refeature` recomputes these files from the
runs' `twins` tables without simulating again.
"""


def build_dataset(scenario_path: Path, seeds: list[int], out: Path, workers: int, tau: float, tau_g: float,
                  progress: bool = True, refeature: bool = False, privileged: bool = False) -> dict:
    """Simulate every seed not yet done (parallel, resumable) and write dataset.json + README.md.

    refeature: first recompute the samples of the runs already in `out` with this version's
    features (allowed to differ from the folder's; tau / tau_g must not), instead of failing.
    privileged: log SUMO's lane-change state every tick and add the privileged columns to the
    samples (vcfusion.prediction.privileged; for the ceiling, never a run-time input).
    """
    from vcfusion.runio import atomic_write, write_json
    from vcfusion.scenario import load_scenario

    if tau <= 0 or tau_g < 0:
        raise DatasetError(f"--tau/--tau-g: expected tau > 0 and tau_g >= 0, got {tau}, {tau_g}")
    scenario = load_scenario(scenario_path)
    out = Path(out)
    meta_file = out / DATASET_JSON
    params = {"scenario": scenario.name, "scenario_file": str(Path(scenario_path).resolve()),
              "tau": tau, "tau_g": tau_g, "period_s": scenario.v2c.period_s,
              # a change whose end the run did not see ends this long after its midpoint: the labels
              # use it, and so must the evaluation and the tuning (vcfusion.prediction.train)
              "lanechange_end_after_mid_s": scenario.simulation.lanechange_duration_s / 2,
              "feature_names": list(FEATURE_NAMES), "samples_version": SAMPLES_VERSION}
    if privileged:  # only then: datasets built before keep comparing equal
        from vcfusion.prediction.privileged import PRIVILEGED_NAMES

        params["privileged_names"] = list(PRIVILEGED_NAMES)
    if meta_file.is_file():
        old = read_dataset_json(meta_file)
        free = {"scenario_file"} | ({"feature_names", "samples_version"} if refeature else set())
        if "lanechange_end_after_mid_s" not in old:  # a folder from before the key was written
            free.add("lanechange_end_after_mid_s")
        keys = [*params, *({"privileged_names"} - set(params))]  # a privileged folder stays privileged
        clash = {k: (old.get(k), params.get(k)) for k in keys if k not in free and old.get(k) != params.get(k)}
        if clash:
            hint = (" (or --refeature, when only the features differ)"
                    if set(clash) <= {"feature_names", "samples_version"} else "")
            raise DatasetError(f"{meta_file}: the folder holds a dataset with other parameters "
                               f"({', '.join(f'{k}: {a!r} vs {b!r}' for k, (a, b) in clash.items())}); "
                               f"choose a new --out{hint}")
    # the seeds already in the folder stay in the dataset (a command adding seeds 3-4 to a dataset of
    # seeds 0-2 listed only 3-4 and dropped the others from its splits)
    kept = [s for s in complete_seeds(out / "runs") if (seed_folder(out / "runs", s) / SAMPLES).is_file()]
    every_seed = sorted(set(seeds) | set(kept))
    # before anything is written: a refused run must leave the dataset as it was
    check_kept_runs(Path(scenario_path), every_seed, out / "runs")
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(meta_file, lambda tmp: write_json(tmp, params))
    refeatured, stale = [], []
    if refeature:
        refeatured, stale = refeature_runs(Path(scenario_path), every_seed, out / "runs", workers, tau, tau_g, progress)
    task = functools.partial(_dataset_seed, tau=tau, tau_g=tau_g, privileged=privileged)
    report = run_batch(Path(scenario_path), seeds, out / "runs", workers=workers, progress=progress, task=task)
    report["failed"] = sorted(report["failed"] + stale)  # a seed with old features is left out
    stale_seeds = {s for s, _ in stale}
    done = [s for s in every_seed if (seed_folder(out / "runs", s) / SAMPLES).is_file() and s not in stale_seeds]
    counts = {"seeds": len(done), "samples": 0, "window_positive": 0, "window_negative": 0, "lane_changes": 0}
    for s in done:
        lab = pd.read_parquet(seed_folder(out / "runs", s) / SAMPLES, columns=["window_label"])["window_label"]
        counts["samples"] += int(len(lab))
        counts["window_positive"] += int((lab == 1).sum())
        counts["window_negative"] += int((lab == 0).sum())
        counts["lane_changes"] += int(len(pd.read_parquet(seed_folder(out / "runs", s) / "lane_changes.parquet",
                                                         columns=["event_id"])))
    params |= {"splits": split_seeds(done), "counts": counts}
    atomic_write(meta_file, lambda tmp: write_json(tmp, params))
    atomic_write(out / "README.md", lambda tmp: tmp.write_text(README.format(features=", ".join(FEATURE_NAMES))))
    return report | {"counts": counts, "splits": params["splits"], "refeatured": len(refeatured)}
