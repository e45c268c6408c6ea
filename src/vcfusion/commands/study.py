"""`vcfusion study identification | guidance | hitl`: studies over many runs (the studies are in
vcfusion.studies and vcfusion.hitl; this module parses and checks their arguments)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vcfusion.commands.checks import (check_folder_path, check_min_area, check_new_folder, check_pose_noise_deg,
                                      check_seed, float_list, parse_seeds)
from vcfusion.errors import UsageError
from vcfusion.metrics.highlights import MIN_VISIBLE_PX
from vcfusion.scenario import find_scenario, load_scenario


def with_sensors(scenario, depth_sensor: str | None, pose_noise_deg: float | None):
    """The scenario with its camera's depth sensor and pose noise replaced where given (the pose
    noise: a mount calibration error of that std and the body's pitch and roll on its suspension)."""
    update = {}
    if depth_sensor is not None:
        update["depth"] = depth_sensor
    if pose_noise_deg is not None:
        check_pose_noise_deg(pose_noise_deg)
        update["pose_noise"] = scenario.camera.pose_noise.model_copy(
            update={"mount_std_deg": pose_noise_deg, "body_motion": pose_noise_deg > 0})
    if not update:
        return scenario
    return scenario.model_copy(update={"camera": scenario.camera.model_copy(update=update)})


def cmd_study_identification(args: argparse.Namespace) -> int:
    from vcfusion.scenario import require_camera_world
    from vcfusion.detection.detector_net import DetectorFileError, TorchDetector, default_weights_path
    from vcfusion.detection.detectors import OracleDetector
    from vcfusion.detection.family_eval import depth_counts_table
    from vcfusion.studies.identification import default_conditions, run_identification_study, summary_lines
    from vcfusion.fusion.box_refine import BoxRefineParams
    from vcfusion.fusion.stage import RenderedFrameSources, depth_params, scenario_road

    check_min_area(args.min_area)
    out = check_new_folder(Path(args.out))  # a study is not resumed: another one's outputs would be replaced
    scenarios = [with_sensors(load_scenario(path), args.depth_sensor, args.pose_noise_deg) for path in args.scenario]
    for scenario in scenarios:
        require_camera_world(scenario)  # every frame is rendered
    names = [sc.name for sc in scenarios]
    if len(set(names)) != len(names):
        raise UsageError(f"scenario: expected scenarios with distinct names, got {names}")
    seeds = parse_seeds(args.seeds)  # UsageError on a bad range
    conditions = default_conditions(float_list(args.latencies, "--latencies"), float_list(args.noises, "--noises"))
    detectors, refine = {}, {}
    for name in (d.strip() for d in args.detectors.split(",")):
        if name == "oracle":
            detectors[name] = OracleDetector()
        elif name in ("cnn", "cnn-rgb"):
            try:
                detectors[name] = TorchDetector(args.weights or default_weights_path())
            except DetectorFileError as exc:
                raise UsageError(f"--weights: {exc}") from None
            # cnn: boxes refined by depth (the fusion stage's default; the first scenario's road);
            # cnn-rgb: the boxes as detected
            refine[name] = BoxRefineParams(road=scenario_road(scenarios[0])) if name == "cnn" else None
        else:
            raise UsageError(f"--detectors: expected names among oracle, cnn, cnn-rgb; got {name!r}")
    for path, scenario in zip(args.scenario, scenarios):
        if scenario.ego is None:
            raise UsageError(f"{path}: ego: the camera rides on the ego; the scenario has no ego block")
    sources = RenderedFrameSources()
    try:
        # Algorithm 1's th, n, reducer: the first scenario's fusion block (one setting per study)
        rows = run_identification_study(scenarios, seeds, sources, detectors, out, conditions,
                                        depth_params=depth_params(scenarios[0]), min_gt_area_px=args.min_area,
                                        fallback_radius_px=args.anchor_radius, progress=sys.stderr.isatty(),
                                        refine=refine)
    finally:
        sources.close()
    n_targets = rows[(rows["latency_s"] == 0) & (rows["gnss_noise_m"] == 0)].groupby(["detector", "method"]).size()
    print(f"identification study {', '.join(names)}, seeds {args.seeds}: "
          f"{int(n_targets.min()) if len(n_targets) else 0} target-frames per detector and method (clean V2C)")
    for line in summary_lines(rows, 0.7):
        print(line)
    depth_counts = depth_counts_table(rows.attrs.get("depth_counts", {}))
    if depth_counts:
        print(depth_counts)
    print(f"outputs: {out}/identification_*.csv, *.png, identification_rows.parquet")
    return 0


def _add_identification_parser(study) -> None:
    p = study.add_parser("identification", help="target identification accuracy (paper Fig. 4) vs latency, noise")
    p.add_argument("scenario", nargs="+", help="one or more scenario files (each run with every seed)")
    p.add_argument("--seeds", required=True, help="e.g. 0-19")
    p.add_argument("--out", default="renders/identification")
    p.add_argument("--detectors", default="oracle,cnn",
                   help="comma-separated: oracle, cnn (boxes refined by depth), cnn-rgb (the CNN's boxes as detected)")
    p.add_argument("--weights", help="cnn weights (default: the shipped detector)")
    p.add_argument("--latencies", default="0,0.1,0.2,0.3,0.5", help="V2C latencies (s), at zero noise")
    p.add_argument("--noises", default="0,0.5,1,2", help="GNSS noise std (m), at zero latency")
    p.add_argument("--min-area", type=float, default=MIN_VISIBLE_PX,
                   help="smallest ground-truth box (px^2) counted as a target")
    p.add_argument("--depth-sensor", choices=("exact", "stereo", "tof", "lidar"), default=None,
                   help="the depth the fusion sees (default: each scenario's camera.depth)")
    p.add_argument("--pose-noise-deg", type=float, default=None, metavar="DEG",
                   help="camera mount calibration error std, deg, with the body's pitch and roll on its suspension "
                        "(default: each scenario's camera.pose_noise)")
    p.add_argument("--anchor-radius", type=float, default=None,
                   help="baseline and paper: with no box containing the anchor, take the nearest box within "
                        "this many pixels (default: off, the paper's rule)")
    p.set_defaults(func=cmd_study_identification,
                   interrupted="the study wrote nothing; run the same command again (its runs start over)")


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
        result = run_guidance_study(find_scenario(args.scenario), args.trips, args.workers, out, Path(args.renders),
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
        protocol = run_hitl_study(find_scenario(args.scenario), args.participant, args.trips, out,
                                  input_spec=args.input, axis_map_file=Path(args.axis_map) if args.axis_map else None,
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


def add_parsers(sub) -> None:
    p = sub.add_parser("study", help="studies over many runs: guidance (Fig. 8/9), identification (Fig. 4)")
    study = p.add_subparsers(dest="study", required=True)
    _add_identification_parser(study)
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
    p.add_argument("--out", help="study folder; resumable: the trips it logged (trips.jsonl) for the same scenario, "
                                 "arms and code are taken, not run again (default: runs/guidance-study-SCENARIO, "
                                 "runs/guidance-study-from-runs with --from-runs)")
    p.add_argument("--renders", default="renders", help="folder for the figures (default: renders)")
    p.add_argument("--process-model", action="append", default=[], metavar="MODULE:FACTORY",
                   help="extra cloud twin process model: FACTORY(scenario) returns fn(twins, store) -> "
                        "{'lc_prob': ...}; repeatable; one writer per output (a stand-in predictor needs "
                        "prediction.enabled: false in the scenario)")
    p.set_defaults(func=cmd_study_guidance,
                   interrupted="finished trips are kept (OUT/trips.jsonl); run the same command again to go on")

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
