"""`vcfusion drive`: a person drives the ego (keyboard, wheel, game pad), or a recorded drive is replayed."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from vcfusion.commands.checks import check_seed, default_run_dir
from vcfusion.errors import UsageError
from vcfusion.scenario import load_scenario


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
    out = Path(args.out) if args.out else default_run_dir(f"{scenario.name}-{participant or 'drive'}", seed)
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
    if rt.get("vision_pipeline"):
        latency = rt["vision_latency_ms_median"]
        print(f"  vision beside the loop: {rt['vision_results']} results of {rt['vision_ticks_due']} due ticks, "
              f"{rt['vision_ticks_dropped']} dropped (worker busy)"
              + (f", latency median {latency:.0f} ms" if latency is not None else ""))
    if rt.get("ar_age_ms_median") is not None:
        print(f"  AR age: median {rt['ar_age_ms_median']:.0f} ms, max {rt['ar_age_ms_max']:.0f} ms")
    print(f"run folder: {out}")
    return 0


def add_parsers(sub) -> None:
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
