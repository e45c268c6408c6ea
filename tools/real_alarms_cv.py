"""Cross-fitted validation streams of the US-101 recordings and the decision chosen on them
(docs/components/real-data.md, "False alarms on real data").

The development and validation parts of the frozen splits (splits/) are cut into 4 folds of whole
units (CommonRoad recordings, NGSIM vehicles; seeded); for each fold k a GRU is fine-tuned from a
simulated model on the other folds (fold k+1 stops it and calibrates it) and scores fold k. The
held-out parts are in no fold: they are in every fold dataset's test part and never scored here.
The pooled out-of-fold streams (94 lane changes, 2.9 vehicle-hours) give the curve of lane changes
predicted, mean advance and false alarms per vehicle-hour against the threshold (aggressive
smoothing, tau_a given), and the setting predicting most lane changes with at most BUDGET false
alarms per vehicle-hour in each recording (ties: larger mean advance, then fewer false alarms).
The rate bounded is `--false-alarm-rate`: all (every false alarm over all vehicle-hours, the
headline rate) or judged (censoring-aware: the false alarms whose confirming window fits in the
track over the vehicle-hours where it fits, `vcfusion.prediction.events`); curve.csv holds both.

    python tools/real_alarms_cv.py NGSIM_DS CR_DS INIT_MODEL WORK_DIR \
        [--lr 3e-4] [--tau-ticks 50] [--budget 4] [--false-alarm-rate all|judged] [--apply MODEL --out FILE] \
        [--seeds 0,1,2] [other `vcfusion train` options, e.g. --seed 1]

--seeds S1,S2,...: per fold one fine-tuning per seed (WORK_DIR/ft_cv{k}_seed{S}.npz) and their
ensemble (`vcfusion ensemble-models`: the members' calibrated probabilities averaged) scored as
WORK_DIR/ft_cv{k}.npz; without it one fine-tuning per fold (seed 0, or `--seed S`). A WORK_DIR
holds one or the other: its scored files are never silently replaced by the other kind.

NGSIM_DS / CR_DS: the imports (`vcfusion dataset --from-...`); run from the repository root (it
reads splits/). Writes WORK_DIR/curve.csv and prints the choice; with --apply, writes it into
a copy of MODEL (`vcfusion set-decision`, the reason naming this procedure). Four fine-tunings of about a minute each on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.prediction.dataset import load_dataset
from vcfusion.prediction.decision_curve import RATE_COLUMN, choose_threshold, threshold_curve, weak_judged_bounds
from vcfusion.prediction.features import stored_columns, with_derived_columns
from vcfusion.prediction.model import load_model
from vcfusion.prediction.realsplit import base_vehicle_id
from vcfusion.prediction.train import stream_with_events

FOLDS = 4
SPLITS = {"ngsim": "splits/us101_ngsim_0750.json", "cr": "splits/us101_commonroad.json"}
THRESHOLDS = np.round(np.arange(0.20, 0.705, 0.01), 2)


def fold_files(work: Path) -> None:
    for name, path in SPLITS.items():
        split = json.loads(Path(path).read_text())
        units = sorted(split["parts"]["development"] + split["parts"]["validation"])
        order = np.random.default_rng(1).permutation(len(units))
        folds = [[units[i] for i in order[k::FOLDS]] for k in range(FOLDS)]
        for k in range(FOLDS):
            nxt = (k + 1) % FOLDS
            parts = {"held_out": folds[k] + split["parts"]["held_out"], "validation": folds[nxt],
                     "development": [u for j in range(FOLDS) if j not in (k, nxt) for u in folds[j]]}
            (work / f"{name}_cv{k}.json").write_text(json.dumps({**split, "parts": parts,
                                                                "name": f"{split['name']}-cv{k}"}, indent=1))


def run(*args: str) -> None:
    print("+ vcfusion", " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "vcfusion", *args], check=True)


def fine_tune(work: Path, k: int, init: str, lr: str, train_extra: list[str], out: Path, seed: int = 0) -> None:
    run("train", str(work / f"ngsim-cv{k}"), str(work / f"cr-cv{k}"), "--kind", "gru", "--seed", str(seed),
        "--threads", "1", "--init", init, "--epochs", "10", "--patience", "4", "--learning-rate", lr,
        "--false-alarm-budget", "5", *[x for x in train_extra if x != "--"], "--out", str(out))


def scored_models(work: Path, k: int, init: str, lr: str, train_extra: list[str], seeds: list[int] | None) -> None:
    """WORK/ft_cv{k}.npz, the model scored on fold k: one fine-tuning, or the ensemble of one per seed."""
    from vcfusion.prediction.ensemble import EnsembleModel

    scored = work / f"ft_cv{k}.npz"
    if scored.exists() and isinstance(load_model(scored), EnsembleModel) != bool(seeds):
        raise SystemExit(f"error: {scored}: {'a single fine-tuning' if seeds else 'an ensemble (--seeds)'} of an "
                         f"earlier run; use another WORK_DIR")
    if not seeds:
        if not scored.exists():
            fine_tune(work, k, init, lr, train_extra, scored)
        return
    members = [work / f"ft_cv{k}_seed{s}.npz" for s in seeds]
    for s, member in zip(seeds, members):
        if not member.exists():
            fine_tune(work, k, init, lr, train_extra, member, seed=s)
    run("ensemble-models", *map(str, members), "--out", str(scored), "--force")


def out_of_fold(work: Path, extra_columns: tuple[str, ...] = ()) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The pooled out-of-fold streams (seed, vehicle_id, time, prob, source, original_seed and
    `extra_columns` of the samples) and their lane changes; seeds offset per fold and source."""
    streams, events = [], []
    for k in range(FOLDS):
        model = load_model(work / f"ft_cv{k}.npz")
        names = list(model.feature_names)
        for j, name in enumerate(("ngsim", "cr")):
            info = load_dataset(work / f"{name}-cv{k}")
            wanted = ["seed", "vehicle_id", "time", *stored_columns(names)]
            s, e = stream_with_events(info, "test", columns=wanted + [c for c in extra_columns if c not in wanted])
            with_derived_columns(s, names, model.period_s)
            s["prob"] = model.stream_proba(s, names)
            held_out = set(json.loads(Path(SPLITS[name]).read_text())["parts"]["held_out"])
            if name == "cr":
                recording = {int(seed): m["recording"] for seed, m in info.meta["seeds"].items()}
                keep = ~s["seed"].map(recording).isin(held_out)
            else:
                keep = ~s["vehicle_id"].astype(str).map(base_vehicle_id).isin(held_out)
            original = {int(seed): m.get("original_seed", int(seed)) for seed, m in info.meta["seeds"].items()}
            s["original_seed"] = s["seed"].map(original)
            s = s.loc[keep.to_numpy(), ["seed", "vehicle_id", "time", "prob", "original_seed",
                                        *[c for c in extra_columns if c not in ("seed", "vehicle_id", "time")]]]
            s = s.assign(source=name)
            offset = (k * 2 + j) * 10_000_000  # keeps the folds' and sources' seeds apart
            s["seed"] += offset
            e = e.assign(seed=e["seed"] + offset)
            e = e[e.set_index(["seed", "vehicle_id"]).index.isin(s.set_index(["seed", "vehicle_id"]).index)]
            streams.append(s)
            events.append(e)
    stream = pd.concat(streams, ignore_index=True).sort_values(["seed", "vehicle_id", "time"], kind="stable")
    return stream.reset_index(drop=True), pd.concat(events, ignore_index=True)


def curve(stream: pd.DataFrame, events: pd.DataFrame, tau_ticks: int) -> pd.DataFrame:
    return threshold_curve(stream, events, THRESHOLDS, tau_ticks, 0.1, 10.0)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)  # --seed is `vcfusion train`'s
    for name in ("ngsim", "cr", "init", "work"):
        p.add_argument(name)
    p.add_argument("--lr", default="3e-4")
    p.add_argument("--tau-ticks", type=int, default=50)
    p.add_argument("--budget", type=float, default=4.0)
    p.add_argument("--false-alarm-rate", dest="rate", choices=sorted(RATE_COLUMN), default="all",
                   help="the rate bounded by --budget in each recording: all (headline) or judged (censoring-aware)")
    p.add_argument("--apply", help="model file to write the chosen decision into (with --out)")
    p.add_argument("--out", help="the model file --apply writes")
    p.add_argument("--seeds", help="comma-separated fine-tuning seeds, e.g. 0,1,2: per fold the ensemble of one "
                                   "fine-tuning per seed is scored (vcfusion ensemble-models)")
    a, train_extra = p.parse_known_args()  # the rest: options of `vcfusion train`
    if bool(a.apply) != bool(a.out):
        p.error("--apply and --out go together")
    seeds = None
    if a.seeds is not None:
        try:
            seeds = [int(x) for x in a.seeds.split(",")]
        except ValueError:
            p.error(f"--seeds: expected comma-separated whole numbers, e.g. 0,1,2, got {a.seeds!r}")
        if len(set(seeds)) != len(seeds):
            p.error(f"--seeds: expected different seeds, got {a.seeds}")
        if any(x == "--seed" or x.startswith("--seed=") for x in train_extra):
            p.error("--seeds and --seed: give one of them")
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    fold_files(work)
    for k in range(FOLDS):
        for name, ds in (("ngsim", a.ngsim), ("cr", a.cr)):
            if not (work / f"{name}-cv{k}").exists():
                run("real-split", "apply", ds, str(work / f"{name}_cv{k}.json"), "--out", str(work / f"{name}-cv{k}"))
        scored_models(work, k, a.init, a.lr, train_extra, seeds)
    stream, events = out_of_fold(work)
    table = curve(stream, events, a.tau_ticks)
    table.to_csv(work / "curve.csv", index=False)
    print(f"out-of-fold: {len(events)} lane changes, {len(stream) * 0.1 / 3600:.2f} vehicle-hours -> {work}/curve.csv")
    try:
        best = choose_threshold(table, a.budget, ("ngsim", "cr"), a.rate)
    except ValueError as exc:
        print(f"--false-alarm-rate judged: {exc}", file=sys.stderr)
        return 2
    if best is None:
        print(f"no threshold keeps both recordings at <= {a.budget} false alarms / veh-h ({a.rate})")
        return 1
    print(f"false-alarm rate bounded: {a.rate}")
    print(best.to_string())
    if a.rate == "judged":
        for note in weak_judged_bounds(best, a.budget, ("ngsim", "cr")):
            print(f"note: {note}")
    if a.apply:
        run("set-decision", a.apply, "--out", a.out, "--smoothing", "aggressive", "--threshold", f"{best['threshold']:.2f}",
            "--tau-ticks", str(a.tau_ticks), "--force", "--reason",
            f"tools/real_alarms_cv.py: cross-fitted validation streams of the development and validation parts "
            f"({FOLDS} folds, {len(events)} lane changes, {len(stream) * 0.1 / 3600:.2f} veh-h), most lane changes "
            f"with <= {a.budget:g} false alarms / veh-h in each recording"
            + (f"; fold models: ensembles of the fine-tuning seeds {a.seeds}" if seeds else "")
            + (" (judged: uncensored false alarms over the exposure where the confirming window fits)"
               if a.rate == "judged" else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
