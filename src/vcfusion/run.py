"""One run of a scenario: wire the stages the scenario asks for, simulate, write the run folder."""

from __future__ import annotations

from pathlib import Path

from vcfusion.cosim import CoSimulation, RunResult
from vcfusion.runio import package_versions, write_run_folder
from vcfusion.scenario import Scenario


def build_cosimulation(scenario: Scenario, seed: int, recorder=None) -> CoSimulation:
    """The co-simulation with every stage the scenario enables."""
    hooks = []
    # (the rendering stage's camera hook goes first: the fusion hook reads its frame)
    if scenario.fusion.enabled:
        from vcfusion.vision.stage import build_fusion_hook

        hooks.append(build_fusion_hook(scenario, seed, recorder))
    return CoSimulation(scenario, seed, hooks=hooks)


def video_dir_for(out_dir: Path) -> Path:
    """Where a run's AR overlay frames and mp4 go: renders/<run folder name>/."""
    return Path("renders") / Path(out_dir).name


def manifest_for(scenario: Scenario, seed: int) -> dict:
    return {
        "scenario": scenario.to_dict() | {"network": scenario.network.name, "vehicle_types": scenario.vehicle_types.name},
        "scenario_file": str(scenario.source) if scenario.source else None,
        "seed": seed,
        "versions": package_versions(),
    }


def execute_run(scenario: Scenario, seed: int, out_dir: Path | None, progress: bool = False) -> RunResult:
    """Simulate one seed; write the run folder when out_dir is given (and the AR video when the
    scenario asks for it: renders/<run folder name>/overlay.mp4 + frames/)."""
    recorder = None
    if out_dir is not None and scenario.fusion.enabled and scenario.ar.video:
        from vcfusion.vision.overlay import OverlayRecorder

        recorder = OverlayRecorder(video_dir_for(out_dir), fps=1.0 / scenario.ar.period_s)
    try:
        result = build_cosimulation(scenario, seed, recorder).run(progress=progress)
        if out_dir is not None:
            write_run_folder(Path(out_dir), result.tables, manifest_for(scenario, seed), result.summary)
    except BaseException:
        if recorder is not None:
            recorder.abort()
        raise
    if recorder is not None:
        recorder.close()
    return result
