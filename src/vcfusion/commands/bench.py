"""`vcfusion bench | bench-render`: the benchmark suite and the ego camera's benchmark."""

from __future__ import annotations

import argparse
from pathlib import Path

from vcfusion.errors import UsageError


def cmd_bench(args: argparse.Namespace) -> int:
    from vcfusion.bench import DEFAULT_SECTIONS, SECTIONS, run_suite, to_markdown

    sections = [s.strip() for s in args.sections.split(",")] if args.sections else list(DEFAULT_SECTIONS)
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        raise UsageError(f"--sections: unknown {unknown}; expected some of {sorted(SECTIONS)}")
    p2: dict = {}
    if args.depth_sensor is not None:
        p2["depth_sensor"] = args.depth_sensor
    if args.pose_noise_deg is not None:
        from vcfusion.commands.checks import check_pose_noise_deg

        p2["pose_noise_deg"] = check_pose_noise_deg(args.pose_noise_deg)
    if p2 and "P2" not in sections:
        raise UsageError("--depth-sensor / --pose-noise-deg: they set P2's camera; expected P2 among --sections, got "
                         f"{','.join(sections)}")
    gpu: dict = {}
    if args.gpu_reference is not None and args.write_gpu_reference is not None:
        raise UsageError("--gpu-reference / --write-gpu-reference: expected one of them, got both")
    for flag, key in (("gpu_reference", "reference"), ("write_gpu_reference", "write_reference")):
        value = getattr(args, flag)
        if value is None:
            continue
        if "GPU" not in sections:
            raise UsageError(f"--{flag.replace('_', '-')}: it sets the GPU check; expected GPU among --sections, "
                             f"got {','.join(sections)}")
        if not value.endswith(".npz"):
            raise UsageError(f"--{flag.replace('_', '-')} {value}: expected a .npz file")
        if key == "reference" and not Path(value).is_file():
            raise UsageError(f"--gpu-reference {value}: no such file (write it with --write-gpu-reference on a "
                             "machine with OSMesa)")
        gpu[key] = str(Path(value).resolve())
    results = run_suite(sections, "quick" if args.quick else "full", Path(args.out), {"P2": p2, "GPU": gpu})
    print(to_markdown(results))
    print(f"written: {Path(args.out) / 'bench.json'}, {Path(args.out) / 'bench.md'}")
    failed = 0
    for r in results:  # the GPU check's verdict, on its own line (counted: skipped is not passed)
        if "status" in r:
            print(f"{r['name']}: {r['status']}; {r.get('failed', 0)} failed, {r.get('skipped', 0)} skipped")
            failed += r.get("failed", 0)
    return 1 if failed else 0


def cmd_bench_render(args: argparse.Namespace) -> int:
    from vcfusion.commands.checks import check_seed
    from vcfusion.render.bench import bench_render
    from vcfusion.scenario import load_scenario

    if args.frames < 1:
        raise UsageError(f"--frames: expected a positive number of frames, got {args.frames}")
    scenario = load_scenario(args.scenario)
    if scenario.ego is None:
        raise UsageError(f"{args.scenario}: ego: the camera rides on the ego; the scenario has no ego block")
    print(bench_render(scenario, args.frames, check_seed(args.seed), args.preset))
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("bench", help="benchmark suite: print figures, write bench.json and bench.md")
    p.add_argument("--sections", help="comma-separated subset, e.g. P1,P4 (default: P1-P7); GPU: the GPU path "
                                      "checked against the CPU path (says 'no GPU: skipped' without one)")
    p.add_argument("--quick", action="store_true", help="small sizes (a smoke run, not figures to report)")
    p.add_argument("--out", default="runs/bench")
    p.add_argument("--depth-sensor", choices=("exact", "stereo", "tof", "lidar"),
                   help="P2: the camera's depth sensor (default: the accident scenario's, exact)")
    p.add_argument("--pose-noise-deg", type=float, metavar="DEG",
                   help="P2: camera mount calibration error std (pitch, yaw, roll), deg, with body motion when > 0 "
                        "(default: the scenario's)")
    p.add_argument("--gpu-reference", metavar="FILE.npz",
                   help="GPU: the CPU half from FILE (written by --write-gpu-reference where OSMesa is installed) "
                        "instead of rendering it here: for a GPU machine without OSMesa")
    p.add_argument("--write-gpu-reference", metavar="FILE.npz",
                   help="GPU: only the CPU half (OSMesa renders, CPU boxes, the vehicle states), written to FILE")
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("bench-render", help="time RGB + depth + instance rendering (median ms per frame)")
    p.add_argument("--scenario", default="accident")
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--seed", type=int, default=0, help="the simulated run whose states are rendered (default 0)")
    p.add_argument("--preset", choices=("fast", "quality"), help="render preset (default: the scenario's camera.render_preset)")
    p.set_defaults(func=cmd_bench_render)
