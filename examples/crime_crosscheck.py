"""The ego's TTC, time headway and headway by vcfusion's metrics and by CommonRoad-CriMe, on runs of a
scenario exported to CommonRoad (vcfusion.control.crime has the definitions of both sides).

Needs commonroad-crime in an environment of its own (it pins commonroad-io 2024.3 and protobuf
3.20.2, which the dev extra's onnx refuses).

    python examples/crime_crosscheck.py --seeds 0-4 --out renders/crime
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import pandas as pd

from vcfusion.control.commonroad import export_commonroad
from vcfusion.control.crime import agreement, crime_problem, crosscheck
from vcfusion.run import execute_run
from vcfusion.scenario import load_scenario


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", type=Path, default=Path("accident"),
                        help="scenario file or shipped scenario name")
    parser.add_argument("--seeds", default="0-4", help="first-last")
    parser.add_argument("--out", type=Path, default=None, help="folder for the per-sample table and the figures")
    args = parser.parse_args()
    problem = crime_problem()
    if problem is not None:
        raise SystemExit(f"error: {problem}")
    first, last = (int(x) for x in args.seeds.split("-"))
    scenario = load_scenario(args.scenario)
    tables = []
    with tempfile.TemporaryDirectory(prefix="vcfusion-crime-") as tmp:
        for seed in range(first, last + 1):
            folder = Path(tmp) / f"seed{seed}"
            result = execute_run(scenario, seed, folder)
            export_commonroad(folder, folder / "run.xml", args.scenario)
            samples = crosscheck(folder, folder / "run.xml").assign(seed=seed)
            print(f"seed {seed}: {len(samples)} ego samples with a leader, leaders {sorted(set(samples['leader']))}, "
                  f"cut-ins ahead of the ego {result.summary['cut_ins_ahead_of_ego']}")
            tables.append(samples)
    samples = pd.concat(tables, ignore_index=True)
    figures = {"scenario": scenario.name, "seeds": args.seeds, "all": agreement(samples),
               "ttc_below_10_s": agreement(samples[samples["ttc_s_ours"] < 10.0])}
    print(json.dumps(figures, indent=1))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        samples.to_csv(args.out / "crime_samples.csv", index=False)
        (args.out / "crime_agreement.json").write_text(json.dumps(figures, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
