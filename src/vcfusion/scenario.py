"""Scenario files: schema, loading and validation.

A scenario is a YAML file. Every field is checked on load, and so is every file it names (the
network, the vehicle types, the lane-change model, the detector weights): a scenario that loads
can run. A bad file raises :class:`ScenarioError` whose message names the file, the field and
what was expected.

`extends: base.yaml` merges the file over its base (mappings merge key by key, any other value,
lists included, replaces the base's); a base may extend another. Paths inside a scenario
(network, vehicle types, model files, the base) are relative to the file that names them.
"""

from __future__ import annotations

import math
import re
import typing
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import (BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, field_validator, model_serializer,
                      model_validator)

from vcfusion.errors import ScenarioError  # the loader's error; importable from here as before
from vcfusion.fusion import sensors as _sensors


NonNegative = Annotated[float, Field(ge=0.0)]


class _NumberText:
    """A number YAML read from a plain scalar, with the text it was written as: an id such as an
    OSM edge `123456` or `0123` is text to SUMO, and str(number) would lose a leading zero."""

    text: str


class _IntWithText(int, _NumberText):
    pass


class _FloatWithText(float, _NumberText):
    pass


def _id_text(value):
    """An id (edge, vType, group, scenario name) written without quotes is the text written: YAML
    reads `123` or `1.5` as numbers, which SUMO's ids are not."""
    if isinstance(value, _NumberText):
        return value.text
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    return value


# An id of SUMO's (edge, vType) or of the scenario's (group, name): text, even when it looks like a number.
Name = Annotated[str, BeforeValidator(_id_text), Field(min_length=1)]
# A route: edge ids of the network in driving order (vcfusion.traffic.roadframe).
Route = Annotated[list[Name], Field(min_length=1)]
Positive = Annotated[float, Field(gt=0.0)]
Probability = Annotated[float, Field(ge=0.0, le=1.0)]


class _Strict(BaseModel):
    # no inf or nan: a period or a time that never ends
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SimulationConfig(_Strict):
    """SUMO's clock and the trajectory log."""

    step_s: Positive = Field(0.01, description="SUMO step; a whole number of milliseconds, at least 0.001 s "
                                               "(SUMO's time resolution)")
    max_time_s: Positive = Field(120.0, description="simulated time after which the run ends")
    lanechange_duration_s: Positive = Field(3.0, description="SUMO --lanechange.duration: a lane change takes "
                                                             "this long instead of one step")
    trajectory_period_s: Positive = Field(0.1, description="period of the all-vehicle trajectory table (the ego "
                                                           "is also logged every SUMO step); at most 1 s with "
                                                           "metrics enabled")

    @field_validator("step_s")
    @classmethod
    def _whole_milliseconds(cls, v: float) -> float:
        # SUMO keeps time in milliseconds: it rounds another step (0.0015 s runs as 0.002 s) and
        # refuses one under 1 ms, and every time stamp here would disagree with SUMO's
        if v < 0.001 - 1e-12 or abs(v * 1000 - round(v * 1000)) > 1e-6:
            raise ValueError("expected a whole number of milliseconds, at least 0.001 (SUMO's time resolution)")
        return v


class V2CConfig(_Strict):
    """Vehicle-to-cloud channel (uplink GNSS reports) and the cloud's twin store."""

    period_s: Positive = Field(0.1, description="period of the GNSS reports and of the cloud's tick")
    latency_s: NonNegative = Field(0.0, description="uplink latency of a report")
    jitter_s: NonNegative = Field(0.0, description="standard deviation of a zero-mean Gaussian added to the "
                                                   "latency (clipped at 0)")
    loss_probability: Probability = Field(0.0, description="probability that a report is lost")
    gnss_noise_std_m: NonNegative = Field(0.0, description="standard deviation of the GNSS position error, "
                                                           "per horizontal axis")
    history_s: Annotated[float, Field(ge=30.0)] = Field(30.0, description="history each twin keeps in the cloud")
    twin_timeout_s: Positive = Field(3.0, description="a twin with no report for this long is gone (vehicle "
                                                      "left the road); more than latency_s + 3 jitter_s + "
                                                      "period_s")
    # with the camera fusing, at least vcfusion.fusion.stage.matching_reach_m(driver.guidance_view_range_m)
    # (199 m for 150 m), so that every vehicle whose box the matcher could give to a warned twin has a
    # twin of its own (curved.yaml seed 0: trucks at 184 m took the warnings of the cars before them)
    neighbour_range_m: Positive = Field(200.0, description="the ego receives the twins within this horizontal "
                                                           "range; with the camera fusing at least the joint "
                                                           "matcher's reach (199 m for a 150 m guidance view)")

    @model_validator(mode="after")
    def _timeout_outlasts_latency(self) -> "V2CConfig":
        # the timeout counts from the newest report's measurement time, and a report is latency (plus
        # jitter) old when it arrives: with less room every twin would vanish, or flicker, on arrival
        oldest = self.latency_s + 3.0 * self.jitter_s + self.period_s
        if self.twin_timeout_s <= oldest:
            raise ValueError(f"v2c.twin_timeout_s: expected more than latency_s + 3 jitter_s + period_s ({oldest:g} s: "
                             f"the age of a report when the next one is due), got {self.twin_timeout_s:g}")
        return self


class AROverlayConfig(_Strict):
    """The AR overlay and the guidance levels (vcfusion.guidance)."""

    period_s: Positive = Field(0.1, description="period of the AR updates; a whole multiple of v2c.period_s "
                                                "with fusion enabled")
    # why 0.3 / 0.6: the module doc of vcfusion.guidance
    medium_threshold: Probability = Field(0.3, description="calibrated lane-change probability at or above "
                                                           "which a flagged neighbour is yellow (medium), for the "
                                                           "overlay, the cloud guidance and the driver alike; at "
                                                           "most high_threshold")
    high_threshold: Probability = Field(0.6, description="calibrated lane-change probability at or above which "
                                                         "a flagged neighbour is red (high)")
    video: bool = Field(False, description="write the AR overlay as PNG frames and an mp4 into the run folder "
                                           "(needs fusion.enabled and vision.only_when_warning: false)")

    @model_validator(mode="after")
    def _ordered(self) -> "AROverlayConfig":
        if self.medium_threshold > self.high_threshold:
            raise ValueError(f"ar.medium_threshold: expected <= ar.high_threshold ({self.high_threshold}), "
                             f"got {self.medium_threshold}")
        return self


class FusionConfig(_Strict):
    """Vision-cloud fusion: detector, depth evaluation (Algorithm 1) and twin-to-box matching."""

    enabled: bool = Field(False, description="run the fusion stage (needs vision.enabled)")
    detector: Literal["cnn", "oracle", "onnx-yolo"] = Field("cnn", description="cnn: the shipped CNN (or "
                                                            "weights); oracle: ground-truth boxes; onnx-yolo: a "
                                                            "YOLO exported by Ultralytics to ONNX")
    weights: Path | None = Field(None, description="weights of the cnn detector (relative to the scenario file; "
                                                   "null: the shipped model); the ONNX file with onnx-yolo "
                                                   "(required there, read by OpenCV DNN); none with oracle")
    yolo_input_px: tuple[Annotated[int, Field(ge=32, le=4096)], Annotated[int, Field(ge=32, le=4096)]] = Field(
        (640, 640), description="onnx-yolo only: the model's input size (width, height)")
    yolo_classes: Annotated[tuple[str, ...], Field(min_length=1)] = Field(
        ("car", "bus", "truck"), description="onnx-yolo only: the COCO classes kept as vehicles")
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="where the cnn detector runs: auto (CUDA when "
                                                   "torch finds a GPU, else the CPU), cpu or cuda (refused where "
                                                   "there is no GPU); `vcfusion --device` overrides it")
    method: Literal["baseline", "baseline_centre", "paper", "joint"] = Field(
        "joint", description="twin-to-box matching: baseline (the paper's RGB-only rule), baseline_centre "
                             "(nearest box centre), paper (Algorithm 2), joint (the joint matcher)")
    refine_boxes: bool = Field(True, description="snap the detector's boxes to the vehicle surfaces of the depth "
                                                 "image before matching and add boxes for vehicles it missed, "
                                                 "from depth segments (vcfusion.fusion.box_refine; never the "
                                                 "oracle's); false: the detector's RGB boxes as they are")
    road: Literal["auto", "flat", "from_depth"] = Field(
        "auto", description="heights above the road for the depth step: from_depth (the road plane fitted to each "
                            "depth image; the nominal pose's flat road where the fit fails, counted), flat (the "
                            "nominal pose's flat road at z = 0), auto (flat with camera.depth exact and no "
                            "camera.pose_noise, from_depth otherwise)")
    depth_th: Annotated[float, Field(gt=0.0, le=1.0)] = Field(0.8, description="Algorithm 1: each box side is "
                                                                              "scaled by this about the centre "
                                                                              "before depth sampling")
    depth_samples: Annotated[int, Field(ge=1)] = Field(30, description="Algorithm 1: depth pixels drawn in the "
                                                                      "box's lower quarter")
    depth_reducer: Literal["mean", "median"] = Field("mean", description="Algorithm 1: how the samples become "
                                                                         "the box's depth (the paper: mean)")

    @model_validator(mode="after")
    def _detector_settings(self) -> "FusionConfig":
        if self.detector == "onnx-yolo":
            if self.weights is None:
                raise ValueError("weights: expected the ONNX file of the YOLO model with detector: onnx-yolo")
            from vcfusion.detection.detectors import coco_column_categories

            coco_column_categories(self.yolo_classes)  # names checked here, with the known ones in the message
        # a setting the chosen detector never reads was ignored silently: a run with `detector: oracle`
        # and a weights file looked like a run of those weights
        if self.detector == "oracle" and self.weights is not None:
            raise ValueError("weights: the oracle detector reads no weights file (it boxes the ground truth); "
                             "expected no weights with detector: oracle, or detector: cnn / onnx-yolo")
        # by value, not by what was written: a run's manifest holds every field, defaults included
        unread = [name for name in ("yolo_input_px", "yolo_classes")
                  if getattr(self, name) != type(self).model_fields[name].default]
        if self.detector != "onnx-yolo" and unread:
            raise ValueError(f"{unread[0]}: read only with detector: onnx-yolo (this scenario's detector is "
                             f"{self.detector}); expected no {' / '.join(unread)} here")
        return self


_DEPTH = _sensors.DepthSensorParams()
_POSE = _sensors.PoseNoiseParams()


class DepthSensorConfig(_Strict):
    """Parameters of the depth sensor models (vcfusion.fusion.sensors: rule, unit and source of each)."""

    baseline_m: Positive = Field(_DEPTH.baseline_m, description="stereo baseline")
    disparity_noise_px: NonNegative = Field(_DEPTH.disparity_noise_px, description="stereo: Gaussian disparity error (std)")
    min_disparity_px: Positive = Field(_DEPTH.min_disparity_px, description="stereo: smaller disparities are holes (beyond the matcher's range)")
    texture_min: NonNegative = Field(_DEPTH.texture_min, description="stereo: holes where the image's local texture (intensity std in a window) is below this")
    tof_sigma0_m: NonNegative = Field(_DEPTH.tof_sigma0_m, description="ToF: range noise std at zero range")
    tof_sigma_rel: NonNegative = Field(_DEPTH.tof_sigma_rel, description="ToF: range noise std per metre of range (fraction)")
    tof_max_range_m: Positive = Field(_DEPTH.tof_max_range_m, description="ToF: no return beyond this range")
    flying_edge_m: Positive = Field(_DEPTH.flying_edge_m, description="ToF: a 3x3 neighbourhood spanning a larger depth step gives flying pixels")
    lidar_beams: Annotated[int, Field(ge=2, le=512)] = Field(_DEPTH.lidar_beams, description="LiDAR: beams evenly spaced in elevation")
    lidar_elevation_deg: tuple[Annotated[float, Field(ge=-90, le=90)], Annotated[float, Field(ge=-90, le=90)]] = \
        Field(_DEPTH.lidar_elevation_deg, description="LiDAR: lowest and highest beam elevation")
    lidar_azimuth_step_deg: Annotated[float, Field(gt=0.0, le=10.0)] = Field(_DEPTH.lidar_azimuth_step_deg, description="LiDAR: one return every this many degrees of azimuth")
    lidar_range_noise_m: NonNegative = Field(_DEPTH.lidar_range_noise_m, description="LiDAR: Gaussian range noise (std)")


class PoseNoiseConfig(_Strict):
    """The camera pose error the fusion does not know of (vcfusion.fusion.sensors)."""

    mount_std_deg: Annotated[float, Field(ge=0.0, le=10.0)] = Field(_POSE.mount_std_deg, description="mount calibration error (std, drawn once per run, each axis)")
    body_motion: bool = Field(_POSE.body_motion, description="the body's pitch and roll on its suspension from the ego's own accelerations")
    pitch_gain_deg_per_mps2: Annotated[float, Field(ge=0.0, le=5.0)] = Field(_POSE.pitch_gain_deg_per_mps2, description="body pitch per longitudinal acceleration")
    roll_gain_deg_per_mps2: Annotated[float, Field(ge=0.0, le=5.0)] = Field(_POSE.roll_gain_deg_per_mps2, description="body roll per lateral acceleration")
    suspension_tau_s: Positive = Field(_POSE.suspension_tau_s, description="suspension: time constant of the first-order lag")


class CameraConfig(_Strict):
    """The ego's forward camera (paper Sec. II-B): mount on the ego and pinhole intrinsics.

    The mount is relative to the ego's footprint centre and heading: `forward_m` along the
    heading, `lateral_m` to the left, `height_m` above the ground; `pitch_deg` > 0 tilts the
    optical axis down. Square pixels, principal point at the image centre.
    """

    height_m: Positive = Field(1.4, description="mount height above the ground")
    forward_m: float = Field(0.6, description="mount along the heading from the footprint centre")
    lateral_m: float = Field(0.0, description="mount to the left of the footprint centre")
    pitch_deg: Annotated[float, Field(ge=-45.0, le=45.0)] = Field(3.0, description="tilt of the optical axis, "
                                                                                  "down positive")
    hfov_deg: Annotated[float, Field(gt=1.0, lt=170.0)] = Field(70.0, description="horizontal field of view")
    width_px: Annotated[int, Field(ge=16, le=8192)] = Field(640, description="image width")
    height_px: Annotated[int, Field(ge=16, le=8192)] = Field(480, description="image height")
    near_m: Positive = Field(0.3, description="near clip plane of the renderer")
    far_m: Positive = Field(600.0, description="far clip plane (greater than near_m); depth beyond reads as sky")
    render_preset: Literal["fast", "quality"] = Field(
        "fast", description="how the RGB image is finished (vcfusion.render.presets): fast for batch renders, "
                            "quality (2x2 supersampling, lens blur, exposure and sensor noise, ~6x the render "
                            "time) for studies; depth and instances are the same")
    depth: Literal["exact", "stereo", "tof", "lidar"] = Field(
        "exact", description="the depth the fusion and detector get (vcfusion.fusion.sensors): exact, stereo "
                             "(disparity noise and holes), tof (range noise, flying pixels), lidar (a sparse scan)")
    depth_params: DepthSensorConfig = Field(DepthSensorConfig(), description="the depth sensor's parameters")
    pose_noise: PoseNoiseConfig = Field(PoseNoiseConfig(), description="the camera pose error the fusion does not "
                                                                        "know of")

    @model_validator(mode="after")
    def _planes(self) -> "CameraConfig":
        if self.far_m <= self.near_m:
            raise ValueError(f"expected far_m > near_m ({self.near_m}), got far_m = {self.far_m}")
        return self


class VisionConfig(_Strict):
    """Whether the tick loop renders the ego camera (stages 4-6 of a tick)."""

    enabled: bool = Field(False, description="render the ego camera in the tick loop (needs an ego)")
    every_ticks: Annotated[int, Field(ge=1)] = Field(1, description="render every this many V2C ticks "
                                                                   "(1 = every tick)")
    # at other ticks the overlay would draw no warning, so the driver is shown the same warnings;
    # off by default: the joint matcher's position filter then gets fewer updates
    only_when_warning: bool = Field(False, description="render and fuse only at ticks where a neighbour twin "
                                                       "carries a warning (faster; fewer updates for the joint "
                                                       "matcher's position filter; no AR video)")


class EgoConfig(_Strict):
    """The ego vehicle: driven by the driver model (or a person), carrying the camera."""

    vtype: Name = Field("ego", description="vehicle type (of vehicle_types)")
    route: Route | None = Field(None, description="the ego's route, edge ids in driving order (null: the "
                                                  "scenario's)")
    lane: Annotated[int, Field(ge=0)] = Field(2, description="a track of the route, index from the right "
                                                            "(0 = rightmost); it must run trip_distance_m")
    depart_pos_m: NonNegative = Field(50.0, description="front bumper along the route at t = 0")
    speed_mps: NonNegative = Field(19.0, description="speed at t = 0")
    desired_speed_mps: Positive = Field(19.0, description="the driver's desired speed")
    trip_distance_m: Positive = Field(300.0, description="the trip ends when the ego has travelled this far (or "
                                                         "at simulation.max_time_s)")
    controller: str | None = Field(None, description="the ego's controller (vcfusion.control) by import path "
                                                     "\"package.module:Name\"; null: the built-in driver model")
    controller_params: dict[str, Any] = Field({}, description="keyword arguments the controller is built with")

    @field_validator("controller")
    @classmethod
    def _importable(cls, v: str | None) -> str | None:
        if v is not None:
            from vcfusion.control.stage import ControllerError, resolve

            try:
                resolve(v)
            except ControllerError as exc:
                raise ValueError(str(exc)) from None
        return v

    @model_validator(mode="after")
    def _params_fit(self) -> "EgoConfig":
        if self.controller_params and self.controller is None:
            raise ValueError("controller_params: given without ego.controller; expected a controller to pass them to")
        if self.controller is not None:
            from vcfusion.control.stage import ControllerError, check_params

            try:
                check_params(self.controller, dict(self.controller_params))
            except ControllerError as exc:
                raise ValueError(f"controller_params: {exc}") from None
        return self

    @model_serializer(mode="wrap")
    def _without_unset_controller(self, handler):
        # a scenario without a controller records what it recorded before the field existed
        data = handler(self)
        if self.controller is None:
            data.pop("controller", None)
            data.pop("controller_params", None)
        return data


class DriverConfig(_Strict):
    """The ego's driver model (vcfusion.driver) and the guidance it is shown."""

    guidance: bool = Field(True, description="whether the driver uses the AR guidance in a single run (the "
                                             "guidance study runs both)")
    guidance_view_range_m: Positive = Field(150.0, description="guidance items are made for neighbours ahead "
                                                               "within this range; levels follow the ar block")
    field_of_view_deg: Annotated[float, Field(gt=1.0, lt=180.0)] | None = Field(
        None, description="the driver's forward field of view (null: the camera's hfov_deg; "
                          "vcfusion.driver.perception)")


class VehicleGroup(_Strict):
    """Vehicles placed at t = 0 at random positions (drawn per seed) in the given lanes."""

    name: Name = Field(description="group name (vehicles.parquet `group`; metrics.exclude_groups)")
    count: Annotated[int, Field(ge=1)] = Field(description="number of vehicles")
    vtype: Name = Field("car", description="vehicle type (of vehicle_types)")
    route: Route | None = Field(None, description="the group's route (null: the scenario's)")
    lanes: list[Annotated[int, Field(ge=0)]] = Field(min_length=1, description="tracks of the route (index from "
                                                                               "the right) the vehicles are drawn in")
    pos_m: tuple[NonNegative, NonNegative] = Field(description="[low, high] range of the front bumpers along the "
                                                               "route, low <= high")
    speed_mps: NonNegative = Field(17.0, description="speed at t = 0")
    desired_speed_mps: Positive | None = Field(None, description="desired speed (null: the vehicle type's)")
    # SUMO refuses to insert at 17 m/s with much less
    min_spacing_m: NonNegative = Field(20.0, description="minimum bumper-to-bumper spacing in one lane")

    @field_validator("pos_m")
    @classmethod
    def _ordered(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] > v[1]:
            raise ValueError("expected [low, high] with low <= high")
        return v


class Flow(_Strict):
    """Poisson arrivals at the start of the route (the flow's, default the scenario's) over the
    whole run, in the given tracks of that route's first edge."""

    vtype: Name = Field("car", description="vehicle type (of vehicle_types)")
    route: Route | None = Field(None, description="the flow's route (null: the scenario's)")
    vehs_per_hour: Positive = Field(description="mean arrival rate (Poisson)")
    lanes: list[Annotated[int, Field(ge=0)]] = Field(min_length=1, description="tracks of the route's first edge")
    speed_mps: NonNegative = Field(25.0, description="departure speed")


class AccidentConfig(_Strict):
    """Stopped vehicles closing lanes (SUMO <stop parking="false">): tracks of the scenario's
    route at pos_m (front bumper) along `edge`, or along the route when no edge is given."""

    edge: Name | None = Field(None, description="edge of the stop (null: positions along the route)")
    pos_m: NonNegative = Field(description="front bumper along `edge`, or along the route")
    lanes: list[Annotated[int, Field(ge=0)]] = Field(min_length=1, description="tracks closed (index from the "
                                                                               "right)")
    vtype: Name = Field("truck", description="vehicle type of the stopped vehicles")


class LaneChangeDurationConfig(_Strict):
    """Each vehicle's own lane-change duration, drawn when it departs: SUMO's per-vehicle lateral
    speed limit (maxSpeedLat) is set to lane width / duration (SUMO: a vehicle's maxSpeedLat
    overrides --lanechange.duration; with the sublane model's lcAccelLat the move takes about
    maxSpeedLat / lcAccelLat longer)."""

    distribution: Literal["fixed", "lognormal", "uniform"] = Field(
        "lognormal", description="fixed: every change median_s; lognormal: median median_s, log-space std sigma; "
                                 "uniform: between min_s and max_s; draws are clipped to [min_s, max_s]")
    median_s: Positive = Field(4.0, description="median lane-change duration")
    sigma: NonNegative = Field(0.3, description="log-space standard deviation (lognormal)")
    min_s: Positive = Field(1.0, description="shortest duration drawn")
    max_s: Positive = Field(12.0, description="longest duration drawn")

    @model_validator(mode="after")
    def _ordered(self) -> "LaneChangeDurationConfig":
        if not self.min_s <= self.median_s <= self.max_s:
            raise ValueError(f"lane_change_model.duration: expected min_s <= median_s <= max_s, got {self.min_s:g}, "
                             f"{self.median_s:g}, {self.max_s:g}")
        return self


class LaneChangeModelConfig(_Strict):
    """SUMO's lane-change model for the traffic's vehicle types (not the ego, which our code
    drives). Unset parameters keep the vehicle types file's values (SUMO's defaults where it has
    none). Calibrated sets and how they were chosen: docs/components/real-data.md
    (`vcfusion calibrate-lane-changes` against US-101 development data)."""

    model: Literal["LC2013", "SL2015"] = Field(
        "LC2013", description="LC2013: SUMO's default, lanes as units (a change moves across at constant lateral "
                              "speed); SL2015: the sublane model (needs lateral_resolution_m: vehicles move within "
                              "and across lanes with bounded lateral speed and acceleration)")
    vtypes: list[Name] | None = Field(None, description="vehicle types given these parameters; null: every type "
                                                        "of the scenario's vehicles and flows")
    lateral_resolution_m: Positive | None = Field(None, description="SUMO --lateral-resolution; SL2015 only")
    lc_sigma: NonNegative | None = Field(None, description="SUMO lcSigma: lateral imperfection; SL2015 only")
    max_speed_lat_mps: Positive | None = Field(None, description="SUMO maxSpeedLat")
    lc_accel_lat_mps2: Positive | None = Field(None, description="SUMO lcAccelLat; SL2015 only")
    lc_strategic: NonNegative | None = Field(None, description="SUMO lcStrategic: eagerness for route changes")
    lc_cooperative: Annotated[float, Field(ge=0.0, le=1.0)] | None = Field(None, description="SUMO lcCooperative")
    lc_speed_gain: NonNegative | None = Field(None, description="SUMO lcSpeedGain: eagerness to overtake")
    lc_keep_right: NonNegative | None = Field(None, description="SUMO lcKeepRight: eagerness to return right")
    duration: LaneChangeDurationConfig | None = Field(None, description="per-vehicle lane-change durations "
                                                                        "(exclusive with max_speed_lat_mps)")

    @model_validator(mode="after")
    def _consistent(self) -> "LaneChangeModelConfig":
        sublane = self.model == "SL2015"
        if sublane != (self.lateral_resolution_m is not None):
            raise ValueError("lane_change_model: expected lateral_resolution_m exactly with model SL2015 (SUMO runs "
                             "LC2013 without sublanes only, and SL2015 on sublanes)")
        for name in ("lc_sigma", "lc_accel_lat_mps2"):
            if getattr(self, name) is not None and not sublane:
                raise ValueError(f"lane_change_model.{name}: only the sublane model (model: SL2015) moves vehicles "
                                 "laterally this way; with LC2013 it would have no effect")
        if self.duration is not None and self.max_speed_lat_mps is not None:
            raise ValueError("lane_change_model: expected one of duration (per-vehicle maxSpeedLat) and "
                             "max_speed_lat_mps, not both")
        return self

    def vtype_attributes(self) -> dict[str, str]:
        """The SUMO vType attributes this block sets (name -> value text)."""
        names = {"lc_sigma": "lcSigma", "max_speed_lat_mps": "maxSpeedLat", "lc_accel_lat_mps2": "lcAccelLat",
                 "lc_strategic": "lcStrategic", "lc_cooperative": "lcCooperative", "lc_speed_gain": "lcSpeedGain",
                 "lc_keep_right": "lcKeepRight"}
        out = {"laneChangeModel": self.model}
        out |= {sumo: repr(float(getattr(self, field))) for field, sumo in names.items()
                if getattr(self, field) is not None}
        return out


class PredictionConfig(_Strict):
    """The cloud's lane-change predictor (a twin process model, vcfusion.prediction)."""

    enabled: bool = Field(True, description="run the predictor on every twin every V2C tick")
    model: Path | None = Field(None, description="model file from `vcfusion train` (relative to the scenario); "
                                                 "null: the shipped GRU")
    smoothing: Literal["none", "aggressive", "conservative"] | None = Field(
        None, description="smoothing of the per-tick decisions (paper Algorithms 3 and 4); null: the model "
                          "file's (chosen on validation seeds by `vcfusion train`)")
    threshold: Probability | None = Field(None, description="calibrated probability above which the raw "
                                                            "per-tick decision is positive; null: the model "
                                                            "file's, tuned for that smoothing")
    tau_a_ticks: Annotated[int, Field(ge=0)] | None = Field(None, description="Algorithm 3: a positive lasts "
                                                                             "this many more V2C ticks; null: "
                                                                             "the model file's")
    tau_c_ticks: Annotated[int, Field(ge=0)] | None = Field(None, description="Algorithm 4: mean over the last "
                                                                             "tau_c + 1 V2C ticks; null: the "
                                                                             "model file's")
    conservative_threshold: Probability | None = Field(None, description="Algorithm 4's vote threshold; null: "
                                                                         "the model file's (0.5 in the shipped "
                                                                         "ones)")


class MetricsConfig(_Strict):
    """Safety, comfort and emission metrics of every vehicle of a run (vcfusion.metrics).

    One place for the thresholds and definitions: runs, batches, `vcfusion metrics` and the
    guidance study all read them from here (docs/components/metrics.md).
    """

    enabled: bool = Field(True, description="compute the metrics tables and the summary's metrics block")
    # 1.5 s: the SSAM default (Gettman & Head, "Surrogate Safety Measures From Traffic Simulation
    # Models", FHWA-RD-03-050, 2003; Gettman et al., "Surrogate Safety Assessment Model and
    # Validation", FHWA-HRT-08-051, 2008)
    ttc_threshold_s: Positive = Field(1.5, description="TTC below which a following situation is a conflict "
                                                       "(TET/TIT, conflict episodes); the SSAM default")
    # one V2C tick: the ego's command is piecewise constant over a tick; at the 0.1 s trajectory
    # period it is no smoothing
    jerk_window_s: Positive = Field(0.1, description="centred moving average of the acceleration before it is "
                                                     "differentiated into jerk")
    ttc_clip_s: Positive = Field(20.0, description="the guidance study's mean TTC to the cut-in vehicle is also "
                                                   "given with TTC clipped here")
    # 10 s: the ego's response to a cut-in (a reaction of 1-2 s, then settling behind the new leader)
    # and not the queue at the curve's closure a minute later, where the same vehicle gave the
    # least gap of two trips (curved seeds 5042, 5124: within 10 s the arms differ by 0 and +9 m,
    # over the whole stay by -182 and -77 m; docs/components/guidance-loop.md)
    cut_in_window_s: Positive = Field(10.0, description="the guidance study's minimum gap to the cut-in vehicle "
                                                        "is read over this time from the cut-in's mid time "
                                                        "(min_gap_stay_m: over its whole stay in the ego's lane)")
    leader_range_m: Positive = Field(250.0, description="a vehicle's leader is the nearest vehicle ahead in its "
                                                        "lane within this range (bumper to bumper)")
    movestar: dict[Name, Literal[1, 2]] = Field({"passenger": 1}, description="MOVESTAR source type (1 "
                                                "light-duty passenger car, 2 light-duty truck) by SUMO vType id "
                                                "or vClass (the vType id wins); other types (trucks, buses) get "
                                                "SUMO's emission model only")
    sumo_emissions: Literal["others", "all", "none"] = Field(
        "others", description="the vehicles SUMO's own emission model rates (HBEFA/PHEMlight, their vType's "
                              "class): others = those without a MOVESTAR type; all = the cars too (SUMO then "
                              "rates every vehicle every step, ~20-30 % more run time); none")
    exclude_groups: list[Name] = Field(["accident"], description="placement groups (vehicles.parquet `group`) "
                                                                 "left out of the traffic-wide figures; they keep "
                                                                 "their rows and still lead others")


class RewardConfig(_Strict):
    """Weights of the Gymnasium environment's reward per V2C tick (vcfusion.gym.reward has the
    terms and the reasons for these defaults); set in a scenario's `reward:` block."""

    progress: float = Field(1.0, description="weight of travel along the route: 1 per tick driven at "
                                             "ego.desired_speed_mps")
    ttc: NonNegative = Field(1.0, description="weight of (threshold - TTC) / threshold to the radar leader while "
                                              "TTC < metrics.ttc_threshold_s (0..1)")
    drac: NonNegative = Field(0.5, description="weight of DRAC to the radar leader / 3.35 m/s^2 (the conflict "
                                               "threshold of Archer 2005)")
    jerk: NonNegative = Field(0.05, description="weight of |jerk| of the command from one tick to the next / "
                                                "10 m/s^3")
    fuel: NonNegative = Field(1.0, description="weight of the tick's MOVESTAR fuel, per gram")
    collision: NonNegative = Field(100.0, description="penalty, once, at a collision of the ego (the episode ends)")


class Scenario(_Strict):
    """A scenario file: the top level."""

    name: Name = Field(description="the scenario's name (default run folder names)")
    description: str = Field("", description="one line shown by `vcfusion scenarios`")
    network: Path = Field(description="SUMO .net.xml (relative to the file that sets it)")
    route: Route | None = Field(None, description="edge ids in driving order: the road frame and every "
                                                  "vehicle's default route; not needed on a network that is one "
                                                  "chain of edges")
    vehicle_types: Path = Field(description="SUMO additional file with the <vType>s (relative to the file that "
                                            "sets it)")
    simulation: SimulationConfig = SimulationConfig()
    v2c: V2CConfig = V2CConfig()
    ar: AROverlayConfig = AROverlayConfig()
    fusion: FusionConfig = FusionConfig()
    ego: EgoConfig | None = None
    driver: DriverConfig = DriverConfig()
    camera: CameraConfig = CameraConfig()
    vision: VisionConfig = VisionConfig()
    vehicles: list[VehicleGroup] = []
    flows: list[Flow] = []
    accident: AccidentConfig | None = None
    prediction: PredictionConfig = PredictionConfig()
    metrics: MetricsConfig = MetricsConfig()
    # the Gymnasium environment's reward weights (vcfusion.gym); unused by `vcfusion run`
    reward: RewardConfig = RewardConfig()
    lane_change_model: LaneChangeModelConfig | None = None
    # Where the scenario was read from (set by the loader, not by the file): the file given and,
    # when it extends others, the chain of files it was merged from (the given file first).
    source: Path | None = Field(default=None, exclude=True)
    chain: tuple[Path, ...] = Field(default=(), exclude=True)

    @model_validator(mode="after")
    def _consistent(self) -> "Scenario":
        step = self.simulation.step_s
        if self.simulation.max_time_s < step - 1e-12:
            raise ValueError(f"simulation.max_time_s: expected at least one step (simulation.step_s, {step:g} s), "
                             f"got {self.simulation.max_time_s:g}")
        for name, period in (
            ("v2c.period_s", self.v2c.period_s),
            ("ar.period_s", self.ar.period_s),
            ("simulation.trajectory_period_s", self.simulation.trajectory_period_s),
        ):
            ratio = period / step
            if abs(ratio - round(ratio)) > 1e-6:
                raise ValueError(f"{name}: expected a whole multiple of simulation.step_s ({step}), got {period}")
        if self.metrics.enabled and self.simulation.trajectory_period_s > 1.0:
            raise ValueError("simulation.trajectory_period_s: expected at most 1 s with metrics enabled (MOVESTAR "
                             f"rates every second of the trajectory; or metrics.enabled: false), got "
                             f"{self.simulation.trajectory_period_s:g}")
        # the AR stage (fusion) runs on V2C ticks: another period would skip ticks unevenly (and
        # the video's frames would not come at one rate: overlay_period_s)
        ratio = self.ar.period_s / self.v2c.period_s
        if self.fusion.enabled and (ratio < 1 - 1e-6 or abs(ratio - round(ratio)) > 1e-6):
            raise ValueError(f"ar.period_s: expected a whole multiple of v2c.period_s ({self.v2c.period_s}), "
                             f"got {self.ar.period_s}")
        if self.vision.enabled and self.ego is None:
            raise ValueError("vision.enabled: the camera rides on the ego; expected an ego block")
        if self.fusion.enabled:
            if not self.vision.enabled:
                raise ValueError("fusion.enabled: expected vision.enabled: true (fusion needs the ego camera)")
        if self.ar.video and not self.fusion.enabled:
            raise ValueError("ar.video: expected fusion.enabled: true (the overlay needs the fusion stage)")
        if self.ar.video and self.vision.only_when_warning:
            # frames only at warnings: no video of one frame rate (and none at all without a warning)
            raise ValueError("ar.video: expected vision.only_when_warning: false (the video needs a frame at every "
                             "AR update; only_when_warning renders only where a neighbour carries a warning)")
        if not self.vehicles and not self.flows and self.ego is None:
            raise ValueError("expected at least one of ego, vehicles, flows")
        return self

    @model_serializer(mode="wrap")
    def _without_default_reward(self, handler):
        # the reward weights are recorded where a scenario sets them (runs before the block existed
        # record the same scenario)
        data = handler(self)
        if self.reward == RewardConfig():
            data.pop("reward", None)
        return data

    def overlay_period_s(self) -> float:
        """Simulated time between two frames of the AR video: the fusion stage draws at the AR updates
        (every ar.period_s) that have a camera frame (every vision.every_ticks V2C ticks); both start
        at the first tick."""
        ar_ticks = int(round(self.ar.period_s / self.v2c.period_s))
        return math.lcm(ar_ticks, self.vision.every_ticks) * self.v2c.period_s

    def steps(self, period_s: float) -> int:
        """Number of SUMO steps in one period."""
        return int(round(period_s / self.simulation.step_s))

    def to_dict(self) -> dict:
        out = self.model_dump(mode="json")
        if self.lane_change_model is None:  # unset: the record every run of SUMO's own lane changes keeps
            del out["lane_change_model"]
        return out


# ---------------------------------------------------------------------------------------------
# loading: the chain of files, their merge, validation with the file each field came from

PATH_FIELDS = (("network",), ("vehicle_types",), ("prediction", "model"), ("fusion", "weights"))


class _UniqueKeyLoader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """YAML's safe loader (libyaml's parser where installed: a batch loads its scenario once per
    seed), refusing a key given twice in one mapping (YAML would keep the last silently, so a
    second `v2c:` block would drop the first).

    Booleans are YAML 1.2's (true / false only): YAML 1.1 also reads yes / no / on / off / y / n as
    booleans, which turned an edge called `off` into False (a true/false field still takes "yes" or
    "on": the schema reads them). Numbers keep the text they were written as, for ids (`_id_text`)."""

    yaml_implicit_resolvers = {
        first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:bool"]
        for first, resolvers in getattr(yaml, "CSafeLoader", yaml.SafeLoader).yaml_implicit_resolvers.items()}

    def construct_yaml_int(self, node):
        value = super().construct_yaml_int(node)
        out = _IntWithText(value)
        out.text = node.value
        return out

    def construct_yaml_float(self, node):
        value = super().construct_yaml_float(node)
        out = _FloatWithText(value)
        out.text = node.value
        return out

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"key {key!r} given twice in one mapping",
                                                        key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


_UniqueKeyLoader.add_implicit_resolver("tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
                                       list("tTfF"))
_UniqueKeyLoader.add_constructor("tag:yaml.org,2002:int", _UniqueKeyLoader.construct_yaml_int)
_UniqueKeyLoader.add_constructor("tag:yaml.org,2002:float", _UniqueKeyLoader.construct_yaml_float)


def _read_mapping(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ScenarioError(f"{path}: not a UTF-8 text file; expected a YAML scenario") from None
    except OSError as exc:
        raise ScenarioError(f"{path}: cannot read the scenario file: {exc.strerror or exc}") from None
    try:
        raw = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a safe loader
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = " ".join(str(exc.problem or exc.context or "syntax error").split())
        raise ScenarioError(f"{path}: {where}not valid YAML ({problem})") from None
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{path}: not valid YAML ({' '.join(str(exc).split())})") from None
    if not isinstance(raw, dict):
        got = "an empty file" if raw is None else f"a {type(raw).__name__}"
        raise ScenarioError(f"{path}: expected a mapping of scenario fields at the top level, got {got}")
    return raw


def read_chain(path: Path) -> list[tuple[Path, dict]]:
    """The file and the files it extends, as (path, fields without `extends`), the given file first."""
    chain: list[tuple[Path, dict]] = []
    seen: set[Path] = set()
    current = path
    while True:
        seen.add(current.resolve())
        raw = _read_mapping(current)
        base = raw.pop("extends", None)
        chain.append((current, raw))
        if base is None:
            return chain
        if not isinstance(base, str) or not base.strip():
            raise ScenarioError(f"{current}: extends: expected the path of a base scenario file "
                                f"(relative to this file), got {base!r}")
        target = current.parent / base
        if not target.is_file():
            raise ScenarioError(f"{current}: extends: file not found: {base} (relative to the scenario file)")
        if target.resolve() in seen:
            cycle = " -> ".join(str(p) for p, _ in chain) + f" -> {target}"
            raise ScenarioError(f"{current}: extends: {base} makes a cycle ({cycle}); expected a chain that ends "
                                "in a file without `extends`")
        current = target


def merge_over(base: dict, over: dict, source: Path, origin: dict, prefix: tuple = ()) -> dict:
    """`over` merged over `base`: mappings key by key, any other value (lists too) replaces.
    `origin` maps key paths to the file that set them (a deeper entry wins over a shorter one)."""
    merged = dict(base)
    for key, value in over.items():
        loc = prefix + (key,)
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge_over(merged[key], value, source, origin, loc)
            continue
        merged[key] = value
        for stale in [k for k in origin if k[:len(loc)] == loc]:
            del origin[stale]
        origin[loc] = source
    return merged


class _Origins:
    """Which file of the chain a field came from, for messages and for relative paths."""

    def __init__(self, leaf: Path, origin: dict):
        self.leaf = leaf
        self.origin = origin

    def file_of(self, loc: tuple) -> Path:
        for n in range(len(loc), 0, -1):
            if loc[:n] in self.origin:
                return self.origin[loc[:n]]
        return self.leaf

    def label(self, loc: tuple) -> str:
        """The file to name in a message about `loc` (with the file given, when they differ)."""
        f = self.file_of(loc)
        return str(f) if f == self.leaf else f"{f} (extended by {self.leaf})"


def _format_location(loc: tuple) -> str:
    parts = []
    for item in loc:
        if isinstance(item, int):
            parts.append(f"[{item}]")
        else:
            parts.append(("." if parts else "") + str(item))
    return "".join(parts) or "(top level)"


def _model_at(loc: tuple) -> type[BaseModel] | None:
    """The schema class holding the last key of `loc` (list indices skipped)."""
    model: type[BaseModel] | None = Scenario
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        field = model.model_fields.get(part) if model else None
        model = _inner_model(field.annotation) if field else None
    return model


def _inner_model(tp) -> type[BaseModel] | None:
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return tp
    for arg in typing.get_args(tp):
        found = _inner_model(arg)
        if found is not None:
            return found
    return None


def _describe(err: dict) -> str:
    kind = err.get("type", "")
    if kind == "extra_forbidden":
        model = _model_at(err["loc"])
        known = [k for k, f in model.model_fields.items() if not f.exclude] if model else []
        return "unknown key" + (f"; expected one of: {', '.join(known)}" if known else "")
    if kind == "missing":
        return "required field is missing"
    msg = err.get("msg", "invalid value")
    msg = msg.removeprefix("Value error, ")
    got = err.get("input")
    if not isinstance(got, (dict, list)):
        msg += f" (got {got!r})"
    return msg


def _validation_lines(exc: ValidationError, origins: _Origins) -> list[str]:
    lines = []
    for err in exc.errors():
        loc = err["loc"]
        if err["type"] == "value_error" and not loc and ":" in err["msg"]:
            # a cross-field check: its message starts with the field it names
            where, _, rest = err["msg"].removeprefix("Value error, ").partition(": ")
            lines.append(f"{origins.label(tuple(where.split('.')))}: {where}: {rest}")
        else:
            lines.append(f"{origins.label(loc)}: {_format_location(loc)}: {_describe(err)}")
    return lines


def find_scenario(path: str | Path) -> Path:
    """The scenario file `path` names: the file itself when it exists, else the shipped scenario of
    that name (`accident`, `families/dense`: see vcfusion.resources.shipped_scenarios); ScenarioError
    listing the shipped names when it is neither."""
    from vcfusion.resources import SCENARIO_SUFFIX, shipped_scenarios

    path = Path(path)
    if path.is_file():
        return path
    shipped = shipped_scenarios()
    name = path.as_posix()
    if name in shipped and not path.suffix:
        return shipped[name]
    hint = (f"expected a scenario file, or the name of a shipped scenario: {', '.join(shipped)}"
            if not path.suffix or path.suffix == SCENARIO_SUFFIX else "expected a scenario file (YAML)")
    raise ScenarioError(f"{path}: scenario file not found ({hint})")


def describe_scenario_file(path: Path) -> str:
    """One line about a scenario file: its own `description` field (not a base's), else its leading
    YAML comment, whitespace collapsed; empty when it has neither."""
    raw = _read_mapping(path)
    if isinstance(raw.get("description"), str) and raw["description"].strip():
        return " ".join(raw["description"].split())
    comment = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        comment.append(line.lstrip("#").strip())
    return " ".join(" ".join(comment).split())


def load_scenario(path: str | Path) -> Scenario:
    """Read, merge (`extends`) and validate a scenario file (or a shipped scenario by name: see
    find_scenario) and the files it names; raises ScenarioError with one line per problem naming
    the file, the field and what was expected."""
    path = find_scenario(path)
    chain = read_chain(path)
    merged: dict = {}
    origin: dict = {}
    for source, raw in reversed(chain):  # the last base first, the given file last
        merged = merge_over(merged, raw, source, origin)
    origins = _Origins(path, origin)
    try:
        scenario = Scenario.model_validate(merged)
    except ValidationError as exc:
        raise ScenarioError("\n".join(_validation_lines(exc, origins))) from None
    resolved = {}
    for loc in PATH_FIELDS:
        block = scenario if len(loc) == 1 else getattr(scenario, loc[0])
        value = getattr(block, loc[-1])
        if value is None or (loc[0] == "prediction" and not scenario.prediction.enabled):
            continue
        target = (origins.file_of(loc).parent / value).resolve()
        if not target.is_file():
            raise ScenarioError(f"{origins.label(loc)}: {'.'.join(loc)}: file not found: {value} "
                                "(relative to the scenario file)")
        if len(loc) == 1:
            resolved[loc[0]] = target
        else:
            resolved[loc[0]] = resolved.get(loc[0], block).model_copy(update={loc[1]: target})
    scenario = scenario.model_copy(update={**resolved, "source": path, "chain": tuple(p for p, _ in chain)})
    _check_named_files(scenario, origins)
    return scenario


def _open_somewhere(frame, track: int, positions: list[float], is_range: bool, closed: frozenset[str]) -> bool:
    """Whether the track has a SUMO lane not in `closed` at the position, or somewhere in the range
    (every metre: a placement draws again where the lane is closed)."""
    from vcfusion.traffic.network import sumo_lane_id, sumo_place

    lo, hi = (positions[0], min(positions[1], frame.length_m)) if is_range else (positions[0], positions[0])
    for s in np.unique(np.r_[np.arange(lo, hi, 1.0), hi]):
        place = sumo_place(frame, track, float(s))
        if place is not None and sumo_lane_id(place) not in closed:
            return True
    return False


def camera_vclass_problem(scenario: Scenario, vtypes: dict) -> tuple[tuple, str] | None:
    """(where in the scenario, message) for the first vehicle type the scenario uses whose class the
    ego camera can neither draw nor label (records.CATEGORY_OF_VCLASS), else None."""
    from vcfusion.records import CATEGORY_OF_VCLASS

    used = [(("ego", "vtype"), scenario.ego.vtype)] if scenario.ego is not None else []
    used += [(("vehicles", i, "vtype"), g.vtype) for i, g in enumerate(scenario.vehicles)]
    used += [(("flows", i, "vtype"), f.vtype) for i, f in enumerate(scenario.flows)]
    used += [(("accident", "vtype"), scenario.accident.vtype)] if scenario.accident is not None else []
    for loc, vtype in used:
        vclass = vtypes.get(vtype, {}).get("vClass", "passenger")  # SUMO's default class
        if vclass not in CATEGORY_OF_VCLASS:
            return loc, (f"vehicle type {vtype!r} of {scenario.vehicle_types.name} has vClass {vclass!r}, which the "
                         f"ego camera can neither draw nor label; expected one of: {', '.join(CATEGORY_OF_VCLASS)} "
                         "(or run without the camera)")
    return None


def require_camera_world(scenario: Scenario) -> None:
    """InputError unless the ego camera can render this scenario: a flat network
    (traffic.network.require_flat_network) and road vehicle classes it has categories for. For the
    commands that render whatever the scenario's vision block says (render, drive, the studies)."""
    from vcfusion.traffic.network import NetworkFileError, read_vehicle_types, require_flat_network

    require_flat_network(scenario.network)
    problem = camera_vclass_problem(scenario, read_vehicle_types(scenario.vehicle_types))
    if problem is not None:
        loc, message = problem
        raise NetworkFileError(f"{scenario.source or scenario.name}: {_format_location(loc)}: {message}")


def _route_error(origins: _Origins, loc: tuple, exc) -> ScenarioError:
    """A RouteError of the frame of the route at `loc` (e.g. ("vehicles", 1)), naming its field."""
    where = _format_location(loc)
    part = exc.where.removeprefix("route") if exc.where else ""  # "[2]", or "" for the route as a whole
    field = f"{where}.route{part}" if loc else f"route{part}"
    return ScenarioError(f"{origins.label(loc + ('route',))}: {field}: {exc.detail} (network {exc.net_file.name})")


def _check_ego_lane(scenario: Scenario, road, origins: _Origins) -> None:
    """The ego keeps its lane for the whole trip (the driver model does not change lanes), and
    its lane is the guidance's and the metrics' ego lane, a track of the scenario's route: the
    lane must run to the trip's end, and an own route must number it as the scenario's does."""
    from vcfusion.traffic.network import read_road, sumo_place

    ego = scenario.ego
    frame = read_road(scenario.network, ego.route) if ego.route is not None else road
    lane_id = "{0[0]}_{1}".format(*sumo_place(frame, ego.lane, ego.depart_pos_m))
    track = road.track_of.get(lane_id)
    if track != ego.lane:
        where = (f"which is lane {track} of the scenario's route {list(road.route)}, not {ego.lane}" if track is not None
                 else f"which is not on the scenario's route {list(road.route)}")
        raise ScenarioError(f"{origins.label(('ego', 'route'))}: ego.route: the ego departs in SUMO lane {lane_id}, "
                            f"{where}; expected an ego route on which the ego's lane has the scenario's index "
                            "(e.g. a part of the scenario's route)")
    end = float(frame.lane_end_ahead(ego.lane, ego.depart_pos_m))
    trip_end = ego.depart_pos_m + ego.trip_distance_m
    if end < trip_end:
        raise ScenarioError(f"{origins.label(('ego', 'lane'))}: ego.lane: lane {ego.lane} ends at {end:g} m along the "
                            f"ego's route, before the trip's end ({trip_end:g} m); the ego keeps its lane: expected "
                            "a lane that runs to the trip's end")


def _check_named_files(scenario: Scenario, origins: _Origins) -> None:
    """Read the files the scenario names and check the scenario against them (routes, lanes,
    positions, vehicle types), so a bad one stops the command before anything is written."""
    from vcfusion.traffic.network import (NetworkFileError, accident_s, closed_lanes, read_road, read_vehicle_types,
                                          require_flat_network)
    from vcfusion.traffic.roadframe import RouteError

    try:
        road = read_road(scenario.network, scenario.route)
    except NetworkFileError as exc:
        raise ScenarioError(f"{origins.label(('network',))}: network: {exc}") from None
    except RouteError as exc:
        raise _route_error(origins, (), exc) from None
    if scenario.vision.enabled:
        try:
            require_flat_network(scenario.network)
        except NetworkFileError as exc:
            raise ScenarioError(f"{origins.label(('network',))}: network (vision.enabled): {exc}") from None
    try:
        vtypes = read_vehicle_types(scenario.vehicle_types)
    except NetworkFileError as exc:
        raise ScenarioError(f"{origins.label(('vehicle_types',))}: vehicle_types: {exc}") from None
    # (loc, vtype, route frame, lanes, [(field, positions along the route)]): a group's lanes must
    # exist somewhere in its range (draws where one is absent are drawn again), the others' where they are
    uses: list[tuple[tuple, str, object, list[int], str, list[float], bool]] = []
    if scenario.ego is not None:
        uses.append((("ego",), scenario.ego.vtype, scenario.ego.route, [scenario.ego.lane], "depart_pos_m",
                     [scenario.ego.depart_pos_m], False))
    # a range partly beyond the road is left to the seeds (a draw outside is an impossible departure
    # of that seed, RunError); one wholly beyond it can never run
    uses += [(("vehicles", i), g.vtype, g.route, g.lanes, "pos_m", list(g.pos_m), True)
             for i, g in enumerate(scenario.vehicles)]
    uses += [(("flows", i), f.vtype, f.route, f.lanes, "", [0.0], False) for i, f in enumerate(scenario.flows)]
    lcm = scenario.lane_change_model
    for k, vtype in enumerate((lcm.vtypes or []) if lcm is not None else []):
        if vtype not in vtypes:
            raise ScenarioError(f"{origins.label(('lane_change_model', 'vtypes', k))}: lane_change_model.vtypes: "
                                f"{vtype!r} is not defined in {scenario.vehicle_types.name}; expected one of: "
                                f"{', '.join(vtypes)}")
    acc = scenario.accident
    if acc is not None:
        if acc.edge is not None and acc.edge not in road.route:
            raise ScenarioError(f"{origins.label(('accident', 'edge'))}: accident.edge: expected an edge of "
                                f"the route {list(road.route)}, got {acc.edge!r}")
        uses.append((("accident",), acc.vtype, None, acc.lanes, "pos_m", [accident_s(acc, road)], False))
    for loc, vtype, route, lanes, pos_field, positions, is_range in uses:
        where = _format_location(loc)
        if vtype not in vtypes:
            raise ScenarioError(f"{origins.label(loc + ('vtype',))}: {where}.vtype: {vtype!r} is not defined in "
                                f"{scenario.vehicle_types.name}; expected one of: {', '.join(vtypes)}")
        frame = road
        if route is not None:
            try:
                frame = read_road(scenario.network, route)
            except RouteError as exc:
                raise _route_error(origins, loc, exc) from None
        field = "depart_pos_m" if loc == ("ego",) else "pos_m"
        on = f"route {list(frame.route)}" if len(frame.route) > 1 else "the road"
        for pos in positions[:1]:
            if pos > frame.length_m:
                raise ScenarioError(f"{origins.label(loc + (field,))}: {where}.{field}: expected a position on "
                                    f"{on} (at most its length, {frame.length_m:g} m), got {pos:g}")
        field = "lane" if loc == ("ego",) else "lanes"
        for lane in lanes:
            if lane >= frame.num_tracks:
                raise ScenarioError(f"{origins.label(loc + (field,))}: {where}.{field}: expected a lane of "
                                    f"{scenario.network.name} (0 to {frame.num_tracks - 1}), got {lane}")
            if is_range:  # somewhere in the range
                lo, hi = positions
                spans = frame.lane_spans(lane)
                ok = bool(((spans[:, 0] <= min(hi, frame.length_m)) & (spans[:, 1] > lo)).any())
                at = f"between {lo:g} and {hi:g} m"
            else:
                pos = min(positions[0], frame.length_m)
                ok = bool(frame.lane_exists(lane, pos))
                at = f"at {pos:g} m" + (" (the route's start, where flows enter)" if loc[0] == "flows" else "")
            if not ok:
                present = np.flatnonzero(frame.lane_exists(np.arange(frame.num_tracks),
                                                           positions[0] if not is_range else positions[0]))
                raise ScenarioError(f"{origins.label(loc + (field,))}: {where}.{field}: lane {lane} does not exist "
                                    f"{at} along {on} (lanes there: {present.tolist()}); expected a lane "
                                    "present there (lanes are indexed from the right)")
            vclass = vtypes[vtype].get("vClass", "passenger")
            closed = closed_lanes(scenario.network, vclass)
            if closed and not _open_somewhere(frame, lane, positions, is_range, closed):
                raise ScenarioError(f"{origins.label(loc + (field,))}: {where}.{field}: lane {lane} is closed to "
                                    f"{vclass} vehicles (vehicle type {vtype!r}) {at} along {on} (the network's "
                                    "allow / disallow); expected a lane they may drive in")
    if scenario.vision.enabled:
        problem = camera_vclass_problem(scenario, vtypes)
        if problem is not None:
            loc, message = problem
            raise ScenarioError(f"{origins.label(loc)}: {_format_location(loc)} (vision.enabled): {message}")
    # departure speeds SUMO would refuse ("too high for the vehicle type") where the type sets maxSpeed
    departing = [(("vehicles", i), g.vtype, g.speed_mps) for i, g in enumerate(scenario.vehicles)]
    departing += [(("ego",), scenario.ego.vtype, scenario.ego.speed_mps)] if scenario.ego is not None else []
    for loc, vtype, speed in departing:
        try:
            max_speed = float(vtypes[vtype]["maxSpeed"])
        except (KeyError, ValueError):
            continue  # SUMO's default for the vehicle class, or SUMO's own error on a bad value
        if speed > max_speed:
            raise ScenarioError(f"{origins.label(loc + ('speed_mps',))}: {_format_location(loc)}.speed_mps: expected "
                                f"at most the maxSpeed of vehicle type {vtype!r} in {scenario.vehicle_types.name} "
                                f"({max_speed:g} m/s), got {speed:g}")
    if scenario.ego is not None:
        _check_ego_lane(scenario, road, origins)
    if scenario.prediction.enabled:
        from vcfusion.prediction.model import ModelFileError, load_model

        label = origins.label(("prediction", "model"))
        try:
            model = load_model(scenario.prediction.model)
        except ModelFileError as exc:
            raise ScenarioError(f"{label}: prediction.model: {exc}") from None
        if abs(model.period_s - scenario.v2c.period_s) > 1e-9:
            raise ScenarioError(f"{label}: prediction.model: trained for a V2C period of {model.period_s} s; "
                                f"expected v2c.period_s to match, got {scenario.v2c.period_s} s")
    if scenario.fusion.enabled and scenario.fusion.detector != "oracle":
        from vcfusion.detection.detector_net import (DetectorFileError, check_weights, check_yolo_model,
                                                     default_weights_path)

        f = scenario.fusion
        try:  # every file the scenario names is checked before a run starts (an ONNX one too)
            if f.detector == "onnx-yolo":
                check_yolo_model(f.weights, tuple(f.yolo_input_px), tuple(f.yolo_classes))
            else:
                check_weights(f.weights or default_weights_path())
        except DetectorFileError as exc:
            raise ScenarioError(f"{origins.label(('fusion', 'weights'))}: fusion.weights: {exc}") from None
