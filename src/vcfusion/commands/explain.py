"""`vcfusion explain-highlights RUN_FOLDER --out DIR` (vcfusion.studies.explain) and
`vcfusion guidance-matrix SCENARIO... --trips N --out DIR` or `--from-studies FOLDER...`
(vcfusion.studies.matrix)."""

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


def cmd_guidance_matrix(args: argparse.Namespace) -> int:
    from vcfusion.errors import UsageError
    from vcfusion.studies.guidance import parse_arms
    from vcfusion.studies.matrix import matrix_from_studies, run_matrix

    tuned = {n.strip() for n in args.tuned_on.split(",") if n.strip()}
    if bool(args.scenarios) == bool(args.from_studies):
        raise UsageError("expected scenario files to run, or --from-studies FOLDER... (studies already run), "
                         "not both and not neither")
    if args.from_studies:
        res = matrix_from_studies([Path(p) for p in args.from_studies], Path(args.out), tuned)
    else:
        if args.trips < 2:
            raise UsageError(f"--trips: expected at least 2 paired trips per scenario for a confidence interval, "
                             f"got {args.trips}")
        if args.workers < 1:
            raise UsageError(f"--workers: expected at least 1, got {args.workers}")
        try:
            arms = parse_arms(args.arms)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        res = run_matrix([Path(p) for p in args.scenarios], args.trips, args.workers, Path(args.out), tuned, arms,
                         args.first_seed)
    print(res["text"])
    print(f"tables: {Path(args.out) / 'matrix_summary.csv'}, {Path(args.out) / 'matrix_highlights.csv'}")
    return 0


def add_parsers(sub) -> None:
    p = sub.add_parser("explain-highlights",
                       help="per warning episode of a run: the twin, the drawn box, the vehicle in it, why it is "
                            "right, wrong, missed or unseen (with the AR frame where the run recorded frames)")
    p.add_argument("run", metavar="RUN_FOLDER", help="a run folder with the camera fusing (fusion.enabled)")
    p.add_argument("--out", help="folder to create (default: RUN_FOLDER/highlights)")
    p.set_defaults(func=cmd_explain_highlights)

    p = sub.add_parser("guidance-matrix",
                       help="the guidance study over several scenarios: per-scenario and pooled paired tables "
                            "with 95%% CIs, highlight episodes, collision seeds, tuned-on / held-out labels")
    p.add_argument("scenarios", nargs="*", metavar="SCENARIO", help="scenario YAML files with an ego")
    p.add_argument("--from-studies", nargs="+", metavar="FOLDER",
                   help="instead of running: the folders of `vcfusion study guidance` runs of several scenarios "
                        "(the same arms), tabled per scenario and pooled")
    p.add_argument("--trips", type=int, default=20, help="paired trips per scenario (seeds FIRST..FIRST+N-1)")
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--arms", default="none,fusion", help="comma-separated arms (as study guidance)")
    p.add_argument("--tuned-on", default="accident",
                   help="comma-separated scenario names the chain was tuned on (labelled tuned-on; the others "
                        "held-out)")
    p.add_argument("--out", required=True, help="matrix folder (one study folder per scenario inside; resumable "
                                                "as study guidance's)")
    p.set_defaults(func=cmd_guidance_matrix, interrupted="each scenario's finished trips are kept "
                   "(OUT/<scenario>/trips.jsonl); run the same command again to go on")
