"""Wiring of the vision-cloud fusion stage from a scenario's settings (used by vcfusion.run and
the identification study).

The ego camera frames come from the renderer through one plug: a module
``vcfusion.vision.render`` exposing ``fusion_frame_source(scenario, seed)`` that returns a
:class:`vcfusion.vision.fusion.FrameSource` (a callable tick -> CameraFrame).
"""

from __future__ import annotations

from vcfusion.scenario import Scenario, ScenarioError
from vcfusion.vision.depth_eval import DepthEvalParams
from vcfusion.vision.overlay import OverlayParams, OverlayRecorder


def renderer_frame_source_factory():
    """The renderer's frame-source factory (scenario, seed) -> FrameSource, or a clear error."""
    try:
        from vcfusion.vision import render
    except ImportError as exc:
        raise ScenarioError(f"fusion: needs the ego camera renderer (vcfusion.vision.render), which cannot be "
                            f"imported here: {exc}") from None
    factory = getattr(render, "fusion_frame_source", None)
    if factory is None:
        raise ScenarioError("fusion: vcfusion.vision.render has no fusion_frame_source(scenario, seed)")
    return factory


def build_detector(scenario: Scenario, seed: int):
    from vcfusion.vision.detectors import OracleDetector

    cfg = scenario.fusion
    if cfg.detector == "oracle":
        return OracleDetector()
    from vcfusion.vision.detector_net import DetectorFileError, TorchDetector, default_weights_path

    try:
        return TorchDetector(cfg.weights or default_weights_path())
    except DetectorFileError as exc:
        raise ScenarioError(f"{scenario.source}: fusion.weights: {exc}") from None


def depth_params(scenario: Scenario) -> DepthEvalParams:
    f = scenario.fusion
    return DepthEvalParams(th=f.depth_th, n=f.depth_samples, reducer=f.depth_reducer)


def overlay_params(scenario: Scenario) -> OverlayParams:
    return OverlayParams(medium_threshold=scenario.ar.medium_threshold, high_threshold=scenario.ar.high_threshold)


def build_fusion_hook(scenario: Scenario, seed: int, recorder: OverlayRecorder | None = None, frame_source=None):
    """The tick hook of the fusion stage as the scenario configures it."""
    from vcfusion.vision.fusion import VisionFusionHook

    source = frame_source if frame_source is not None else renderer_frame_source_factory()(scenario, seed)
    return VisionFusionHook(source, build_detector(scenario, seed), seed, method=scenario.fusion.method,
                            depth_params=depth_params(scenario), overlay=overlay_params(scenario),
                            recorder=recorder, period_s=scenario.ar.period_s)
