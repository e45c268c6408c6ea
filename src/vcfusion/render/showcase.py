"""Showcase frames for people: RGB beside colourised depth (and box outlines from the instance map).

    python -m vcfusion.render.showcase [--out renders/showcase]

Renders a few fixed moments of scenarios/accident.yaml, scenarios/overlap.yaml and the on-ramp
merge seen from the main line, scenarios/onramp_camera.yaml (seed 0); each scenario is simulated
up to its last shot, and the camera renders only at the shots.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

SHOTS = (("accident.yaml", 0, (3.0, 9.0)), ("overlap.yaml", 0, (4.0,)), ("onramp_camera.yaml", 0, (2.0,)))
PANEL_W = 480


def colourise_depth(depth: np.ndarray, max_m: float = 120.0) -> np.ndarray:
    """Turbo colour map of log depth (near = red, far = blue), sky black; RGB uint8."""
    finite = np.isfinite(depth)
    scaled = np.log1p(np.clip(np.where(finite, depth, max_m), 0, max_m)) / np.log1p(max_m)
    bgr = cv2.applyColorMap((255 * (1 - scaled)).astype(np.uint8), cv2.COLORMAP_TURBO)
    bgr[~finite] = 0
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def panel(frame, boxes) -> np.ndarray:
    rgb = frame.rgb.copy()
    for j in range(len(boxes)):
        x1, y1, x2, y2 = (int(round(v)) for v in boxes.box[j] + [0.5, 0.5, -0.5, -0.5])
        colour = (40, 220, 40) if boxes.visible_fraction[j] >= 0.99 else (255, 200, 0)
        cv2.rectangle(rgb, (x1, y1), (x2, y2), colour, 1)
    both = np.concatenate([rgb, colourise_depth(frame.depth)], axis=1)
    scale = 2 * PANEL_W / both.shape[1]
    return cv2.resize(both, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vcfusion.render.showcase", description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="renders/showcase")
    args = parser.parse_args(argv)
    from vcfusion.cosim import CoSimulation
    from vcfusion.driver.idm import IdmController
    from vcfusion.scenario import load_scenario
    from vcfusion.render.gt_boxes import ground_truth_boxes
    from vcfusion.render.hook import CameraHook
    from vcfusion.resources import scenarios_dir

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for path, seed, times in SHOTS:
        scenario = load_scenario(scenarios_dir() / path)
        scenario = scenario.model_copy(update={"simulation": scenario.simulation.model_copy(
            update={"max_time_s": min(scenario.simulation.max_time_s, max(times) + 0.5)})})

        def keep(frame, tick, scenario=scenario, times=times):
            if any(abs(frame.time - t) < 1e-6 for t in times):
                boxes = ground_truth_boxes(frame, tick.truth, hook.renderer)
                name = out / f"{scenario.name}_seed{seed}_t{frame.time:04.1f}.png"
                cv2.imwrite(str(name), cv2.cvtColor(panel(frame, boxes), cv2.COLOR_RGB2BGR))
                print(name)

        hook = CameraHook(scenario, on_frame=keep,
                          when=lambda tick, times=times: any(abs(tick.time - t) < 1e-6 for t in times))
        CoSimulation(scenario, seed, controller=IdmController.for_scenario(scenario), hooks=[hook]).run()
        hook.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
