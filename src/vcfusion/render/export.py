"""`vcfusion render`: run seeds of a scenario and write a COCO dataset of ego-camera frames.

OUT/
  rgb/seedNNNN_tSSSS.SS.png         RGB
  depth/seedNNNN_tSSSS.SS.png       uint16 camera Z / 0.01 m (0 = sky)
  instances/seedNNNN_tSSSS.SS.png   uint16 instance map (see vcfusion.render.coco)
  annotations.json                  COCO: images with camera K, T_world_to_camera, time and the
                                    vehicles' GNSS anchors; one annotation per visible vehicle
  manifest.json                     scenario, seeds, every, versions
Written into OUT.tmp-writing-PID and renamed when complete.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
from tqdm import tqdm

from vcfusion.cosim import CoSimulation
from vcfusion.driver.idm import IdmController
from vcfusion.runio import atomic_folder, package_versions, write_json
from vcfusion.scenario import Scenario
from vcfusion.records import EGO_ID


def render_dataset(scenario: Scenario, seeds: list[int], every: int, out: Path, progress: bool = True) -> dict:
    """Render every `every`-th V2C tick of each seed into a dataset folder; returns counts."""
    from vcfusion.render.coco import CocoBuilder, depth_to_png16, vehicle_anchors
    from vcfusion.render.gt_boxes import ground_truth_boxes
    from vcfusion.render.hook import CameraHook

    if scenario.ego is None:
        raise ValueError(f"{scenario.source}: ego: the camera rides on the ego; expected an ego block")
    coco = CocoBuilder(f"vcfusion ego-camera frames of scenario {scenario.name}")
    bar = tqdm(total=len(seeds), unit="seed", desc=f"render {scenario.name}", disable=not progress)
    hook = None
    try:
        with atomic_folder(Path(out), "dataset folder") as tmp:
            for sub in ("rgb", "depth", "instances"):
                (tmp / sub).mkdir()
            for seed in seeds:
                def save(frame, tick, seed=seed):
                    stem = f"seed{seed:04d}_t{frame.time:07.2f}"
                    files = {kind: f"{kind}/{stem}.png" for kind in ("rgb", "depth", "instances")}
                    cv2.imwrite(str(tmp / files["rgb"]), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
                    cv2.imwrite(str(tmp / files["depth"]), depth_to_png16(frame.depth))
                    cv2.imwrite(str(tmp / files["instances"]), (frame.instances + 1).astype("uint16"))
                    boxes = ground_truth_boxes(frame, tick.truth, hook.renderer, near=scenario.camera.near_m)
                    coco.add(frame, boxes, vehicle_anchors(frame, tick.truth, EGO_ID), files, extra={"seed": seed})
                    bar.set_postfix(frames=len(coco.images), refresh=False)

                # One renderer (and its scene) for all seeds.
                hook = CameraHook(scenario, every_ticks=every, on_frame=save,
                                  **({"renderer": hook.renderer} if hook is not None else {}))
                CoSimulation(scenario, seed, controller=IdmController.for_scenario(scenario), hooks=[hook]).run()
                bar.update(1)
            bar.close()
            data = coco.to_dict()
            (tmp / "annotations.json").write_text(json.dumps(data))
            write_json(tmp / "manifest.json", {
                "scenario": scenario.to_dict() | {"network": scenario.network.name,
                                                  "vehicle_types": scenario.vehicle_types.name},
                "scenario_file": str(scenario.source) if scenario.source else None,
                "seeds": seeds, "every_ticks": every, "versions": package_versions(),
                "images": len(data["images"]), "annotations": len(data["annotations"]),
            })
    finally:
        if hook is not None:
            hook.close()
    return {"images": len(coco.images), "annotations": len(coco.annotations)}


def progress_default() -> bool:
    return sys.stderr.isatty()
