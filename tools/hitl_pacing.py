"""A paced drive's display: bench P6's drive (accident_ar seed 0, 640x480, the vision tick in a
worker process, headless, the keyboard idle) at a chosen display rate, with how evenly the frames
were shown.

    python tools/hitl_pacing.py [--fps 60] [--seconds 10] [--in-loop]

Prints the drive's `realtime` block (vcfusion.hitl.driver.realtime_summary) as JSON with the
intervals between shown frames rounded to whole ms, with their counts (60 frames/s over 10-ms
SUMO steps: the frames' flips against their due times, docs/performance.md "On an NVIDIA H200").
On a GPU machine set PYOPENGL_PLATFORM=egl.
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

    from vcfusion.bench import p6_drive_once

    result = p6_drive_once(args.seconds, display_fps=args.fps, vision_pipeline=not args.in_loop)
    frames = result.tables["frames"]
    gaps_ms = 1e3 * np.diff(frames.wall_s[frames.shown].to_numpy())
    rounded, counts = np.unique(np.round(gaps_ms), return_counts=True)
    print(json.dumps({"display_fps": args.fps,
                      "frame_intervals_ms_rounded": {f"{r:.0f}": int(c) for r, c in zip(rounded, counts)},
                      **result.summary["realtime"]}))


if __name__ == "__main__":
    main()
