"""Benchmark of the ego camera: median ms per frame for RGB + depth + instances.

    vcfusion bench-render [--scenario accident] [--frames 100] [--seed 0] [--preset fast]

Simulates one seed of the scenario (traffic only), then renders its states at the scenario's
camera settings (default 640x480) and prints the median, 10th and 90th percentile per frame,
the median CPU time of all threads per frame (for A/B comparisons on a busy machine), the median
CPU time of the calling thread (pyrender, PyOpenGL and the read-back: what a GPU does not take
over; under OSMesa also llvmpipe's work on that thread), and the median of its parts: the draw
pass with read-back (RGB, instances, depth) and the RGB finish (sky gradient, supersampling for
the quality preset, camera model).
"""

from __future__ import annotations

import os
import time

import numpy as np


def bench_render(scenario, frames: int, seed: int = 0, preset: str | None = None) -> str:
    """Simulate `seed` of the scenario (traffic only), render `frames` of its states evenly spread
    over the run, and return the report (`vcfusion bench-render` prints it)."""
    from vcfusion.cosim import CoSimulation
    from vcfusion.driver.idm import IdmController
    from vcfusion.render.renderer import EgoCameraRenderer

    states = []

    class Collect:
        table = "bench"

        def __call__(self, tick):
            states.append(tick.truth)

    CoSimulation(scenario, seed, controller=IdmController.for_scenario(scenario), hooks=[Collect()]).run()
    states = [s for s in states if "ego" in s.ids]
    picks = [states[i] for i in np.linspace(0, len(states) - 1, frames).astype(int)]
    camera = scenario.camera if preset is None else scenario.camera.model_copy(update={"render_preset": preset})
    renderer = EgoCameraRenderer.for_scenario(scenario, camera)
    renderer.render(picks[0])  # warm-up: shader compilation, buffer uploads
    times, cpu, own, seen, parts = [], [], [], [], []
    for truth in picks:
        t0, c0, h0 = time.perf_counter(), time.process_time(), time.thread_time()
        frame = renderer.render(truth)
        times.append(1000.0 * (time.perf_counter() - t0))
        cpu.append(1000.0 * (time.process_time() - c0))
        own.append(1000.0 * (time.thread_time() - h0))
        seen.append(int((np.unique(frame.instances) >= 0).sum()))
        parts.append(renderer.last_timings_ms)
    renderer.close()
    ms = np.array(times)
    cam = camera
    lines = [f"ego camera {cam.width_px}x{cam.height_px}, preset {cam.render_preset}, {len(ms)} frames of "
             f"{scenario.name} seed {seed} (PYOPENGL_PLATFORM={os.environ.get('PYOPENGL_PLATFORM')}, {os.cpu_count()} CPUs, "
             f"{np.mean(seen):.1f} vehicles seen per frame)",
             f"RGB + depth + instances: median {np.median(ms):.1f} ms/frame "
             f"(p10 {np.percentile(ms, 10):.1f}, p90 {np.percentile(ms, 90):.1f})"]
    # CPU time of all the process's threads (llvmpipe's too): steadier than wall time on a busy
    # machine, so A/B comparisons of two versions can use it there.
    lines.append(f"  CPU time: median {np.median(cpu):.1f} ms/frame (all threads), {np.median(own):.1f} ms/frame "
                 f"(the calling thread)")
    lines.append("  parts (median ms): " + ", ".join(f"{k} {np.median([p[k] for p in parts]):.1f}" for k in parts[0]))
    return "\n".join(lines)

