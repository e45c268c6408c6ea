"""`vcfusion compare-lane-changes`: argparse setup and handler (the library code is
vcfusion.prediction.manoeuvres). A bad dataset folder raises DatasetError (the CLI prints it and
exits with 2)."""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_compare_lane_changes(args: argparse.Namespace) -> int:
    from vcfusion.prediction.manoeuvres import compare_lane_changes

    names = [n.strip() for n in args.names.split(",")] if args.names else None
    report = compare_lane_changes(Path(args.sim), [Path(r) for r in args.real], Path(args.out), args.label, names)
    ks = report["ks"]
    print(f"lane changes: {', '.join(f'{k} {v}' for k, v in report['meta']['lane_changes'].items())}")
    columns = ["quantity", "real", "n_sim", "n_real", "median_sim", "median_real", "ks"]
    print(ks[columns].to_string(index=False, float_format="%.3g"))
    print(f"comparison -> {args.out} (ks.md, ks.csv, events.parquet, profiles.parquet, profiles.png, quantities.png)")
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from vcfusion.errors import UsageError
    from vcfusion.prediction.lc_calibration import run_search
    from vcfusion.scenario import load_scenario
    from vcfusion.commands.checks import parse_seeds

    load_scenario(args.scenario)  # fail fast on a bad file
    seeds = parse_seeds(args.seeds)
    if args.workers < 1:
        raise UsageError(f"--workers: expected a positive number of processes, got {args.workers}")
    names = [n.strip() for n in args.names.split(",")] if args.names else None
    if names is not None and len(names) != len(args.real):
        raise UsageError(f"--names: expected {len(args.real)} names (one per REAL_DATASET), got {len(names)}")
    chosen = [c.strip() for c in args.candidates.split(",")] if args.candidates else None
    table = run_search(Path(args.scenario), seeds, [Path(r) for r in args.real], Path(args.out), names, args.workers,
                       candidates=chosen)
    print((Path(args.out) / "search.md").read_text())
    print(f"best: {table.loc[table['objective'].idxmin(), 'candidate']} (lowest mean KS); search -> {args.out}")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("compare-lane-changes",
                       help="how a simulated dataset's lane changes differ from recorded ones: kinematics around the "
                            "lane crossing (-10 .. +3 s) and KS distances per quantity")
    p.add_argument("sim", metavar="SIM_DATASET", help="dataset folder of simulated runs (`vcfusion dataset SCENARIO`)")
    p.add_argument("real", metavar="REAL_DATASET", nargs="+",
                   help="dataset folder(s) of imported recordings (`vcfusion dataset --from-...`); each is compared "
                        "with SIM_DATASET")
    p.add_argument("--out", required=True, help="new folder for the table, figures and per-event quantities")
    p.add_argument("--names", help="comma-separated names of SIM then each REAL for tables and figures "
                                   "(default: the folder names)")
    p.add_argument("--label", default="",
                   help="what the figures are, printed on them, e.g. 'development data US-101; nothing held out'")
    p.set_defaults(func=cmd_compare_lane_changes,
                   interrupted="the comparison folder is written only when complete; nothing was written")

    p = sub.add_parser("calibrate-lane-changes",
                       help="simulate the documented lane-change model candidates on a base scenario and score each "
                            "by its KS distances to recorded lane changes")
    p.add_argument("scenario", metavar="BASE_SCENARIO", help="scenario file the candidates extend")
    p.add_argument("real", metavar="REAL_DATASET", nargs="+", help="dataset folder(s) of imported recordings")
    p.add_argument("--seeds", required=True, help="seeds of each candidate, e.g. 0-1")
    p.add_argument("--out", required=True, help="search folder (resumable: finished seeds are kept)")
    p.add_argument("--names", help="comma-separated names of the REAL_DATASETs")
    p.add_argument("--candidates", help="comma-separated candidate names (default: all of "
                                        "vcfusion.prediction.lc_calibration.CANDIDATES)")
    p.add_argument("--workers", type=int, default=1)
    p.set_defaults(func=cmd_calibrate, interrupted="finished seeds are kept; run the same command again to go on")
