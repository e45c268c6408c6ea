"""CommonRoad scenarios (XML, format 2018b / 2020a) as :class:`Recording`s.

Read with commonroad-io's XML reader (`commonroad.common.reader.file_reader_xml.XMLFileReader`:
the lanelet network, the dynamic obstacles and their trajectories). What is used:

- paths: scenario files (`.xml`), folders (every `*.xml` below them) and `.tar.xz` / `.tar.gz` /
  `.tar` archives (their `*.xml` members, read from the archive);
- main lanes, from the lanelet network's adjacency: a lanelet's lane counted from the LEFT
  (median) edge is the number of same-direction left neighbours (adjacentLeft, drivingDir
  same) until there is none; a *cross-section* is a set of lanelets joined by same-direction
  adjacency. The road has N main lanes, N = the narrowest cross-section of at least two
  lanelets (one lanelet when none is wider). Lane index (0 = rightmost, the project's
  convention) = N - 1 - lane from the left, for lanelets of cross-sections of at least N
  lanelets; other lanelets (an auxiliary lane right of the N, an on-ramp lanelet that touches
  no other lanelet) are off the road, as NGSIM's lanes 6-8: the twin leaves there;
- lane of a sample: the lanelet that holds the obstacle's centre (commonroad-io's
  `find_lanelet_by_position`); on a shared boundary (held by two lanelets) the one whose centre
  line is nearer; in none: off the road;
- s, d: along / across the main lanes' left edge (the chained left bounds of the lanes with no
  left neighbour): s = the centre's distance along that polyline, d = N x lane width - its
  distance right of it (lane width: the mean width of the main lanelets), so that, as for NGSIM
  and highD, d grows to the left from the main lanes' right edge;
- speed = the state's velocity (m/s); acceleration = the state's acceleration (missing: from
  the speed); a trajectory without velocities: the speed from s (counted);
- size = the rectangle's length / width; another shape (circle, polygon): class default
  (counted); class from the obstacle type (car, taxi, priorityVehicle -> passenger; truck,
  bus -> truck; motorcycle -> motorcycle); other types (bicycle, pedestrian, ...) and
  obstacles without a trajectory (a set-based prediction) are dropped (counted);
- duplicated recordings: CommonRoad repeats one recording in several files (another planning
  problem each). An obstacle is identified by its trajectory (first and last position to 1 cm
  and its number of states); files that share an obstacle are one recording (their time steps
  aligned on the shared obstacles), each obstacle imported once (the copies counted); a
  different obstacle under an id already taken becomes ID-2, ID-3, ... (counted).
The planning problem's ego vehicle is not an obstacle and is not imported (it is not recorded
in the file's trajectories).
"""

from __future__ import annotations

import tarfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from vcfusion.prediction.sources.trajectories import Recording, RealDataError, size_defaults, straight_road

ARCHIVE_SUFFIXES = (".tar.xz", ".tar.gz", ".tgz", ".tar")
CLASS_BY_TYPE = {"car": "passenger", "taxi": "passenger", "priorityVehicle": "passenger", "truck": "truck",
                 "bus": "truck", "motorcycle": "motorcycle"}
FINGERPRINT_DECIMALS = 2  # positions of a duplicated obstacle agree to 1 cm


def _xml_reader():
    try:
        from commonroad.common.reader.file_reader_xml import XMLFileReader
    except ImportError as exc:
        raise RealDataError(f"--from-commonroad: commonroad-io is not installed ({exc}); install it with "
                            "`pip install --no-deps commonroad-io` plus the extra `vcfusion[commonroad]` "
                            "(see pyproject.toml)") from None
    return XMLFileReader


def scenario_sources(paths) -> list[tuple[str, object]]:
    """(name, path or bytes) of every scenario file at `paths` (files, folders, tar archives)."""
    out = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            found = sorted(p.rglob("*.xml"))
            if not found:
                raise RealDataError(f"{p}: no CommonRoad scenario (*.xml) in this folder")
            out += [(str(f.relative_to(p)), f) for f in found]
        elif p.is_file() and p.name.endswith(ARCHIVE_SUFFIXES):
            try:
                with tarfile.open(p) as tar:
                    members = sorted((m for m in tar.getmembers() if m.isfile() and m.name.endswith(".xml")),
                                     key=lambda m: m.name)
                    if not members:
                        raise RealDataError(f"{p}: no CommonRoad scenario (*.xml) in this archive")
                    out += [(f"{p.name}:{m.name}", tar.extractfile(m).read()) for m in members]
            except (tarfile.TarError, OSError, EOFError) as exc:
                raise RealDataError(f"{p}: not a readable tar archive: {exc}") from None
        elif p.is_file() and p.suffix == ".xml":
            out.append((p.name, p))
        elif not p.exists():
            raise RealDataError(f"{p}: no such file or folder")
        else:
            raise RealDataError(f"{p}: expected a CommonRoad scenario (.xml), a folder of them or a .tar.xz of them")
    return out


@dataclass
class _Track:
    obstacle_id: int
    vclass: str
    length: float
    width: float
    steps: np.ndarray  # time steps (int)
    xy: np.ndarray  # (n, 2) centre positions, m
    speed: np.ndarray  # m/s, NaN where not recorded
    accel: np.ndarray  # m/s^2, NaN where not recorded

    @property
    def fingerprint(self) -> tuple:
        a, b = np.round(self.xy[0], FINGERPRINT_DECIMALS), np.round(self.xy[-1], FINGERPRINT_DECIMALS)
        return (float(a[0]), float(a[1]), float(b[0]), float(b[1]), len(self.steps))


@dataclass
class _Scenario:
    name: str
    dt: float
    network: object  # commonroad LaneletNetwork
    tracks: list[_Track]
    counts: Counter = field(default_factory=Counter)


def _state_value(state, name: str) -> float:
    v = getattr(state, name, None)
    if v is None:
        return float("nan")
    try:
        return float(v)
    except (TypeError, ValueError):  # an interval (uncertain state): its midpoint
        start, end = getattr(v, "start", None), getattr(v, "end", None)
        return float((start + end) / 2) if start is not None and end is not None else float("nan")


def _read_scenario(name: str, source) -> _Scenario:
    reader = _xml_reader()
    try:
        scenario, _ = reader(source).open()
    except Exception as exc:  # noqa: BLE001 - the library raises many kinds on a bad file
        raise RealDataError(f"{name}: not a readable CommonRoad scenario ({type(exc).__name__}: {exc})") from None
    dt = float(scenario.dt)
    if not dt > 0:
        raise RealDataError(f"{name}: timeStepSize: expected a positive step in seconds, got {scenario.dt}")
    counts = Counter()
    tracks = []
    for obstacle in scenario.dynamic_obstacles:
        kind = getattr(obstacle.obstacle_type, "value", str(obstacle.obstacle_type))
        if kind not in CLASS_BY_TYPE:
            counts[f"obstacles_dropped_type_{kind}"] += 1
            continue
        trajectory = getattr(obstacle.prediction, "trajectory", None)
        if trajectory is None:
            counts["obstacles_dropped_no_trajectory"] += 1
            continue
        states = [obstacle.initial_state, *trajectory.state_list]
        steps = np.array([int(_state_value(s, "time_step")) for s in states])
        order = np.argsort(steps, kind="stable")
        states = [states[k] for k in order]
        xy = np.array([np.asarray(s.position, dtype=float)[:2] if getattr(s, "position", None) is not None
                       and np.ndim(s.position) else (np.nan, np.nan) for s in states])
        shape = obstacle.obstacle_shape
        length, width = float(getattr(shape, "length", np.nan)), float(getattr(shape, "width", np.nan))
        speed, accel = (np.array([_state_value(s, q) for s in states]) for q in ("velocity", "acceleration"))
        # commonroad-io fills an initial state's missing fields with 0: a quantity the trajectory's
        # states lack was not recorded, in the initial state either
        initial = int(np.flatnonzero(order == 0)[0])
        for values in (speed, accel):
            if len(values) > 1 and np.isnan(np.delete(values, initial)).all():
                values[initial] = np.nan
        tracks.append(_Track(int(obstacle.obstacle_id), CLASS_BY_TYPE[kind], length, width, steps[order], xy,
                             speed, accel))
    bad = [t for t in tracks if np.isnan(t.xy).any()]
    if bad:
        raise RealDataError(f"{name}: dynamicObstacle {bad[0].obstacle_id}: a state without an exact position "
                            "(expected a point in every state of the trajectory)")
    return _Scenario(name, dt, scenario.lanelet_network, tracks, counts)


# ------------------------------------------------------------------ the lanelet network

@dataclass(frozen=True)
class LaneMap:
    """The main lanes of a lanelet network (see the module docstring)."""

    lane_of: dict  # lanelet id -> lane index (0 = rightmost), -1 off the main lanes
    num_lanes: int
    lane_width_m: float
    edge: np.ndarray  # (m, 2) polyline of the main lanes' left edge, in the driving direction


def lane_map(network) -> LaneMap:
    lanelets = {ll.lanelet_id: ll for ll in network.lanelets}
    if not lanelets:
        raise RealDataError("the lanelet network has no lanelets")

    def same_left(ll):
        return ll.adj_left if ll.adj_left is not None and ll.adj_left_same_direction and ll.adj_left in lanelets \
            else None

    def same_right(ll):
        return ll.adj_right if ll.adj_right is not None and ll.adj_right_same_direction and ll.adj_right in lanelets \
            else None

    from_left, size = {}, {}
    for lid, ll in lanelets.items():
        k, cur, seen = 0, ll, {lid}
        while (nxt := same_left(cur)) is not None and nxt not in seen:
            seen.add(nxt)
            cur, k = lanelets[nxt], k + 1
        r, cur2 = 0, ll
        while (nxt := same_right(cur2)) is not None and nxt not in seen:
            seen.add(nxt)
            cur2, r = lanelets[nxt], r + 1
        from_left[lid], size[lid] = k, k + r + 1
    wide = [s for s in size.values() if s >= 2]
    n = min(wide) if wide else 1
    lane_of = {lid: (n - 1 - from_left[lid]) if size[lid] >= n and from_left[lid] < n else -1 for lid in lanelets}
    main = [lanelets[lid] for lid, lane in lane_of.items() if lane >= 0]
    width = float(np.mean([np.linalg.norm(ll.left_vertices - ll.right_vertices, axis=1).mean() for ll in main]))
    # the left edge: the leftmost main lanelets' left bounds, chained by successor
    left = {ll.lanelet_id: ll for ll in main if lane_of[ll.lanelet_id] == n - 1}
    heads = [lid for lid, ll in left.items() if not any(p in left for p in ll.predecessor)] or list(left)
    chain, used = [], set()
    for head in heads:
        cur = head
        while cur is not None and cur not in used:
            used.add(cur)
            chain.append(cur)
            cur = next((s for s in left[cur].successor if s in left and s not in used), None)
    # chains that are not linked: ordered along the first one's direction
    first = left[chain[0]].left_vertices
    axis = first[-1] - first[0]
    axis = axis / max(np.linalg.norm(axis), 1e-9)
    pieces = sorted({lid: left[lid].left_vertices for lid in chain}.items(),
                    key=lambda kv: float(kv[1][0] @ axis)) if len(heads) > 1 else \
        [(lid, left[lid].left_vertices) for lid in chain]
    edge = np.concatenate([v for _, v in pieces])
    keep = np.r_[True, np.linalg.norm(np.diff(edge, axis=0), axis=1) > 1e-6]
    edge = edge[keep]
    if len(edge) < 2:
        raise RealDataError("the lanelet network's main lanes have no length")
    return LaneMap(lane_of, n, width, edge)


def project(edge: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(s along the polyline, distance to its right) of points (n, 2); nearest segment, clamped."""
    a, b = edge[:-1], edge[1:]
    seg = b - a
    seg_len = np.linalg.norm(seg, axis=1)
    cum = np.r_[0.0, np.cumsum(seg_len)]
    rel = xy[:, None, :] - a[None, :, :]
    t = np.clip((rel * seg[None]).sum(-1) / np.maximum(seg_len**2, 1e-12)[None], 0.0, 1.0)
    foot = a[None] + t[..., None] * seg[None]
    dist = np.linalg.norm(xy[:, None, :] - foot, axis=-1)
    k = np.argmin(dist, axis=1)
    rows = np.arange(len(xy))
    s = cum[k] + t[rows, k] * seg_len[k]
    unit = seg[k] / np.maximum(seg_len[k], 1e-12)[:, None]
    r = xy - a[k]
    right = r[:, 0] * unit[:, 1] - r[:, 1] * unit[:, 0]  # cross(unit, r) < 0 left of it: right > 0
    return s, right


def lanes_at(network, lanes: LaneMap, xy: np.ndarray) -> tuple[np.ndarray, int]:
    """Lane index of each point from the lanelet that holds it; and how many points lay on two
    lanelets (a boundary: the nearer centre line decides)."""
    from shapely.geometry import LineString, Point

    found = network.find_lanelet_by_position([p for p in xy])
    out = np.full(len(xy), -1, dtype=np.int64)
    ambiguous = 0
    centres = {}
    for i, ids in enumerate(found):
        if not ids:
            continue
        if len(ids) > 1:
            ambiguous += 1
            for lid in ids:
                if lid not in centres:
                    centres[lid] = LineString(network.find_lanelet_by_id(lid).center_vertices)
            ids = [min(ids, key=lambda lid: centres[lid].distance(Point(xy[i])))]
        out[i] = lanes.lane_of.get(ids[0], -1)
    return out, ambiguous


# ------------------------------------------------------------------ recordings

def _group(scenarios: list[_Scenario]) -> list[list[tuple[int, int]]]:
    """Files sharing an obstacle, as groups of (scenario index, time-step offset to the group's first)."""
    owner: dict[tuple, tuple[int, int]] = {}  # fingerprint -> (scenario, its first step)
    parent = list(range(len(scenarios)))
    offset = [0] * len(scenarios)  # step offset to the parent

    def find(i):
        while parent[i] != i:
            i = parent[i]
        return i

    def offset_to_root(i):
        total = 0
        while parent[i] != i:
            total += offset[i]
            i = parent[i]
        return total

    for i, sc in enumerate(scenarios):
        for tr in sc.tracks:
            fp = tr.fingerprint
            if fp not in owner:
                owner[fp] = (i, int(tr.steps[0]))
                continue
            j, step_j = owner[fp]
            ri, rj = find(i), find(j)
            if ri == rj:
                continue
            # time step in j's frame = step in i's frame + (step_j - step_i)
            shift = (step_j - int(tr.steps[0])) + offset_to_root(j) - offset_to_root(i)
            parent[ri], offset[ri] = rj, shift
    groups: dict[int, list[tuple[int, int]]] = {}
    for i in range(len(scenarios)):
        groups.setdefault(find(i), []).append((i, offset_to_root(i)))
    return [groups[k] for k in sorted(groups)]


def _recording(scenarios: list[_Scenario], members: list[tuple[int, int]]) -> Recording:
    first = scenarios[members[0][0]]
    names = [scenarios[i].name for i, _ in members]
    counts = Counter()
    for i, _ in members:
        counts.update(scenarios[i].counts)
    ids = sorted({ll.lanelet_id for ll in first.network.lanelets})
    counts["files_with_another_lanelet_network"] = sum(
        sorted({ll.lanelet_id for ll in scenarios[i].network.lanelets}) != ids for i, _ in members[1:])
    lanes = lane_map(first.network)
    tracks, seen, names_used = [], set(), set()
    for i, shift in members:
        for tr in scenarios[i].tracks:
            if tr.fingerprint in seen:
                counts["obstacles_duplicated"] += 1
                continue
            seen.add(tr.fingerprint)
            # another vehicle under an id already taken (files of one recording number their own
            # obstacles): renamed ID-2, ID-3, ... (counted)
            vid, k = str(tr.obstacle_id), 1
            while vid in names_used:
                k += 1
                vid = f"{tr.obstacle_id}-{k}"
            counts["obstacle_ids_renamed"] += k > 1
            names_used.add(vid)
            tracks.append((tr, shift, vid))
    rows = []
    for tr, shift, vid in tracks:
        steps = tr.steps + shift
        rows.append(pd.DataFrame({"vehicle_id": vid, "step": steps, "x": tr.xy[:, 0],
                                  "y": tr.xy[:, 1], "speed": tr.speed, "accel": tr.accel, "vclass": tr.vclass,
                                  "length": tr.length, "width": tr.width}))
    if not rows:
        raise RealDataError(f"{', '.join(names)}: no vehicle obstacle with a trajectory; nothing to import")
    raw = pd.concat(rows, ignore_index=True)
    xy = raw[["x", "y"]].to_numpy(float)
    s, right = project(lanes.edge, xy)
    lane, ambiguous = lanes_at(first.network, lanes, xy)
    d = lanes.num_lanes * lanes.lane_width_m - right
    raw["time"] = (raw["step"] - raw["step"].min()) * first.dt
    speed = raw["speed"].to_numpy(float)
    speed_from_positions = int(np.isnan(speed).sum())
    if speed_from_positions:  # not recorded: the rate of s
        time = raw["time"].to_numpy(float)
        from_s = np.full(len(raw), np.nan)
        for idx in raw.groupby("vehicle_id", sort=False).indices.values():
            if len(idx) > 1:
                from_s[idx] = np.gradient(s[idx], time[idx])
        speed = np.where(np.isnan(speed), from_s, speed)
    vclass = raw["vclass"].to_numpy(str)
    sizes = size_defaults(vclass, raw["length"].to_numpy(float), raw["width"].to_numpy(float),
                          np.full(len(raw), np.nan))
    # the centre's s is the footprint centre
    samples = pd.DataFrame({
        "vehicle_id": raw["vehicle_id"].to_numpy(str), "time": raw["time"].to_numpy(float), "s": s, "d": d,
        "lane": lane, "speed": speed, "accel": raw["accel"].to_numpy(float),
        "length": sizes["length"], "width": sizes["width"], "height": sizes["height"], "vclass": vclass,
    })
    per_vehicle = samples.groupby("vehicle_id")["s"]
    if (per_vehicle.last() < per_vehicle.first()).mean() > 0.5:
        raise RealDataError(f"{names[0]}: most vehicles drive against the main lanes' direction; expected "
                            "trajectories in the lanelets' driving direction")
    name = Path(names[0].split(":")[-1]).stem
    quality = {
        "files": names, "obstacles": len(tracks), "rows": int(len(samples)),
        "rows_off_main_lanes": int((lane < 0).sum()), "rows_on_a_lanelet_boundary": int(ambiguous),
        "speed_from_positions_rows": speed_from_positions,
        "sizes_filled_by_class": sizes["filled"],
        **{k: int(v) for k, v in sorted(counts.items())},
    }
    source = {"format": "commonroad", "file": names[0], "recording": name, "files": names,
              "main_lanes": lanes.num_lanes, "lane_width_m": lanes.lane_width_m, "quality_reader": quality}
    road = straight_road(f"commonroad-{name}", lanes.num_lanes, lanes.lane_width_m, float(np.nanmax(s)) + 1.0,
                         float("nan"))
    return Recording(f"commonroad {name}", road, samples, first.dt, source)


def read_commonroad(paths) -> tuple[list[Recording], dict]:
    """Every distinct recording in the scenario files at `paths` (files, folders, tar archives):
    files that repeat a recording (shared obstacles) are merged and each obstacle kept once.
    Returns the recordings and the files left out (no vehicle with a trajectory, e.g. a
    set-based prediction only), with why."""
    scenarios = [_read_scenario(name, src) for name, src in scenario_sources(paths)]
    empty = {sc.name: ", ".join(f"{k.removeprefix('obstacles_dropped_')} {v}" for k, v in sorted(sc.counts.items()))
             or "no dynamic obstacle" for sc in scenarios if not sc.tracks}
    if len(empty) == len(scenarios):
        raise RealDataError(f"{', '.join(sorted(empty)[:3])}{' ...' if len(empty) > 3 else ''}: no vehicle obstacle "
                            "with a trajectory in any file; nothing to import")
    kept = [sc for sc in scenarios if sc.tracks]
    recordings = [_recording(kept, members) for members in _group(kept)]
    return recordings, {"files_read": len(scenarios), "files_without_vehicle_trajectories": empty,
                        "recordings": len(recordings)}
