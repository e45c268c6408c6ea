"""One run of a scenario: wire the stages the scenario asks for, simulate, write the run folder."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from vcfusion.cloud.twins import ProcessModel
from vcfusion.cosim import CoSimulation, RunResult
from vcfusion.guidance import GuidancePolicy
from vcfusion.resources import default_box_head_path, default_weights_path
from vcfusion.runio import package_versions, video_staging_prefix, write_run_folder
from vcfusion.scenario import Scenario


def build_cosimulation(scenario: Scenario, seed: int, *, guidance_enabled: bool | None = None,
                       extra_process_models: list[tuple[str, ProcessModel]] | None = None,
                       recorder=None, renderer=None, detector=None, fusion_hook=None) -> CoSimulation:
    """The co-simulation with every stage the scenario enables.

    `guidance_enabled` overrides `driver.guidance` of the scenario (the guidance study runs
    both arms of a trip); `extra_process_models` are added to the cloud twins' models;
    `recorder` receives the AR overlay frames (video). `renderer` / `detector`: a camera renderer
    and a detector to reuse (a study's worker keeps them loaded across trips; the caller closes
    the renderer); by default the camera and fusion stages make their own. `fusion_hook`: a fusion
    stage to run in place of the scenario's (a paced drive's, vcfusion.hitl.pipeline).
    """
    from vcfusion.traffic.network import read_road

    road = read_road(scenario.network, scenario.route)
    process_models = []
    if scenario.prediction.enabled:
        from vcfusion.prediction.cloud import predictor_for_scenario

        process_models.append(("lane_change", predictor_for_scenario(scenario, road)))
    process_models += list(extra_process_models or [])
    hooks = []
    controller = None
    # One guidance policy (thresholds, "ahead", lanes, ego id) for the overlay, the cloud guidance
    # and the driver (vcfusion.guidance).
    policy = GuidancePolicy.from_scenario(scenario, road) if scenario.ego is not None else None
    if scenario.vision.enabled:
        # Imported only here: traffic-only runs never load OpenGL.
        from vcfusion.render.hook import CameraHook

        when = None
        if scenario.vision.only_when_warning and policy is not None:
            def when(tick, policy=policy):
                return policy.any_warning(tick.neighbours)
        hooks.append(CameraHook(scenario, every_ticks=scenario.vision.every_ticks, renderer=renderer, when=when))
    if fusion_hook is not None:
        hooks.append(fusion_hook)
    elif scenario.fusion.enabled:
        from vcfusion.fusion.stage import build_fusion_hook

        hooks.append(build_fusion_hook(scenario, seed, policy, recorder, detector=detector))
    if scenario.ego is not None:
        from vcfusion.driver.cloud_guidance import CloudGuidanceFallback
        from vcfusion.driver.model import DriverModel
        from vcfusion.driver.params import draw_driver
        from vcfusion.driver.perception import DriverView

        # with vision fusion the overlay is the only source: the stage logs it (a tick without a
        # frame is counted, never filled from the cloud)
        hooks.append(CloudGuidanceFallback(road, policy, camera=scenario.fusion.enabled))
        enabled = scenario.driver.guidance if guidance_enabled is None else guidance_enabled
        if scenario.ego.controller is not None:  # the scenario's own controller (vcfusion.control)
            from vcfusion.control import ControllerContext, ControllerStage, load_controller

            controller = ControllerStage(load_controller(scenario.ego.controller, dict(scenario.ego.controller_params)),
                                         ControllerContext(scenario, seed, road, enabled))
        else:
            controller = DriverModel(draw_driver(seed, scenario.ego.desired_speed_mps), road, policy, enabled,
                                     view=DriverView.from_scenario(scenario))
    # The order above is what the stages declare they need (checked here, see vcfusion.stages):
    # camera -> fusion (reads tick.frame) -> guidance log (without fusion: the cloud guidance,
    # filling tick.guidance) -> driver (reads tick.guidance).
    return CoSimulation(scenario, seed, controller=controller, process_models=process_models, hooks=hooks)


def _sha256(path: Path) -> str:
    import hashlib

    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def input_files(scenario: Scenario) -> dict[str, Path]:
    """The files a run of the scenario reads besides the scenario itself: the network, the vehicle
    types, and the models that shape its results (the lane-change model, the detector's weights),
    shipped defaults included (another release ships other weights)."""
    files = {"network": scenario.network, "vehicle_types": scenario.vehicle_types}
    if scenario.prediction.enabled:
        from vcfusion.prediction.model import default_model_path

        files["prediction_model"] = scenario.prediction.model or default_model_path()
    if scenario.fusion.enabled and scenario.fusion.detector != "oracle":
        files["detector_weights"] = scenario.fusion.weights or default_weights_path()
    if scenario.fusion.enabled and scenario.fusion.refine_boxes:
        files["box_head_weights"] = default_box_head_path()  # the depth step's far-box head
    return files


def scenario_record(scenario: Scenario) -> dict:
    """The manifest's `scenario`: the resolved scenario (the file merged over the files it extends,
    defaults filled in), its network and vehicle-types files by name."""
    return scenario.to_dict() | {"network": scenario.network.name, "vehicle_types": scenario.vehicle_types.name}


def manifest_for(scenario: Scenario, seed: int) -> dict:
    return {
        "scenario": scenario_record(scenario),
        # the files it names, by content: a network rebuilt under the same name (e.g. with other lane
        # widths) makes other runs, which a batch or dataset must not resume into
        "files_sha256": {name: _sha256(path) for name, path in input_files(scenario).items()},
        "scenario_file": str(scenario.source) if scenario.source else None,
        # the file given and the files it extends, in that order (one file when it extends none)
        "scenario_chain": [str(p) for p in scenario.chain],
        "seed": seed,
        "versions": package_versions(),
    }


def execute_run(scenario: Scenario, seed: int, out_dir: Path | None, progress: bool = False) -> RunResult:
    """Simulate one seed; write the run folder when out_dir is given, with the AR video in it when
    the scenario asks for it (overlay.mp4 + frames/): the folder is whole or absent."""
    recorder, staging = None, None
    if out_dir is not None and scenario.fusion.enabled and scenario.ar.video:
        from vcfusion.fusion.overlay import OverlayRecorder

        out_dir = Path(out_dir)
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        # beside the run folder (same file system: moved in, not copied); removed whatever happens
        # (what killed writers of this folder left goes when the folder is written: atomic_folder)
        staging = Path(tempfile.mkdtemp(prefix=video_staging_prefix(out_dir), dir=out_dir.parent))
        recorder = OverlayRecorder(staging / "video", fps=1.0 / scenario.overlay_period_s())
    try:
        result = build_cosimulation(scenario, seed, recorder=recorder).run(progress=progress)
        if out_dir is not None:
            video = {}
            if recorder is not None:
                folder = recorder.close()
                recorder = None
                video = {name: folder / name for name in ("overlay.mp4", "frames") if (folder / name).exists()}
            write_run_folder(Path(out_dir), result.tables, manifest_for(scenario, seed), result.summary,
                             extra_files=video)
            result.tables.relocate(Path(out_dir))
    finally:
        if recorder is not None:
            recorder.abort()
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
    return result
