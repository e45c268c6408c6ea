"""Benchmark of the ego camera: median ms per frame for RGB + depth + instances.

    python -m vcfusion.render.bench [--scenario scenarios/accident.yaml] [--frames 100] [--preset fast]

Simulates one seed of the scenario (traffic only), then renders its states at the scenario's
camera settings (default 640x480) and prints the median, 10th and 90th percentile per frame,
the median CPU time of all threads per frame (for A/B comparisons on a busy machine), and the
median of its parts: the draw pass with read-back (RGB, instances, depth) and the RGB
finish (sky gradient, supersampling for the quality preset, camera model).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vcfusion.render.bench", description=__doc__.splitlines()[0])
    from vcfusion.scenario import SHIPPED_SCENARIOS

    parser.add_argument("--scenario", default=str(SHIPPED_SCENARIOS / "accident.yaml"))
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", choices=("fast", "quality"), help="render preset (default: the scenario's)")
    args = parser.parse_args(argv)

    from vcfusion.cosim import CoSimulation
    from vcfusion.driver.idm import IdmController
    from vcfusion.errors import UsageError
    from vcfusion.scenario import load_scenario
    from vcfusion.render.renderer import EgoCameraRenderer

    if args.frames < 1:
        raise UsageError(f"--frames: expected a positive number of frames, got {args.frames}")
    scenario = load_scenario(args.scenario)
    if scenario.ego is None:
        raise UsageError(f"{args.scenario}: ego: the camera rides on the ego; the scenario has no ego block")
    states = []

    class Collect:
        table = "bench"

        def __call__(self, tick):
            states.append(tick.truth)

    CoSimulation(scenario, args.seed, controller=IdmController.for_scenario(scenario), hooks=[Collect()]).run()
    states = [s for s in states if "ego" in s.ids]
    picks = [states[i] for i in np.linspace(0, len(states) - 1, args.frames).astype(int)]
    camera = scenario.camera if args.preset is None else scenario.camera.model_copy(update={"render_preset": args.preset})
    renderer = EgoCameraRenderer.for_scenario(scenario, camera)
    renderer.render(picks[0])  # warm-up: shader compilation, buffer uploads
    times, cpu, seen, parts = [], [], [], []
    for truth in picks:
        t0, c0 = time.perf_counter(), time.process_time()
        frame = renderer.render(truth)
        times.append(1000.0 * (time.perf_counter() - t0))
        cpu.append(1000.0 * (time.process_time() - c0))
        seen.append(int((np.unique(frame.instances) >= 0).sum()))
        parts.append(renderer.last_timings_ms)
    renderer.close()
    ms = np.array(times)
    cam = camera
    print(f"ego camera {cam.width_px}x{cam.height_px}, preset {cam.render_preset}, {len(ms)} frames of {scenario.name} seed {args.seed} "
          f"(PYOPENGL_PLATFORM={os.environ.get('PYOPENGL_PLATFORM')}, {os.cpu_count()} CPUs, "
          f"{np.mean(seen):.1f} vehicles seen per frame)")
    print(f"RGB + depth + instances: median {np.median(ms):.1f} ms/frame "
          f"(p10 {np.percentile(ms, 10):.1f}, p90 {np.percentile(ms, 90):.1f})")
    # CPU time of all the process's threads (llvmpipe's too): steadier than wall time on a busy
    # machine, so A/B comparisons of two versions can use it there.
    print(f"  CPU time: median {np.median(cpu):.1f} ms/frame (all threads)")
    print("  parts (median ms): " + ", ".join(f"{k} {np.median([p[k] for p in parts]):.1f}" for k in parts[0]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
