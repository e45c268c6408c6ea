"""One run of a scenario: wire the stages the scenario asks for, simulate, write the run folder."""

from __future__ import annotations

from pathlib import Path

from vcfusion.cloud.twins import ProcessModel
from vcfusion.cosim import CoSimulation, RunResult
from vcfusion.runio import package_versions, write_run_folder
from vcfusion.scenario import Scenario


def build_cosimulation(scenario: Scenario, seed: int, *, guidance_enabled: bool | None = None,
                       extra_process_models: list[tuple[str, ProcessModel]] | None = None) -> CoSimulation:
    """The co-simulation with every stage the scenario enables.

    `guidance_enabled` overrides `driver.guidance` of the scenario (the guidance study runs
    both arms of a trip); `extra_process_models` are added to the cloud twins' models.
    """
    from vcfusion.driver.cloud_guidance import CloudGuidanceFallback
    from vcfusion.driver.model import DriverModel
    from vcfusion.driver.params import draw_driver
    from vcfusion.traffic.network import read_road

    process_models = []
    if scenario.prediction.enabled:
        from vcfusion.prediction.cloud import predictor_for_scenario

        process_models.append(("lane_change", predictor_for_scenario(scenario, read_road(scenario.network))))
    process_models += list(extra_process_models or [])
    hooks = []
    if scenario.vision.enabled:
        # Imported only here: traffic-only runs never load OpenGL.
        from vcfusion.vision.hook import CameraHook

        hooks.append(CameraHook(scenario, every_ticks=scenario.vision.every_ticks))
    controller = None
    if scenario.ego is not None:
        road = read_road(scenario.network)
        cfg = scenario.driver
        # Last hook: fills tick.annotations['guidance'] from the cloud only if no overlay did.
        hooks.append(CloudGuidanceFallback(road, cfg.guidance_medium_prob, cfg.guidance_high_prob,
                                           cfg.guidance_view_range_m))
        enabled = cfg.guidance if guidance_enabled is None else guidance_enabled
        controller = DriverModel(draw_driver(seed, scenario.ego.desired_speed_mps), road, scenario.ego.lane, enabled)
    return CoSimulation(scenario, seed, controller=controller, process_models=process_models, hooks=hooks)


def manifest_for(scenario: Scenario, seed: int) -> dict:
    return {
        "scenario": scenario.to_dict() | {"network": scenario.network.name, "vehicle_types": scenario.vehicle_types.name},
        "scenario_file": str(scenario.source) if scenario.source else None,
        "seed": seed,
        "versions": package_versions(),
    }


def execute_run(scenario: Scenario, seed: int, out_dir: Path | None, progress: bool = False) -> RunResult:
    """Simulate one seed; write the run folder when out_dir is given."""
    cosim = build_cosimulation(scenario, seed)
    result = cosim.run(progress=progress)
    if cosim.controller is not None and hasattr(cosim.controller, "p"):
        result.summary["driver"] = cosim.controller.p.to_dict() | {
            "guidance_enabled": cosim.controller.guidance_enabled}
    if out_dir is not None:
        write_run_folder(Path(out_dir), result.tables, manifest_for(scenario, seed), result.summary)
        result.tables.relocate(Path(out_dir))
    return result
