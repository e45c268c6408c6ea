"""Handlers of `vcfusion real-split` (frozen splits of imported recordings) and `vcfusion sim-to-real`
(the sim-to-real table of lane-change predictors)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vcfusion.commands.checks import check_folder_path
from vcfusion.errors import UsageError


def cmd_real_split_freeze(args: argparse.Namespace) -> int:
    from vcfusion.prediction.realsplit import freeze_split, write_split

    out = Path(args.out)
    if out.exists() and not args.force:
        raise UsageError(f"--out: {out} already exists: a frozen split is not re-drawn (use --force to replace it)")
    check_folder_path(out.parent)
    try:
        split = freeze_split(Path(args.dataset), args.by, args.seed, (args.development, args.validation), args.name)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    write_split(split, out)
    print(f"split of {args.dataset} by {args.by} -> {out}")
    for part, c in split["counts"].items():
        units = f"{c['units']} recordings, " if args.by == "recording" else ""
        print(f"  {part}: {units}{c['vehicles']} vehicles, {c['lane_changes']} lane changes")
    return 0


def cmd_real_split_apply(args: argparse.Namespace) -> int:
    from vcfusion.prediction.realsplit import apply_split

    check_folder_path(Path(args.out))
    report = apply_split(Path(args.dataset), Path(args.split), Path(args.out))
    print(f"split dataset -> {args.out} (train = development, validation, test = held_out)")
    for part, c in report["counts"].items():
        print(f"  {part}: {c['vehicles']} vehicles, {c['lane_changes']} lane changes, {c['samples']} samples")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("real-split", help="freeze a development / validation / held-out split of an imported "
                                          "recording (by recording or by vehicle), or apply a frozen one")
    rs = p.add_subparsers(dest="real_split_command", required=True)
    f = rs.add_parser("freeze", help="draw the split once and write it (unit ids and the rule; no data)")
    f.add_argument("dataset", help="an imported dataset (`vcfusion dataset --from-ngsim | --from-commonroad ...`)")
    f.add_argument("--by", required=True, choices=["recording", "vehicle"],
                   help="the unit kept whole: recording (CommonRoad) or vehicle (one long NGSIM recording)")
    f.add_argument("--out", required=True, help="split file to write (.json); commit it")
    f.add_argument("--seed", type=int, default=0, help="seed of the units' random order")
    f.add_argument("--development", type=float, default=0.6, help="share of the lane changes for development")
    f.add_argument("--validation", type=float, default=0.2, help="share of the lane changes for validation")
    f.add_argument("--name", help="name recorded in the file (default: the dataset folder's name)")
    f.add_argument("--force", action="store_true", help="replace an existing --out")
    f.set_defaults(func=cmd_real_split_freeze)
    a = rs.add_parser("apply", help="write the split dataset: train = development, validation, test = held_out")
    a.add_argument("dataset", help="the imported dataset the split was frozen on")
    a.add_argument("split", help="split file from `vcfusion real-split freeze`")
    a.add_argument("--out", required=True, help="new dataset folder")
    a.set_defaults(func=cmd_real_split_apply,
                   interrupted="the split dataset is written to OUT.partial and renamed when complete; run it again")
