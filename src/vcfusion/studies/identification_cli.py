"""`vcfusion study identification`: argument parsing and the handler (the study is in identification.py)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from vcfusion.errors import UsageError
from vcfusion.metrics.highlights import MIN_VISIBLE_PX


def _float_list(text: str, option: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UsageError(f"{option}: expected comma-separated numbers such as 0,0.1,0.5, got {text!r}") from None
    if not values or any(v < 0 for v in values):
        raise UsageError(f"{option}: expected non-negative numbers, got {text!r}")
    return values


def cmd_study_identification(args: argparse.Namespace) -> int:
    from vcfusion.scenario import load_scenario, require_camera_world
    from vcfusion.studies.batch import parse_seeds
    from vcfusion.detection.detector_net import DetectorFileError, TorchDetector, default_weights_path
    from vcfusion.detection.detectors import OracleDetector
    from vcfusion.studies.identification import default_conditions, run_identification_study, summary_lines
    from vcfusion.fusion.box_refine import BoxRefineParams
    from vcfusion.fusion.stage import RenderedFrameSources, depth_params

    from vcfusion.cli import check_new_folder
    from vcfusion.detection.commands import check_min_area

    check_min_area(args.min_area)
    out = check_new_folder(Path(args.out))  # a study is not resumed: another one's outputs would be replaced
    scenarios = [load_scenario(path) for path in args.scenario]
    for scenario in scenarios:
        require_camera_world(scenario)  # every frame is rendered
    names = [sc.name for sc in scenarios]
    if len(set(names)) != len(names):
        raise UsageError(f"scenario: expected scenarios with distinct names, got {names}")
    seeds = parse_seeds(args.seeds)  # UsageError on a bad range
    conditions = default_conditions(_float_list(args.latencies, "--latencies"), _float_list(args.noises, "--noises"))
    detectors, refine = {}, {}
    for name in (d.strip() for d in args.detectors.split(",")):
        if name == "oracle":
            detectors[name] = OracleDetector()
        elif name in ("cnn", "cnn-rgb"):
            try:
                detectors[name] = TorchDetector(args.weights or default_weights_path())
            except DetectorFileError as exc:
                raise UsageError(f"--weights: {exc}") from None
            # cnn: boxes refined by depth (the fusion stage's default); cnn-rgb: the boxes as detected
            refine[name] = BoxRefineParams() if name == "cnn" else None
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
    print(f"outputs: {out}/identification_*.csv, *.png, identification_rows.parquet")
    return 0


def add_study_parser(ssub) -> None:
    """`vcfusion study identification ...`, added to the subcommands of `vcfusion study`."""
    p = ssub.add_parser("identification", help="target identification accuracy (paper Fig. 4) vs latency, noise")
    p.add_argument("scenario", nargs="+", help="one or more scenario files (each run with every seed)")
    p.add_argument("--seeds", required=True, help="e.g. 0-19")
    p.add_argument("--out", default="renders/identification")
    p.add_argument("--detectors", default="oracle,cnn",
                   help="comma-separated: oracle, cnn (boxes refined by depth), cnn-rgb (the CNN's boxes as detected)")
    p.add_argument("--weights", help="cnn weights (default: the shipped detector)")
    p.add_argument("--latencies", default="0,0.1,0.2,0.3,0.5", help="V2C latencies (s), at zero noise")
    p.add_argument("--noises", default="0,0.5,1,2", help="GNSS noise std (m), at zero latency")
    p.add_argument("--min-area", type=float, default=MIN_VISIBLE_PX, help="smallest ground-truth box (px^2) counted as a target")
    p.add_argument("--anchor-radius", type=float, default=None,
                   help="baseline and paper: with no box containing the anchor, take the nearest box within "
                        "this many pixels (default: off, the paper's rule)")
    p.set_defaults(func=cmd_study_identification,
                   interrupted="the study wrote nothing; run the same command again (its runs start over)")
