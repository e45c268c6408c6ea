"""The `vcfusion` command."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vcfusion.scenario import ScenarioError, load_scenario


class UsageError(ValueError):
    """A bad command-line argument; the message is for the user."""


def _default_run_dir(name: str, seed: int) -> Path:
    base = Path("runs") / f"{name}-seed{seed}"
    candidate, n = base, 1
    while candidate.exists():
        n += 1
        candidate = base.with_name(f"{base.name}-{n}")
    return candidate


def cmd_run(args: argparse.Namespace) -> int:
    from vcfusion.cosim import format_summary
    from vcfusion.run import execute_run

    scenario = load_scenario(args.scenario)
    out = Path(args.out) if args.out else _default_run_dir(scenario.name, args.seed)
    if out.exists():
        raise UsageError(f"--out: {out} already exists; choose a new run folder")
    result = execute_run(scenario, args.seed, out, progress=sys.stderr.isatty())
    print(format_summary(result.summary, result.wall_s))
    print(f"run folder: {out}")
    return 0


def cmd_batch(args: argparse.Namespace) -> int:
    from vcfusion.studies.batch import parse_seeds, run_batch

    scenario = load_scenario(args.scenario)  # fail fast, before any worker starts
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.workers < 1:
        raise UsageError(f"--workers: expected a positive number of processes, got {args.workers}")
    out = Path(args.out) if args.out else Path("runs") / f"{scenario.name}-batch"
    report = run_batch(Path(args.scenario), seeds, out, workers=args.workers)
    print(f"batch {scenario.name} -> {out}: {report['done']} run, {report['skipped']} already complete, "
          f"{len(report['failed'])} failed")
    for seed, error in report["failed"]:
        print(f"  seed {seed}: {error.splitlines()[0]}")
    return 1 if report["failed"] else 0


def cmd_build_net(args: argparse.Namespace) -> int:
    from vcfusion.traffic.network import REPO_NET_DIR, build_network

    out = build_network(Path(args.net_dir) if args.net_dir else REPO_NET_DIR)
    print(f"built {out}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from vcfusion.cosim import format_summary
    from vcfusion.run import execute_run

    scenario = load_scenario(args.scenario)
    out = _default_run_dir(scenario.name, args.seed)
    result = execute_run(scenario, args.seed, out, progress=sys.stderr.isatty())
    print(format_summary(result.summary, result.wall_s))
    print(f"run folder: {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vcfusion", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run one simulation into a run folder")
    p.add_argument("scenario", help="scenario YAML file")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", help="run folder to create (default: runs/NAME-seedN)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("batch", help="run many seeds in parallel processes (resumable)")
    p.add_argument("scenario")
    p.add_argument("--seeds", required=True, help="e.g. 0-99 or 1,4,7-9")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", help="batch folder (default: runs/NAME-batch)")
    p.set_defaults(func=cmd_batch)

    p = sub.add_parser("build-net", help="rebuild sumo_net/highway.net.xml with netconvert")
    p.add_argument("--net-dir", help="folder with highway.nod/edg/typ.xml (default: the repo's sumo_net)")
    p.set_defaults(func=cmd_build_net)

    p = sub.add_parser("demo", help="the main job on the default scenario")
    p.add_argument("--scenario", default="scenarios/accident.yaml")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_demo)

    from vcfusion.vision.commands import add_parsers as add_vision_parsers

    add_vision_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ScenarioError, UsageError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except FileExistsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:
        from vcfusion.traffic.session import RunError

        if isinstance(exc, RunError):
            print(f"error: {exc}", file=sys.stderr)
            return 1
        raise


if __name__ == "__main__":
    sys.exit(main())
