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
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError, field_validator, model_validator

from vcfusion.errors import ScenarioError  # the loader's error; importable from here as before

# the repository's scenario files (the package is installed from the checkout), for defaults that
# must work from any working directory
SHIPPED_SCENARIOS = Path(__file__).resolve().parents[2] / "scenarios"

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
    step_s: Positive = 0.01
    max_time_s: Positive = 120.0
    # SUMO --lanechange.duration: lane changes take this long instead of one step.
    lanechange_duration_s: Positive = 3.0
    # Period of the all-vehicle trajectory table (the ego is also logged every SUMO step).
    trajectory_period_s: Positive = 0.1

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
    # The ego receives the twins within this horizontal range (m): with the camera fusing, at least
    # vcfusion.fusion.stage.matching_reach_m(driver.guidance_view_range_m) (199 m for 150 m), so that
    # every vehicle whose box the matcher could give to a warned twin has a twin of its own.
    neighbour_range_m: Positive = 200.0

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
    period_s: Positive = 0.1
    # calibrated lane-change probability at or above which a flagged neighbour is yellow (medium) /
    # red (high), for the overlay, the cloud guidance and the driver alike; why 0.3 / 0.6: vcfusion.guidance
    medium_threshold: Probability = 0.3
    high_threshold: Probability = 0.6
    # write the AR overlay as PNG frames + an mp4 into the run folder (needs fusion.enabled)
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
    detector: Literal["cnn", "oracle", "onnx-yolo"] = "cnn"
    # weights of the cnn detector (relative to the scenario file); default: the shipped model.
    # onnx-yolo: the user's YOLO exported by Ultralytics to ONNX (required; read by OpenCV DNN)
    weights: Path | None = None
    # onnx-yolo: the model's input size (width, height) and the COCO classes kept as vehicles
    yolo_input_px: tuple[Annotated[int, Field(ge=32, le=4096)], Annotated[int, Field(ge=32, le=4096)]] = (640, 640)
    yolo_classes: Annotated[tuple[str, ...], Field(min_length=1)] = ("car", "bus", "truck")
    method: Literal["baseline", "baseline_centre", "paper", "joint"] = "joint"
    # snap the detector's boxes to the vehicle surfaces of the depth image before matching and add
    # boxes for vehicles it missed, from depth segments (vcfusion.fusion.box_refine; never the
    # oracle's); false: the detector's RGB boxes as they are
    refine_boxes: bool = True
    depth_th: Annotated[float, Field(gt=0.0, le=1.0)] = 0.8
    depth_samples: Annotated[int, Field(ge=1)] = 30
    depth_reducer: Literal["mean", "median"] = "mean"

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
    # Render and fuse only at ticks where a neighbour twin carries a warning (the overlay then has
    # something to warn about; at other ticks it would draw no warning, so the driver is shown the
    # same warnings). Off by default: the joint matcher's position filter then gets fewer
    # updates, so the identification is not the every-tick system's; the video needs it off.
    only_when_warning: bool = False


class EgoConfig(_Strict):
    vtype: Name = "ego"
    # the ego's route (default: the scenario's); lane: a track of it (index from the right), and
    # depart_pos_m (front bumper) along it
    route: Route | None = None
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
    # Guidance items are made for neighbours ahead within this range; levels follow ar.medium_threshold /
    # ar.high_threshold (one GuidancePolicy per run, vcfusion.guidance).
    guidance_view_range_m: Positive = 150.0
    # The driver's forward field of view (degrees); default: the camera's hfov_deg (the AR shows
    # the camera's view). See vcfusion.driver.perception.
    field_of_view_deg: Annotated[float, Field(gt=1.0, lt=180.0)] | None = None


class VehicleGroup(_Strict):
    """Vehicles placed at t = 0 at random positions (drawn per seed) in the given lanes."""

    name: Name
    count: Annotated[int, Field(ge=1)]
    vtype: Name = "car"
    # the group's route (default: the scenario's); lanes are its tracks (index from the right) and
    # pos_m the front bumpers' range along it
    route: Route | None = None
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
    """Poisson arrivals at the start of the route (the flow's, default the scenario's) over the
    whole run, in the given tracks of that route's first edge."""

    vtype: Name = "car"
    route: Route | None = None
    vehs_per_hour: Positive
    lanes: list[Annotated[int, Field(ge=0)]] = Field(min_length=1)
    speed_mps: NonNegative = 25.0


class AccidentConfig(_Strict):
    """Stopped vehicles closing lanes (SUMO <stop parking="false">): tracks of the scenario's
    route at pos_m (front bumper) along `edge`, or along the route when no edge is given."""

    edge: Name | None = None
    pos_m: NonNegative
    lanes: list[Annotated[int, Field(ge=0)]] = Field(min_length=1)
    vtype: Name = "truck"


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
    conservative_threshold: Probability | None = None  # None = the model file's (0.5 in the shipped ones)


class MetricsConfig(_Strict):
    """Safety, comfort and emission metrics of every vehicle of a run (vcfusion.metrics).

    One place for the thresholds and definitions: runs, batches, `vcfusion metrics` and the
    guidance study all read them from here (docs/architecture.md, "Metrics").
    """

    enabled: bool = True
    # TTC below which a following situation is a conflict (TET/TIT, conflict episodes): 1.5 s, the
    # SSAM default (Gettman & Head, "Surrogate Safety Measures From Traffic Simulation Models",
    # FHWA-RD-03-050, 2003; Gettman et al., "Surrogate Safety Assessment Model and Validation",
    # FHWA-HRT-08-051, 2008).
    ttc_threshold_s: Positive = 1.5
    # Jerk: the acceleration (speed difference per sample) is smoothed by a centred moving average
    # over this window before it is differentiated (one V2C tick: the ego's command is piecewise
    # constant over a tick; at the 0.1 s trajectory period it is no smoothing).
    jerk_window_s: Positive = 0.1
    # The guidance study's mean TTC to the cut-in vehicle is also given with TTC clipped here.
    ttc_clip_s: Positive = 20.0
    # A vehicle's leader is the nearest vehicle ahead in its lane within this range (bumper to bumper).
    leader_range_m: Positive = 250.0
    # MOVESTAR source type (1 light-duty passenger car, 2 light-duty truck) by SUMO vType id or vClass
    # (the vType id wins); vehicles of other types (trucks, buses) get SUMO's emission model only.
    movestar: dict[Name, Literal[1, 2]] = {"passenger": 1}
    # The vehicles SUMO's own emission model rates (HBEFA/PHEMlight, the class their vType sets):
    # "others" = those without a MOVESTAR type (trucks, buses: every vehicle gets one model), "all"
    # (the cars too, a second opinion; SUMO then rates every vehicle every step, which costs the run
    # ~20-30 %), "none".
    sumo_emissions: Literal["others", "all", "none"] = "others"
    # Vehicles of these placement groups (vehicles.parquet `group`) keep their rows and still lead
    # others, but are left out of the traffic-wide figures (the parked accident vehicles are obstacles).
    exclude_groups: list[Name] = ["accident"]


class Scenario(_Strict):
    name: Name
    description: str = ""
    network: Path
    # the road frame's route (edge ids in driving order) and every vehicle's default route; a
    # network that is one chain of edges (e.g. one straight edge) needs none
    route: Route | None = None
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
    metrics: MetricsConfig = MetricsConfig()
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
        return self.model_dump(mode="json")


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


def load_scenario(path: str | Path) -> Scenario:
    """Read, merge (`extends`) and validate a scenario file and the files it names; raises
    ScenarioError with one line per problem naming the file, the field and what was expected."""
    path = Path(path)
    if not path.is_file():
        raise ScenarioError(f"{path}: scenario file not found")
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
