"""The highway network: reproducible build with netconvert, and its road geometry.

The road is one straight edge. :class:`Road` is the geometry every other stage needs (lane
centres, road edges, the direction of travel) so no stage has to read SUMO files itself.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from vcfusion.errors import InputError

REPO_NET_DIR = Path(__file__).resolve().parents[3] / "sumo_net"


@dataclass(frozen=True)
class Road:
    """A straight multi-lane road. Lane 0 is the rightmost lane (SUMO's convention)."""

    edge_id: str
    start: tuple[float, float]
    end: tuple[float, float]
    num_lanes: int
    lane_width_m: float
    speed_limit_mps: float

    @cached_property
    def length_m(self) -> float:
        return float(np.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1]))

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
    def width_m(self) -> float:
        return self.num_lanes * self.lane_width_m

    @cached_property
    def _frame(self) -> tuple[float, ...]:
        # plain floats: to_road_frame runs several times per tick, mostly on small arrays
        return (float(self.start[0]), float(self.start[1]), *map(float, self.direction),
                *map(float, self.left_normal), float(self.width_m))

    def to_road_frame(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y) to (s, d): s along the road from its start, d left of the right road edge."""
        x0, y0, dx, dy, nx, ny, width = self._frame
        rel_x = np.asarray(x) - x0
        rel_y = np.asarray(y) - y0
        s = rel_x * dx + rel_y * dy
        # The edge's reference line (its 'shape') is the left road edge in SUMO's right-hand traffic.
        d_left = rel_x * nx + rel_y * ny
        return s, d_left + width

    def to_world(self, s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.asarray(s, dtype=float)
        d_left = np.asarray(d, dtype=float) - self.width_m
        x = self.start[0] + s * self.direction[0] + d_left * self.left_normal[0]
        y = self.start[1] + s * self.direction[1] + d_left * self.left_normal[1]
        return x, y

    def lane_centre_d(self, lane: np.ndarray | int) -> np.ndarray:
        return (np.asarray(lane, dtype=float) + 0.5) * self.lane_width_m

    def lane_of(self, d: np.ndarray) -> np.ndarray:
        """Map-match a lateral road coordinate to a lane index (-1 when off the road)."""
        lane = np.floor(np.asarray(d, dtype=float) / self.lane_width_m).astype(np.int16)
        return np.where((lane >= 0) & (lane < self.num_lanes), lane, -1)


class NetworkFileError(InputError):
    """A network or vehicle-types file that cannot be used; the message names the file and the problem."""


SUPPORTED_ROAD = ("supported: a SUMO .net.xml with one straight edge (plus internal edges) of parallel lanes of "
                  "equal width, as `vcfusion build-net` makes")


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


def read_road(net_file: str | Path) -> Road:
    """Read the single straight edge of a SUMO network file (NetworkFileError when it is not one)."""
    root = _parse_xml(net_file, "SUMO network (.net.xml)", ("net",))
    edges = [e for e in root.iter("edge") if e.get("function") != "internal"]
    if len(edges) != 1:
        raise NetworkFileError(f"{net_file}: found {len(edges)} edges; {SUPPORTED_ROAD}")
    edge = edges[0]
    lanes = list(edge.iter("lane"))
    if not lanes:
        raise NetworkFileError(f"{net_file}: edge {edge.get('id')!r} has no <lane>; {SUPPORTED_ROAD}")
    lanes.sort(key=lambda lane: _lane_attr(net_file, lane, "index", int, "a lane index"))
    widths = {_lane_attr(net_file, lane, "width", lambda v: float(v if v is not None else 3.2), "a width in m")
              for lane in lanes}
    if len(widths) != 1:
        raise NetworkFileError(f"{net_file}: lanes of widths {sorted(widths)}; {SUPPORTED_ROAD}")
    width = widths.pop()
    shapes = [_lane_attr(net_file, lane, "shape", _shape_points, "'x,y x,y ...' (at least two points)")
              for lane in lanes]
    speed = _lane_attr(net_file, lanes[0], "speed", float, "a speed in m/s")
    # Lane shapes are lane centre lines; every one must be a straight segment parallel to the others.
    (x0, y0), (x1, y1) = shapes[-1][0], shapes[-1][-1]
    length = float(np.hypot(x1 - x0, y1 - y0))
    if length <= 0.0:
        raise NetworkFileError(f"{net_file}: lane {lanes[-1].get('id')!r} has zero length; {SUPPORTED_ROAD}")
    direction = np.array([x1 - x0, y1 - y0]) / length
    normal = np.array([-direction[1], direction[0]])
    for i, (lane, points) in enumerate(zip(lanes, shapes)):
        # lane i lies (n - 1 - i) lane widths right of the leftmost lane (lane 0 is the rightmost)
        offsets = (points - shapes[-1][0]) @ normal
        if np.abs(offsets + (len(lanes) - 1 - i) * width).max() > 0.05:
            raise NetworkFileError(f"{net_file}: lane {lane.get('id')!r} is not straight and parallel to the "
                                   f"others at {width} m spacing; {SUPPORTED_ROAD}")
    start = np.array([x0, y0]) + normal * width / 2
    end = np.array([x1, y1]) + normal * width / 2
    return Road(
        edge_id=edge.get("id"),
        start=(float(start[0]), float(start[1])),
        end=(float(end[0]), float(end[1])),
        num_lanes=len(lanes),
        lane_width_m=width,
        speed_limit_mps=speed,
    )


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


def network_names(net_dir: Path = REPO_NET_DIR) -> list[str]:
    """The networks whose sources are in net_dir: plain XML (NAME.nod.xml + NAME.edg.xml) or an
    OpenStreetMap extract (NAME.osm.xml)."""
    plain = {p.name[: -len(".nod.xml")] for p in net_dir.glob("*.nod.xml")
             if (net_dir / p.name.replace(".nod.xml", ".edg.xml")).exists()}
    osm = {p.name[: -len(".osm.xml")] for p in net_dir.glob("*.osm.xml")}
    return sorted(plain | osm)


# OpenStreetMap import options that keep a highway usable (see README, "Networks"): only the
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


def build_network(net_dir: Path = REPO_NET_DIR, name: str = "highway") -> Path:
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


def build_networks(net_dir: Path = REPO_NET_DIR) -> list[Path]:
    """Build every network of net_dir (see network_names)."""
    if not net_dir.is_dir():
        raise RuntimeError(f"{net_dir}: folder not found")
    names = network_names(net_dir)
    if not names:
        raise RuntimeError(f"{net_dir}: nothing to build (expected NAME.nod.xml + NAME.edg.xml, or NAME.osm.xml)")
    return [build_network(net_dir, name) for name in names]
