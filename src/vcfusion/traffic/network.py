"""The highway networks: reproducible build with netconvert, and the road geometry of a run.

Every stage works in the road frame of the scenario's route (:class:`RoadFrame`, see
`vcfusion.traffic.roadframe`): s along the route, d from its right edge, lanes as tracks (index
from the right). :class:`Road` is the frame of the simplest network, one straight edge of
parallel lanes of equal width, in closed form; :func:`read_road` gives the frame of any network.
"""

from __future__ import annotations

import functools
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numba
import numpy as np

from vcfusion.errors import InputError
from vcfusion.traffic.roadframe import RoadFrame, RouteError, _Lane, _Piece


@numba.njit(cache=True)
def _straight_to_frame(x, y, x0, y0, dx, dy, nx, ny, width):
    """Road.to_frame's arithmetic, element by element in its order (no fused multiply-add: the
    same doubles as the NumPy expression), in one call instead of nine array operations: it runs
    on every tick's vehicles and twins. x, y: 1-D float64 of one length."""
    s = np.empty_like(x)
    d = np.empty_like(x)
    for i in range(x.shape[0]):
        rel_x = x[i] - x0
        rel_y = y[i] - y0
        s[i] = rel_x * dx + rel_y * dy
        d[i] = (rel_x * nx + rel_y * ny) + width
    return s, d


@dataclass(init=False, eq=False, repr=False)
class Road(RoadFrame):
    """The road frame of one straight edge of parallel lanes of equal width. Lane 0 is the
    rightmost lane (SUMO's convention), and a lane is its track.

    Its conversions are closed-form: the general frame's map on such an edge to 1e-9 m (tested),
    in the arithmetic the straight-road runs were recorded with, so their tables stay
    byte-identical; the lane structure (tracks, SUMO lane positions) is the general frame's.
    Its defining values are dataclass fields (`dataclasses.asdict(road)`, as before).
    """

    edge_id: str  # (the route's one edge: RoadFrame.edge_id)
    start: tuple[float, float]  # the left road edge's ends (SUMO's edge shape)
    end: tuple[float, float]
    num_lanes: int  # (RoadFrame.num_lanes)
    lane_width_m: float
    speed_limit_mps: float

    def __init__(self, edge_id: str, start: tuple[float, float], end: tuple[float, float], num_lanes: int,
                 lane_width_m: float, speed_limit_mps: float, net_file: str | Path | None = None):
        self.net_file = Path(net_file) if net_file is not None else None
        self.route = (edge_id,)
        self.start = (float(start[0]), float(start[1]))
        self.end = (float(end[0]), float(end[1]))
        self.lane_width_m = float(lane_width_m)
        self.speed_limit_mps = float(speed_limit_mps)
        self.length_m = float(np.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1]))
        w, n = self.lane_width_m, int(num_lanes)
        # start and end lie on the left road edge (SUMO's edge shape); lane 0's centre line is half a
        # lane left of the right one
        offset = self.left_normal * (w / 2 - n * w)
        shape = np.array([self.start + offset, self.end + offset])
        lane0 = _Lane(f"{edge_id}_0", edge_id, 0, w, self.length_m, shape, self.speed_limit_mps)
        self.track_of = {f"{edge_id}_{i}": i for i in range(n)}
        self.edge_start_s = {edge_id: 0.0}
        self._assemble([_Piece(edge_id, 0.0, self.length_m, lane0, 0, {i: w for i in range(n)})])

    @cached_property
    def key(self) -> tuple:
        return ("straight", self.edge_id, self.start, self.end, self.num_tracks, self.lane_width_m,
                self.speed_limit_mps)

    def __repr__(self) -> str:
        return (f"Road({self.edge_id!r}, start={self.start}, end={self.end}, {self.num_tracks} lanes of "
                f"{self.lane_width_m} m)")

    @property
    def is_straight(self) -> bool:
        return True

    @cached_property
    def width_m(self) -> float:
        return self.num_tracks * self.lane_width_m

    @cached_property
    def direction(self) -> np.ndarray:
        d = np.array(self.end) - np.array(self.start)
        return d / np.linalg.norm(d)

    @cached_property
    def left_normal(self) -> np.ndarray:
        d = self.direction
        return np.array([-d[1], d[0]])

    @cached_property
    def heading_rad(self) -> float:
        d = self.direction
        return float(np.arctan2(d[1], d[0]))

    @cached_property
    def _frame(self) -> tuple[float, ...]:
        # plain floats: the conversion runs several times per tick, mostly on small arrays
        return (float(self.start[0]), float(self.start[1]), *map(float, self.direction),
                *map(float, self.left_normal), float(self.width_m))

    def to_frame(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y) to (s, d): s along the road from its start, d left of the right road edge."""
        x0, y0, dx, dy, nx, ny, width = self._frame
        if (type(x) is np.ndarray and type(y) is np.ndarray and x.ndim == 1 and x.shape == y.shape
                and x.dtype == np.float64 and y.dtype == np.float64):  # the per-tick case: one compiled call
            return _straight_to_frame(x, y, x0, y0, dx, dy, nx, ny, width)
        rel_x = np.asarray(x) - x0
        rel_y = np.asarray(y) - y0
        s = rel_x * dx + rel_y * dy
        # The edge's reference line (its 'shape') is the left road edge in SUMO's right-hand traffic.
        d_left = rel_x * nx + rel_y * ny
        return s, d_left + width

    def to_road_frame(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        return self.to_frame(x, y)

    def locate(self, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s, d = self.to_frame(x, y)
        return s, d, self.lane_of(s, d)

    def to_world(self, s, d) -> tuple[np.ndarray, np.ndarray]:
        s = np.asarray(s, dtype=float)
        d_left = np.asarray(d, dtype=float) - self.width_m
        x = self.start[0] + s * self.direction[0] + d_left * self.left_normal[0]
        y = self.start[1] + s * self.direction[1] + d_left * self.left_normal[1]
        return x, y

    def heading(self, s, d=0.0) -> np.ndarray:
        return np.full(np.broadcast(np.asarray(s), np.asarray(d)).shape, self.heading_rad)

    def lane_of(self, s, d) -> np.ndarray:
        """Map-match to a lane index (-1 when off the road); s plays no part on a straight edge."""
        lane = np.floor(np.asarray(d, dtype=float) / self.lane_width_m).astype(np.int16)
        lane = np.where((lane >= 0) & (lane < self.num_tracks), lane, -1)
        shape = np.shape(s)
        if shape != lane.shape:
            lane = np.broadcast_to(lane, np.broadcast_shapes(shape, lane.shape)).copy()
        return lane

    def lane_bounds(self, track, s=0.0) -> tuple[np.ndarray, np.ndarray]:
        t = np.asarray(track, dtype=float) + 0.0 * np.asarray(s, dtype=float)
        return t * self.lane_width_m, (t + 1.0) * self.lane_width_m

    def lane_centre_d(self, track, s=0.0) -> np.ndarray:
        t = np.asarray(track, dtype=float)
        if np.ndim(s):
            t = np.broadcast_to(t, np.broadcast(t, np.asarray(s)).shape)
        return (t + 0.5) * self.lane_width_m

    def road_bounds(self, s) -> tuple[np.ndarray, np.ndarray]:
        """d of the rightmost and leftmost road edge at s (every lane runs the whole edge)."""
        zero = 0.0 * np.asarray(s, dtype=float)
        return zero, zero + self.width_m


class NetworkFileError(InputError):
    """A network or vehicle-types file that cannot be used; the message names the file and the problem."""


def _parse_xml(path: str | Path, what: str, roots: tuple[str, ...]) -> ET.Element:
    """The root element of an XML file, or a NetworkFileError naming the file and line."""
    path = Path(path)
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise NetworkFileError(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    if not text.strip():
        raise NetworkFileError(f"{path}: empty file; expected a {what}")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        line, column = exc.position
        reason = str(exc).split(":")[0]
        raise NetworkFileError(f"{path}: line {line}, column {column + 1}: not well-formed XML ({reason}); "
                               f"expected a {what}") from None
    if root.tag not in roots:
        expected = " or ".join(f"<{r}>" for r in roots)
        raise NetworkFileError(f"{path}: root element <{root.tag}>: expected {expected} (a {what})")
    return root


def _lane_attr(net_file, lane: ET.Element, name: str, convert, expected: str):
    value = lane.get(name)
    try:
        return convert(value)
    except (TypeError, ValueError):
        raise NetworkFileError(f"{net_file}: lane {lane.get('id')!r}: {name}: expected {expected}, "
                               f"got {value!r}") from None


def _shape_points(text: str | None) -> np.ndarray:
    if not text:
        raise ValueError
    points = np.array([[float(c) for c in p.split(",")[:2]] for p in text.split()], dtype=float)
    if points.ndim != 2 or len(points) < 2 or points.shape[1] != 2:
        raise ValueError
    return points


def _straight_edge(net_file, edge: ET.Element) -> Road | None:
    """The closed-form Road of a network's only edge, or None when its lanes are not straight,
    parallel and of one width (the general frame then takes it)."""
    lanes = list(edge.iter("lane"))
    if not lanes:
        raise NetworkFileError(f"{net_file}: edge {edge.get('id')!r} has no <lane>; expected lanes with shapes")
    lanes.sort(key=lambda lane: _lane_attr(net_file, lane, "index", int, "a lane index"))
    widths = {_lane_attr(net_file, lane, "width", lambda v: float(v if v is not None else 3.2), "a width in m")
              for lane in lanes}
    shapes = [_lane_attr(net_file, lane, "shape", _shape_points, "'x,y x,y ...' (at least two points)")
              for lane in lanes]
    speed = _lane_attr(net_file, lanes[0], "speed", float, "a speed in m/s")
    if len(widths) != 1:
        return None
    width = widths.pop()
    # Lane shapes are lane centre lines; every one must be a straight segment parallel to the others.
    (x0, y0), (x1, y1) = shapes[-1][0], shapes[-1][-1]
    length = float(np.hypot(x1 - x0, y1 - y0))
    if length <= 0.0:
        raise NetworkFileError(f"{net_file}: lane {lanes[-1].get('id')!r} has zero length")
    stated = {_lane_attr(net_file, lane, "length", lambda v: float(v if v is not None else length), "a length in m")
              for lane in lanes}
    if any(abs(v - length) > 0.05 for v in stated):
        return None  # a length set apart from the geometry (SUMO's positions follow it): the general frame
    direction = np.array([x1 - x0, y1 - y0]) / length
    normal = np.array([-direction[1], direction[0]])
    for i, points in enumerate(shapes):
        # lane i lies (n - 1 - i) lane widths right of the leftmost lane (lane 0 is the rightmost)
        offsets = (points - shapes[-1][0]) @ normal
        if np.abs(offsets + (len(lanes) - 1 - i) * width).max() > 0.05:
            return None
    start = np.array([x0, y0]) + normal * width / 2
    end = np.array([x1, y1]) + normal * width / 2
    return Road(edge_id=edge.get("id"), start=(float(start[0]), float(start[1])),
                end=(float(end[0]), float(end[1])), num_lanes=len(lanes), lane_width_m=width,
                speed_limit_mps=speed, net_file=net_file)


def _file_version(path: str | Path) -> int | None:
    """A file's modification time, the key under which what was read from it is kept (None for a
    file that cannot be read: reading it names the problem)."""
    try:
        return Path(path).stat().st_mtime_ns
    except OSError:
        return None


# The camera's world is flat: the road mesh, the ground and the depth step's road height are at
# z = 0 (vcfusion.render.meshes, vcfusion.fusion.box_refine). Heights below this are the markings'
# and kerbs' scale (the depth step's object pixels stand higher than 0.05 m).
FLAT_WITHIN_M = 0.05


def network_elevation(net_file: str | Path) -> tuple[float, str]:
    """The largest height |z| (m) of any lane shape point of a network and the id of that lane
    ((0.0, "") for a flat network: netconvert writes z only where it is not 0). Read once per
    file version (every run of a batch asks)."""
    return _elevation(str(Path(net_file)), _file_version(net_file))


@functools.lru_cache(maxsize=16)
def _elevation(net_file: str, stamp: int | None) -> tuple[float, str]:
    root = _parse_xml(net_file, "SUMO network (.net.xml)", ("net",))
    highest, where = 0.0, ""
    for lane in root.iter("lane"):
        for point in (lane.get("shape") or "").split():
            coords = point.split(",")
            if len(coords) > 2:
                try:
                    z = abs(float(coords[2]))
                except ValueError:
                    raise NetworkFileError(f"{net_file}: lane {lane.get('id')!r}: shape: expected 'x,y[,z] ...' "
                                           f"numbers, got {point!r}") from None
                if z > highest:
                    highest, where = z, lane.get("id")
    return highest, where


def closed_lanes(net_file: str | Path, vclass: str) -> frozenset[str]:
    """Ids of the normal lanes that vehicles of SUMO class `vclass` may not use (a lane's `allow`
    without the class, or `disallow` with it; "all" stands for every class): a shoulder, a bus or
    bicycle lane. SUMO refuses a departure there."""
    return _closed_lanes(str(Path(net_file)), _file_version(net_file), vclass)


@functools.lru_cache(maxsize=64)
def _closed_lanes(net_file: str, stamp: int | None, vclass: str) -> frozenset[str]:
    root = _parse_xml(net_file, "SUMO network (.net.xml)", ("net",))
    closed = set()
    for edge in root.iter("edge"):
        if edge.get("function") not in (None, "normal"):
            continue
        for lane in edge.iter("lane"):
            allow, disallow = (set((lane.get(k) or "").split()) for k in ("allow", "disallow"))
            if (allow and not allow & {"all", vclass}) or disallow & {"all", vclass}:
                closed.add(lane.get("id"))
    return frozenset(closed)


def require_flat_network(net_file: str | Path) -> None:
    """NetworkFileError unless the network lies flat at z = 0, as the ego camera's world does: on a
    network with elevation the camera, the vehicles and the road would not meet (vehicles drawn in
    the sky over a flat road, every box and depth check wrong), so the camera refuses it."""
    highest, lane = network_elevation(net_file)
    if highest > FLAT_WITHIN_M:
        raise NetworkFileError(
            f"{net_file}: lane {lane!r} lies {highest:.2f} m off z = 0; the ego camera renders a flat world "
            "(road at z = 0): flatten the network (netconvert -s NET --flatten -o FLAT.net.xml) "
            "or run without the camera (vision.enabled: false)")


# Frames already built, by (network file, its modification time, route): several stages of a run
# (and every seed of a batch in one process) ask for the same one.
_FRAMES: dict[tuple, RoadFrame] = {}


def read_road(net_file: str | Path, route: list[str] | tuple[str, ...] | None = None) -> RoadFrame:
    """The road frame of `route` (edge ids in driving order) through a SUMO network; without a
    route, the network's one chain of edges. A network of one straight edge of parallel lanes of
    equal width gives its closed-form :class:`Road`.

    Raises NetworkFileError for a file that is not a usable network and RouteError (with
    `.where`, e.g. "route[2]") for a route the network cannot carry.
    """
    path = Path(net_file)
    key = (str(path.resolve()), _file_version(path), tuple(route) if route is not None else None)
    if key in _FRAMES:
        return _FRAMES[key]
    root = _parse_xml(net_file, "SUMO network (.net.xml)", ("net",))
    edges = [e for e in root.iter("edge") if e.get("function") in (None, "normal")]
    if not edges:
        raise NetworkFileError(f"{net_file}: no <edge> (other than junction-internal ones); expected a road")
    straight = _straight_edge(net_file, edges[0]) if len(edges) == 1 else None
    if straight is not None and (route is None or tuple(route) == straight.route):
        frame: RoadFrame = straight
    else:
        try:
            frame = RoadFrame.from_net(net_file, route)
        except RouteError:
            raise
        except (ValueError, TypeError, AttributeError, KeyError, IndexError) as exc:
            raise NetworkFileError(f"{net_file}: cannot build a road frame from this network "
                                   f"({type(exc).__name__}: {exc}); expected a netconvert-built .net.xml") from None
    _FRAMES[key] = frame
    return frame


def sumo_place(frame: RoadFrame, track: int, front: float) -> tuple[tuple[str, ...], int, float] | None:
    """(route edges from the insertion edge, SUMO lane index, lane position) of a front bumper at
    `front` along the frame's route in `track`; None where the track is absent there (or in a
    junction). A front beyond the route's ends keeps its lane position (the caller refuses it)."""
    try:
        lane_id, _ = frame.sumo_lane_position(track, min(max(front, 0.0), frame.length_m))
    except ValueError:
        return None
    edge, index = lane_id.rsplit("_", 1)
    k = frame.route.index(edge)
    return frame.route[k:], int(index), front - frame.edge_start_s[edge]


def sumo_lane_id(place: tuple[tuple[str, ...], int, float]) -> str:
    """The SUMO lane id of a placement from :func:`sumo_place`."""
    edges, index, _ = place
    return f"{edges[0]}_{index}"


def accident_s(accident, frame) -> float:
    """The accident's front bumper along the frame's route (its pos_m along `edge` when it names one)."""
    return frame.edge_start_s[accident.edge] + accident.pos_m if accident.edge is not None else accident.pos_m


def read_vehicle_types(vtype_file: str | Path) -> dict[str, dict[str, str]]:
    """The <vType> attributes of an additional file, by type id (NetworkFileError when unreadable)."""
    root = _parse_xml(vtype_file, "SUMO additional file with <vType> elements", ("additional", "routes"))
    types = {}
    for k, vt in enumerate(root.iter("vType")):
        if not vt.get("id"):
            raise NetworkFileError(f"{vtype_file}: vType number {k + 1}: id: expected a vehicle type id")
        types[vt.get("id")] = dict(vt.attrib)
    if not types:
        raise NetworkFileError(f"{vtype_file}: no <vType> elements; expected at least one vehicle type")
    return types


def netconvert_binary() -> str:
    """The netconvert of the eclipse-sumo wheel (falls back to one on PATH)."""
    here = Path(sys.executable).parent / "netconvert"
    if here.exists():
        return str(here)
    found = shutil.which("netconvert")
    if found is None:
        raise RuntimeError("netconvert not found: install the package (it depends on eclipse-sumo)")
    return found


def network_names(net_dir: Path) -> list[str]:
    """The networks whose sources are in net_dir: plain XML (NAME.nod.xml + NAME.edg.xml) or an
    OpenStreetMap extract (NAME.osm.xml)."""
    plain = {p.name[: -len(".nod.xml")] for p in net_dir.glob("*.nod.xml")
             if (net_dir / p.name.replace(".nod.xml", ".edg.xml")).exists()}
    osm = {p.name[: -len(".osm.xml")] for p in net_dir.glob("*.osm.xml")}
    return sorted(plain | osm)


# OpenStreetMap import options that keep a highway usable (see docs/components/traffic.md, "Networks"): only the
# motorway carriageways and their links; geometry-only nodes merged into curved edges; on-ramps
# given acceleration lanes; clustered junctions joined; traffic-light and roundabout guessing (for
# extracts that reach ordinary roads); OSM way ids kept as edge parameters; no U-turns.
OSM_OPTIONS = (
    "--keep-edges.by-type", "highway.motorway,highway.motorway_link",
    "--remove-edges.isolated",
    "--geometry.remove",
    "--ramps.guess",
    "--junctions.join",
    "--tls.guess-signals",
    "--roundabouts.guess",
    "--output.original-names",
)


def build_network(net_dir: Path, name: str = "highway") -> Path:
    """Build NAME.net.xml from NAME.nod.xml / .edg.xml, and .typ.xml / .con.xml where present, or
    from the OpenStreetMap extract NAME.osm.xml (with OSM_OPTIONS).

    netconvert runs inside net_dir on relative names, so the header it writes carries no machine
    paths; a rebuilt network whose content is unchanged keeps the existing file (the header's
    timestamp alone would otherwise change it).
    """
    out = net_dir / f"{name}.net.xml"
    tmp = net_dir / f"{name}.net.xml.tmp-build"
    if (net_dir / f"{name}.nod.xml").exists():
        cmd = [netconvert_binary(), "--node-files", f"{name}.nod.xml", "--edge-files", f"{name}.edg.xml"]
        for option, suffix in (("--type-files", "typ"), ("--connection-files", "con")):
            if (net_dir / f"{name}.{suffix}.xml").exists():
                cmd += [option, f"{name}.{suffix}.xml"]
    else:
        cmd = [netconvert_binary(), "--osm-files", f"{name}.osm.xml", *OSM_OPTIONS]
    cmd += ["--no-turnarounds", "true", "--output-file", tmp.name]
    try:
        subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=net_dir)
    except subprocess.CalledProcessError as exc:
        tmp.unlink(missing_ok=True)
        raise RuntimeError(f"netconvert failed on {net_dir / name}.*.xml:\n{exc.stderr.strip()}") from None

    def body(path: Path) -> str:  # the header comment carries a timestamp
        text = path.read_text()
        return text[text.index("<net "):]

    if out.exists() and body(out) == body(tmp):
        tmp.unlink()
    else:
        tmp.replace(out)
    return out


def build_networks(net_dir: Path) -> list[Path]:
    """Build every network of net_dir (see network_names)."""
    if not net_dir.is_dir():
        raise RuntimeError(f"{net_dir}: folder not found")
    names = network_names(net_dir)
    if not names:
        raise RuntimeError(f"{net_dir}: nothing to build (expected NAME.nod.xml + NAME.edg.xml, or NAME.osm.xml)")
    return [build_network(net_dir, name) for name in names]
