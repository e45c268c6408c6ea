"""Wiring of the vision-cloud fusion stage to the renderer and to a scenario's settings.

The ego camera frames come from the rendering stage: in a run, its camera hook (scenario
``vision.enabled``) sets ``tick.frame`` to a rendered ``Frame`` (rgb, depth, instances,
vehicle_ids, K, T_world_to_camera); the fusion hook, which declares that it needs ``frame``
(checked when the run is built), reads it through :func:`tick_frame_source`, which turns it into a
:class:`CameraFrame` (ground-truth boxes from the instance map, a :class:`CameraView` from K and T). The identification study renders its frames
itself through :class:`RenderedFrameSources` (one renderer reused over all runs).
"""

from __future__ import annotations

import math

import numpy as np

from vcfusion.fusion.depth_eval import DepthEvalParams
from vcfusion.fusion.fuse import CameraFrame
from vcfusion.fusion.matching import CameraView, JointMatcherParams
from vcfusion.fusion.overlay import OverlayRecorder
from vcfusion.fusion.road import DepthNoise
from vcfusion.guidance import GuidancePolicy
from vcfusion.records import EGO_ID
from vcfusion.scenario import Scenario, ScenarioError


def camera_view(K: np.ndarray, T_world_to_camera: np.ndarray, width: int, height: int, time: float) -> CameraView:
    """The matchers' view of a camera given by its intrinsics and OpenCV extrinsics."""
    from vcfusion.render.camera import project_points  # the rendering stage's projection (eq. 1-3)

    K = np.asarray(K, dtype=float)
    T = np.asarray(T_world_to_camera, dtype=float)

    def project(points):
        p = project_points(points, K, T, width, height)
        return p.uv, p.depth

    position = -T[:3, :3].T @ T[:3, 3]
    return CameraView(project=project, position=position, width=int(width), height=int(height), time=float(time),
                      K=K, T_world_to_camera=T)


# the stream of a run's Generator that draws its sensor errors (vcfusion.fusion.sensors)
SENSOR_STREAM = 48


def run_sensors(scenario: Scenario, seed: int):
    """The run's depth sensor and pose error (vcfusion.fusion.sensors), None when exact."""
    from vcfusion.fusion.sensors import SensorModel

    return SensorModel.for_camera(scenario.camera, np.random.default_rng([seed, SENSOR_STREAM]))


def frame_from_render(frame, truth, sensors=None) -> CameraFrame:
    """A rendered frame (vcfusion.render.renderer.Frame) of the traffic state ``truth`` as a
    CameraFrame; with ``sensors`` (a SensorModel) the depth image and camera pose are the sensor's
    (the one place where they are applied); the ground truth (boxes, instances) stays the render's."""
    from vcfusion.render.coco import category_id
    from vcfusion.render.gt_boxes import ground_truth_boxes

    gt = ground_truth_boxes(frame, truth)
    depth, T = frame.depth, frame.T_world_to_camera
    noise = DepthNoise()
    if sensors is not None:
        noise = sensors.noise(frame.K)
        i = truth.index_of(EGO_ID) if EGO_ID in truth.ids else None
        depth = sensors.depth(frame.depth, frame.K, T, frame.rgb)
        T = sensors.believed_pose(T, float(frame.time), *((float(truth.accel[i]), float(truth.speed[i]),
                                                           float(truth.heading[i])) if i is not None else ()))
    return CameraFrame(time=float(frame.time), image=frame.rgb, depth=depth,
                       camera=camera_view(frame.K, T, frame.width, frame.height, frame.time),
                       gt_boxes=np.asarray(gt.box, dtype=float).reshape(-1, 4), gt_ids=tuple(gt.vehicle_ids),
                       gt_patches=np.asarray(gt.patch, dtype=float).reshape(-1, 4),
                       gt_visible_share=gt.visible_share,
                       gt_classes=np.array([category_id(c) for c in gt.vclass], dtype=np.int64),
                       instances=frame.instances, instance_ids=tuple(frame.vehicle_ids), depth_noise=noise)


def tick_frame_source(tick) -> CameraFrame | None:
    """The frame the camera stage put on this tick (None at ticks without one)."""
    frame = tick.frame
    if frame is None or isinstance(frame, CameraFrame):
        return frame
    return frame_from_render(frame, tick.truth)


class SensedTickFrames:
    """The camera stage's frames as the run's sensors deliver them (vcfusion.fusion.sensors)."""

    reads_tick_frame = True

    def __init__(self, sensors):
        self.sensors = sensors

    def __call__(self, tick) -> CameraFrame | None:
        frame = tick.frame
        if frame is None or isinstance(frame, CameraFrame):
            return frame
        return frame_from_render(frame, tick.truth, self.sensors)


class RenderedFrameSources:
    """Frame sources for the study's runs: (scenario, seed) -> (tick -> CameraFrame), all rendered
    by one renderer (building its scene and GL context once), rebuilt only when a scenario's road or
    camera differs from the previous one's. Call :meth:`close` at the end."""

    def __init__(self):
        self._renderer = None
        self._key = None

    def __call__(self, scenario: Scenario, seed: int):
        key = (str(scenario.network), scenario.route, scenario.ego and scenario.ego.route,
               scenario.camera.model_dump_json())
        if self._renderer is not None and key != self._key:
            self.close()
        self._key = key
        if self._renderer is None:
            try:
                from vcfusion.render.renderer import EgoCameraRenderer
            except ImportError as exc:
                raise ScenarioError(f"the ego camera renderer cannot be loaded: {exc}") from None
            self._renderer = EgoCameraRenderer.for_scenario(scenario)
        renderer = self._renderer
        sensors = run_sensors(scenario, seed)

        def source(tick):
            if tick.ego is None:
                return None
            return frame_from_render(renderer.render(tick.truth), tick.truth, sensors)

        return source

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def build_detector(scenario: Scenario, seed: int):
    from vcfusion.detection.detectors import OracleDetector

    cfg = scenario.fusion
    if cfg.detector == "oracle":
        return OracleDetector()
    from vcfusion.detection.detector_net import DetectorFileError, OnnxDetector, TorchDetector, default_weights_path

    try:
        if cfg.detector == "onnx-yolo":
            return OnnxDetector.ultralytics(cfg.weights, tuple(cfg.yolo_input_px), cfg.yolo_classes)
        from vcfusion.accel import torch_device

        device = torch_device(cfg.device, f"{scenario.source}: fusion.device")
        return TorchDetector(cfg.weights or default_weights_path(), device=device)
    except DetectorFileError as exc:
        raise ScenarioError(f"{scenario.source}: fusion.weights: {exc}") from None


def depth_params(scenario: Scenario) -> DepthEvalParams:
    f = scenario.fusion
    return DepthEvalParams(th=f.depth_th, n=f.depth_samples, reducer=f.depth_reducer)


def road_model(road: str, depth: str, pose_error: bool) -> str:
    """The depth step's road, "auto" resolved: the nominal pose's flat road where depth and pose are
    exact (the renderer's road is that plane; a fit only adds its own error: held-out family
    high_mount 97.5 % flat vs 96.3 % fitted), the road fitted to each depth image otherwise (0.3 deg
    of pose error: 75.3 % flat vs 95.1 % fitted; docs/components/fusion.md)."""
    if road != "auto":
        return road
    return "flat" if depth == "exact" and not pose_error else "from_depth"


def scenario_road(scenario: Scenario) -> str:
    """road_model of a scenario's fusion.road, camera.depth and camera.pose_noise."""
    pose = scenario.camera.pose_noise
    return road_model(scenario.fusion.road, scenario.camera.depth, pose.mount_std_deg > 0 or pose.body_motion)


def refine_params(scenario: Scenario):
    """The depth-guided box refinement of the scenario's detector boxes, or None when switched off."""
    from vcfusion.fusion.box_refine import BoxRefineParams

    return BoxRefineParams(road=scenario_road(scenario)) if scenario.fusion.refine_boxes else None


# the most a vehicle's centre lies beyond the range at which guidance measures it (its rear bumper,
# from the ego's front bumper) plus the ego's half length: a 12 m truck's length (sumo_net/vtypes)
VEHICLE_SPAN_M = 12.0


def matching_reach_m(view_range_m: float, params: JointMatcherParams = JointMatcherParams()) -> float:
    """How far from the ego a vehicle can be and its box still pass the joint matcher's depth gate
    for a twin that guidance draws (at most `view_range_m` ahead): the range plus the gate at that
    range (depth_gate sigmas of depth_sigma_rel * range + depth_sigma_abs_m) plus `VEHICLE_SPAN_M`.
    A vehicle within this reach that is not among the ego's neighbour twins has a box no twin claims,
    and the matcher gives it to a warned twin beside it (an accident's trucks at 184 m took the
    warnings of the cars queued before them at 150-165 m, curved.yaml seed 0, neighbour range 150 m)."""
    r = view_range_m + VEHICLE_SPAN_M
    return r + params.depth_gate * (params.depth_sigma_rel * r + params.depth_sigma_abs_m)


def require_matching_range(scenario: Scenario) -> None:
    """ScenarioError unless the ego's neighbour twins (v2c.neighbour_range_m) cover every vehicle
    whose box the matcher could give to a twin guidance draws (`matching_reach_m`)."""
    reach = matching_reach_m(scenario.driver.guidance_view_range_m)
    if scenario.v2c.neighbour_range_m < reach:
        raise ScenarioError(
            f"{scenario.source or scenario.name}: v2c.neighbour_range_m: expected at least {math.ceil(reach):d} m "
            f"with the camera fusing (driver.guidance_view_range_m {scenario.driver.guidance_view_range_m:g} m plus "
            f"the joint matcher's depth gate at that range and a vehicle's length), got "
            f"{scenario.v2c.neighbour_range_m:g} m: the boxes of vehicles beyond the neighbour range, which no twin "
            "claims, would be matched to the warned twins beside them")


def build_fusion_hook(scenario: Scenario, seed: int, policy: GuidancePolicy, recorder: OverlayRecorder | None = None,
                      frame_source=None, detector=None):
    """The tick hook of the fusion stage as the scenario configures it, levelling guidance by the
    run's `policy`. Without `frame_source` it reads ``tick.frame`` (it then needs the camera hook
    before it: the run refuses another order)."""
    from vcfusion.fusion.fuse import VisionFusionHook

    require_matching_range(scenario)
    if frame_source is None:
        sensors = run_sensors(scenario, seed)
        frame_source = SensedTickFrames(sensors) if sensors is not None else None
    return VisionFusionHook(frame_source, detector or build_detector(scenario, seed), seed, policy,
                            method=scenario.fusion.method, depth_params=depth_params(scenario),
                            recorder=recorder, period_s=scenario.ar.period_s,
                            only_when_warning=scenario.vision.only_when_warning,
                            refine=refine_params(scenario))
