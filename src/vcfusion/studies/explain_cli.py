"""`vcfusion explain-highlights RUN_FOLDER --out DIR` (vcfusion.studies.explain)."""

from __future__ import annotations

import argparse
from pathlib import Path


def cmd_explain_highlights(args: argparse.Namespace) -> int:
    from vcfusion.studies.explain import explain_run

    out = Path(args.out) if args.out else Path(args.run) / "highlights"
    res = explain_run(Path(args.run), out)
    counts = res["counts"]
    print(f"{args.run}: warning episodes " + ", ".join(f"{counts.get(k, 0)} {k}" for k in
                                                     ("right", "wrong", "missed", "unseen")))
    print(f"explained: {out / 'highlights.md'}, {out / 'highlights.csv'}"
          + (f", frames in {out / 'frames'}" if res["frames"] else " (the run recorded no AR frames)"))
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("explain-highlights",
                       help="per warning episode of a run: the twin, the drawn box, the vehicle in it, why it is "
                            "right, wrong, missed or unseen (with the AR frame where the run recorded frames)")
    p.add_argument("run", metavar="RUN_FOLDER", help="a run folder with the camera fusing (fusion.enabled)")
    p.add_argument("--out", help="folder to create (default: RUN_FOLDER/highlights)")
    p.set_defaults(func=cmd_explain_highlights)
