"""One run of a scenario: wire the stages the scenario asks for, simulate, write the run folder."""

from __future__ import annotations

from pathlib import Path

from vcfusion.cosim import CoSimulation, RunResult
from vcfusion.runio import package_versions, write_run_folder
from vcfusion.scenario import Scenario


def build_cosimulation(scenario: Scenario, seed: int) -> CoSimulation:
    """The co-simulation with every stage the scenario enables."""
    process_models = []
    if scenario.prediction.enabled:
        from vcfusion.prediction.cloud import predictor_for_scenario
        from vcfusion.traffic.network import read_road

        process_models.append(("lane_change", predictor_for_scenario(scenario, read_road(scenario.network))))
    return CoSimulation(scenario, seed, process_models=process_models)


def manifest_for(scenario: Scenario, seed: int) -> dict:
    return {
        "scenario": scenario.to_dict() | {"network": scenario.network.name, "vehicle_types": scenario.vehicle_types.name},
        "scenario_file": str(scenario.source) if scenario.source else None,
        "seed": seed,
        "versions": package_versions(),
    }


def execute_run(scenario: Scenario, seed: int, out_dir: Path | None, progress: bool = False) -> RunResult:
    """Simulate one seed; write the run folder when out_dir is given."""
    result = build_cosimulation(scenario, seed).run(progress=progress)
    if out_dir is not None:
        write_run_folder(Path(out_dir), result.tables, manifest_for(scenario, seed), result.summary)
    return result
