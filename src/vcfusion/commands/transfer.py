"""Handlers of `vcfusion real-split` (frozen splits of imported recordings), `vcfusion retune`,
`set-decision` and `ensemble-models` (lane-change model files) and `vcfusion sim-to-real` (the
sim-to-real table of lane-change predictors)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vcfusion.commands.checks import check_folder_path
from vcfusion.errors import UsageError


def cmd_real_split_freeze(args: argparse.Namespace) -> int:
    from vcfusion.prediction.realsplit import freeze_split, write_split

    out = Path(args.out)
    if out.exists() and not args.force:
        raise UsageError(f"--out: {out} already exists: a frozen split is not re-drawn (use --force to replace it)")
    check_folder_path(out.parent)
    try:
        split = freeze_split(Path(args.dataset), args.by, args.seed, (args.development, args.validation), args.name)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    write_split(split, out)
    print(f"split of {args.dataset} by {args.by} -> {out}")
    for part, c in split["counts"].items():
        units = f"{c['units']} recordings, " if args.by == "recording" else ""
        print(f"  {part}: {units}{c['vehicles']} vehicles, {c['lane_changes']} lane changes")
    return 0


def cmd_real_split_apply(args: argparse.Namespace) -> int:
    from vcfusion.prediction.realsplit import apply_split

    check_folder_path(Path(args.out))
    report = apply_split(Path(args.dataset), Path(args.split), Path(args.out))
    print(f"split dataset -> {args.out} (train = development, validation, test = held_out)")
    for part, c in report["counts"].items():
        print(f"  {part}: {c['vehicles']} vehicles, {c['lane_changes']} lane changes, {c['samples']} samples")
    return 0


def cmd_retune(args: argparse.Namespace) -> int:
    from vcfusion.prediction.train_sequence import retune_decisions

    out = Path(args.out)
    if out.exists() and not args.force:
        raise UsageError(f"--out: {out} already exists (use --force to replace it)")
    if not args.false_alarm_budget > 0:
        raise UsageError(f"--false-alarm-budget: expected a positive rate per vehicle-hour, got {args.false_alarm_budget}")
    check_folder_path(out.parent)
    try:
        report = retune_decisions(Path(args.model), [Path(d) for d in args.dataset], out, args.false_alarm_budget,
                                  args.horizon, args.false_alarm_rate)
    except ValueError as exc:
        raise UsageError(f"--false-alarm-rate {args.false_alarm_rate}: {exc}") from None
    print(report)
    return 0


def cmd_set_decision(args: argparse.Namespace) -> int:
    from vcfusion.prediction.model import ModelFileError
    from vcfusion.prediction.train_sequence import set_decision

    out = Path(args.out)
    if out.exists() and not args.force:
        raise UsageError(f"--out: {out} already exists (use --force to replace it)")
    check_folder_path(out.parent)
    try:
        print(set_decision(Path(args.model), out, args.smoothing, args.threshold, args.tau_ticks, args.reason))
    except (ValueError, ModelFileError) as exc:
        raise UsageError(str(exc)) from None
    return 0


def cmd_ensemble_models(args: argparse.Namespace) -> int:
    from vcfusion.prediction.ensemble import build_ensemble, save_ensemble

    out = Path(args.out)
    if out.exists() and not args.force:
        raise UsageError(f"--out: {out} already exists (use --force to replace it)")
    if out.resolve() in {Path(m).resolve() for m in args.model}:
        raise UsageError(f"--out: {out} is one of the members; write the ensemble to another file")
    check_folder_path(out.parent)
    model = build_ensemble(args.model)  # ModelFileError (an InputError) naming the file
    save_ensemble(model, out)
    hidden = "/".join(str(m.hidden) for m in model.members)
    print(f"{out}: ensemble of {len(model.members)} GRUs (hidden {hidden}, {len(model.feature_names)} inputs); "
          "the members' calibrated probabilities are averaged each tick")
    print(f"  decision settings copied from {Path(args.model[0]).name} ({model.smoothing}, threshold "
          f"{model.threshold_for(model.smoothing):g}), tuned on that member's probabilities: choose the "
          "ensemble's own with `vcfusion retune` or `vcfusion set-decision`")
    return 0


def _labelled(values: list[str], option: str) -> list[tuple[str, str]]:
    out = []
    for v in values:
        label, sep, rest = v.partition("=")
        if not sep or not label or not rest:
            raise UsageError(f"{option}: expected LABEL=PATH, got {v!r}")
        out.append((label, rest))
    labels = [label for label, _ in out]
    if len(set(labels)) != len(labels):
        raise UsageError(f"{option}: labels must differ, got {labels}")
    return out


def cmd_sim_to_real(args: argparse.Namespace) -> int:
    from vcfusion.prediction.model import load_model
    from vcfusion.prediction.transfer import sim_to_real_table

    if args.bootstrap < 1:
        raise UsageError(f"--bootstrap: expected a positive number of resamples, got {args.bootstrap}")
    models = [(label, Path(path)) for label, path in _labelled(args.model, "--model")]
    evals = []
    for label, spec in _labelled(args.eval, "--eval"):
        path, _, split = spec.rpartition(":") if spec.rsplit(":", 1)[-1] in ("all", "train", "validation", "test") \
            else (spec, "", "test")
        evals.append((label, Path(path), split))
    for _, path in models:  # a bad file stops the command before any scoring
        load_model(path)
    check_folder_path(Path(args.out))
    df = sim_to_real_table(models, evals, Path(args.out), args.bootstrap, args.seed, args.horizon)
    print((Path(args.out) / "sim_to_real.md").read_text())
    print(f"{len(df)} rows -> {args.out}/sim_to_real.csv, sim_to_real.md, sim_to_real.json")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("real-split", help="freeze a development / validation / held-out split of an imported "
                                          "recording (by recording or by vehicle), or apply a frozen one")
    rs = p.add_subparsers(dest="real_split_command", required=True)
    f = rs.add_parser("freeze", help="draw the split once and write it (unit ids and the rule; no data)")
    f.add_argument("dataset", help="an imported dataset (`vcfusion dataset --from-ngsim | --from-commonroad ...`)")
    f.add_argument("--by", required=True, choices=["recording", "vehicle"],
                   help="the unit kept whole: recording (CommonRoad) or vehicle (one long NGSIM recording)")
    f.add_argument("--out", required=True, help="split file to write (.json); commit it")
    f.add_argument("--seed", type=int, default=0, help="seed of the units' random order")
    f.add_argument("--development", type=float, default=0.6, help="share of the lane changes for development")
    f.add_argument("--validation", type=float, default=0.2, help="share of the lane changes for validation")
    f.add_argument("--name", help="name recorded in the file (default: the dataset folder's name)")
    f.add_argument("--force", action="store_true", help="replace an existing --out")
    f.set_defaults(func=cmd_real_split_freeze)
    a = rs.add_parser("apply", help="write the split dataset: train = development, validation, test = held_out")
    a.add_argument("dataset", help="the imported dataset the split was frozen on")
    a.add_argument("split", help="split file from `vcfusion real-split freeze`")
    a.add_argument("--out", required=True, help="new dataset folder")
    a.set_defaults(func=cmd_real_split_apply,
                   interrupted="the split dataset is written to OUT.partial and renamed when complete; run it again")

    p = sub.add_parser("retune", help="re-calibrate a lane-change model and re-tune its decision settings on the "
                                      "validation seeds of other datasets (weights unchanged)")
    p.add_argument("model", help="model file (MLP or GRU)")
    p.add_argument("dataset", nargs="+", help="dataset folder(s) whose validation seeds tune (e.g. split real "
                                              "datasets from `vcfusion real-split apply`)")
    p.add_argument("--out", required=True, help="model file to write")
    p.add_argument("--false-alarm-budget", dest="false_alarm_budget", type=float, default=5.0,
                   help="at most this many false alarms per vehicle-hour on the validation seeds (default 5: the "
                        "real-data target of issue 46)")
    p.add_argument("--false-alarm-rate", dest="false_alarm_rate", choices=["all", "judged"], default="all",
                   help="the rate the budget bounds: all (every false alarm over all vehicle-hours) or judged "
                        "(censoring-aware: false alarms whose confirming window fits in the track, over the "
                        "vehicle-hours where it fits; for short tracks such as CommonRoad's)")
    p.add_argument("--horizon", type=float, default=10.0, help="event horizon, s (as `vcfusion evaluate`)")
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    p.set_defaults(func=cmd_retune, interrupted="the model file was not written; run the same command again")

    p = sub.add_parser("set-decision", help="write a lane-change model file with the decision settings given "
                                            "(smoothing, threshold, window); weights and calibration unchanged")
    p.add_argument("model", help="model file (MLP or GRU)")
    p.add_argument("--out", required=True, help="model file to write")
    p.add_argument("--smoothing", required=True, choices=["none", "aggressive", "conservative"],
                   help="the default smoothing (paper Algorithms 3 / 4, or none)")
    p.add_argument("--threshold", required=True, type=float, help="probability threshold of that smoothing, in (0, 1)")
    p.add_argument("--tau-ticks", dest="tau_ticks", type=int, default=0,
                   help="its window: tau_a (aggressive hold) or tau_c (conservative vote), V2C ticks")
    p.add_argument("--reason", required=True,
                   help="where the settings were chosen (recorded in the file, e.g. the cross-fitted validation "
                        "streams and the false-alarm budget)")
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    p.set_defaults(func=cmd_set_decision, interrupted="the model file was not written; run the same command again")

    p = sub.add_parser("ensemble-models", help="one model file holding several GRUs of the same inputs (e.g. "
                                               "fine-tuned with different --seed); their calibrated probabilities "
                                               "are averaged each tick")
    p.add_argument("model", nargs="+", help="GRU model files (`vcfusion train --kind gru`), the same inputs, label "
                                            "windows and V2C period; the first one's decision settings are copied")
    p.add_argument("--out", required=True, help="model file to write")
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    p.set_defaults(func=cmd_ensemble_models, interrupted="the model file was not written; run the same command again")

    p = sub.add_parser("sim-to-real", help="the sim-to-real table: lane-change models x evaluation sets, with "
                                           "bootstrap intervals over vehicles (CSV + markdown)")
    p.add_argument("--model", action="append", required=True, metavar="LABEL=FILE",
                   help="a model file and its row label; repeat for each model")
    p.add_argument("--eval", action="append", required=True, metavar="LABEL=DATASET[:SPLIT]",
                   help="a dataset folder, its split (default test: a split real dataset's held-out part; all: "
                        "a held-out family) and its column label; repeat for each set")
    p.add_argument("--out", required=True, help="folder for sim_to_real.csv, .md and .json")
    p.add_argument("--bootstrap", type=int, default=1000, help="resamples of the vehicles")
    p.add_argument("--seed", type=int, default=0, help="seed of the resampling")
    p.add_argument("--horizon", type=float, default=10.0, help="event horizon, s (as `vcfusion evaluate`)")
    p.set_defaults(func=cmd_sim_to_real)
