"""Procedural scenes for training and testing the detector, without a SUMO run.

A scene is a :class:`SceneRecipe`: the ego on a straight road, its camera mount (jittered) and a
list of vehicles placed directly on the road relative to the ego's camera. :func:`sample_scene`
draws one from a seed and a *family*: ``train`` (the training sampler) or one of the held-out
families in :data:`HELD_OUT` that the training sampler never emits.

Training distribution (``train``; all draws uniform unless said otherwise, per scene):
- ego: lane uniform over the road's lanes, position s uniform in [300, 1500] m of the road;
- camera mount: height 1.4 +- 0.25 m, pitch 3 +- 3 deg, lateral offset +- 0.4 m, forward 0.6 m
  (the scenario's camera otherwise: field of view, image size);
- 2-7 *patterns*, each one of (weights in brackets): a single vehicle [3], a same-lane chain of 2-4
  vehicles with bumper gaps 0.8-8 m [2], a side-by-side pair in adjacent lanes at the same
  distance (+- 0.5 m) [2], a truck in front of a car (same lane, gap 1-15 m; the car's lateral
  offset from the truck's within +- 1.5 m: hidden, or peeking out beside it) [1],
  a truck beside a car (adjacent lanes, same distance +- 2 m) [1], a vehicle mid lane change
  (yaw 2-9 deg towards a neighbouring lane, centre 0.3-1.7 m off its lane centre) [1.5], a near
  vehicle (rear 3-12 m ahead) in a neighbouring lane, often truncated at the image border (about
  two in five with the default camera) [1];
- a pattern's nearest rear face is 3-150 m ahead of the camera, log-uniform (as many near as far
  vehicles per metre of image height); lanes uniform over all lanes (patterns needing a
  neighbour lane pick one that exists);
- vehicles: car 75 % / truck 25 % (patterns naming a kind excepted); car length 3.8-5.2 m, width
  1.65-2.0 m, height 1.35-1.8 m; truck length 7-16.5 m, width 2.4-2.6 m, height 3.0-4.0 m; lateral
  offset in the lane +- 0.35 m, yaw +- 1 deg (lane changes excepted); body colour uniform over
  the renderer's palette (it follows the vehicle id, which is random); speed 5-36 m/s;
- placement: a vehicle whose footprint (plus 0.3 m) overlaps one already placed is dropped;
- rejection: a scene that matches any held-out family's predicate is redrawn (same generator).

The sun direction is fixed by the renderer (``vcfusion.render.scene``); it is not sampled.

Held-out families (each recipe below; the test ``test_scenes`` checks the training sampler never
matches their predicates, :func:`held_out_families`):
- ``jam``: every lane (of up to 3) holds a chain of >= 3 vehicles within 60 m with bumper gaps
  <= 4 m; speeds 3-5 m/s;
- ``far_chain``: two vehicles in the ego's lane, bumper gap <= 10 m, the nearer one's rear
  60-120 m ahead;
- ``cut_in``: a vehicle in a lane next to the ego's, yawed >= 2 deg towards the ego's lane, its
  centre 10-20 m ahead;
- ``truck_occlusion``: a car further than a truck whose rear is 8-35 m ahead, 30-90 % of the car's
  projected 3D box covered by the truck's (:func:`occluded_fraction`: the car is partly hidden).
- ``high_mount``: the camera of a van or a truck cab, 1.8-2.3 m high (the training sampler's stops at
  1.65 m) and pitched 3-8 deg down, over 3-6 of the training patterns (a view of the road no
  training scene and no tuning of the depth step has seen: the family held out by family, frozen
  before the depth step's road fit was tuned).
- ``low_mount``: the camera of a low car, 0.95-1.10 m high (the training sampler's starts at 1.15 m)
  and pitched -1 to +2 deg (nearly level: the road seen at a grazing angle, nearer cars hide more of
  the ones behind them), over 4-8 of the training patterns (a second view no training scene and no
  tuning of the depth step has seen: frozen before the depth step's noisy-sensor work was tuned).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from vcfusion.errors import InputError
from vcfusion.records import EGO_ID, VehicleStates

CAR, TRUCK = "passenger", "truck"
CAR_SIZE = ((3.8, 5.2), (1.65, 2.0), (1.35, 1.8))  # length, width, height ranges (m)
TRUCK_SIZE = ((7.0, 16.5), (2.4, 2.6), (3.0, 4.0))
EGO_SIZE = (4.6, 1.8, 1.5)
MIN_AHEAD_M, MAX_AHEAD_M = 3.0, 150.0
CAMERA_FORWARD_M = 0.6
EGO_S_RANGE_M = (300.0, 1500.0)  # ego position along the road
FOOTPRINT_MARGIN_M = 0.3

# held-out recipes' thresholds (shared by the generators and the predicates)
JAM_RANGE_M, JAM_GAP_M, JAM_MIN_CHAIN = 60.0, 4.0, 3
FAR_CHAIN_RANGE_M, FAR_CHAIN_GAP_M = (60.0, 120.0), 10.0
CUT_IN_RANGE_M, CUT_IN_MIN_YAW = (10.0, 20.0), math.radians(2.0)
OCCLUSION_RANGE_M, OCCLUSION_SHARE = (8.0, 35.0), (0.3, 0.9)


@dataclass(frozen=True)
class PlacedVehicle:
    """A vehicle of a scene, in the road frame relative to the ego's camera."""

    vehicle_id: str
    vclass: str  # passenger or truck (the renderer's mesh family; COCO category)
    lane: int  # road lane of its centre line (0 = rightmost)
    ahead_m: float  # footprint centre's s minus the camera's s
    lateral_m: float  # footprint centre's offset from its lane centre, + left
    yaw_rad: float  # heading relative to the road, + left
    length: float
    width: float
    height: float
    speed: float

    @property
    def rear_m(self) -> float:
        return self.ahead_m - self.length / 2

    @property
    def front_m(self) -> float:
        return self.ahead_m + self.length / 2


@dataclass(frozen=True)
class CameraMount:
    height_m: float
    pitch_deg: float
    lateral_m: float
    forward_m: float = CAMERA_FORWARD_M


@dataclass(frozen=True)
class SceneRecipe:
    family: str
    seed: int
    num_lanes: int
    lane_width_m: float
    ego_lane: int
    ego_s: float
    mount: CameraMount
    vehicles: tuple[PlacedVehicle, ...] = field(default=())

    def to_dict(self) -> dict:
        return {"family": self.family, "seed": self.seed, "ego_lane": self.ego_lane, "ego_s": self.ego_s,
                "mount": vars(self.mount).copy(), "vehicles": [vars(v).copy() for v in self.vehicles]}


# ---------------------------------------------------------------------------------------------
# held-out predicates (pure geometry of a recipe)


def _lane_chains(recipe: SceneRecipe, lane: int, max_gap: float) -> list[list[PlacedVehicle]]:
    """Runs of vehicles in a lane (ordered by distance) whose bumper gaps are <= max_gap."""
    cars = sorted((v for v in recipe.vehicles if v.lane == lane), key=lambda v: v.ahead_m)
    chains, run = [], []
    for v in cars:
        if run and v.rear_m - run[-1].front_m > max_gap:
            chains.append(run)
            run = []
        run.append(v)
    if run:
        chains.append(run)
    return chains


def is_jam(recipe: SceneRecipe) -> bool:
    lanes = range(recipe.num_lanes)
    need = min(3, recipe.num_lanes)
    full = sum(any(len([v for v in c if v.rear_m <= JAM_RANGE_M]) >= JAM_MIN_CHAIN
                   for c in _lane_chains(recipe, lane, JAM_GAP_M)) for lane in lanes)
    return full >= need


def is_far_chain(recipe: SceneRecipe) -> bool:
    lo, hi = FAR_CHAIN_RANGE_M
    for chain in _lane_chains(recipe, recipe.ego_lane, FAR_CHAIN_GAP_M):
        if any(lo <= a.rear_m <= hi for a in chain[:-1]):
            return True
    return False


def is_cut_in(recipe: SceneRecipe) -> bool:
    lo, hi = CUT_IN_RANGE_M
    for v in recipe.vehicles:
        towards = np.sign(recipe.ego_lane - v.lane)
        if (abs(v.lane - recipe.ego_lane) == 1 and lo <= v.ahead_m <= hi
                and towards * v.yaw_rad >= CUT_IN_MIN_YAW):
            return True
    return False


def _camera_box(v: PlacedVehicle, recipe: SceneRecipe) -> tuple[float, float, float, float] | None:
    """Box (normalised image coordinates, focal length 1) of a vehicle's 3D box seen from the
    recipe's camera; None where part of it is behind the camera. Pitch included; no image border."""
    m = recipe.mount
    cam_d = (recipe.ego_lane + 0.5) * recipe.lane_width_m + m.lateral_m
    d = (v.lane + 0.5) * recipe.lane_width_m + v.lateral_m
    c, s = math.cos(v.yaw_rad), math.sin(v.yaw_rad)
    p = math.radians(m.pitch_deg)
    us, vs = [], []
    for dl in (-v.length / 2, v.length / 2):
        for dw in (-v.width / 2, v.width / 2):
            fwd = v.ahead_m + dl * c - dw * s
            left = d + dl * s + dw * c - cam_d
            for up in (-m.height_m, v.height - m.height_m):
                z = fwd * math.cos(p) - up * math.sin(p)
                y = -fwd * math.sin(p) - up * math.cos(p)
                if z <= 0.1:
                    return None
                us.append(-left / z)
                vs.append(y / z)
    return min(us), min(vs), max(us), max(vs)


def occluded_fraction(far: PlacedVehicle, near: PlacedVehicle, recipe: SceneRecipe) -> float:
    """Share of ``far``'s projected box covered by ``near``'s (0 where either is behind the camera)."""
    a, b = _camera_box(far, recipe), _camera_box(near, recipe)
    if a is None or b is None:
        return 0.0
    w = min(a[2], b[2]) - max(a[0], b[0])
    h = min(a[3], b[3]) - max(a[1], b[1])
    area = (a[2] - a[0]) * (a[3] - a[1])
    return max(w, 0.0) * max(h, 0.0) / area if area > 0 else 0.0


def is_truck_occlusion(recipe: SceneRecipe) -> bool:
    lo, hi = OCCLUSION_RANGE_M
    for truck in (v for v in recipe.vehicles if v.vclass == TRUCK and lo <= v.rear_m <= hi):
        for car in recipe.vehicles:
            if (car.vclass == CAR and car.ahead_m > truck.ahead_m
                    and OCCLUSION_SHARE[0] <= occluded_fraction(car, truck, recipe) <= OCCLUSION_SHARE[1]):
                return True
    return False


HIGH_MOUNT_HEIGHT_M, HIGH_MOUNT_PITCH_DEG = (1.8, 2.3), (3.0, 8.0)


def is_high_mount(recipe: SceneRecipe) -> bool:
    return recipe.mount.height_m >= HIGH_MOUNT_HEIGHT_M[0] - 0.05


LOW_MOUNT_HEIGHT_M, LOW_MOUNT_PITCH_DEG = (0.95, 1.10), (-1.0, 2.0)


def is_low_mount(recipe: SceneRecipe) -> bool:
    return recipe.mount.height_m <= LOW_MOUNT_HEIGHT_M[1] + 0.02


HELD_OUT = {"jam": is_jam, "far_chain": is_far_chain, "cut_in": is_cut_in, "truck_occlusion": is_truck_occlusion,
            "high_mount": is_high_mount, "low_mount": is_low_mount}
FAMILIES = ("train", *HELD_OUT)


def held_out_families(recipe: SceneRecipe) -> list[str]:
    """The held-out families whose predicate the recipe matches."""
    return [name for name, pred in HELD_OUT.items() if pred(recipe)]


# ---------------------------------------------------------------------------------------------
# sampling


class _Builder:
    def __init__(self, rng: np.random.Generator, recipe: SceneRecipe, prefix: str):
        self.rng = rng
        self.recipe = recipe
        self.prefix = prefix
        self.placed: list[PlacedVehicle] = []

    def size(self, vclass: str) -> tuple[float, float, float]:
        ranges = TRUCK_SIZE if vclass == TRUCK else CAR_SIZE
        return tuple(float(self.rng.uniform(lo, hi)) for lo, hi in ranges)

    def kind(self) -> str:
        return TRUCK if self.rng.random() < 0.25 else CAR

    def vehicle(self, vclass: str, lane: int, rear_m: float | None, lateral_m: float | None = None,
                yaw: float | None = None, speed: float | None = None,
                centre_m: float | None = None) -> PlacedVehicle | None:
        """Place a vehicle by its rear (or its centre); None (nothing placed) where it would collide,
        where its lane is not a lane of the road, or outside the 3-150 m range (a lateral offset is
        not checked against the road's edge: a body may reach over it, as in a lane change)."""
        length, width, height = self.size(vclass)
        if rear_m is None:
            rear_m = centre_m - length / 2
        if not 0 <= lane < self.recipe.num_lanes or rear_m < MIN_AHEAD_M or rear_m > MAX_AHEAD_M:
            return None
        rng = self.rng
        v = PlacedVehicle(
            vehicle_id=f"{self.prefix}{len(self.placed)}_{rng.integers(1 << 30):08x}", vclass=vclass, lane=int(lane),
            ahead_m=float(rear_m + length / 2),
            lateral_m=float(rng.uniform(-0.35, 0.35) if lateral_m is None else lateral_m),
            yaw_rad=float(rng.uniform(-1, 1) * math.radians(1.0) if yaw is None else yaw),
            length=length, width=width, height=height,
            speed=float(rng.uniform(5.0, 36.0) if speed is None else speed))
        if any(_footprints_overlap(v, o, self.recipe.lane_width_m) for o in self.placed):
            return None
        self.placed.append(v)
        return v

    def chain(self, lane: int, rear_m: float, n: int, gap: tuple[float, float], kind=None, speed=None,
              jitter_m: float = 0.35) -> list[PlacedVehicle]:
        out = []
        for _ in range(n):
            lat = float(self.rng.uniform(-jitter_m, jitter_m))
            v = self.vehicle(kind or self.kind(), lane, rear_m, lateral_m=lat, speed=speed)
            if v is None:
                break
            out.append(v)
            rear_m = v.front_m + float(self.rng.uniform(*gap))
        return out


def _footprints_overlap(a: PlacedVehicle, b: PlacedVehicle, lane_width: float) -> bool:
    """Conservative: road-frame bounding rectangles of the (yawed) footprints plus a margin."""
    def rect(v):
        c, s = abs(math.cos(v.yaw_rad)), abs(math.sin(v.yaw_rad))
        half_s = (v.length * c + v.width * s) / 2 + FOOTPRINT_MARGIN_M / 2
        half_d = (v.length * s + v.width * c) / 2 + FOOTPRINT_MARGIN_M / 2
        d = (v.lane + 0.5) * lane_width + v.lateral_m
        return v.ahead_m - half_s, v.ahead_m + half_s, d - half_d, d + half_d

    a0, a1, a2, a3 = rect(a)
    b0, b1, b2, b3 = rect(b)
    return a0 < b1 and b0 < a1 and a2 < b3 and b2 < a3


def _log_uniform(rng, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _neighbour(rng, lane: int, num_lanes: int) -> int | None:
    options = [k for k in (lane - 1, lane + 1) if 0 <= k < num_lanes]
    return int(rng.choice(options)) if options else None


PATTERN_WEIGHTS = {"single": 3.0, "chain": 2.0, "pair": 2.0, "truck_front": 1.0, "truck_beside": 1.0,
                   "lane_change": 1.5, "near_side": 1.0}


def _train_pattern(b: _Builder, name: str) -> None:
    rng, r = b.rng, b.recipe
    lane = int(rng.integers(r.num_lanes))
    rear = _log_uniform(rng, MIN_AHEAD_M, MAX_AHEAD_M)
    if name == "single":
        b.vehicle(b.kind(), lane, rear)
    elif name == "chain":
        b.chain(lane, rear, int(rng.integers(2, 5)), (0.8, 8.0))
    elif name == "pair":
        other = _neighbour(rng, lane, r.num_lanes)
        if b.vehicle(b.kind(), lane, rear) and other is not None:
            b.vehicle(b.kind(), other, rear + float(rng.uniform(-0.5, 0.5)))
    elif name == "truck_front":
        truck = b.vehicle(TRUCK, lane, rear)
        if truck is not None:
            b.vehicle(CAR, lane, truck.front_m + float(rng.uniform(1.0, 15.0)),
                      lateral_m=truck.lateral_m + float(rng.uniform(-1.5, 1.5)))
    elif name == "truck_beside":
        other = _neighbour(rng, lane, r.num_lanes)
        if b.vehicle(TRUCK, lane, rear) and other is not None:
            b.vehicle(CAR, other, rear + float(rng.uniform(-2.0, 2.0)))
    elif name == "lane_change":
        other = _neighbour(rng, lane, r.num_lanes)
        if other is not None:
            side = np.sign(other - lane)
            b.vehicle(b.kind(), lane, rear, lateral_m=float(side * rng.uniform(0.3, 1.7)),
                      yaw=float(side * math.radians(rng.uniform(2.0, 9.0))))
    elif name == "near_side":
        other = _neighbour(rng, r.ego_lane, r.num_lanes)
        if other is not None:
            b.vehicle(b.kind(), other, float(rng.uniform(MIN_AHEAD_M, 12.0)))
    else:
        raise ValueError(f"unknown pattern {name!r}")


def _held_out_scene(b: _Builder, family: str) -> None:
    rng, r = b.rng, b.recipe
    if family == "jam":
        speed = float(rng.uniform(3.0, 5.0))
        for lane in range(r.num_lanes):
            start = float(rng.uniform(MIN_AHEAD_M, 8.0))
            # gaps 1.5-4 m up to 60 m, then a few more vehicles
            b.chain(lane, start, int(rng.integers(6, 12)), (1.5, JAM_GAP_M), speed=speed, jitter_m=0.3)
    elif family == "far_chain":
        rear = float(rng.uniform(*FAR_CHAIN_RANGE_M))
        b.chain(r.ego_lane, rear, int(rng.integers(2, 5)), (1.0, FAR_CHAIN_GAP_M), jitter_m=0.3)
        for _ in range(int(rng.integers(0, 3))):  # context in the other lanes
            b.vehicle(b.kind(), int(rng.integers(r.num_lanes)), _log_uniform(rng, 10.0, MAX_AHEAD_M))
    elif family == "cut_in":
        lane = _neighbour(rng, r.ego_lane, r.num_lanes)
        side = np.sign(r.ego_lane - lane)  # towards the ego's lane
        b.vehicle(b.kind(), lane, None, centre_m=float(rng.uniform(*CUT_IN_RANGE_M)),
                  lateral_m=float(side * rng.uniform(0.6, 1.8)), yaw=float(side * math.radians(rng.uniform(3.0, 9.0))))
        b.vehicle(b.kind(), r.ego_lane, float(rng.uniform(25.0, 70.0)))  # the gap it cuts into
        for _ in range(int(rng.integers(0, 3))):
            b.vehicle(b.kind(), int(rng.integers(r.num_lanes)), _log_uniform(rng, 25.0, MAX_AHEAD_M))
    elif family in ("high_mount", "low_mount"):
        names = list(PATTERN_WEIGHTS)
        p = np.array(list(PATTERN_WEIGHTS.values()))
        n = int(rng.integers(3, 7)) if family == "high_mount" else int(rng.integers(4, 9))
        for name in rng.choice(names, size=n, p=p / p.sum()):
            _train_pattern(b, str(name))
    elif family == "truck_occlusion":
        side = _neighbour(rng, r.ego_lane, r.num_lanes)
        lane = r.ego_lane if side is None or rng.random() < 0.5 else side
        truck = b.vehicle(TRUCK, lane, float(rng.uniform(*OCCLUSION_RANGE_M)))
        side = _neighbour(rng, lane, r.num_lanes)
        car_lane = lane if side is None or rng.random() < 0.6 else side
        shift = float(rng.choice([-1, 1]) * rng.uniform(0.3, 1.6)) if car_lane == lane else None
        b.vehicle(CAR, car_lane, truck.front_m + float(rng.uniform(1.0, 15.0)),
                  lateral_m=None if shift is None else truck.lateral_m + shift)
        # context only in the other lanes, so that nothing nearer hides the pair
        others = [k for k in range(r.num_lanes) if k not in (lane, car_lane)]
        for _ in range(int(rng.integers(0, 3)) if others else 0):
            b.vehicle(b.kind(), int(rng.choice(others)), _log_uniform(rng, 10.0, MAX_AHEAD_M))
    else:
        raise ValueError(f"family: expected one of {', '.join(FAMILIES)}, got {family!r}")


def sample_scene(family: str, seed: int, num_lanes: int = 3, lane_width_m: float = 3.5,
                 max_attempts: int = 200) -> SceneRecipe:
    """The recipe of scene ``seed`` of ``family`` (deterministic in family, seed and road)."""
    if family not in FAMILIES:
        raise ValueError(f"family: expected one of {', '.join(FAMILIES)}, got {family!r}")
    rng = np.random.default_rng([FAMILIES.index(family), seed])
    for _ in range(max_attempts):
        if family == "high_mount":
            mount = CameraMount(height_m=float(rng.uniform(*HIGH_MOUNT_HEIGHT_M)),
                                pitch_deg=float(rng.uniform(*HIGH_MOUNT_PITCH_DEG)), lateral_m=float(rng.uniform(-0.4, 0.4)))
        elif family == "low_mount":
            mount = CameraMount(height_m=float(rng.uniform(*LOW_MOUNT_HEIGHT_M)),
                                pitch_deg=float(rng.uniform(*LOW_MOUNT_PITCH_DEG)), lateral_m=float(rng.uniform(-0.4, 0.4)))
        else:
            mount = CameraMount(height_m=float(rng.uniform(1.15, 1.65)), pitch_deg=float(rng.uniform(0.0, 6.0)),
                                lateral_m=float(rng.uniform(-0.4, 0.4)))
        ego_lane = int(rng.integers(num_lanes))
        if family == "cut_in" and num_lanes < 2:
            raise ValueError("family cut_in: expected a road of at least 2 lanes")
        recipe = SceneRecipe(family, seed, num_lanes, lane_width_m, ego_lane, float(rng.uniform(*EGO_S_RANGE_M)), mount)
        b = _Builder(rng, recipe, prefix=f"{family[:2]}{seed}_")
        if family == "train":
            names = list(PATTERN_WEIGHTS)
            p = np.array(list(PATTERN_WEIGHTS.values()))
            for name in rng.choice(names, size=int(rng.integers(2, 8)), p=p / p.sum()):
                _train_pattern(b, str(name))
        else:
            _held_out_scene(b, family)
        recipe = replace(recipe, vehicles=tuple(b.placed))
        matched = held_out_families(recipe)
        if family == "train" and not matched and recipe.vehicles:
            return recipe
        if family != "train" and family in matched:
            return recipe
    raise RuntimeError(f"{family} scene {seed}: no valid scene in {max_attempts} draws")


# ---------------------------------------------------------------------------------------------
# recipe -> world


def scene_states(recipe: SceneRecipe, road, time: float = 0.0) -> VehicleStates:
    """Ground truth of a recipe on ``road`` (ego first), as the renderer and the GT code take it."""
    cam_s = recipe.ego_s + recipe.mount.forward_m
    vs = recipe.vehicles
    s = np.array([recipe.ego_s] + [cam_s + v.ahead_m for v in vs])
    d = np.array([road.lane_centre_d(recipe.ego_lane)]
                 + [float(road.lane_centre_d(v.lane)) + v.lateral_m for v in vs], dtype=float)
    x, y = road.to_world(s, d)
    n = len(s)
    lengths = np.array([EGO_SIZE[0]] + [v.length for v in vs])
    return VehicleStates(
        time=float(time), ids=(EGO_ID, *(v.vehicle_id for v in vs)), vtype=("ego", *(v.vclass for v in vs)),
        vclass=(CAR, *(v.vclass for v in vs)), x=np.asarray(x, float), y=np.asarray(y, float), z=np.zeros(n),
        heading=np.asarray(road.heading(s, d), float) + np.array([0.0] + [v.yaw_rad for v in vs]),
        speed=np.array([10.0] + [v.speed for v in vs]), accel=np.zeros(n),
        lane=np.array([recipe.ego_lane] + [v.lane for v in vs], np.int16),
        lateral_offset=np.array([0.0] + [v.lateral_m for v in vs]), length=lengths,
        width=np.array([EGO_SIZE[1]] + [v.width for v in vs]), height=np.array([EGO_SIZE[2]] + [v.height for v in vs]))


def mounted_camera(camera, mount: CameraMount):
    """The scenario's camera (a CameraConfig) with the recipe's mount."""
    return camera.model_copy(update={"height_m": mount.height_m, "pitch_deg": mount.pitch_deg,
                                     "lateral_m": mount.lateral_m, "forward_m": mount.forward_m})


# ---------------------------------------------------------------------------------------------
# rendering into a COCO dataset folder


def _twin_rows(truth: VehicleStates) -> list[dict]:
    """Every vehicle but the ego, seen or not, with its pose: the twins of the identification check."""
    return [{"vehicle_id": vid, "footprint_world": [float(truth.x[i]), float(truth.y[i]), float(truth.z[i])],
             "yaw": float(truth.heading[i]), "size": [float(truth.length[i]), float(truth.width[i]), float(truth.height[i])],
             "speed": float(truth.speed[i])} for i, vid in enumerate(truth.ids) if vid != EGO_ID]


def _render_scene(renderer, road, scenario, family: str, seed: int, folder: Path, coco) -> None:
    """Render one scene into ``folder``'s rgb/, depth/ and instances/ and add it to ``coco``."""
    from vcfusion.render.camera import world_to_camera
    from vcfusion.render.coco import vehicle_anchors, write_frame_files
    from vcfusion.render.gt_boxes import ground_truth_boxes

    recipe = sample_scene(family, seed, road.num_lanes, road.lane_width_m)
    truth = scene_states(recipe, road)
    camera = mounted_camera(scenario.camera, recipe.mount)
    T = world_to_camera(float(truth.x[0]), float(truth.y[0]), 0.0, float(truth.heading[0]), camera)
    frame = renderer.render(truth, T)
    files = write_frame_files(folder, f"{family}_{seed:06d}", frame)
    boxes = ground_truth_boxes(frame, truth, renderer, near=scenario.camera.near_m)
    coco.add(frame, boxes, vehicle_anchors(frame, truth, EGO_ID), files,
             extra={"seed": seed, "family": family, "scene": recipe.to_dict(), "twins": _twin_rows(truth)})


def _render_chunk(scenario, family: str, seeds: list[int], folder: str) -> tuple[list[dict], list[dict]]:
    """A worker's share of :func:`render_scenes`: these seeds into ``folder``, with their COCO records
    (image and annotation ids counted from 1; the parent renumbers them)."""
    from vcfusion.render.coco import CocoBuilder
    from vcfusion.render.renderer import EgoCameraRenderer
    from vcfusion.traffic.network import read_road

    road = read_road(scenario.network)
    coco = CocoBuilder("")
    with EgoCameraRenderer(road, scenario.camera) as renderer:
        for seed in seeds:
            _render_scene(renderer, road, scenario, family, seed, Path(folder), coco)
    return coco.images, coco.annotations


def _chunks(seeds: list[int], workers: int) -> list[list[int]]:
    # consecutive seeds, several chunks per worker (an even load and a moving progress bar); each
    # chunk opens its own GL context, so not too small
    size = max(10, min(200, -(-len(seeds) // (4 * workers))))
    return [seeds[k:k + size] for k in range(0, len(seeds), size)]


def render_scenes(scenario, family: str, seeds, out, progress: bool = True, workers: int = 1) -> dict:
    """Render the scenes ``seeds`` of ``family`` on the scenario's road with its camera (mount jittered
    per scene) into a COCO dataset folder laid out as `vcfusion render` writes it (rgb/, depth/,
    instances/, annotations.json, manifest.json); each image also records ``family``, ``seed``, its
    ``scene`` (the recipe) and ``twins`` (every placed vehicle, seen or not, with its world pose). Written into OUT.tmp-writing-PID and
    renamed when complete. ``workers`` > 1 renders consecutive runs of seeds in that many processes
    (each with its GL context); the folder is the same as one process writes. Returns counts."""
    import json

    from tqdm import tqdm

    from vcfusion.render.coco import FRAME_KINDS, CocoBuilder
    from vcfusion.render.renderer import EgoCameraRenderer
    from vcfusion.runio import atomic_folder, package_versions, write_json
    from vcfusion.traffic.network import read_road
    from vcfusion.workers import results_in_order

    road = read_road(scenario.network)  # the road the camera stage draws (as its hook reads it)
    if not road.is_straight or road.length_m < EGO_S_RANGE_M[1] + MAX_AHEAD_M + 10.0:
        raise InputError(f"{scenario.source}: network: procedural scenes need a straight road of at least "
                         f"{EGO_S_RANGE_M[1] + MAX_AHEAD_M + 10.0:.0f} m (ego positions up to {EGO_S_RANGE_M[1]:.0f} m, "
                         f"vehicles up to {MAX_AHEAD_M:.0f} m ahead), got {road!r}")
    if workers < 1:
        raise ValueError(f"workers: expected at least 1, got {workers}")
    seeds = list(seeds)
    chunks = _chunks(seeds, workers)
    coco = CocoBuilder(f"vcfusion procedural scenes, family {family}, road of scenario {scenario.name}")
    bar = tqdm(total=len(seeds), desc=f"render {family} scenes", unit="scene", disable=not progress)
    with atomic_folder(Path(out), "dataset folder") as tmp:
        for sub in FRAME_KINDS:
            (tmp / sub).mkdir()
        if min(workers, len(chunks)) == 1:
            with EgoCameraRenderer(road, scenario.camera) as renderer:
                for seed in seeds:
                    _render_scene(renderer, road, scenario, family, seed, tmp, coco)
                    bar.update()
        else:
            parts = results_in_order(_render_chunk, [(scenario, family, c, str(tmp)) for c in chunks], workers,
                                     lambda k: f"render-scenes: seeds {chunks[k][0]}-{chunks[k][-1]}",
                                     lambda k: bar.update(len(chunks[k])))
            for images, annotations in parts:  # in seed order: the ids one process gives
                coco.extend(images, annotations)
        bar.close()
        data = coco.to_dict()
        (tmp / "annotations.json").write_text(json.dumps(data))
        write_json(tmp / "manifest.json", {
            "family": family, "seeds": seeds, "scenario_file": str(scenario.source) if scenario.source else None,
            "network": scenario.network.name, "camera": scenario.camera.model_dump(),
            "versions": package_versions(), "images": len(data["images"]), "annotations": len(data["annotations"])})
    return {"images": len(data["images"]), "annotations": len(data["annotations"])}
