"""`vcfusion run | scenarios | batch | build-net | render | demo`: simulations and what they write."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vcfusion.commands.checks import (INTERRUPTED_BATCH, check_folder_path, check_new_folder, check_seed,
                                      default_run_dir, parse_seeds)
from vcfusion.errors import UsageError
from vcfusion.scenario import find_scenario, load_scenario


def cmd_run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    if args.arm is not None:
        from vcfusion.studies.guidance import arm_run_scenario

        scenario = arm_run_scenario(scenario, args.arm)
    check_seed(args.seed)
    out = check_new_folder(Path(args.out) if args.out else default_run_dir(scenario.name, args.seed))
    _run_and_report(scenario, args.seed, out)
    return 0


def _run_and_report(scenario, seed: int, out: Path) -> None:
    from vcfusion.cosim import format_summary
    from vcfusion.run import execute_run

    from vcfusion.metrics.run_metrics import format_run_metrics

    result = execute_run(scenario, seed, out, progress=sys.stderr.isatty())
    print(format_summary(result.summary, result.wall_s))
    if "metrics" in result.summary:
        print(format_run_metrics(result.summary))
    print(f"run folder: {out}")


def cmd_scenarios(args: argparse.Namespace) -> int:
    from vcfusion.resources import scenarios_dir, shipped_scenarios
    from vcfusion.scenario import describe_scenario_file

    shipped = shipped_scenarios()
    width = max(len(name) for name in shipped)
    print(f"shipped scenarios (in {scenarios_dir()}); give a name where a scenario file goes, "
          "e.g. vcfusion run accident")
    for name, path in shipped.items():
        print(f"  {name:<{width}}  {describe_scenario_file(path)}")
    return 0


def cmd_batch(args: argparse.Namespace) -> int:
    from vcfusion.studies.batch import Executor, run_batch

    scenario = load_scenario(args.scenario)  # fail fast, before any worker starts
    seeds = parse_seeds(args.seeds)  # UsageError on a bad range
    if args.workers < 1:
        raise UsageError(f"--workers: expected a positive number of processes, got {args.workers}")
    if args.dask_local is not None and args.dask_local < 1:
        raise UsageError(f"--dask-local: expected a positive number of worker processes, got {args.dask_local}")
    if args.scheduler is not None and not args.scheduler.startswith(("tcp://", "tls://", "inproc://", "ucx://")):
        raise UsageError(f"--scheduler: expected a Dask scheduler address like tcp://HOST:PORT, got {args.scheduler!r}")
    out = check_folder_path(Path(args.out) if args.out else Path("runs") / f"{scenario.name}-batch")
    executor = Executor(workers=args.workers, dask_scheduler=args.scheduler, dask_local=args.dask_local)
    report = run_batch(find_scenario(args.scenario), seeds, out, executor=executor)
    print(f"batch {scenario.name} -> {out}: {report['done']} run, {report['skipped']} already complete, "
          f"{len(report['failed'])} failed")
    for seed, error in report["failed"]:
        print(f"  seed {seed}: {error.splitlines()[0]}")
    from vcfusion.metrics.folders import print_batch_metrics

    print_batch_metrics(out)
    return 1 if report["failed"] else 0


def cmd_build_net(args: argparse.Namespace) -> int:
    from vcfusion.resources import networks_dir, networks_dir_is_checkout
    from vcfusion.traffic.network import build_networks

    if args.net_dir:
        net_dir = Path(args.net_dir)
    elif networks_dir_is_checkout():  # the checkout's sumo_net, rebuilt in place
        net_dir = networks_dir()
    else:
        raise UsageError(f"--net-dir: required when vcfusion is installed (the shipped networks in {networks_dir()} "
                         "are the package's and are not rewritten); copy that folder, edit its sources and give "
                         "the copy")
    # a network whose content did not change keeps its file (netconvert's header timestamp aside)
    before = {p.name: p.stat().st_mtime_ns for p in net_dir.glob("*.net.xml")} if net_dir.is_dir() else {}
    try:
        built = build_networks(net_dir)
    except RuntimeError as exc:
        raise UsageError(str(exc)) from None
    for out in built:
        print(f"{'up to date' if before.get(out.name) == out.stat().st_mtime_ns else 'built'} {out}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    check_seed(args.seed)
    if args.trips < 2:
        raise UsageError(f"--trips: expected at least 2 paired trips for a confidence interval, got {args.trips}")
    _run_and_report(scenario, args.seed, default_run_dir(scenario.name, args.seed))
    return _demo_guidance_study(args)


def _demo_guidance_study(args: argparse.Namespace) -> int:
    """The demo ends with the guidance study (paper Fig. 8/9) on a few paired trips."""
    from vcfusion.studies.guidance import StudyError, run_guidance_study

    out = default_run_dir("guidance-study", args.seed)
    specs = tuple(args.process_model)
    print(f"\nguidance study on {args.trips} paired trips (arms none and fusion: without AR, and with the "
          f"rendered camera, detector and AR overlay):")
    try:
        result = run_guidance_study(find_scenario(args.scenario), args.trips, 2, out, Path("renders"),
                                    first_seed=args.seed, process_model_specs=specs, progress=sys.stderr.isatty())
    except StudyError as exc:
        print(f"guidance study skipped: {exc}")
        return 0
    print(result["text"])
    print(f"study folder: {out}; figures: " + ", ".join(str(p) for p in result["figures"]))
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    seeds = parse_seeds(args.seeds)  # UsageError on a bad range
    if args.every < 1:
        raise UsageError(f"--every: expected a positive number of V2C ticks, got {args.every}")
    if args.workers < 1:
        raise UsageError(f"--workers: expected at least 1, got {args.workers}")
    if scenario.ego is None:
        raise UsageError(f"{args.scenario}: ego: the camera rides on the ego; the scenario has no ego block")
    from vcfusion.scenario import require_camera_world

    require_camera_world(scenario)  # a flat world of road vehicles
    out = check_new_folder(Path(args.out) if args.out else Path("renders") / f"{scenario.name}-dataset")
    from vcfusion.render.export import render_dataset

    counts = render_dataset(scenario, seeds, args.every, out, progress=sys.stderr.isatty(), workers=args.workers)
    print(f"rendered {counts['images']} frames, {counts['annotations']} boxes -> {out}")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("run", help="run one simulation into a run folder")
    p.add_argument("scenario", help="scenario YAML file, or the name of a shipped scenario (vcfusion scenarios)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="run folder to create (default: runs/NAME-seedN)")
    p.add_argument("--arm", choices=("none", "cloud", "fusion", "oracle"),
                   help="run the scenario as this arm of `vcfusion study guidance` runs the same seed (the "
                        "camera arms with their AR frames, for `vcfusion explain-highlights`)")
    p.set_defaults(func=cmd_run, interrupted="no run folder was written; run the same command again to redo the run")

    p = sub.add_parser("scenarios", help="list the shipped scenarios (usable by name: vcfusion run accident)")
    p.set_defaults(func=cmd_scenarios)

    p = sub.add_parser("batch", help="run many seeds in parallel processes (resumable)")
    p.add_argument("scenario")
    p.add_argument("--seeds", required=True, help="e.g. 0-99 or 1,4,7-9")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", help="batch folder (default: runs/NAME-batch)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--scheduler", help="run the seeds on this Dask scheduler (tcp://HOST:PORT); "
                                           "its workers must share this file system")
    where.add_argument("--dask-local", type=int, metavar="N", help="start a local Dask cluster of N worker processes")
    p.set_defaults(func=cmd_batch, interrupted=INTERRUPTED_BATCH)

    p = sub.add_parser("build-net", help="rebuild every sumo_net/NAME.net.xml with netconvert")
    p.add_argument("--net-dir", help="folder with NAME.nod/edg.xml (+ .typ/.con.xml) (default: the checkout's "
                                     "sumo_net; required when vcfusion is installed)")
    p.set_defaults(func=cmd_build_net)

    p = sub.add_parser("render", help="render ego-camera frames of seeds into a COCO dataset")
    p.add_argument("scenario")
    p.add_argument("--seeds", required=True, help="e.g. 0-9 or 1,4,7-9")
    p.add_argument("--every", type=int, default=5, help="render every K-th V2C tick (default 5)")
    p.add_argument("--out", help="dataset folder to create (default: renders/NAME-dataset)")
    p.add_argument("--workers", type=int, default=2,
                   help="processes, one seed each (default 2; the folder is the same for any number)")
    p.set_defaults(func=cmd_render, interrupted="no dataset folder was written; run the same command again")

    p = sub.add_parser("demo", help="the main job on the default scenario")
    p.add_argument("--scenario", default="accident")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--trips", type=int, default=8, help="paired trips of the closing guidance study")
    p.add_argument("--process-model", action="append", default=[], metavar="MODULE:FACTORY",
                   help="extra cloud process model for the guidance study (see `study guidance`)")
    p.set_defaults(func=cmd_demo)
