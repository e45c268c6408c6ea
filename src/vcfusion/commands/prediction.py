"""Handlers of the `vcfusion dataset | train | evaluate | bench-predict` commands. A bad dataset or
model file raises DatasetError / ModelFileError (InputError: the CLI prints it and exits with 2)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vcfusion.commands.checks import INTERRUPTED_BATCH, check_folder_path, parse_seeds
from vcfusion.errors import UsageError


def cmd_dataset(args: argparse.Namespace) -> int:
    from vcfusion.prediction.dataset import build_dataset
    from vcfusion.scenario import find_scenario, load_scenario

    sources = [name for name, given in (("SCENARIO", args.scenario), ("--from-ngsim", args.from_ngsim),
                                        ("--from-highd", args.from_highd),
                                        ("--from-commonroad", getattr(args, "from_commonroad", None))) if given]
    if len(sources) != 1:
        raise UsageError("dataset: expected exactly one of SCENARIO (simulate seeds), --from-ngsim FILE, --from-highd "
                         f"PATH or --from-commonroad PATH, got {' and '.join(sources) if sources else 'none'}")
    if args.scenario is None:
        args.interrupted = "an import writes its folder only when complete; nothing was written, run it again"
        return _import_recordings(args)
    if args.seeds is None:
        raise UsageError("--seeds: required with a SCENARIO, e.g. --seeds 0-199")
    load_scenario(args.scenario)  # fail fast on a bad file
    seeds = parse_seeds(args.seeds)  # UsageError on a bad range
    check_folder_path(Path(args.out))
    if args.workers < 1:
        raise UsageError(f"--workers: expected a positive number of processes, got {args.workers}")
    report = build_dataset(find_scenario(args.scenario), seeds, Path(args.out), args.workers, args.tau, args.tau_g,
                           refeature=args.refeature, privileged=args.privileged)
    c = report["counts"]
    if args.refeature:
        print(f"recomputed the features of {report['refeatured']} existing runs")
    print(f"dataset -> {args.out}: {report['done']} seeds run, {report['skipped']} already complete, "
          f"{len(report['failed'])} failed")
    print(f"  {c['seeds']} seeds, {c['lane_changes']} lane changes, {c['samples']} stream samples, "
          f"{c['window_positive']} positive / {c['window_negative']} negative window samples")
    print("  splits: " + ", ".join(f"{k} {len(v)} seeds" for k, v in report["splits"].items()))
    for seed, error in report["failed"]:
        print(f"  seed {seed}: {error.splitlines()[0]}")
    return 1 if report["failed"] else 0


def _import_recordings(args: argparse.Namespace) -> int:
    """`vcfusion dataset --from-ngsim FILE... | --from-highd PATH --out DIR`."""
    from vcfusion.prediction.sources.trajectories import import_recordings

    if args.refeature or args.privileged:
        raise UsageError(f"{'--refeature' if args.refeature else '--privileged'}: only for simulated datasets "
                         f"(a recording has no SUMO state; import it again after a feature change)")
    check_folder_path(Path(args.out))
    # a bad file raises RealDataError (an InputError: the CLI prints it and exits with 2)
    if args.from_ngsim:
        from vcfusion.prediction.sources.ngsim import parse_main_lanes, read_ngsim

        lanes = parse_main_lanes(args.main_lanes)
        recordings = [rec for f in args.from_ngsim for rec in read_ngsim(f, lanes, args.ngsim_location,
                                                                         args.ngsim_units, args.ngsim_lane_one)]
        source = {"format": "ngsim", "files": [str(f) for f in args.from_ngsim], "main_lanes": list(lanes),
                  "location": args.ngsim_location, "units": args.ngsim_units, "lane_one": args.ngsim_lane_one}
    elif getattr(args, "from_commonroad", None):
        from vcfusion.prediction.sources.commonroad import read_commonroad

        recordings, notes = read_commonroad(args.from_commonroad)
        source = {"format": "commonroad", "paths": [str(p) for p in args.from_commonroad], "reader": notes}
        print(f"{notes['files_read']} scenario files -> {notes['recordings']} distinct recordings; "
              f"{len(notes['files_without_vehicle_trajectories'])} files without vehicle trajectories left out")
    else:
        from vcfusion.prediction.sources.highd import read_highd_path

        recordings = read_highd_path(args.from_highd)
        source = {"format": "highd", "path": str(args.from_highd)}
    report = import_recordings(recordings, Path(args.out), args.tau, args.tau_g, args.chunk, source)
    c = report["counts"]
    print(f"dataset -> {args.out}: {len(report['recordings'])} recordings (driving directions) imported as "
          f"{c['seeds']} seeds of {args.chunk:g} s")
    for rec in report["recordings"]:
        q = rec["quality"]
        print(f"  {rec['name']}: {q['twins']} twins of {q['vehicles']} vehicles, {q['lane_changes']} lane changes "
              f"({q['lane_changes_end_unseen']} without a seen end); repaired: {q['duplicate_samples']} duplicate "
              f"samples, {q['tracks_split_at_gaps']} tracks split at gaps, {q['gaps_interpolated']} gaps "
              f"interpolated, {q['lane_flicker_removed']} lane flickers; {q['samples_off_main_lanes']} samples off "
              f"the main lanes, {q['lateral_unknown_samples']} without lateral position")
        for key, value in rec.get("quality_reader", {}).items():
            if value:
                print(f"    {key}: {value}")
    print(f"  {c['lane_changes']} lane changes, {c['samples']} stream samples, "
          f"{c['window_positive']} positive / {c['window_negative']} negative window samples")
    print("  splits: " + ", ".join(f"{k} {len(v)} seeds" for k, v in report["splits"].items()))
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from vcfusion.prediction.train import TrainConfig, train_model
    from vcfusion.prediction.train_sequence import SequenceConfig, check_sequence_columns, train_sequence_model

    gru = args.kind == "gru"
    defaults = SequenceConfig() if gru else TrainConfig()
    for option in ("hidden", "epochs", "patience", "background_negatives"):  # not given: the kind's default
        if getattr(args, option) is None:
            setattr(args, option, getattr(defaults, option))
    for option in ("hidden", "epochs", "patience", "threads", "bptt_ticks"):
        if getattr(args, option) < 1:
            raise UsageError(f"--{option.replace('_', '-')}: expected a positive number, got {getattr(args, option)}")
    if not (args.learning_rate > 0 and args.weight_decay >= 0 and args.background_negatives >= 0):  # NaN too
        raise UsageError("--learning-rate / --weight-decay / --background-negatives: expected a positive rate and "
                         f"non-negative others, got {args.learning_rate}, {args.weight_decay}, "
                         f"{args.background_negatives}")
    if not (args.early_weight >= 0) or (args.early_weight and not gru):
        raise UsageError("--early-weight: expected a non-negative weight for the GRU (--kind gru), "
                         f"got {args.early_weight}")
    if gru and args.privileged:
        raise UsageError("--privileged: the ceiling is an MLP (--kind mlp)")
    if not gru and (args.inputs != "base" or args.init or args.false_alarm_budget is not None):
        raise UsageError("--inputs / --init / --false-alarm-budget: options of the GRU (--kind gru)")
    if args.false_alarm_budget is not None and not args.false_alarm_budget > 0:
        raise UsageError(f"--false-alarm-budget: expected a positive rate per vehicle-hour, got {args.false_alarm_budget}")
    if args.init and args.inputs != "base":
        raise UsageError("--init and --inputs: a fine-tuned model keeps its initial model's inputs; "
                         "give one of them")
    out = Path(args.out)
    if out.exists() and not args.force:
        raise UsageError(f"--out: {out} already exists (use --force to replace it)")
    check_folder_path(out.parent)
    datasets = [Path(d) for d in args.dataset]
    if gru:
        from vcfusion.prediction.train import load_datasets

        from vcfusion.prediction.features import SEQUENCE_INPUT_SETS
        from vcfusion.prediction.model import load_model

        names = load_model(args.init).feature_names if args.init else SEQUENCE_INPUT_SETS[args.inputs]
        check_sequence_columns(load_datasets(datasets), names)  # before any training: a bad folder stops here
        cfg = SequenceConfig(hidden=args.hidden, epochs=args.epochs, patience=args.patience, seed=args.seed,
                             background_negatives=args.background_negatives, threads=args.threads,
                             learning_rate=args.learning_rate, weight_decay=args.weight_decay,
                             bptt_ticks=args.bptt_ticks, inputs=args.inputs, early_weight=args.early_weight,
                             init=str(args.init) if args.init else None,
                             **({} if args.false_alarm_budget is None else
                                {"false_alarm_budget": args.false_alarm_budget}))
        report = train_sequence_model(datasets, out, cfg)
    else:
        cfg = TrainConfig(hidden=args.hidden, epochs=args.epochs, patience=args.patience, seed=args.seed,
                          background_negatives=args.background_negatives, threads=args.threads,
                          learning_rate=args.learning_rate, weight_decay=args.weight_decay,
                          privileged=args.privileged)
        report = train_model(datasets, out, cfg)
    print(report)
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from vcfusion.prediction.evaluate import evaluate

    if not args.horizon > 0:
        raise UsageError(f"--horizon: expected a positive number of seconds, got {args.horizon}")
    if args.out:
        check_folder_path(Path(args.out))
    report_path = evaluate(Path(args.model), Path(args.dataset), Path(args.out) if args.out else None,
                           split=args.split, horizon_s=args.horizon, baselines=args.baselines)
    print(Path(report_path).read_text())
    print(f"report: {report_path}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from vcfusion.prediction.bench import run_bench

    for option in ("twins", "repeats"):
        if getattr(args, option) < 1:
            raise UsageError(f"--{option}: expected a positive number, got {getattr(args, option)}")
    print(run_bench(args.twins, args.repeats, args.model))
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("dataset", help="simulate seeds (or import NGSIM / highD / CommonRoad recordings) and write "
                                       "a labelled lane-change dataset (Parquet)")
    p.add_argument("scenario", nargs="?", help="scenario YAML file, e.g. scenarios/dense.yaml")
    p.add_argument("--seeds", help="e.g. 0-199 or 1,4,7-9 (with a SCENARIO)")
    p.add_argument("--out", required=True, help="dataset folder (resumable for a SCENARIO; new for an import)")
    p.add_argument("--from-ngsim", dest="from_ngsim", nargs="+", metavar="FILE",
                   help="import NGSIM trajectory files (18 columns, .csv / .txt, optionally .gz) instead of simulating")
    p.add_argument("--from-highd", dest="from_highd", metavar="PATH",
                   help="import highD recordings: a folder (every XX_tracks.csv) or one XX_tracks.csv")
    p.add_argument("--from-commonroad", dest="from_commonroad", nargs="+", metavar="PATH",
                   help="import CommonRoad scenarios: .xml files, folders of them or a .tar.xz of them (needs "
                        "commonroad-io); files repeating a recording are imported once")
    p.add_argument("--main-lanes", dest="main_lanes", default="1-5",
                   help="NGSIM Lane_IDs of the main lanes (1 = leftmost); others (ramps, auxiliary) are off the "
                        "road. US-101: 1-5, I-80: 1-6")
    p.add_argument("--ngsim-location", dest="ngsim_location", metavar="NAME",
                   help="the combined NGSIM release (all sites in one CSV): import the rows of this Location, "
                        "e.g. us-101 or i-80")
    p.add_argument("--ngsim-units", dest="ngsim_units", choices=["ft", "m"], default="ft",
                   help="NGSIM files: the unit of positions, sizes, speeds (NGSIM's own: ft; metric re-releases: m)")
    p.add_argument("--ngsim-lane-one", dest="ngsim_lane_one", choices=["left", "right"], default="left",
                   help="NGSIM files: which edge Lane_ID 1 is at (NGSIM: the leftmost lane)")
    p.add_argument("--chunk", type=float, default=300.0,
                   help="imports: seconds of a recording per seed (the unit of the train/validation/test split)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--tau", type=float, default=5.0, help="time window tau, s (Fig. 5)")
    p.add_argument("--tau-g", dest="tau_g", type=float, default=2.0, help="gap tau_g, s (Fig. 5)")
    p.add_argument("--refeature", action="store_true",
                   help="recompute the samples of runs already in --out with this version's features "
                        "(from their logged twins tables, no simulation) instead of refusing a feature change")
    p.add_argument("--privileged", action="store_true",
                   help="also log SUMO's own lane-change state every tick (table lc_state) and add it to the "
                        "samples as sumo_* columns, for the privileged ceiling (`vcfusion train --privileged`)")
    p.set_defaults(func=cmd_dataset, interrupted=INTERRUPTED_BATCH)

    p = sub.add_parser("train", help="train the lane-change MLP or GRU on one or several datasets")
    p.add_argument("dataset", nargs="+",
                   help="dataset folder(s) from `vcfusion dataset`; several = scenario families trained on together "
                        "(each one's train seeds train, its validation seeds stop and tune)")
    p.add_argument("--out", required=True, help="model file to write (.npz)")
    p.add_argument("--kind", choices=["mlp", "gru"], default="mlp",
                   help="mlp: the paper's MLP on each tick's features; gru: the sequence model over each twin's history")
    p.add_argument("--hidden", type=int, default=None,
                   help="units of each of the MLP's two hidden layers (default 64) or of the GRU's state (default 48)")
    p.add_argument("--epochs", type=int, default=None, help="at most this many epochs (default: MLP 60, GRU 8)")
    p.add_argument("--patience", type=int, default=None,
                   help="early stopping: epochs without validation gain (default: MLP 8, GRU 3)")
    p.add_argument("--bptt-ticks", dest="bptt_ticks", type=int, default=100,
                   help="GRU: truncated backpropagation through time over chunks of this many V2C ticks")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--background-negatives", dest="background_negatives", type=float, default=None,
                   help="add this many negatives per window sample drawn from ticks outside the windows "
                        "(default 0 for the MLP = the paper's Fig. 5 windows only; the GRU weighs all such ticks "
                        "to this total, default 3)")
    p.add_argument("--learning-rate", dest="learning_rate", type=float, default=1e-3, help="Adam learning rate")
    p.add_argument("--weight-decay", dest="weight_decay", type=float, default=1e-5, help="Adam weight decay (L2)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    p.add_argument("--privileged", action="store_true",
                   help="the privileged ceiling: also feed SUMO's lane-change state (a dataset built with "
                        "--privileged); such a model cannot run in the cloud")
    p.add_argument("--inputs", choices=["base", "availability", "lateral", "sway"], default="base",
                   help="GRU inputs (features.SEQUENCE_INPUT_SETS): base (the shipped GRU's), availability (also "
                        "the flags: a neighbour observed or not), lateral (also the lateral motion: drift and "
                        "lateral speed, with a known-flag), sway (also both over the vehicle's own recent "
                        "lane-keeping sway, with a known-flag); the model file records its inputs")
    p.add_argument("--init", metavar="MODEL",
                   help="GRU: fine-tune: start from this GRU file's weights, inputs and standardisation "
                        "(e.g. a model trained on simulation, fine-tuned on a real recording's development part)")
    p.add_argument("--early-weight", dest="early_weight", type=float, default=0.0,
                   help="GRU: weigh a positive tick t s before the change's end 1 + EARLY_WEIGHT x t / tau (before "
                        "balancing): early warning counts more; default 0 (all positives alike)")
    p.add_argument("--false-alarm-budget", dest="false_alarm_budget", type=float, default=None,
                   help="GRU: the decision settings' false alarms per vehicle-hour on the validation seeds "
                        "(default 1.5)")
    p.set_defaults(func=cmd_train, interrupted="the model file was not written; run the same command again")

    p = sub.add_parser("evaluate", help="frame- and event-level evaluation of a model on a dataset's test seeds")
    p.add_argument("model", help="model file from `vcfusion train`")
    p.add_argument("dataset", help="dataset folder")
    p.add_argument("--out", help="report folder (default: DATASET/eval-MODELNAME)")
    p.add_argument("--split", default="test", choices=["all", "train", "validation", "test"],
                   help="seeds to score (all: every seed, i.e. every vehicle of an imported dataset)")
    p.add_argument("--horizon", type=float, default=10.0,
                   help="a lane change counts as predicted by a positive decision at most this many s before its end")
    p.add_argument("--no-baselines", dest="baselines", action="store_false",
                   help="score the model alone (no logistic regression / gap-speed rule fitted on the dataset): "
                        "for comparing models across many datasets")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("bench-predict", help="time the cloud lane-change predictor for N twins in one tick")
    p.add_argument("--twins", type=int, default=100)
    p.add_argument("--repeats", type=int, default=2000)
    p.add_argument("--model", action="append", metavar="FILE",
                   help="also time this model file (after the shipped ones); repeat for several")
    p.set_defaults(func=cmd_bench)
