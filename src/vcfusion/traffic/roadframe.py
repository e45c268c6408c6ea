"""The road frame of a route through any SUMO network: (s, d) coordinates and lane identity.

A route is a list of edges. Its frame is built from the ``.net.xml`` lane shapes:

- **reference line**: the route's right road boundary at d = 0 (the right edge of the rightmost
  lane the route ever has), stitched along the route's edges and the junction-internal lanes
  between them. Where that lane does not exist (the acceleration lane before the merge), the
  line runs where its right edge would be (the lanes' nominal widths);
- **s**: distance along the route as SUMO counts it (lane lengths, internal lanes included), so a
  vehicle at lane position p on a route edge has s = ``edge_start_s[edge] + p``: continuous across
  edge boundaries. Along an edge s spreads SUMO's length over the middle of the road (an edge's
  length is its middle's); SUMO spreads it over each lane's own shape, so on an edge that is part
  straight, part curved the lanes beside the middle differ from SUMO's positions by up to their
  offset times half the edge's turn (0.6 m for 3.5 m and 20 degrees);
- **d**: metres left of the reference line, along its normal: the same lane is one constant d
  range on every edge it continues through;
- **tracks**: a lane's index from the right, stable across edges where SUMO's connections say the
  lane continues (the main line's lanes keep their index when an acceleration lane is added to
  their right: that lane gets the lower index, and the main line's index 0 is then track 1).
  A SUMO lane maps to its track with ``track_of[lane_id]``; the lanes present change along s.

Geometry. The stored polyline P_i is the line of constant d in the middle of the widest road
(d = half its width; the reference line is that line offset by -d). It carries at every vertex a
miter vector M_i (the bisector of the adjacent segments' left normals, scaled so its projection
on each normal is 1): SUMO offsets lane shapes the same way, so lanes are lines of constant d.
Inside segment i the map is Q(t, e) = P_i + t (P_i+1 - P_i) + e (M_i + t (M_i+1 - M_i)), with
e = d - the middle's d and s linear in t: an exact, continuous inverse of itself (world -> (s, d)
solves a quadratic in t). Before the route's start and after its end the first and last segments
extend straight, as the straight road does. Where lanes join, split, appear or end:

- each piece's geometry is one lane's shape (an edge's lane 0; in a junction, the internal lane
  of the continuing lane with the lowest track), its vertices within 1.5 cm of their neighbours'
  chord dropped (SUMO's 0.01 m coordinates make a few-cm segment's direction noise);
- where two pieces meet, the miter is the bend's, unless SUMO cut the lanes along a junction
  border that is not square to them (a kink, a ramp's angle): then the line of constant s there
  runs through the lanes' ends, so each lane's s starts and ends where SUMO's positions do;
- on the inside of a junction bend tighter than the stored line's offset, the line would fold
  back: its two vertices are pulled together, and the lines of constant d fan about that point;
- in a junction s is spread over the lanes that continue along the route (not a ramp's lane);
- lanes that jump sideways within a junction (more than 0.5 m, more across than along) are
  refused with a RouteError naming the junction lane.

The conversion runs for every twin on every tick: it is a compiled kernel with a uniform grid over
the segments (points farther than 60 m from the road fall back to a scan of all segments).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numba
import numpy as np

# Longest segment the lookup grid stores (longer straight segments are split: the same map).
_MAX_SEGMENT_M = 25.0
_CELL_M = 25.0
_MAX_CELLS = 1_000_000
# Lateral band around the road whose points are found through the grid (the other carriageway,
# ramps alongside); beyond it, a scan of all segments.
_BAND_M = 60.0
# Within this band the segments' maps do not overlap (curve radii are larger): the first segment
# whose map holds a point is the one.
_UNIQUE_BAND_M = 15.0
# Reference lines of consecutive pieces meet within this distance (SUMO's lane ends and the next
# piece's starts coincide to its 0.01 m output precision; offsetting bends adds a few cm).
_JOIN_TOL_M = 0.5
# Lane shape vertices closer than this to the chord of their neighbours are dropped before the
# offset (SUMO writes coordinates to 0.01 m; a junction lane's shape has vertices a few cm apart).
_SHAPE_NOISE_M = 0.015
# Lane ends off the bend's miter by more than this lie on a skewed junction border (SUMO cuts
# lanes at the junction's shape; square to the road they agree to its 0.01 m output precision).
# Chosen on generated seeds 0-599 (a fan-shaped junction turns 1.2 cm into 0.17 m of s: seed 424);
# held out, seeds 600-799: 199 of 200 networks keep every promise (docs: roadframe figures).
_CUT_TOL_M = 0.01


class RouteError(ValueError):
    """A route the network cannot carry (unknown edge, edges that do not connect).

    `where` names the part of the route ("route[2]", "route"; "" for the network as a whole) and
    `detail` what is wrong, so a scenario's validation can name its own field instead."""

    def __init__(self, net_file, where: str, detail: str):
        super().__init__(f"{net_file}: {where}: {detail}" if where else f"{net_file}: {detail}")
        self.net_file, self.where, self.detail = Path(net_file), where, detail


@dataclass(frozen=True)
class _Lane:
    lane_id: str
    edge_id: str
    index: int
    width: float
    length: float
    shape: np.ndarray  # (k, 2)
    speed: float = math.nan


@dataclass(frozen=True)
class _Connection:
    from_edge: str
    to_edge: str
    from_lane: int
    to_lane: int
    via: str | None


class _Net:
    """The parts of a .net.xml the frame needs (ElementTree: sumolib's reader is much slower on
    large imported networks and hides the internal lanes' connection chain)."""

    def __init__(self, net_file: Path):
        root = ET.parse(net_file).getroot()
        if root.get("lefthand") in ("1", "true"):
            # there lane 0 is the leftmost lane: tracks and d would run the wrong way
            raise RouteError(net_file, "", f"a left-hand-traffic network (lefthand=\"{root.get('lefthand')}\"); "
                             "the road frame supports right-hand traffic only")
        self.lanes: dict[str, _Lane] = {}
        self.edge_lanes: dict[str, list[_Lane]] = {}
        self.internal_edges: set[str] = set()
        for edge in root.iter("edge"):
            eid = edge.get("id")
            if edge.get("function") == "internal":
                self.internal_edges.add(eid)
            elif edge.get("function") not in (None, "normal"):
                continue  # walking areas, crossings
            lanes = []
            for lane in edge.iter("lane"):
                shape = np.array([[float(c) for c in p.split(",")[:2]] for p in lane.get("shape").split()])
                lanes.append(_Lane(lane.get("id"), eid, int(lane.get("index")), float(lane.get("width", 3.2)),
                                   float(lane.get("length")), shape, float(lane.get("speed", "nan"))))
            lanes.sort(key=lambda ln: ln.index)
            self.edge_lanes[eid] = lanes
            self.lanes.update({ln.lane_id: ln for ln in lanes})
        self.connections: list[_Connection] = [
            _Connection(c.get("from"), c.get("to"), int(c.get("fromLane")), int(c.get("toLane")), c.get("via"))
            for c in root.iter("connection")]
        self.between: dict[tuple[str, str], list[_Connection]] = {}
        self.into: dict[str, list[_Connection]] = {}
        for c in self.connections:
            self.between.setdefault((c.from_edge, c.to_edge), []).append(c)
            self.into.setdefault(c.to_edge, []).append(c)
        # internal lane -> the next internal lane of its chain (junctions with internal stops)
        self._next_via = {f"{c.from_edge}_{c.from_lane}": c.via for c in self.connections
                          if c.from_edge in self.internal_edges and c.via}

    @property
    def normal_edges(self) -> list[str]:
        return [e for e in self.edge_lanes if e not in self.internal_edges]

    def via_chain(self, connection: _Connection) -> list[_Lane]:
        chain, via = [], connection.via
        while via is not None:
            chain.append(self.lanes[via])
            via = self._next_via.get(via)
        return chain


def _miters(points: np.ndarray) -> np.ndarray:
    """Per vertex: the left normal bisector, scaled so its projection on both adjacent segments'
    normals is 1 (an offset by e along it keeps distance e from both segments)."""
    seg = np.diff(points, axis=0)
    seg /= np.hypot(seg[:, 0], seg[:, 1])[:, None]
    normals = np.column_stack([-seg[:, 1], seg[:, 0]])
    m = np.empty_like(points)
    m[0], m[-1] = normals[0], normals[-1]
    if len(points) > 2:
        b = normals[:-1] + normals[1:]
        b /= np.hypot(b[:, 0], b[:, 1])[:, None]
        cos_half = np.maximum(np.einsum("ij,ij->i", b, normals[1:]), 0.1)  # no spikes at hairpins
        m[1:-1] = b / cos_half[:, None]
    return m


def _bend_miter(n_in: np.ndarray, n_out: np.ndarray) -> np.ndarray:
    """The miter where a segment of left normal n_in meets one of n_out (as _miters' inner vertices)."""
    b = n_in + n_out
    b = b / np.hypot(*b)
    return b / max(float(b @ n_out), 0.1)


def _unfold(pts: np.ndarray, tangents: np.ndarray) -> np.ndarray:
    """Where the reference line runs backwards, its two vertices pulled together (in place);
    returns which vertices were. Offset to the inside of a tight bend (a junction lane that turns
    a few degrees within a metre, the reference line lanes away on its inner side) a polyline
    folds over itself; a segment of no length instead is a fan: the lines of constant d turn
    about one point, with s along the turn, which keeps s monotonic and the map invertible."""
    pinned = np.zeros(len(pts), dtype=bool)
    for _ in range(4 * len(pts)):
        seg = pts[1:] - pts[:-1]
        length = np.hypot(seg[:, 0], seg[:, 1])
        ahead = np.einsum("ij,ij->i", seg, tangents[:-1] + tangents[1:])
        back = np.flatnonzero((ahead <= 0.0) & (length > 1e-9))
        if not len(back):
            break
        j = back[0]
        pts[j] = pts[j + 1] = 0.5 * (pts[j] + pts[j + 1])
        pinned[j] = pinned[j + 1] = True
    return pinned


def _cut_direction(p: "_Piece", p_bounds: np.ndarray, q: "_Piece", q_bounds: np.ndarray,
                   anchor_end: np.ndarray, bend: np.ndarray) -> np.ndarray | None:
    """Where piece p hands over to piece q: the direction (per metre of d) of the line through
    p's lanes' ends and q's lanes' starts, or None where they lie on the bend's miter within
    _CUT_TOL_M (a junction square to the road) or do not lie on one line."""
    points, ds = [], []
    for piece, bounds, end in ((p, p_bounds, -1), (q, q_bounds, 0)):
        for track, lane in piece.own:
            points.append(lane.shape[end])
            ds.append(bounds[track] + piece.widths[track] / 2)
    if len(set(np.round(ds, 6))) < 2:
        return None
    points, ds = np.array(points), np.array(ds)
    d_anchor = p_bounds[p.anchor_track] + p.widths[p.anchor_track] / 2
    if np.hypot(*(anchor_end + np.outer(ds - d_anchor, bend) - points).T).max() <= _CUT_TOL_M:
        return None
    dd = ds - ds.mean()
    v = (dd @ (points - points.mean(axis=0))) / (dd @ dd)
    centre = points.mean(axis=0) - ds.mean() * v
    normal = bend / np.hypot(*bend)
    along = v @ normal
    if not 0.5 < along < 2.0 or np.hypot(*(centre + np.outer(ds, v) - points).T).max() > _CUT_TOL_M + 0.05:
        return None  # not one straight border: the bend's miter
    return v


def _dedupe(points: np.ndarray, min_gap: float = 1e-3) -> np.ndarray:
    keep = [0]
    for i in range(1, len(points)):
        if np.hypot(*(points[i] - points[keep[-1]])) > min_gap:
            keep.append(i)
    if len(keep) == 1:  # a lane of (almost) zero extent: keep its ends
        keep.append(len(points) - 1)
    return points[keep]


def _simplify(points: np.ndarray, tol: float = _SHAPE_NOISE_M) -> np.ndarray:
    """The vertices of a polyline that stand out of its chords by more than `tol` (Douglas-Peucker):
    the direction of a segment a few cm long, its ends rounded to SUMO's 0.01 m, is noise, which
    the offset to lanes several metres away multiplies."""
    keep = np.zeros(len(points), dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, len(points) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        chord = points[j] - points[i]
        n = np.hypot(*chord)
        rel = points[i + 1:j] - points[i]
        dist = np.abs(rel[:, 0] * chord[1] - rel[:, 1] * chord[0]) / n if n > 0 else np.hypot(rel[:, 0], rel[:, 1])
        k = int(np.argmax(dist))
        if dist[k] > tol:
            keep[i + 1 + k] = True
            stack += [(i, i + 1 + k), (i + 1 + k, j)]
    return points[keep]


@dataclass(frozen=True)
class _Piece:
    """One stretch of the route: a route edge, or one internal lane between two route edges."""

    edge_id: str
    s0: float
    length: float
    anchor: _Lane  # the lane whose shape gives this piece's geometry
    anchor_track: int
    widths: dict[int, float]  # track -> width of the lane present here
    # tracks over whose middle s is spread (empty: every lane present); in a junction, the lanes
    # that continue along the route (not those of a ramp that joins it, which curve their own way)
    through: tuple[int, ...] = ()
    # (track, lane) of the piece's lanes that follow the route: where SUMO cuts them at a junction
    # border, they end (and the next piece's begin)
    own: tuple = ()


class RoadFrame:
    """(s, d) frame and lane tracks of one route of a SUMO network (see the module docstring).

    Build with :meth:`from_net`. All queries take and return NumPy arrays (scalars broadcast).
    """

    def __init__(self, net_file: str | Path, route: list[str] | tuple[str, ...]):
        self.net_file = Path(net_file)
        self.route = tuple(route)
        net = _Net(self.net_file)
        self._build(net)

    @classmethod
    def from_net(cls, net_file: str | Path, route: list[str] | tuple[str, ...] | None = None) -> "RoadFrame":
        """The frame of `route` (edge ids in driving order); without a route, the network's one
        chain of edges (a network with branches needs a route)."""
        if route is None:
            route = default_route(net_file)
        return cls(net_file, route)

    # value semantics: stages that each build the frame of the same route share cached results
    @cached_property
    def key(self) -> tuple:
        return (str(self.net_file.resolve()), self.route)

    def __eq__(self, other) -> bool:
        return isinstance(other, RoadFrame) and self.key == other.key

    def __hash__(self) -> int:
        return hash(self.key)

    def __repr__(self) -> str:
        return f"RoadFrame({self.net_file.name}, route={list(self.route)}, length={self.length_m:.2f} m)"

    # ------------------------------------------------------------------ construction
    def _build(self, net: _Net) -> None:
        if not self.route:
            raise RouteError(self.net_file, "route", "expected at least one edge")
        for k, edge in enumerate(self.route):
            if edge not in net.edge_lanes or edge in net.internal_edges:
                raise RouteError(self.net_file, f"route[{k}]", f"unknown edge {edge!r}")
        shift = self._track_shifts(net)
        low = min(shift[k] for k in range(len(self.route)))
        shift = [v - low for v in shift]  # the rightmost lane the route ever has is track 0
        self.track_of: dict[str, int] = {}
        self.edge_start_s: dict[str, float] = {}
        pieces: list[_Piece] = []
        s = 0.0
        for k, edge in enumerate(self.route):
            lanes = net.edge_lanes[edge]
            for ln in lanes:
                self.track_of[ln.lane_id] = ln.index + shift[k]
            self.edge_start_s[edge] = s
            pieces.append(_Piece(edge, s, lanes[0].length, lanes[0], shift[k],
                                 {ln.index + shift[k]: ln.width for ln in lanes},
                                 own=tuple((ln.index + shift[k], ln) for ln in lanes)))
            s += lanes[0].length
            if k + 1 < len(self.route):
                s = self._junction_pieces(net, k, shift, s, pieces)
        self.length_m = s
        self._assemble(pieces)

    def _assemble(self, pieces: list[_Piece]) -> None:
        """Lane bounds, reference line, lookup grid and track spans of the route's pieces."""
        self.num_tracks = 1 + max(max(p.widths, default=0) for p in pieces)
        nominal = {}
        for p in pieces:  # a track's width where the route first has it
            for t, w in p.widths.items():
                nominal.setdefault(t, w)
        # Per piece: right boundary of every track (virtual tracks at their nominal width).
        bounds = np.zeros((len(pieces), self.num_tracks + 1))
        present = np.zeros((len(pieces), self.num_tracks), dtype=bool)
        for i, p in enumerate(pieces):
            for t in range(self.num_tracks):
                bounds[i, t + 1] = bounds[i, t] + p.widths.get(t, nominal[t])
                present[i, t] = t in p.widths
        self._pieces = pieces
        self._piece_s0 = np.array([p.s0 for p in pieces])
        self._bounds = bounds
        self._present = present
        self.max_width_m = float(bounds[:, -1].max())
        self._build_reference(pieces, bounds)
        self._build_track_intervals()

    def _track_shifts(self, net: _Net) -> list[int]:
        """Track of lane j of route edge k = j + shift[k]. The shift between consecutive edges is
        the one most of their connections agree on (a lane that ends or starts breaks no
        continuity); ties go to the lanes that line up geometrically."""
        shift = [0]
        for k in range(len(self.route) - 1):
            a, b = self.route[k], self.route[k + 1]
            conns = net.between.get((a, b), [])
            if not conns:
                raise RouteError(self.net_file, f"route[{k + 1}]", f"edges {a!r} and {b!r} do not connect "
                                 "(no lane of the first continues onto the second)")
            votes = Counter(c.from_lane - c.to_lane for c in conns)

            def gap(delta: int) -> float:
                pairs = [c for c in conns if c.from_lane - c.to_lane == delta]
                return float(np.mean([np.hypot(*(net.edge_lanes[a][c.from_lane].shape[-1]
                                                 - net.edge_lanes[b][c.to_lane].shape[0])) for c in pairs]))

            best = max(votes, key=lambda delta: (votes[delta], -gap(delta)))
            shift.append(shift[-1] + best)
        return shift

    def _junction_pieces(self, net: _Net, k: int, shift: list[int], s: float, pieces: list[_Piece]) -> float:
        """The internal lanes between route edges k and k+1: geometry from the continuing lane
        with the lowest track; the lanes present are those entering edge k+1 (from any edge)."""
        a, b = self.route[k], self.route[k + 1]
        into_b = [c for c in net.into.get(b, []) if c.via and c.from_edge not in net.internal_edges]
        continuing = [c for c in into_b if c.from_edge == a and c.from_lane + shift[k] == c.to_lane + shift[k + 1]]
        if not continuing:
            return s  # no internal lanes (networks built with --no-internal-links)
        anchor = min(continuing, key=lambda c: c.to_lane)
        widths_by_step: list[dict[int, float]] = []
        for c in into_b:
            track = c.to_lane + shift[k + 1]
            for step, ln in enumerate(net.via_chain(c)):
                while len(widths_by_step) <= step:
                    widths_by_step.append({})
                widths_by_step[step].setdefault(track, ln.width)
                self.track_of.setdefault(ln.lane_id, track)
        start = s
        through_chains = [(c, net.via_chain(c)) for c in continuing]
        for step, ln in enumerate(net.via_chain(anchor)):
            widths = widths_by_step[step] if step < len(widths_by_step) else {}
            pieces.append(_Piece(ln.edge_id, s, ln.length, ln, anchor.to_lane + shift[k + 1], widths,
                                 tuple(sorted({c.to_lane + shift[k + 1] for c in continuing} & set(widths))),
                                 tuple((c.to_lane + shift[k + 1], chain[step]) for c, chain in through_chains
                                       if step < len(chain))))
            self.edge_start_s.setdefault(ln.edge_id, s)
            s += ln.length
        # the other connections' internal lanes start where the junction starts
        for c in into_b:
            for ln in net.via_chain(c):
                self.edge_start_s.setdefault(ln.edge_id, start)
        return s

    def _refuse_sideways_jump(self, before: tuple, p: _Piece, shape: np.ndarray) -> None:
        """RouteError where a junction's lanes move more sideways than along the road, by more
        than _JOIN_TOL_M: lines of constant d cannot follow a lane that jumps across (netconvert's
        --ramps.guess shifts the edge before an exit half a lane sideways at its start when the
        OpenStreetMap ways already carry the exit's lanes)."""
        prev = before[2]
        direction = prev[-1] - prev[-2]
        direction = direction / np.hypot(*direction)
        chord = shape[-1] - shape[0]
        along = float(chord @ direction)
        across = abs(float(chord[0] * direction[1] - chord[1] * direction[0]))
        if across > _JOIN_TOL_M and across > along:
            raise RouteError(
                self.net_file, "route", f"the lanes jump {across:.2f} m sideways within junction lane "
                f"{p.anchor.lane_id!r} after {before[1].edge_id!r} ({along:.2f} m along the road), which the "
                "road frame cannot follow; expected lanes that continue along the road (an OpenStreetMap import: "
                "netconvert's --ramps.guess shifts the edge before an exit when the ways already carry "
                "the exit's lanes; build without it)")

    def _build_reference(self, pieces: list[_Piece], bounds: np.ndarray) -> None:
        # The polyline stored is the line of constant d in the middle of the widest road, not the
        # reference line d = 0 (the same map: lines of constant d are offsets along the miters):
        # offset from the lanes to the inside of a junction bend, a line far from them folds over
        # itself (a reference line several lanes right of a lane that turns within a metre).
        self._d_line = 0.5 * self.max_width_m
        pts_all: list[np.ndarray] = []
        s_all: list[np.ndarray] = []
        tan_all: list[np.ndarray] = []  # the lanes' direction at each vertex
        fix_all: list[np.ndarray] = []
        mit_all: list[np.ndarray] = []  # the pieces' miters at each vertex
        self.max_join_gap_m = 0.0
        kept = []
        for i, p in enumerate(pieces):
            shape = _simplify(_dedupe(p.anchor.shape))
            if np.hypot(*(shape[-1] - shape[0])) < 1e-6 and len(shape) == 2:
                continue  # a junction lane of no extent (its length joins the next segment's s)
            if kept and p.edge_id.startswith(":"):
                self._refuse_sideways_jump(kept[-1], p, shape)
            kept.append((i, p, shape, _miters(shape)))
        # where two pieces meet, both are offset along the miter of the bend between them, as one
        # polyline would be: each offset along its own end normal put a junction lane that swerves
        # (a lane drop on a centre-spread edge, an OSM motorway: 5-10 degrees) 0.5 m off its edge
        # where SUMO cuts the lanes at a junction border that is not square to them (a bend, a
        # ramp's angle), the lanes' ends lie on that border: lines of constant s follow it
        cut: dict[int, np.ndarray] = {}  # kept index -> the cut's direction (per metre of d)
        for k, ((i, p, shape, before), (j, q, _, after)) in enumerate(zip(kept, kept[1:])):
            before[-1] = after[0] = _bend_miter(before[-1], after[0])
            v = _cut_direction(p, bounds[i], q, bounds[j], shape[-1], before[-1])
            if v is not None:
                cut[k] = v
        for k, (i, p, shape, miters) in enumerate(kept):
            if k in cut:
                miters[-1] = cut[k]
            if k - 1 in cut:
                miters[0] = cut[k - 1]
            centre_d = bounds[i, p.anchor_track] + p.widths[p.anchor_track] / 2
            ref = shape + (self._d_line - centre_d) * miters
            # SUMO spreads a lane's length over the lane's own geometry, and an edge's length is
            # that of its middle: s spreads the length over the middle of the lanes present, so
            # on a bend the lanes left and right of it are off SUMO's positions by half as much
            present = sorted(p.through or p.widths)
            middle_d = 0.5 * (bounds[i, present[0]] + bounds[i, present[-1] + 1])
            middle = shape + (middle_d - centre_d) * miters
            geo = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(middle, axis=0).T))])
            s_vertices = p.s0 + geo * (p.length / geo[-1])
            if pts_all:
                gap = float(np.hypot(*(ref[0] - pts_all[-1][-1])))
                if gap > _JOIN_TOL_M:
                    a, b = pieces[i - 1].edge_id, p.edge_id
                    if a in self.route and b in self.route:  # two route edges: no junction lanes between
                        raise RouteError(
                            self.net_file, "route", f"no junction lanes join {a!r} to {b!r} (a network built "
                            f"with --no-internal-links?) and their lanes lie {gap:.2f} m apart, which the road "
                            "frame cannot bridge; expected a network with junction lanes (netconvert without "
                            "--no-internal-links)")
                    raise RouteError(
                        self.net_file, "route", f"the lane geometry jumps by {gap:.2f} m where "
                        f"{a!r} meets {b!r}; the road frame cannot follow it")
                self.max_join_gap_m = max(self.max_join_gap_m, gap)
                pts_all[-1][-1] = 0.5 * (pts_all[-1][-1] + ref[0])  # both pieces end at the midpoint
                ref, s_vertices, miters = ref[1:], s_vertices[1:], miters[1:]
            pts_all.append(ref.copy())
            s_all.append(s_vertices)
            normals = _miters(shape)[len(shape) - len(ref):]
            tan_all.append(np.column_stack([normals[:, 1], -normals[:, 0]]))
            mit_all.append(miters)
            fixed = np.full(ref.shape, np.nan)  # the cut directions, kept through the stitching
            if k in cut:
                fixed[-1] = cut[k]
            fix_all.append(fixed)
        pts = np.concatenate(pts_all)
        svals = np.concatenate(s_all)
        fixed = np.concatenate(fix_all)
        carried = np.concatenate(mit_all)
        # beside a cut the stored line is no parallel offset of the lanes (the cut moved its vertex
        # along the road): its bisector there is not the lanes' miter, the pieces' one is
        skewed = ~np.isnan(fixed[:, 0])
        beside = np.zeros(len(fixed), dtype=bool)
        beside[:-1] |= skewed[1:]
        beside[1:] |= skewed[:-1]
        beside &= ~skewed
        fixed[beside] = carried[beside]
        pinned = _unfold(pts, np.concatenate(tan_all))
        fixed[pinned] = carried[pinned]
        # drop vertices that coincide (zero-length internal lanes): their segment has no direction
        keep = [0]
        for j in range(1, len(pts)):
            if np.hypot(*(pts[j] - pts[keep[-1]])) > 1e-6 or (pinned[j] and pinned[keep[-1]]):
                keep.append(j)
            elif j == len(pts) - 1:
                keep[-1] = j  # the route ends exactly at its last point
        pts, svals, fixed, pinned = pts[keep], svals[keep], fixed[keep], pinned[keep]
        if len(pts) < 2:
            raise RouteError(self.net_file, "route", "the route has no extent")
        # (a fan's vertices coincide: the miters of the polyline without its repeats)
        distinct = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-9])
        miters = _miters(pts[distinct])[np.cumsum(distinct) - 1]
        skewed = ~np.isnan(fixed[:, 0])
        miters[skewed] = fixed[skewed]
        # split long segments (same bilinear map) so the grid's cells list few segments each
        P, M, S = [pts[:1]], [miters[:1]], [svals[:1]]
        for i in range(len(pts) - 1):
            n = max(1, math.ceil(np.hypot(*(pts[i + 1] - pts[i])) / _MAX_SEGMENT_M))
            t = (np.arange(1, n + 1) / n)[:, None]
            t[-1] = 1.0
            P.append(pts[i] + t * (pts[i + 1] - pts[i]))
            M.append(miters[i] + t * (miters[i + 1] - miters[i]))
            S.append(svals[i] + t[:, 0] * (svals[i + 1] - svals[i]))
            P[-1][-1], M[-1][-1], S[-1][-1] = pts[i + 1], miters[i + 1], svals[i + 1]
        self._P = np.ascontiguousarray(np.concatenate(P))
        self._M = np.ascontiguousarray(np.concatenate(M))
        self._S = np.ascontiguousarray(np.concatenate(S))
        self._build_grid()

    def _build_grid(self) -> None:
        P, M = self._P, self._M
        lo, hi = -self._d_line - _BAND_M, self._d_line + _BAND_M
        corners = np.stack([P[:-1] + lo * M[:-1], P[:-1] + hi * M[:-1], P[1:] + lo * M[1:], P[1:] + hi * M[1:]])
        cmin, cmax = corners.min(axis=0), corners.max(axis=0)  # (n_seg, 2)
        origin = cmin.min(axis=0)
        extent = cmax.max(axis=0) - origin
        cell = max(_CELL_M, float(np.sqrt(extent[0] * extent[1] / _MAX_CELLS)))  # long routes: coarser
        nx, ny = (np.floor(extent / cell).astype(int) + 1)
        i0 = np.floor((cmin - origin) / cell).astype(int)
        i1 = np.floor((cmax - origin) / cell).astype(int)
        cells, segs = [], []
        for seg in range(len(P) - 1):
            gx, gy = np.meshgrid(np.arange(i0[seg, 0], i1[seg, 0] + 1), np.arange(i0[seg, 1], i1[seg, 1] + 1))
            cells.append((gx * ny + gy).ravel())
            segs.append(np.full(gx.size, seg))
        cells, segs = np.concatenate(cells), np.concatenate(segs)
        order = np.argsort(cells, kind="stable")
        self._grid_items = np.ascontiguousarray(segs[order], dtype=np.int64)
        self._grid_start = np.searchsorted(cells[order], np.arange(nx * ny + 1)).astype(np.int64)
        # origin, cell size, cells along x and y, d of the stored line (the band's centre), the
        # band's half-width (see _to_frame)
        self._grid_f = np.array([origin[0], origin[1], cell, nx, ny, self._d_line, self._d_line + _UNIQUE_BAND_M])

    def _build_track_intervals(self) -> None:
        """Per track, the [start, end) stretches of s where it exists (consecutive pieces merged)."""
        ends = np.append(self._piece_s0[1:], self.length_m)
        self._intervals: list[np.ndarray] = []
        for t in range(self.num_tracks):
            spans: list[list[float]] = []
            for i in np.flatnonzero(self._present[:, t]):
                if spans and abs(spans[-1][1] - self._piece_s0[i]) < 1e-9:
                    spans[-1][1] = ends[i]
                else:
                    spans.append([self._piece_s0[i], ends[i]])
            self._intervals.append(np.array(spans).reshape(-1, 2))

    # ------------------------------------------------------------------ the straight Road's names
    # (kept for the code written against the single straight edge; see vcfusion.traffic.network.Road)
    @property
    def num_lanes(self) -> int:
        """Number of tracks (lanes from the right) the route ever has."""
        return self.num_tracks

    @cached_property
    def lane_width_m(self) -> float:
        """The tracks' nominal width (their mean where they differ)."""
        return float(np.mean(np.diff(self._bounds[0])))

    @property
    def width_m(self) -> float:
        return self.max_width_m

    @property
    def edge_id(self) -> str:
        """The route's first edge."""
        return self.route[0]

    @cached_property
    def speed_limit_mps(self) -> float:
        """The speed limit of the route's first edge."""
        return self._pieces[0].anchor.speed

    @property
    def is_straight(self) -> bool:
        """A single straight edge of equal lanes (the case the camera renderer draws)."""
        return False

    # ------------------------------------------------------------------ queries
    def to_frame(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y) -> (s along the route, d left of the reference line)."""
        x, y, shape = _flat_pair(x, y)
        s, d = _to_frame(x, y, self._P, self._M, self._S, self._grid_f, self._grid_start, self._grid_items)
        return s.reshape(shape), d.reshape(shape)

    # the straight Road's name: records cache road_frame(road) through it (vcfusion.records)
    def to_road_frame(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        return self.to_frame(x, y)

    def locate(self, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World (x, y) -> (s, d, track): :meth:`to_frame` and :meth:`lane_of` in one pass (the
        per-tick map matching of every twin)."""
        x, y, shape = _flat_pair(x, y)
        s, d = _to_frame(x, y, self._P, self._M, self._S, self._grid_f, self._grid_start, self._grid_items)
        lane = _lane_of(s, d, self._piece_s0, self._bounds, self._present)
        return s.reshape(shape), d.reshape(shape), lane.reshape(shape)

    def to_world(self, s, d) -> tuple[np.ndarray, np.ndarray]:
        """(s, d) -> world (x, y); beyond the route's ends the first/last segment extends straight."""
        s, d, shape = _flat_pair(s, d)
        x, y = _to_world(s, d, self._P, self._M, self._S, self._d_line)
        return x.reshape(shape), y.reshape(shape)

    def _segment_of(self, s: np.ndarray):
        S = self._S
        i = np.clip(np.searchsorted(S, s, side="right") - 1, 0, len(S) - 2)
        t = (s - S[i]) / (S[i + 1] - S[i])
        return i, t, (t < 0) | (t > 1)

    def heading(self, s, d=0.0) -> np.ndarray:
        """Yaw (rad, counter-clockwise from +x) of the line of constant d at (s, d)."""
        s, d = np.broadcast_arrays(np.asarray(s, dtype=np.float64), np.asarray(d, dtype=np.float64))
        i, t, off = self._segment_of(s)
        P, M = self._P, self._M
        tangent = (P[i + 1] - P[i]) + np.where(off, 0.0, d - self._d_line)[..., None] * (M[i + 1] - M[i])
        return np.arctan2(tangent[..., 1], tangent[..., 0])

    def _piece_of(self, s) -> np.ndarray:
        return np.clip(np.searchsorted(self._piece_s0, s, side="right") - 1, 0, len(self._pieces) - 1)

    def lane_of(self, s, d) -> np.ndarray:
        """Track (lane index from the right) at (s, d); -1 off the road or in a lane absent there.
        Beyond the route's ends the end pieces' lanes continue."""
        s, d, shape = _flat_pair(s, d)
        return _lane_of(s, d, self._piece_s0, self._bounds, self._present).reshape(shape)

    def lane_bounds(self, track, s=0.0) -> tuple[np.ndarray, np.ndarray]:
        """(d of the right edge, d of the left edge) of a track at s (its nominal place where absent;
        on a route whose lanes keep their widths, the same at every s)."""
        track, s = np.broadcast_arrays(np.asarray(track, dtype=np.int64), np.asarray(s, dtype=np.float64))
        k = self._piece_of(s)
        return self._bounds[k, track], self._bounds[k, track + 1]

    def lane_centre_d(self, track, s=0.0) -> np.ndarray:
        right, left = self.lane_bounds(track, s)
        return 0.5 * (right + left)

    def lane_exists(self, track, s) -> np.ndarray:
        track, s = np.broadcast_arrays(np.asarray(track, dtype=np.int64), np.asarray(s, dtype=np.float64))
        valid = (track >= 0) & (track < self.num_tracks)
        k = self._piece_of(s)
        return valid & self._present[k, np.clip(track, 0, self.num_tracks - 1)]

    def lanes_present(self, s) -> np.ndarray:
        """(..., num_tracks) bool: which tracks exist at each s."""
        return self._present[self._piece_of(s)]

    @cached_property
    def breaks_s(self) -> np.ndarray:
        """s of the reference line's vertices and of the pieces' starts: between two consecutive
        ones every line of constant d is straight and the lanes present do not change."""
        return np.unique(np.concatenate([self._S, self._piece_s0]))

    @cached_property
    def piece_starts_s(self) -> np.ndarray:
        """s where a piece begins: the only places where the lanes present and their edges change
        (:meth:`road_bounds` is constant in between)."""
        return self._piece_s0.copy()

    @cached_property
    def all_lanes_everywhere(self) -> bool:
        """Every track exists at every s (no lane begins or ends along the route)."""
        return bool(self._present.all())

    def lane_count(self, s) -> np.ndarray:
        return self._present[self._piece_of(s)].sum(axis=-1)

    def road_bounds(self, s) -> tuple[np.ndarray, np.ndarray]:
        """d of the rightmost and leftmost edge of the lanes present at s."""
        k = self._piece_of(s)
        present, b = self._present[k], self._bounds[k]
        right = np.min(np.where(present, b[..., :-1], np.inf), axis=-1)
        left = np.max(np.where(present, b[..., 1:], -np.inf), axis=-1)
        return right, left

    def lane_end_ahead(self, track, s) -> np.ndarray:
        """s where the track, present at s, ends ahead (a lane drop, the end of an acceleration
        lane, a lane that leaves the route); inf where it runs to the route's end; nan where the
        track is absent at s."""
        track, s = np.broadcast_arrays(np.asarray(track, dtype=np.int64), np.asarray(s, dtype=np.float64))
        out = np.full(s.shape, np.nan)
        for t in np.unique(track):
            if not 0 <= t < self.num_tracks:
                continue
            spans = self._intervals[t]
            sel = track == t
            q = np.clip(s[sel], 0.0, self.length_m)  # beyond the ends: the end pieces' lanes
            j = np.searchsorted(spans[:, 0], q, side="right") - 1
            end = spans[np.maximum(j, 0), 1]
            # a lane's end is where the next piece begins (absent there), except the route's end
            inside = (j >= 0) & ((q < end) | (end >= self.length_m - 1e-9))
            end = np.where(end >= self.length_m - 1e-9, np.inf, end)
            out[sel] = np.where(inside, end, np.nan)
        return out

    def lane_start_ahead(self, track, s) -> np.ndarray:
        """s where the track next begins ahead of s (an acceleration lane, a lane added at a
        widening); inf where it does not begin again before the route's end."""
        track, s = np.broadcast_arrays(np.asarray(track, dtype=np.int64), np.asarray(s, dtype=np.float64))
        out = np.full(s.shape, np.inf)
        for t in np.unique(track):
            if 0 <= t < self.num_tracks:
                starts = np.append(self._intervals[t][:, 0], np.inf)
                sel = track == t
                out[sel] = starts[np.searchsorted(starts, s[sel], side="right")]
        return out

    def lane_spans(self, track: int) -> np.ndarray:
        """(k, 2) [start, end) stretches of s where a track exists."""
        return self._intervals[track].copy()

    def sumo_lane_position(self, track: int, s: float) -> tuple[str, float]:
        """SUMO's (lane id, lane position) of a track at s on a route edge: where to insert a
        vehicle placed at s. ValueError where the track is absent at s or s is in a junction."""
        if not 0.0 <= s <= self.length_m:
            raise ValueError(f"s = {s:.2f} m is off the route (0 to {self.length_m:.2f} m)")
        k = int(self._piece_of(s))
        piece = self._pieces[k]
        if piece.edge_id.startswith(":"):
            raise ValueError(f"s = {s:.2f} m is inside junction lane {piece.anchor.lane_id!r}: "
                             "place vehicles on the route's edges")
        if not (0 <= track < self.num_tracks and self._present[k, track]):
            raise ValueError(f"track {track} does not exist at s = {s:.2f} m on edge {piece.edge_id!r} "
                             f"(its tracks there: {sorted(piece.widths)})")
        # an edge piece's anchor is its lane 0
        return f"{piece.edge_id}_{track - piece.anchor_track}", min(s - piece.s0, piece.length)

    def route_position(self, lane_id: str, pos_m) -> np.ndarray:
        """s of SUMO's lane position `pos_m` on a lane of the route (edges and junction lanes)."""
        edge = lane_id.rsplit("_", 1)[0]
        if edge not in self.edge_start_s:
            raise KeyError(f"lane {lane_id!r} is not on the route {list(self.route)}")
        return self.edge_start_s[edge] + np.asarray(pos_m, dtype=np.float64)


def edge_lane_shapes(net_file: str | Path) -> dict[str, list[np.ndarray]]:
    """Every normal edge's lane shapes ((k, 2) polylines, lane 0 first)."""
    net = _Net(Path(net_file))
    return {e: [ln.shape for ln in net.edge_lanes[e]] for e in net.normal_edges}


def default_route(net_file: str | Path) -> tuple[str, ...]:
    """The route of a network that is one chain of edges (e.g. a single straight edge)."""
    net = _Net(Path(net_file))
    edges = net.normal_edges
    succ: dict[str, set[str]] = {e: set() for e in edges}
    pred: dict[str, set[str]] = {e: set() for e in edges}
    for c in net.connections:
        if c.from_edge in succ and c.to_edge in succ:
            succ[c.from_edge].add(c.to_edge)
            pred[c.to_edge].add(c.from_edge)
    starts = [e for e in edges if not pred[e]]
    if len(starts) != 1 or any(len(v) > 1 for v in succ.values()):
        raise RouteError(net_file, "route", f"the network is not one chain of edges (starts {sorted(starts)}): "
                         "give the route (list of edges)")
    route = [starts[0]]
    while succ[route[-1]]:
        nxt = next(iter(succ[route[-1]]))
        if nxt in route:
            raise RouteError(net_file, "route", "the network's edges form a loop: give the route")
        route.append(nxt)
    if len(route) != len(edges):
        raise RouteError(net_file, "route", "the network is not one chain of edges: give the route")
    return tuple(route)


# ---------------------------------------------------------------------- compiled kernels
@numba.njit(cache=True)
def _solve_segment(qx, qy, i, P, M, n_seg):
    """(ok, t, e) of point q in segment i's bilinear map; the first and last segments extend
    straight beyond the route's ends (t < 0, t > 1)."""
    px, py = P[i, 0], P[i, 1]
    dx, dy = P[i + 1, 0] - px, P[i + 1, 1] - py
    m0x, m0y = M[i, 0], M[i, 1]
    dmx, dmy = M[i + 1, 0] - m0x, M[i + 1, 1] - m0y
    ax, ay = qx - px, qy - py
    if i == 0 or i == n_seg - 1:
        # beyond the route's ends: the end segment extends straight (the end vertex's miter is
        # its segment's unit normal, so the boundary is the same line P_end + e M_end)
        t = (ax * dx + ay * dy) / (dx * dx + dy * dy)
        if i == 0 and t < 0.0:
            return True, t, ax * m0x + ay * m0y
        if i == n_seg - 1 and t > 1.0:
            return True, t, (qx - P[i + 1, 0]) * M[i + 1, 0] + (qy - P[i + 1, 1]) * M[i + 1, 1]
    # inside: cross(A - t D, M0 + t dM) = 0, a quadratic in t (linear where the miters agree)
    a2 = -(dx * dmy - dy * dmx)
    a1 = (ax * dmy - ay * dmx) - (dx * m0y - dy * m0x)
    a0 = ax * m0y - ay * m0x
    if abs(a2) <= 1e-12 * abs(a1):
        if a1 == 0.0:
            return False, 0.0, 0.0
        t = -a0 / a1
    else:
        disc = a1 * a1 - 4.0 * a2 * a0
        if disc < 0.0:
            return False, 0.0, 0.0
        sq = math.sqrt(disc)
        q = -0.5 * (a1 + sq) if a1 >= 0.0 else -0.5 * (a1 - sq)
        r1 = q / a2
        r2 = a0 / q if q != 0.0 else np.inf
        # the root inside the segment (the other lies near the offset lines' crossing)
        t = r1 if abs(r1 - 0.5) <= abs(r2 - 0.5) else r2
    eps = 1e-9
    if t < -eps or t > 1.0 + eps:
        return False, t, 0.0
    mx, my = m0x + t * dmx, m0y + t * dmy
    rx, ry = ax - t * dx, ay - t * dy
    return True, t, (rx * mx + ry * my) / (mx * mx + my * my)


def _flat_pair(a, b) -> tuple[np.ndarray, np.ndarray, tuple]:
    """Two coordinate arrays as contiguous float64 1-D arrays of one length, and their shape."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        a, b = np.broadcast_arrays(a, b)
    shape = a.shape
    return np.ascontiguousarray(a.reshape(-1)), np.ascontiguousarray(b.reshape(-1)), shape


@numba.njit(cache=True)
def _to_frame(x, y, P, M, S, grid, grid_start, grid_items):
    gx0, gy0, cell, nx, ny, d_line, e_half = grid[0], grid[1], grid[2], int(grid[3]), int(grid[4]), grid[5], grid[6]
    n = x.shape[0]
    n_seg = P.shape[0] - 1
    s_out = np.empty(n)
    d_out = np.empty(n)
    for k in range(n):
        qx, qy = x[k], y[k]
        best_i, best_t, best_e, best_cost = -1, 0.0, 0.0, np.inf
        cx = int(math.floor((qx - gx0) / cell))
        cy = int(math.floor((qy - gy0) / cell))
        if 0 <= cx < nx and 0 <= cy < ny:
            c = cx * ny + cy
            for j in range(grid_start[c], grid_start[c + 1]):
                i = grid_items[j]
                ok, t, e = _solve_segment(qx, qy, i, P, M, n_seg)
                if ok and abs(e) < best_cost:
                    best_i, best_t, best_e, best_cost = i, t, e, abs(e)
                    if best_cost <= e_half:
                        break  # near the road the segments' maps tile the plane: this is the one
        if best_i < 0:  # far from the route: every segment
            for i in range(n_seg):
                ok, t, e = _solve_segment(qx, qy, i, P, M, n_seg)
                if ok and abs(e) < best_cost:
                    best_i, best_t, best_e, best_cost = i, t, e, abs(e)
        if best_i < 0:  # no segment's map reaches it (beyond a curve's centre): nearest point
            best_d2 = np.inf
            for i in range(n_seg):
                dx, dy = P[i + 1, 0] - P[i, 0], P[i + 1, 1] - P[i, 1]
                t = ((qx - P[i, 0]) * dx + (qy - P[i, 1]) * dy) / (dx * dx + dy * dy)
                t = min(max(t, 0.0), 1.0)
                rx, ry = qx - P[i, 0] - t * dx, qy - P[i, 1] - t * dy
                d2 = rx * rx + ry * ry
                if d2 < best_d2:
                    sign = 1.0 if dx * ry - dy * rx >= 0.0 else -1.0
                    best_i, best_t, best_e, best_d2 = i, t, sign * math.sqrt(d2), d2
        s_out[k] = S[best_i] + best_t * (S[best_i + 1] - S[best_i])
        d_out[k] = best_e + d_line
    return s_out, d_out


@numba.njit(cache=True)
def _to_world(s, d, P, M, S, d_line):
    n = s.shape[0]
    last = S.shape[0] - 2
    x_out = np.empty(n)
    y_out = np.empty(n)
    for k in range(n):
        i = min(max(np.searchsorted(S, s[k], side="right") - 1, 0), last)
        t = (s[k] - S[i]) / (S[i + 1] - S[i])
        tm = min(max(t, 0.0), 1.0)  # off the ends the end vertex's normal: a straight extension
        mx = M[i, 0] + tm * (M[i + 1, 0] - M[i, 0])
        my = M[i, 1] + tm * (M[i + 1, 1] - M[i, 1])
        e = d[k] - d_line
        x_out[k] = P[i, 0] + t * (P[i + 1, 0] - P[i, 0]) + e * mx
        y_out[k] = P[i, 1] + t * (P[i + 1, 1] - P[i, 1]) + e * my
    return x_out, y_out


@numba.njit(cache=True)
def _lane_of(s, d, piece_s0, bounds, present):
    n = s.shape[0]
    last = piece_s0.shape[0] - 1
    n_tracks = present.shape[1]
    out = np.full(n, -1, dtype=np.int16)
    for k in range(n):
        p = min(max(np.searchsorted(piece_s0, s[k], side="right") - 1, 0), last)
        for t in range(n_tracks):
            if bounds[p, t] <= d[k] < bounds[p, t + 1]:
                if present[p, t]:
                    out[k] = t
                break
    return out
