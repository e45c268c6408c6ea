"""Typed records passed between the stages of a tick.

All are struct-of-arrays: one NumPy array per field, one element per vehicle, so a stage
works on all vehicles at once and can be tested without SUMO by building a record by hand.

Conventions (see docs/architecture.md):
- world frame is SUMO's (x east, y north, z up), metres;
- (x, y, z) of a vehicle is the centre of its footprint on the ground, not SUMO's front bumper;
- heading is the yaw in radians, counter-clockwise from +x (SUMO's angle is converted once,
  in vcfusion.traffic.session);
- a vehicle's GNSS point is the centre of its body: the footprint centre raised by half the
  vehicle height (:func:`gnss_antenna_points`), as the paper's simulator reports a vehicle's
  position. (A roof-top point would project onto the top edge of the vehicle's image box, where
  the paper's "anchor inside the box" test is ill-conditioned.)
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

# The ego's vehicle id, in SUMO and in every table (one definition for all stages).
EGO_ID = "ego"

# The camera's vehicle categories (SUMO vehicle classes; dataset and detector ids are index + 1,
# fixed so datasets of different scenarios share them), and the SUMO classes each one covers.
# Other classes (bicycle, pedestrian, tram, rail, ship, ...) the camera can neither draw nor label.
VEHICLE_CATEGORIES = ("passenger", "truck", "bus", "coach", "delivery", "trailer", "motorcycle", "emergency", "taxi")
CATEGORY_OF_VCLASS = {c: c for c in VEHICLE_CATEGORIES} | {
    "private": "passenger", "evehicle": "passenger", "hov": "passenger", "vip": "passenger",
    "authority": "passenger", "moped": "motorcycle"}

_FIELD_NAMES: dict[type, tuple[str, ...]] = {}


def _take(record, index):
    """The same record restricted to `index` (for every per-vehicle field)."""
    names = _FIELD_NAMES.get(type(record))
    if names is None:  # dataclasses.fields() is slow on the per-tick path: look it up once
        names = _FIELD_NAMES[type(record)] = tuple(f.name for f in fields(record))
    index = np.asarray(index)
    if index.dtype == bool:
        index = index.nonzero()[0]
    listed = None  # the index as Python ints, for the tuple fields (ids, types)
    values = {}
    for name in names:
        v = getattr(record, name)
        if isinstance(v, np.ndarray):
            values[name] = v[index]
        elif isinstance(v, tuple):
            if listed is None:
                listed = index.tolist()
            values[name] = tuple([v[i] for i in listed])
        else:
            values[name] = v
    sub = type(record)(**values)
    cached = record.__dict__.get(_ROAD_FRAME)
    if cached is not None:
        keep_road_frame(sub, cached[0], cached[1][index], cached[2][index])
    return sub


_ROAD_FRAME = "_road_frame"  # per-record cache: (road, s, d)


def keep_road_frame(record, road, s: np.ndarray, d: np.ndarray) -> None:
    """Hand a record the (s, d) its producer already computed on `road` (see _road_frame)."""
    object.__setattr__(record, _ROAD_FRAME, (road, s, d))


def _road_frame(record, road) -> tuple[np.ndarray, np.ndarray]:
    """(s, d) of every vehicle of a record on `road`, computed once per record: several stages of
    a tick need them, and the records are immutable (a changed position is a new record). Keyed
    by the road's value: equal roads (stages each read the network file) share it."""
    cached = record.__dict__.get(_ROAD_FRAME)
    if cached is None or cached[0] != road:
        cached = (road, *road.to_road_frame(record.x, record.y))
        keep_road_frame(record, *cached)
    return cached[1], cached[2]


@dataclass(frozen=True)
class VehicleStates:
    """Ground truth of every vehicle at one instant (from SUMO)."""

    time: float
    ids: tuple[str, ...]
    vtype: tuple[str, ...]
    vclass: tuple[str, ...]
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    heading: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    lane: np.ndarray  # int16, track of the scenario's route (lane index from the right), -1 off the route
    lateral_offset: np.ndarray  # metres left of the lane centre
    length: np.ndarray
    width: np.ndarray
    height: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    def index_of(self, vehicle_id: str) -> int:
        return self.ids.index(vehicle_id)

    def select(self, index) -> "VehicleStates":
        return _take(self, index)

    def road_frame(self, road) -> tuple[np.ndarray, np.ndarray]:
        """(s, d) of the footprint centres on `road` (see RoadFrame.to_frame); computed once."""
        return _road_frame(self, road)


# Height of the GNSS point above the ground, as a fraction of the vehicle height.
GNSS_HEIGHT_FRACTION = 0.5


def gnss_antenna_points(x: np.ndarray, y: np.ndarray, z: np.ndarray, height: np.ndarray) -> np.ndarray:
    """World positions (N, 3) of the GNSS point: the centre of the vehicle body."""
    out = np.empty((*np.shape(x), 3))
    out[..., 0], out[..., 1], out[..., 2] = x, y, z + GNSS_HEIGHT_FRACTION * np.asarray(height)
    return out


def add_gnss_error(antenna: np.ndarray, std_m: float, rng: np.random.Generator) -> np.ndarray:
    """``antenna`` (N, 3) with a zero-mean Gaussian error of ``std_m`` added to each horizontal axis
    (in place; returned), the GNSS model of the V2C channel; nothing drawn when ``std_m`` is 0."""
    if std_m > 0 and len(antenna):
        antenna[:, :2] += rng.normal(0.0, std_m, size=(len(antenna), 2))
    return antenna


@dataclass(frozen=True)
class GnssReports:
    """What vehicles send over the V2C uplink, stamped with the time they were measured."""

    measured_time: np.ndarray  # s
    ids: tuple[str, ...]
    x: np.ndarray  # GNSS antenna point, with GNSS error
    y: np.ndarray
    z: np.ndarray
    heading: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    length: np.ndarray
    width: np.ndarray
    height: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    def select(self, index) -> "GnssReports":
        return _take(self, index)


@dataclass(frozen=True)
class TwinStates:
    """The cloud Digital Twins' latest states, as the ego receives them.

    `outputs` holds the columns written by twin process models (e.g. `lc_prob`), aligned
    with `ids`.
    """

    time: float  # cloud time of this snapshot
    ids: tuple[str, ...]
    measured_time: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    heading: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    lane: np.ndarray  # track map-matched from the GNSS position (RoadFrame.locate), -1 off the road
    length: np.ndarray
    width: np.ndarray
    height: np.ndarray
    outputs: dict

    def __len__(self) -> int:
        return len(self.ids)

    def select(self, index) -> "TwinStates":
        sub = _take(self, index)
        # `outputs` is a dict, which _take passes through: restrict its columns too.
        object.__setattr__(sub, "outputs", {k: np.asarray(v)[index] for k, v in self.outputs.items()})
        return sub

    def road_frame(self, road) -> tuple[np.ndarray, np.ndarray]:
        """(s, d) of the twins' GNSS points on `road` (see RoadFrame.to_frame); computed once."""
        return _road_frame(self, road)


@dataclass(frozen=True)
class Guidance:
    """One item of AR guidance shown to the driver at a tick (part of a :class:`GuidanceSet`).

    Made by the vision-cloud fusion stage (a twin's lane-change probability drawn on the box the
    matcher gave it: no matched box, no item) or by the cloud guidance stage (no image: the item
    marks the twin itself); its level follows the run's :class:`vcfusion.guidance.GuidancePolicy`.
    ``vehicle_id`` is the twin the cloud meant; ``box_vehicle_id`` the vehicle actually inside the
    drawn box (the one owning most of the box's pixels in the rendered instance map; None when no
    vehicle is). The driver model responds to :attr:`shown_vehicle_id`, the vehicle it sees
    highlighted: a box drawn around the wrong car misleads the driver, as it would a person.
    """

    time: float
    vehicle_id: str
    lc_prob: float
    level: str  # one of vcfusion.guidance.GUIDANCE_LEVELS
    box: tuple[float, float, float, float] | None  # matched image box (x1, y1, x2, y2) px; None: no image
    box_vehicle_id: str | None = None  # the vehicle owning most pixels of `box` (fusion items)
    # camera-Z of the matched box's vehicle, m, as the fusion measured it (Algorithm 1 on the depth
    # image it saw); the display moves the box between vision ticks with it. None: not measured
    box_depth_m: float | None = None

    @property
    def shown_vehicle_id(self) -> str | None:
        """The vehicle the driver sees highlighted: the one in the box, or the twin itself for an
        item without a box (cloud guidance); None for a box around no vehicle."""
        return self.box_vehicle_id if self.box is not None else self.vehicle_id


GUIDANCE_SOURCES = ("fusion", "cloud", "none")


@dataclass(frozen=True)
class GuidanceSet:
    """What the driver is shown at one tick (``Tick.guidance``) and where it came from:
    ``fusion`` (the AR overlay's matched boxes), ``cloud`` (the cloud's predictions, no image) or
    ``none`` (no process model writes ``lc_prob``: nothing can be shown)."""

    items: tuple[Guidance, ...]
    source: str

    def __post_init__(self):
        if self.source not in GUIDANCE_SOURCES:
            raise ValueError(f"guidance source: expected one of {GUIDANCE_SOURCES}, got {self.source!r}")
