"""The `vcfusion` command."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vcfusion import interrupts
from vcfusion.errors import InputError, UsageError
from vcfusion.scenario import SHIPPED_SCENARIOS, load_scenario


def check_seed(seed: int, option: str = "--seed") -> int:
    from vcfusion.studies.batch import MAX_SEED

    if not 0 <= seed <= MAX_SEED:
        raise UsageError(f"{option}: expected a seed from 0 to {MAX_SEED}, got {seed}")
    return seed


def check_new_folder(out: Path, option: str = "--out") -> Path:
    """A folder the command will create: it must not exist, and no part of its path may be a file."""
    if out.exists():
        raise UsageError(f"{option}: {out} already exists; choose a new folder")
    check_folder_path(out, option)
    return out


def check_folder_path(out: Path, option: str = "--out") -> Path:
    """A folder the command creates or reuses: neither it nor a parent may be a file."""
    for part in (out, *out.parents):
        if part.exists() and not part.is_dir():
            raise UsageError(f"{option}: {part} is a file; expected a folder path")
    return out

# What Ctrl-C leaves of a resumable batch of seeds (batch, dataset), for the user.
INTERRUPTED_BATCH = ("complete seeds are kept, partial ones removed; run the same command again to resume "
                     "(complete seeds are skipped)")


def _default_run_dir(name: str, seed: int) -> Path:
    base = Path("runs") / f"{name}-seed{seed}"
    candidate, n = base, 1
    while candidate.exists():
        n += 1
        candidate = base.with_name(f"{base.name}-{n}")
    return candidate


def cmd_run(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    check_seed(args.seed)
    out = check_new_folder(Path(args.out) if args.out else _default_run_dir(scenario.name, args.seed))
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


def cmd_batch(args: argparse.Namespace) -> int:
    from vcfusion.studies.batch import Executor, parse_seeds, run_batch

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
    report = run_batch(Path(args.scenario), seeds, out, executor=executor)
    print(f"batch {scenario.name} -> {out}: {report['done']} run, {report['skipped']} already complete, "
          f"{len(report['failed'])} failed")
    for seed, error in report["failed"]:
        print(f"  seed {seed}: {error.splitlines()[0]}")
    from vcfusion.metrics.commands import print_batch_metrics

    print_batch_metrics(out)
    return 1 if report["failed"] else 0


# the model study's options and their defaults (None in the parser: --from-runs refuses them)
GUIDANCE_STUDY_DEFAULTS = {"arms": "none,fusion", "trips": 200, "workers": 2, "first_seed": 0}


def cmd_study_guidance(args: argparse.Namespace) -> int:
    from vcfusion.studies.guidance import StudyError, parse_arms, run_guidance_study

    if args.from_runs is not None:
        return _study_guidance_from_runs(args)
    if not args.scenario:
        raise UsageError("study guidance: give a SCENARIO file (the driver model's trips) or --from-runs DIR... "
                         "(existing run folders)")
    for name, default in GUIDANCE_STUDY_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    load_scenario(args.scenario)  # fail fast, before any worker starts
    if args.trips < 2:
        raise UsageError(f"--trips: expected at least 2 paired trips for a confidence interval, got {args.trips}")
    if args.workers < 1:
        raise UsageError(f"--workers: expected a positive number of processes, got {args.workers}")
    check_seed(args.first_seed, "--first-seed")
    check_seed(args.first_seed + args.trips - 1, "--first-seed + --trips - 1")
    out = check_folder_path(Path(args.out) if args.out else Path("runs") / f"guidance-study-{Path(args.scenario).stem}")
    check_folder_path(Path(args.renders), "--renders")
    try:
        arms = parse_arms(args.arms)
        result = run_guidance_study(Path(args.scenario), args.trips, args.workers, out, Path(args.renders),
                                    first_seed=args.first_seed, process_model_specs=tuple(args.process_model),
                                    progress=True, arms=arms)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    except StudyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(result["text"])
    print(f"tables: {out}/trips.parquet, {out}/summary.csv; figures: " + ", ".join(str(p) for p in result["figures"]))
    for seed, error in result["failed"]:  # also in OUT/failures.json
        print(f"  trip {seed} failed: {error.splitlines()[0]}")
    return 1 if result["failed"] else 0


def _study_guidance_from_runs(args: argparse.Namespace) -> int:
    from vcfusion.studies.from_runs import study_of_runs
    from vcfusion.studies.guidance import StudyError

    if args.scenario:
        raise UsageError(f"--from-runs: the trips are the run folders' own; not with a SCENARIO ({args.scenario})")
    given = [name for name in GUIDANCE_STUDY_DEFAULTS if getattr(args, name) is not None]
    if args.process_model:
        given.append("process_model")
    if given:
        option = "--" + given[0].replace("_", "-")
        raise UsageError(f"{option}: not with --from-runs (the run folders' trips, arms and process models are "
                         "the study's)")
    out = check_folder_path(Path(args.out) if args.out else Path("runs") / "guidance-study-from-runs")
    check_folder_path(Path(args.renders), "--renders")
    try:
        result = study_of_runs([Path(p) for p in args.from_runs], out, Path(args.renders))
    except StudyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(result["text"])
    for folder, arms in result["unpaired"]:  # also in OUT/summary.json
        print(f"  unpaired, left out: {folder} (its trip has only {', '.join(arms)})")
    for folder in result["skipped"]:
        print(f"  skipped: {folder} (not a complete run folder)")
    print(f"tables: {out}/trips.parquet, {out}/summary.csv; figures: " + ", ".join(str(p) for p in result["figures"]))
    return 0


def cmd_study_hitl(args: argparse.Namespace) -> int:
    from vcfusion.hitl.driver import DriveAborted
    from vcfusion.hitl.study import run_hitl_study

    if args.speed not in ("1", "max"):
        raise UsageError(f"--speed: expected 1 or max, got {args.speed!r}")
    check_seed(args.first_seed, "--first-seed")
    check_seed(args.first_seed + max(args.trips, 1) - 1, "--first-seed + --trips - 1")
    if args.practice_seed is not None:
        check_seed(args.practice_seed, "--practice-seed")
    out = Path(args.out) if args.out else Path("runs") / f"hitl-{args.participant}"
    try:
        protocol = run_hitl_study(Path(args.scenario), args.participant, args.trips, out, input_spec=args.input,
                                  axis_map_file=Path(args.axis_map) if args.axis_map else None,
                                  first_seed=args.first_seed, practice_seed=args.practice_seed, order=args.order,
                                  ssq=args.ssq, headless=args.headless,
                                  speed=None if args.speed == "max" else 1.0,
                                  screen_timeout_s=0.0 if args.headless else None)  # headless: nobody to press a key
    except DriveAborted as exc:
        print(f"{exc}: finished trips are kept in {out}; run the same command again to go on", file=sys.stderr)
        return 130
    print(f"participant {protocol['participant']} ({protocol['order']}): practice + {len(protocol['trips'])} trips "
          f"-> {out} (protocol.json" + (", ssq.json)" if protocol["ssq"] else ")"))
    return 0


def cmd_build_net(args: argparse.Namespace) -> int:
    from vcfusion.traffic.network import REPO_NET_DIR, build_networks

    net_dir = Path(args.net_dir) if args.net_dir else REPO_NET_DIR
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
    _run_and_report(scenario, args.seed, _default_run_dir(scenario.name, args.seed))
    return _demo_guidance_study(args)


def _demo_guidance_study(args: argparse.Namespace) -> int:
    """The demo ends with the guidance study (paper Fig. 8/9) on a few paired trips."""
    from vcfusion.studies.guidance import StudyError, run_guidance_study

    out = _default_run_dir("guidance-study", args.seed)
    specs = tuple(args.process_model)
    print(f"\nguidance study on {args.trips} paired trips (arms none and fusion: without AR, and with the "
          f"rendered camera, detector and AR overlay):")
    try:
        result = run_guidance_study(Path(args.scenario), args.trips, 2, out, Path("renders"),
                                    first_seed=args.seed, process_model_specs=specs, progress=sys.stderr.isatty())
    except StudyError as exc:
        print(f"guidance study skipped: {exc}")
        return 0
    print(result["text"])
    print(f"study folder: {out}; figures: " + ", ".join(str(p) for p in result["figures"]))
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from vcfusion.bench import SECTIONS, run_suite, to_markdown

    sections = [s.strip() for s in args.sections.split(",")] if args.sections else sorted(SECTIONS)
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        raise UsageError(f"--sections: unknown {unknown}; expected some of {sorted(SECTIONS)}")
    results = run_suite(sections, "quick" if args.quick else "full", Path(args.out))
    print(to_markdown(results))
    print(f"written: {Path(args.out) / 'bench.json'}, {Path(args.out) / 'bench.md'}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from vcfusion.studies.batch import parse_seeds

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


def _recorded_trip(input_spec: str) -> tuple[dict, dict]:
    """The summary and manifest of the trip whose inputs a replay reads (beside the file; empty when
    the file is not a trip's: a hand-written CSV)."""
    if not input_spec.startswith("replay:"):
        return {}, {}
    from vcfusion.runio import MANIFEST, SUMMARY

    folder = Path(input_spec[len("replay:"):]).parent
    out = []
    for name in (SUMMARY, MANIFEST):
        try:
            data = json.loads((folder / name).read_text())
        except (OSError, ValueError):
            data = {}
        out.append(data if isinstance(data, dict) else {})
    return out[0], out[1]


def _recorded_guidance(summary: dict) -> str | None:
    """The guidance condition of a replayed trip, so that it lands in its own arm of the guidance study."""
    hitl = summary.get("hitl")
    guidance = hitl.get("guidance") if isinstance(hitl, dict) else None
    return guidance if guidance in ("on", "off") else None


def _replay_seed(args: argparse.Namespace, manifest: dict) -> int:
    """A replay drives the recorded trip's traffic: its seed unless --seed names the same one (the
    inputs steered through that traffic; under another seed they drive blind)."""
    recorded = manifest.get("seed")
    if not isinstance(recorded, int):
        return 0 if args.seed is None else args.seed
    if args.seed is not None and args.seed != recorded:
        raise UsageError(f"--seed {args.seed}: the replayed trip ({args.input[len('replay:'):]}) was driven on seed "
                         f"{recorded}; leave --seed out (or give {recorded}): its inputs steered through that "
                         "traffic")
    return recorded


MIN_DISPLAY_FPS, MAX_DISPLAY_FPS = 1.0, 240.0


def cmd_drive(args: argparse.Namespace) -> int:
    if args.calibrate:
        from vcfusion.hitl.drive import calibrate

        if not args.axis_map:
            raise UsageError("--calibrate: give --axis-map FILE to write the axis map to")
        axis_map = calibrate(Path(args.axis_map), headless=args.headless)
        print(f"axis map of {axis_map.device!r} -> {args.axis_map}: steer axis {axis_map.steer.axis}, "
              f"throttle axis {axis_map.throttle.axis}, brake axis {axis_map.brake.axis}")
        return 0
    if not args.scenario:
        raise UsageError("drive: give a SCENARIO file (or --calibrate)")
    from vcfusion.cosim import format_summary
    from vcfusion.hitl.drive import drive
    from vcfusion.hitl.study import check_participant
    from vcfusion.scenario import require_camera_world

    scenario = load_scenario(args.scenario)
    require_camera_world(scenario)  # the driver sees the camera's world
    if args.speed not in ("1", "max"):
        raise UsageError(f"--speed: expected 1 or max, got {args.speed!r}")
    # a frame period of 0 (inf) never advanced: the display loop ran on and took every byte of memory
    if not MIN_DISPLAY_FPS <= args.fps <= MAX_DISPLAY_FPS:
        raise UsageError(f"--fps: expected display frames per second from {MIN_DISPLAY_FPS:g} to "
                         f"{MAX_DISPLAY_FPS:g}, got {args.fps:g}")
    if args.axis_map and args.input != "joystick":
        raise UsageError(f"--axis-map: read only with --input joystick (this drive's input is {args.input})")
    summary, manifest = _recorded_trip(args.input)
    seed = check_seed(_replay_seed(args, manifest))
    hitl = manifest.get("hitl") if isinstance(manifest.get("hitl"), dict) else {}
    participant = args.participant or str(hitl.get("participant") or "")  # a replay is that person's trip
    if participant:
        check_participant(participant)
    out = Path(args.out) if args.out else _default_run_dir(f"{scenario.name}-{participant or 'drive'}", seed)
    if isinstance(manifest.get("scenario"), dict):
        from vcfusion.run import scenario_record
        from vcfusion.runio import differing_keys

        differs = differing_keys(scenario_record(scenario), manifest["scenario"])
        if differs:  # on purpose (another camera, fusion setting) or not: said, not silent
            print(f"note: the replayed trip was driven on another scenario (it differs in: {', '.join(differs[:4])}"
                  f"{' ...' if len(differs) > 4 else ''})", file=sys.stderr)
    if scenario.ar.video:
        print("note: a drive writes no overlay.mp4 (ar.video); --record-video records what the driver saw "
              "(drive.mp4)", file=sys.stderr)
    from vcfusion.hitl.driver import DriveAborted

    guidance = args.guidance or _recorded_guidance(summary) or "on"
    try:
        result = drive(scenario, seed, input_spec=args.input, guidance_on=guidance == "on",
                       speed=None if args.speed == "max" else 1.0, out_dir=out, participant=participant,
                       axis_map_file=Path(args.axis_map) if args.axis_map else None, record_video=args.record_video,
                       window=not args.no_window, headless=args.headless, display_fps=args.fps,
                       start_screen_s=0.0 if args.headless else None)  # headless: nobody to press a key
    except DriveAborted as exc:
        print(f"{exc}: the trip was not written", file=sys.stderr)
        return 130
    print(format_summary(result.summary, result.wall_s))
    rt = result.summary["realtime"]
    pace = (f"median {rt['display_fps_median']:.1f} frames/s; max lag {rt['max_lag_s']:.3f} s"
            if rt["display_fps_median"] is not None and rt["max_lag_s"] is not None
            else "frame rate and lag not measured (not in real time)")
    print(f"  display: {rt['frames_shown']} frames shown, {rt['dropped_frames']} dropped, {pace}")
    print(f"run folder: {out}")
    return 0


def cmd_bench_render(args: argparse.Namespace) -> int:
    from vcfusion.render.bench import main as bench_main

    # the bench checks its frames and the scenario's ego when it loads the scenario
    return bench_main(["--scenario", args.scenario, "--frames", str(args.frames)]
                      + (["--preset", args.preset] if args.preset else []))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vcfusion", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run one simulation into a run folder")
    p.add_argument("scenario", help="scenario YAML file")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="run folder to create (default: runs/NAME-seedN)")
    p.set_defaults(func=cmd_run, interrupted="no run folder was written; run the same command again to redo the run")

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

    p = sub.add_parser("study", help="studies over many runs: guidance (Fig. 8/9), identification (Fig. 4)")
    study = p.add_subparsers(dest="study", required=True)
    from vcfusion.studies.identification_cli import add_study_parser as add_identification_parser

    add_identification_parser(study)
    p = study.add_parser("guidance", help="paired trips with and without AR guidance (paper Fig. 8/9)")
    p.add_argument("scenario", nargs="?", help="scenario YAML file: the driver model drives the trips "
                                               "(not with --from-runs)")
    p.add_argument("--from-runs", nargs="+", metavar="DIR",
                   help="instead of simulating: the study of existing run folders (human trips of vcfusion drive / "
                        "study hitl, model trips of vcfusion run / batch, or both), paired by driver and seed; "
                        "DIR is a run folder or a folder of them (a batch, an hitl session)")
    p.add_argument("--arms",
                   help="comma-separated arms among none (no AR), cloud (highlights from the cloud alone), "
                        "fusion (camera + CNN + matcher + overlay: the paper's system), oracle (ground-truth "
                        "boxes); paired on seeds and driver draws, each compared with none (default: none,fusion)")
    p.add_argument("--trips", type=int, help="number of paired trips (seeds FIRST..FIRST+N-1; default 200)")
    p.add_argument("--workers", type=int, help="worker processes (one simulation each; default 2)")
    p.add_argument("--first-seed", type=int, help="default 0")
    p.add_argument("--out", help="study folder (default: runs/guidance-study-SCENARIO, "
                                 "runs/guidance-study-from-runs with --from-runs)")
    p.add_argument("--renders", default="renders", help="folder for the figures (default: renders)")
    p.add_argument("--process-model", action="append", default=[], metavar="MODULE:FACTORY",
                   help="extra cloud twin process model: FACTORY(scenario) returns fn(twins, store) -> "
                        "{'lc_prob': ...}; repeatable; one writer per output (a stand-in predictor needs "
                        "prediction.enabled: false in the scenario)")
    p.set_defaults(func=cmd_study_guidance,
                   interrupted="the study wrote nothing; run the same command again (its trips start over)")

    p = study.add_parser("hitl", help="a participant drives: practice, counterbalanced trips with / without "
                                      "guidance, optional SSQ (vcfusion drive for each trip)")
    p.add_argument("scenario")
    p.add_argument("--participant", required=True)
    p.add_argument("--trips", type=int, default=4, help="paired trips: each seed driven with and without guidance")
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--practice-seed", type=int, default=1000)
    p.add_argument("--order", choices=("on-first", "off-first"), help="default: alternates between participants")
    p.add_argument("--ssq", action="store_true", help="simulator sickness questionnaire before and after")
    p.add_argument("--input", default="keyboard", help="keyboard, joystick or replay:FILE")
    p.add_argument("--axis-map", help="axis-map JSON of the wheel (vcfusion drive --calibrate)")
    p.add_argument("--speed", default="1", help="1 (real time) or max (replay inputs only)")
    p.add_argument("--headless", action="store_true", help="SDL dummy video/audio drivers (no screen)")
    p.add_argument("--out", help="session folder (default: runs/hitl-PARTICIPANT)")
    p.set_defaults(func=cmd_study_hitl, interrupted="finished trips are kept; run the same command again to go on")

    p = sub.add_parser("build-net", help="rebuild every sumo_net/NAME.net.xml with netconvert")
    p.add_argument("--net-dir", help="folder with NAME.nod/edg.xml (+ .typ/.con.xml) (default: the repo's sumo_net)")
    p.set_defaults(func=cmd_build_net)

    p = sub.add_parser("bench", help="benchmark suite: print figures, write bench.json and bench.md")
    p.add_argument("--sections", help="comma-separated subset, e.g. P1,P4 (default: all)")
    p.add_argument("--quick", action="store_true", help="small sizes (a smoke run, not figures to report)")
    p.add_argument("--out", default="runs/bench")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("render", help="render ego-camera frames of seeds into a COCO dataset")
    p.add_argument("scenario")
    p.add_argument("--seeds", required=True, help="e.g. 0-9 or 1,4,7-9")
    p.add_argument("--every", type=int, default=5, help="render every K-th V2C tick (default 5)")
    p.add_argument("--out", help="dataset folder to create (default: renders/NAME-dataset)")
    p.add_argument("--workers", type=int, default=2,
                   help="processes, one seed each (default 2; the folder is the same for any number)")
    p.set_defaults(func=cmd_render, interrupted="no dataset folder was written; run the same command again")

    p = sub.add_parser("drive", help="drive the ego yourself (keyboard, wheel, game pad) or replay a drive")
    p.add_argument("scenario", nargs="?", help="scenario YAML file (not needed with --calibrate)")
    p.add_argument("--seed", type=int, default=None, help="traffic seed (default 0; replaying a trip's "
                                                               "inputs.parquet: that trip's)")
    p.add_argument("--guidance", choices=("on", "off"), default=None,
                   help="show the AR guidance (default on; replaying a trip's inputs.parquet: that trip's)")
    p.add_argument("--input", default="keyboard", help="keyboard, joystick or replay:FILE (CSV / Parquet)")
    p.add_argument("--speed", default="1", help="1 (real time) or max (replay only)")
    p.add_argument("--participant", default="", help="participant id, stored with the trip (default: a replayed "
                                                      "trip's)")
    p.add_argument("--out", help="run folder to create (default: runs/SCENARIO-PARTICIPANT-seedN)")
    p.add_argument("--axis-map", help="axis-map JSON of the wheel (written by --calibrate)")
    p.add_argument("--calibrate", action="store_true", help="calibrate the wheel / pedals into --axis-map FILE")
    p.add_argument("--record-video", action="store_true", help="also write the driver's view as drive.mp4 "
                                                               "in the run folder")
    p.add_argument("--fps", type=float, default=30.0, help="display frames per simulated second (default 30)")
    p.add_argument("--headless", action="store_true", help="SDL dummy video/audio drivers (no screen)")
    p.add_argument("--no-window", action="store_true", help="no display at all (replays: tables only)")
    p.set_defaults(func=cmd_drive, interrupted="the trip was not written")

    p = sub.add_parser("bench-render", help="time RGB + depth + instance rendering (median ms per frame)")
    p.add_argument("--scenario", default=str(SHIPPED_SCENARIOS / "accident.yaml"))
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--preset", choices=("fast", "quality"), help="render preset (default: the scenario's camera.render_preset)")
    p.set_defaults(func=cmd_bench_render)

    p = sub.add_parser("demo", help="the main job on the default scenario")
    p.add_argument("--scenario", default=str(SHIPPED_SCENARIOS / "accident.yaml"))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--trips", type=int, default=8, help="paired trips of the closing guidance study")
    p.add_argument("--process-model", action="append", default=[], metavar="MODULE:FACTORY",
                   help="extra cloud process model for the guidance study (see `study guidance`)")
    p.set_defaults(func=cmd_demo)

    from vcfusion.prediction.commands import add_parsers as add_prediction_parsers

    add_prediction_parsers(sub)  # dataset, train, evaluate, bench-predict

    from vcfusion.detection.commands import add_parsers as add_detection_parsers

    add_detection_parsers(sub)

    from vcfusion.metrics.commands import add_parsers as add_metrics_parsers

    add_metrics_parsers(sub)  # metrics, report
    __import__("vcfusion.studies.explain_cli", fromlist=["add_parsers"]).add_parsers(sub)  # explain-highlights
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    with interrupts.recorded():  # Ctrl-C stops the command even when numba swallowed its KeyboardInterrupt
        try:
            return args.func(args)
        except SystemExit:
            raise
        except BaseException as exc:
            if interrupts.is_interrupt(exc):  # also when numba mangled it on its way up
                # What Ctrl-C left and how to go on: the command's set_defaults(interrupted=...).
                # The workers were stopped and temporary folders removed on the way up.
                hint = getattr(args, "interrupted", None)
                terminated = interrupts.terminated()  # SIGTERM, else Ctrl-C
                print(("terminated" if terminated else "interrupted") + (f": {hint}" if hint else ""), file=sys.stderr)
                return 143 if terminated else 130
            # scenario, model, dataset, command-line values; an output that exists (our own message)
            if isinstance(exc, InputError) or (isinstance(exc, FileExistsError) and exc.filename is None):
                for line in str(exc).splitlines():  # one line per problem (a scenario file may have several)
                    print(f"error: {line}", file=sys.stderr)
                return 2
            if isinstance(exc, OSError) and exc.filename is not None:
                # a path the command could not write or read (no permission, a folder where a file
                # goes, a missing parent, a file where a folder goes): the path and the reason
                what = f" (-> {exc.filename2})" if exc.filename2 else ""
                reason = exc.strerror or str(exc)
                if isinstance(exc, FileExistsError) and Path(exc.filename).is_file():
                    reason = "is a file; expected a folder (or a path that does not exist yet)"
                print(f"error: {exc.filename}{what}: {reason}", file=sys.stderr)
                return 2
            from vcfusion.errors import JobError
            from vcfusion.traffic.session import RunError

            if isinstance(exc, (RunError, JobError)):
                print(f"error: {exc}", file=sys.stderr)
                return 1
            raise


if __name__ == "__main__":
    sys.exit(main())
