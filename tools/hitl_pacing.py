"""A paced drive's display: bench P6's drive (accident_ar seed 0, 640x480, the vision tick in a
worker process, headless, the keyboard idle) at a chosen display rate, with how evenly the frames
were shown.

    python tools/hitl_pacing.py [--fps 60] [--seconds 10] [--in-loop]

Prints the drive's `realtime` block (vcfusion.hitl.driver.realtime_summary) as JSON with the
median interval between shown frames and the intervals rounded to whole ms with their counts
(60 frames/s over 10-ms SUMO steps: the frames' flips against their due times,
docs/performance.md "On an NVIDIA H200"). On a GPU machine set PYOPENGL_PLATFORM=egl.
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fps", type=float, default=60.0, help="display frames per second (default 60)")
    parser.add_argument("--seconds", type=float, default=10.0, help="simulated seconds driven (default 10)")
    parser.add_argument("--in-loop", action="store_true", help="the vision tick in the loop's process")
    args = parser.parse_args()

    import torch

    from vcfusion.bench import ACCIDENT_AR
    from vcfusion.hitl.drive import drive
    from vcfusion.scenario import load_scenario

    torch.set_num_threads(2)  # as bench P6
    sc = load_scenario(ACCIDENT_AR)
    sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": args.seconds}),
                               "ar": sc.ar.model_copy(update={"video": False})})
    result = drive(sc, 0, input_spec="keyboard", guidance_on=True, speed=1.0, out_dir=None, headless=True,
                   display_fps=args.fps, start_screen_s=0.0, vision_pipeline=not args.in_loop)
    frames = result.tables["frames"]
    gaps_ms = 1e3 * np.diff(frames.wall_s[frames.shown].to_numpy())
    rounded, counts = np.unique(np.round(gaps_ms), return_counts=True)
    print(json.dumps({"display_fps": args.fps, "frame_interval_ms_p50": round(float(np.median(gaps_ms)), 2),
                      "frame_intervals_ms_rounded": {f"{r:.0f}": int(c) for r, c in zip(rounded, counts)},
                      **result.summary["realtime"]}))


if __name__ == "__main__":
    main()
