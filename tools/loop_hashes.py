"""Hashes of the run tables and summaries of a set of short runs: the check that a change to the
tick loop leaves every result byte-identical. Run it with the old and the new code and compare
the printed lines (one per run, then a total).

    PYTHONPATH=src python tools/loop_hashes.py            # the default set
    PYTHONPATH=src python tools/loop_hashes.py --quick    # accident seeds 0-1, curved, v2c_poor
    PYTHONPATH=src python tools/loop_hashes.py --vision   # and 6 s of accident_ar (renders, detects)
    PYTHONPATH=src python tools/loop_hashes.py --quick --sensors  # and accident_ar with stereo, ToF,
                                                                  # LiDAR depth and 0.3 deg pose noise

Each table's hash covers its column names, dtypes and values (pandas' row hashes, NaN included);
the summary's covers its JSON with sorted keys (floats written with repr).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
# (scenario file, seed, max_time_s or None for the scenario's own)
DEFAULT_RUNS = [
    ("scenarios/accident.yaml", 0, None), ("scenarios/accident.yaml", 1, None),
    ("scenarios/accident.yaml", 2, 30.0), ("scenarios/accident.yaml", 3, 30.0),
    ("scenarios/dense.yaml", 0, 30.0), ("scenarios/onramp.yaml", 0, 30.0),
    ("scenarios/curved.yaml", 0, 30.0), ("scenarios/overlap.yaml", 0, 30.0),
    ("scenarios/families/v2c_poor.yaml", 0, 30.0), ("scenarios/families/v2c_poor.yaml", 1, 30.0),
]
QUICK_RUNS = [DEFAULT_RUNS[0], DEFAULT_RUNS[1], DEFAULT_RUNS[6], DEFAULT_RUNS[8]]
# the full vision tick (camera, detector, fusion, overlay): PYOPENGL_PLATFORM=osmesa without a display
VISION_RUNS = [("scenarios/accident_ar.yaml", 0, 6.0)]
# the same with each noisy depth sensor and a 0.3 deg mount error with body motion (as `vcfusion study
# identification --depth-sensor S --pose-noise-deg 0.3` sets them): the sensor models' draws and the
# depth step's noisy-depth path
SENSOR_RUNS = [("scenarios/accident_ar.yaml", 0, 6.0, (depth, 0.3)) for depth in ("stereo", "tof", "lidar")]


def table_hash(frame: pd.DataFrame) -> str:
    h = hashlib.sha256()
    h.update(repr([(str(c), str(t)) for c, t in frame.dtypes.items()]).encode())
    h.update(pd.util.hash_pandas_object(frame, index=True).to_numpy().tobytes())
    return h.hexdigest()[:16]


def run_hashes(path: str, seed: int, max_time_s: float | None,
               sensors: tuple[str, float] | None = None) -> dict[str, str]:
    from vcfusion.commands.study import with_sensors
    from vcfusion.run import build_cosimulation
    from vcfusion.scenario import load_scenario

    sc = load_scenario(ROOT / path)
    if max_time_s is not None:
        sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": max_time_s})})
    if sensors is not None:
        sc = with_sensors(sc, *sensors)
    result = build_cosimulation(sc, seed).run()
    out = {name: table_hash(result.tables[name]) for name in sorted(result.tables)}
    out["summary"] = hashlib.sha256(json.dumps(result.summary, sort_keys=True, default=repr).encode()).hexdigest()[:16]
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="four runs instead of ten")
    p.add_argument("--vision", action="store_true", help="also 6 s of accident_ar with the full vision tick")
    p.add_argument("--sensors", action="store_true",
                   help="also 6 s of accident_ar with stereo, ToF and LiDAR depth and 0.3 deg pose noise each")
    args = p.parse_args(argv)
    total = hashlib.sha256()
    runs = [(*r, None) for r in (QUICK_RUNS if args.quick else DEFAULT_RUNS) + (VISION_RUNS if args.vision else [])]
    for path, seed, max_time_s, sensors in runs + (SENSOR_RUNS if args.sensors else []):
        hashes = run_hashes(path, seed, max_time_s, sensors)
        line = json.dumps(hashes, sort_keys=True)
        total.update(line.encode())
        given = f", {sensors[0]} depth, {sensors[1]:g} deg" if sensors else ""
        print(f"{path} seed {seed} ({max_time_s or 'full'} s{given}): {line}", flush=True)
    print("total", total.hexdigest()[:16])
    return 0


if __name__ == "__main__":
    sys.exit(main())
