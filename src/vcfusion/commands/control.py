"""`vcfusion export-commonroad RUN_FOLDER --out FILE.xml` (vcfusion.control.commonroad)."""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_export_commonroad(args: argparse.Namespace) -> int:
    from vcfusion.errors import UsageError

    from vcfusion.control.commonroad import commonroad_problem, export_commonroad

    problem = commonroad_problem()
    if problem is not None:
        raise UsageError(f"export-commonroad: {problem}")
    table = export_commonroad(Path(args.run_folder), Path(args.out), Path(args.scenario) if args.scenario else None)
    print(f"written: {args.out} ({len(table['obstacle_ids'])} vehicles, time step {table['dt']:g} s; ego = obstacle "
          f"{table['ego_obstacle_id']}), ids: {Path(args.out).with_suffix('.ids.json')}")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("export-commonroad", help="a run folder as a CommonRoad scenario (XML)")
    p.add_argument("run_folder", help="run folder of vcfusion run / drive")
    p.add_argument("--out", required=True, help="CommonRoad XML file to write")
    p.add_argument("--scenario", help="the run's scenario file (default: the manifest's scenario_file)")
    p.set_defaults(func=cmd_export_commonroad, interrupted="nothing was written")
