"""Scenario files: schema, loading and validation.

A scenario is a YAML file. Every field is checked on load; a bad file raises
:class:`ScenarioError` whose message names the file, the field and what was expected.
Paths inside a scenario (network, vehicle types) are relative to the scenario file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

NonNegative = Annotated[float, Field(ge=0.0)]
Positive = Annotated[float, Field(gt=0.0)]
Probability = Annotated[float, Field(ge=0.0, le=1.0)]


class ScenarioError(ValueError):
    """A scenario file that cannot be used. The message is meant for the user as is."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SimulationConfig(_Strict):
    step_s: Positive = 0.01
    max_time_s: Positive = 120.0
    # SUMO --lanechange.duration: lane changes take this long instead of one step.
    lanechange_duration_s: Positive = 3.0
    # Period of the all-vehicle trajectory table (the ego is also logged every SUMO step).
    trajectory_period_s: Positive = 0.1


class V2CConfig(_Strict):
    """Vehicle-to-cloud channel (uplink GNSS reports) and the cloud's twin store."""

    period_s: Positive = 0.1
    latency_s: NonNegative = 0.0
    # Standard deviation of a zero-mean Gaussian added to the latency (clipped at 0).
    jitter_s: NonNegative = 0.0
    loss_probability: Probability = 0.0
    # Standard deviation (per horizontal axis) of the GNSS position error.
    gnss_noise_std_m: NonNegative = 0.0
    history_s: Annotated[float, Field(ge=30.0)] = 30.0
    # A twin with no report for this long is taken as gone (vehicle left the road).
    twin_timeout_s: Positive = 3.0
    neighbour_range_m: Positive = 150.0


class AROverlayConfig(_Strict):
    period_s: Positive = 0.1
    # lane-change probability at or above which a neighbour is flagged yellow (medium) / red (high)
    medium_threshold: Probability = 0.3
    high_threshold: Probability = 0.6
    # write the AR overlay as PNG frames + an mp4 under renders/ (needs fusion.enabled)
    video: bool = False

    @model_validator(mode="after")
    def _ordered(self) -> "AROverlayConfig":
        if self.medium_threshold > self.high_threshold:
            raise ValueError(f"ar.medium_threshold: expected <= ar.high_threshold ({self.high_threshold}), "
                             f"got {self.medium_threshold}")
        return self


class FusionConfig(_Strict):
    """Vision-cloud fusion: detector, depth evaluation (Algorithm 1) and twin-to-box matching."""

    enabled: bool = False
    detector: Literal["cnn", "oracle"] = "cnn"
    # weights of the cnn detector (relative to the scenario file); default: the shipped model
    weights: Path | None = None
    method: Literal["baseline", "baseline_centre", "paper", "joint"] = "joint"
    depth_th: Annotated[float, Field(gt=0.0, le=1.0)] = 0.8
    depth_samples: Annotated[int, Field(ge=1)] = 30
    depth_reducer: Literal["mean", "median"] = "mean"


class CameraConfig(_Strict):
    """The ego's forward camera (paper Sec. II-B): mount on the ego and pinhole intrinsics.

    The mount is relative to the ego's footprint centre and heading: `forward_m` along the
    heading, `lateral_m` to the left, `height_m` above the ground; `pitch_deg` > 0 tilts the
    optical axis down. Square pixels, principal point at the image centre.
    """

    height_m: Positive = 1.4
    forward_m: float = 0.6
    lateral_m: float = 0.0
    pitch_deg: Annotated[float, Field(ge=-45.0, le=45.0)] = 3.0
    hfov_deg: Annotated[float, Field(gt=1.0, lt=170.0)] = 70.0
    width_px: Annotated[int, Field(ge=16, le=8192)] = 640
    height_px: Annotated[int, Field(ge=16, le=8192)] = 480
    # Clip planes of the renderer; depth beyond far_m reads as sky.
    near_m: Positive = 0.3
    far_m: Positive = 600.0
    # How the RGB image is finished (vcfusion.render.presets): "fast" for batch renders,
    # "quality" (supersampling, lens blur, noise) for studies; depth and instances are the same.
    render_preset: Literal["fast", "quality"] = "fast"

    @model_validator(mode="after")
    def _planes(self) -> "CameraConfig":
        if self.far_m <= self.near_m:
            raise ValueError(f"expected far_m > near_m ({self.near_m}), got far_m = {self.far_m}")
        return self


class VisionConfig(_Strict):
    """Whether the tick loop renders the ego camera (stages 4-6 of a tick)."""

    enabled: bool = False
    # Render every this many V2C ticks (1 = every tick).
    every_ticks: Annotated[int, Field(ge=1)] = 1


class EgoConfig(_Strict):
    vtype: str = "ego"
    lane: Annotated[int, Field(ge=0)] = 2
    depart_pos_m: NonNegative = 50.0
    speed_mps: NonNegative = 19.0
    desired_speed_mps: Positive = 19.0
    # The trip ends when the ego has travelled this far (or at simulation.max_time_s).
    trip_distance_m: Positive = 300.0


class DriverConfig(_Strict):
    """The ego's driver model (vcfusion.driver) and the guidance it is shown."""

    # Whether the driver uses the AR guidance in a single run (the guidance study runs both).
    guidance: bool = True
    # Guidance levels follow ar.medium_threshold / ar.high_threshold (one setting for overlay and driver).
    guidance_view_range_m: Positive = 150.0


class VehicleGroup(_Strict):
    """Vehicles placed at t = 0 at random positions (drawn per seed) in the given lanes."""

    name: str
    count: Annotated[int, Field(ge=1)]
    vtype: str = "car"
    lanes: list[Annotated[int, Field(ge=0)]] = Field(min_length=1)
    pos_m: tuple[NonNegative, NonNegative]
    speed_mps: NonNegative = 17.0
    desired_speed_mps: Positive | None = None
    # Minimum bumper-to-bumper spacing in one lane (SUMO refuses to insert at 17 m/s with much less).
    min_spacing_m: NonNegative = 20.0

    @field_validator("pos_m")
    @classmethod
    def _ordered(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] > v[1]:
            raise ValueError("expected [low, high] with low <= high")
        return v


class Flow(_Strict):
    """Poisson arrivals at the start of the road over the whole run."""

    vtype: str = "car"
    vehs_per_hour: Positive
    lanes: list[Annotated[int, Field(ge=0)]] = Field(min_length=1)
    speed_mps: NonNegative = 25.0


class AccidentConfig(_Strict):
    """Stopped vehicles closing lanes (SUMO <stop parking="false">)."""

    pos_m: NonNegative
    lanes: list[Annotated[int, Field(ge=0)]] = Field(min_length=1)
    vtype: str = "truck"


class PredictionConfig(_Strict):
    """The cloud's lane-change predictor (a twin process model, vcfusion.prediction)."""

    enabled: bool = True
    # Model file from `vcfusion train`; None = the model shipped in vcfusion/assets.
    model: Path | None = None
    # Smoothing of the per-tick decisions (paper Algorithms 3 and 4): none | aggressive | conservative;
    # None = the model file's default (chosen on validation seeds by `vcfusion train`).
    smoothing: Literal["none", "aggressive", "conservative"] | None = None
    # Probability above which the raw per-tick decision is positive (None = the model file's threshold
    # tuned for that smoothing).
    threshold: Probability | None = None
    # Algorithm 3: a positive lasts tau_a more V2C ticks; Algorithm 4: mean of the last tau_c + 1 ticks.
    # None = the values stored in the model file (tuned on validation seeds by `vcfusion train`).
    tau_a_ticks: Annotated[int, Field(ge=0)] | None = None
    tau_c_ticks: Annotated[int, Field(ge=0)] | None = None
    conservative_threshold: Probability = 0.5


class Scenario(_Strict):
    name: str
    description: str = ""
    network: Path
    vehicle_types: Path
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
    # Where the scenario was read from (set by the loader, not by the file).
    source: Path | None = Field(default=None, exclude=True)

    @model_validator(mode="after")
    def _consistent(self) -> "Scenario":
        step = self.simulation.step_s
        for name, period in (
            ("v2c.period_s", self.v2c.period_s),
            ("ar.period_s", self.ar.period_s),
            ("simulation.trajectory_period_s", self.simulation.trajectory_period_s),
        ):
            ratio = period / step
            if abs(ratio - round(ratio)) > 1e-6:
                raise ValueError(f"{name}: expected a whole multiple of simulation.step_s ({step}), got {period}")
        if self.vision.enabled and self.ego is None:
            raise ValueError("vision.enabled: the camera rides on the ego; expected an ego block")
        if self.fusion.enabled:
            if not self.vision.enabled:
                raise ValueError("fusion.enabled: expected vision.enabled: true (fusion needs the ego camera)")
        if self.ar.video and not self.fusion.enabled:
            raise ValueError("ar.video: expected fusion.enabled: true (the overlay needs the fusion stage)")
        if not self.vehicles and not self.flows and self.ego is None:
            raise ValueError("expected at least one of ego, vehicles, flows")
        return self

    def steps(self, period_s: float) -> int:
        """Number of SUMO steps in one period."""
        return int(round(period_s / self.simulation.step_s))

    def to_dict(self) -> dict:
        return self.model_dump(mode="json")


def _format_location(loc: tuple) -> str:
    parts = []
    for item in loc:
        if isinstance(item, int):
            parts.append(f"[{item}]")
        else:
            parts.append(("." if parts else "") + str(item))
    return "".join(parts) or "(top level)"


def _describe(err: dict) -> str:
    kind = err.get("type", "")
    if kind == "extra_forbidden":
        return "unknown key"
    if kind == "missing":
        return "required field is missing"
    msg = err.get("msg", "invalid value")
    msg = msg.removeprefix("Value error, ")
    got = err.get("input")
    if kind not in ("missing",) and not isinstance(got, (dict, list)):
        msg += f" (got {got!r})"
    return msg


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario file; raises ScenarioError with one clear message."""
    path = Path(path)
    if not path.is_file():
        raise ScenarioError(f"{path}: scenario file not found")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(raw, dict):
        raise ScenarioError(f"{path}: expected a mapping of scenario fields at the top level")
    try:
        scenario = Scenario.model_validate(raw)
    except ValidationError as exc:
        lines = []
        for err in exc.errors():
            where = _format_location(err["loc"])
            if err["type"] == "value_error" and not err["loc"] and ":" in err["msg"]:
                where, _, rest = err["msg"].removeprefix("Value error, ").partition(": ")
                lines.append(f"{path}: {where}: {rest}")
            else:
                lines.append(f"{path}: {where}: {_describe(err)}")
        raise ScenarioError("\n".join(lines)) from None
    base = path.parent
    resolved = {}
    for field in ("network", "vehicle_types"):
        target = (base / getattr(scenario, field)).resolve()
        if not target.is_file():
            raise ScenarioError(f"{path}: {field}: file not found: {getattr(scenario, field)} (relative to the scenario file)")
        resolved[field] = target
    pred = scenario.prediction
    if pred.enabled and pred.model is not None:
        target = (base / pred.model).resolve()
        if not target.is_file():
            raise ScenarioError(f"{path}: prediction.model: file not found: {pred.model} (relative to the scenario file)")
        resolved["prediction"] = pred.model_copy(update={"model": target})
    if scenario.fusion.weights is not None:
        weights = (base / scenario.fusion.weights).resolve()
        if not weights.is_file():
            raise ScenarioError(f"{path}: fusion.weights: file not found: {scenario.fusion.weights} "
                                "(relative to the scenario file)")
        resolved["fusion"] = scenario.fusion.model_copy(update={"weights": weights})
    return scenario.model_copy(update={**resolved, "source": path})

