"""Handlers of the `vcfusion metrics | report` commands."""

from __future__ import annotations

import argparse
from pathlib import Path

from vcfusion.metrics.folders import (batch_seed_folders, print_batch_metrics, rebuild_batch_summary,
                                      recompute_folder, run_folders)


def cmd_metrics(args: argparse.Namespace) -> int:
    if args.scenario:
        from vcfusion.scenario import load_scenario

        load_scenario(args.scenario)  # fail fast on a bad file
    targets = [(Path(p), *run_folders(Path(p))) for p in args.paths]
    missing_sumo = []
    for path, folders, is_batch in targets:
        for folder in folders:
            if not recompute_folder(folder, args.scenario):
                missing_sumo.append(folder)
        print(f"{path}: metrics of {len(folders)} run folder{'s' if len(folders) != 1 else ''} recomputed")
        if is_batch:
            rebuild_batch_summary(path, folders)
            print_batch_metrics(path)
    if missing_sumo:
        print(f"note: {len(missing_sumo)} run folder(s) have no sumo_emissions.parquet (run with metrics.enabled "
              "false, or written before SUMO's emission totals were recorded): their SUMO emission columns are "
              "empty; rerun those seeds with metrics enabled to get them. First: " + str(missing_sumo[0]))
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from vcfusion.metrics.report import write_report

    batch = Path(args.batch)
    folders, is_batch = run_folders(batch)
    if is_batch:  # the header, tables and figures cover the seeds the seeds table does
        folders = batch_seed_folders(batch, folders)
    out = Path(args.out) if args.out else batch / "report"
    report = write_report(batch, folders, out)
    print(f"report: {report}")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("metrics", help="(re)compute safety, comfort and emission metrics of existing run folders")
    p.add_argument("paths", nargs="+", metavar="RUN_OR_BATCH_DIR", help="run folders or batch folders (seed_NNNN)")
    p.add_argument("--scenario", help="take the metrics: block (thresholds, definitions) from this scenario file "
                                      "instead of the one each run recorded")
    p.set_defaults(func=cmd_metrics)

    p = sub.add_parser("report", help="figures and a one-page Markdown report of a batch's metrics")
    p.add_argument("batch", metavar="BATCH_DIR")
    p.add_argument("--out", help="report folder (default: BATCH_DIR/report)")
    p.set_defaults(func=cmd_report)
