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

from tqdm import tqdm

from vcfusion.cosim import CoSimulation
from vcfusion.driver.idm import IdmController
from vcfusion.runio import atomic_folder, package_versions, write_json
from vcfusion.scenario import Scenario
from vcfusion.records import EGO_ID


def _seed_frames(scenario: Scenario, seed: int, every: int, folder: Path, coco, renderer=None, on_frame=None):
    """Run one seed and write every `every`-th V2C tick's frame into `folder`, adding it to `coco`;
    returns the camera hook (its renderer can serve the next seed; the caller closes it)."""
    from vcfusion.render.coco import vehicle_anchors, write_frame_files
    from vcfusion.render.gt_boxes import ground_truth_boxes
    from vcfusion.render.hook import CameraHook

    def save(frame, tick):
        files = write_frame_files(folder, f"seed{seed:04d}_t{frame.time:07.2f}", frame)
        boxes = ground_truth_boxes(frame, tick.truth, hook.renderer, near=scenario.camera.near_m)
        coco.add(frame, boxes, vehicle_anchors(frame, tick.truth, EGO_ID), files, extra={"seed": seed})
        if on_frame is not None:
            on_frame()

    hook = CameraHook(scenario, every_ticks=every, on_frame=save, **({"renderer": renderer} if renderer else {}))
    try:
        CoSimulation(scenario, seed, controller=IdmController.for_scenario(scenario), hooks=[hook]).run()
    except BaseException:
        if renderer is None:  # a renderer handed in is the caller's to close
            hook.close()
        raise
    return hook


def _render_seed_job(scenario: Scenario, seed: int, every: int, folder: str) -> tuple[list[dict], list[dict]]:
    """A worker's seed: its frames into `folder` and their COCO records (ids from 1; the parent renumbers)."""
    from vcfusion.render.coco import CocoBuilder

    coco = CocoBuilder("")
    _seed_frames(scenario, seed, every, Path(folder), coco).close()
    return coco.images, coco.annotations


def render_dataset(scenario: Scenario, seeds: list[int], every: int, out: Path, progress: bool = True,
                   workers: int = 1) -> dict:
    """Render every `every`-th V2C tick of each seed into a dataset folder; returns counts.
    ``workers`` > 1 runs the seeds in that many processes; the folder is the same as one process
    writes (records merged in seed order)."""
    from vcfusion.render.coco import FRAME_KINDS, CocoBuilder
    from vcfusion.workers import results_in_order

    if scenario.ego is None:
        raise ValueError(f"{scenario.source}: ego: the camera rides on the ego; expected an ego block")
    if workers < 1:
        raise ValueError(f"workers: expected at least 1, got {workers}")
    coco = CocoBuilder(f"vcfusion ego-camera frames of scenario {scenario.name}")
    bar = tqdm(total=len(seeds), unit="seed", desc=f"render {scenario.name}", disable=not progress)
    hook = None
    try:
        with atomic_folder(Path(out), "dataset folder") as tmp:
            for sub in FRAME_KINDS:
                (tmp / sub).mkdir()
            if min(workers, len(seeds)) == 1:
                for seed in seeds:
                    # one renderer (and its scene) for all seeds
                    hook = _seed_frames(scenario, seed, every, tmp, coco, hook.renderer if hook else None,
                                        lambda: bar.set_postfix(frames=len(coco.images), refresh=False))
                    bar.update(1)
            else:
                parts = results_in_order(_render_seed_job, [(scenario, s, every, str(tmp)) for s in seeds], workers,
                                         lambda k: f"render: seed {seeds[k]}", lambda k: bar.update(1))
                for images, annotations in parts:  # in seed order: the ids one process gives
                    coco.extend(images, annotations)
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
