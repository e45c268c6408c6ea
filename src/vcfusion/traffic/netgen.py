"""Seeded random highway networks (plain XML + netconvert) to test the road frame on roads
nobody drew by hand.

A network is one carriageway of 3-6 edges ("main line") and the ramps that join or leave it:

- 2-5 lanes on every main edge (an acceleration lane may make it one more for its length);
- each main edge straight or a circular arc (radius 400-2000 m, left or right; consecutive arcs
  of opposite direction make S-curves), and at some nodes a kink of 2-8 degrees, which netconvert
  turns into a curve inside the junction;
- between consecutive main edges one change: none, a lane added on the right or on the left, a
  lane dropped on the right or on the left (the lane ends: no connection), an on-ramp (a one-lane
  ramp joins at 3-30 degrees from the right into an acceleration lane that ends at the next node),
  an off-ramp (the rightmost lane leaves at 3-30 degrees as a one-lane exit edge);
- each main edge its own speed limit.

Lanes keep a global track: the main line is built around a base line (the right edge of track
0); an edge holding tracks lo..hi-1 has its shape (the left road edge: netconvert spreads lanes
to its right) hi lane widths left of the base line, so a lane that continues lines up across
nodes. Every connection is written explicitly (.con.xml): a continuing lane keeps its track.

Routes: "main" (every main edge), "ramp_K" (on-ramp K, then the main line from its merge) and
"exit_K" (the main line up to exit K, then the exit edge).

`generate(seed, out_dir)` writes NAME.nod/.edg/.con/.typ.xml, builds NAME.net.xml with the
package's netconvert and writes NAME.rou.xml with the routes; `vcfusion gen-net --seed N --out
DIR` does the same from the command line (to reproduce a seed that fails a property test).
"""

from __future__ import annotations

import math
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vcfusion.traffic.network import netconvert_binary

# Speed limits a main edge draws from (m/s: 80, 90, 100, 120 km/h) and the ramps' (60 km/h).
MAIN_SPEEDS_MPS = (22.22, 25.0, 27.78, 33.33)
RAMP_SPEED_MPS = 16.67
MIN_LANES, MAX_LANES = 2, 5
# Arc radii (m): motorway design radii for 80-120 km/h are 250-900 m; 400 m keeps the lanes beside
# the road's middle within 2 % of its length on a five-lane road (the s-rate property).
RADIUS_RANGE_M = (400.0, 2000.0)
JOIN_ANGLE_DEG = (3.0, 30.0)  # ramps join and leave at these angles
KINK_DEG = (2.0, 8.0)  # heading change at a node: a curve inside the junction
CHANGES = ("none", "add_right", "add_left", "drop_right", "drop_left", "on_ramp", "off_ramp")


@dataclass
class _Edge:
    eid: str
    lo: int  # global tracks lo..hi-1
    hi: int
    speed: float
    base: np.ndarray  # (k, 2) base line (right edge of track 0)
    normal: np.ndarray  # (k, 2) its left unit normals


@dataclass
class GeneratedNet:
    """What `generate` wrote: the network, its routes (name -> edge ids) and the spec drawn."""

    seed: int
    net_file: Path
    route_file: Path
    routes: dict[str, list[str]]
    changes: list[str] = field(default_factory=list)  # the change at each inner main node
    lane_width_m: float = 3.5


def _arc(start: np.ndarray, heading: float, length: float, curvature: float, step_m: float = 10.0):
    """Points and left normals of a path of constant curvature (1/m, + left) from `start`."""
    n = max(1, int(math.ceil(length / step_m)))
    if abs(curvature) * length > 0:
        n = max(n, int(math.ceil(abs(curvature) * length / math.radians(2.0))))
    u = np.linspace(0.0, length, n + 1)
    theta = heading + curvature * u
    if curvature == 0.0:
        pts = start + np.outer(u, [math.cos(heading), math.sin(heading)])
    else:
        r = 1.0 / curvature
        pts = np.column_stack([start[0] + r * (np.sin(theta) - math.sin(heading)),
                               start[1] - r * (np.cos(theta) - math.cos(heading))])
    normals = np.column_stack([-np.sin(theta), np.cos(theta)])
    return pts, normals, float(theta[-1])


def _fmt(points: np.ndarray) -> str:
    return " ".join(f"{x:.3f},{y:.3f}" for x, y in points)


def _draw(rng: np.random.Generator, spec: dict | None = None):
    """The main line's edges (tracks, speed, geometry) and the ramps, as plain data: drawn, or
    as `spec` gives them (see `generate`)."""
    if spec is not None:
        return _from_spec(spec)
    width = float(rng.choice([3.25, 3.5, 3.75]))
    n_edges = int(rng.integers(3, 7))
    lo, hi = 0, int(rng.integers(MIN_LANES, MAX_LANES + 1))
    heading = float(rng.uniform(-math.pi, math.pi))
    pos = np.zeros(2)
    edges: list[_Edge] = []
    changes: list[str] = []
    ramps: list[tuple] = []  # (kind, node index, angle rad)
    last_curv = 0.0
    for i in range(n_edges):
        if i > 0:
            prev = edges[-1]
            n = prev.hi - prev.lo
            if changes and changes[-1] == "on_ramp":
                change = "drop_right"  # the acceleration lane ends
            else:
                allowed = ["none"]
                if n < MAX_LANES:
                    allowed += ["add_right", "add_left", "on_ramp"]
                if n > MIN_LANES:
                    allowed += ["drop_right", "drop_left", "off_ramp"]
                if i == n_edges - 1:
                    allowed = [c for c in allowed if c != "on_ramp"]  # its lane must end on the route
                change = str(rng.choice(allowed))
            changes.append(change)
            lo, hi = prev.lo, prev.hi
            if change in ("add_right", "on_ramp"):
                lo -= 1
            elif change == "add_left":
                hi += 1
            elif change in ("drop_right", "off_ramp"):
                lo += 1
            elif change == "drop_left":
                hi -= 1
            if change in ("on_ramp", "off_ramp"):
                ramps.append((change, i, math.radians(float(rng.uniform(*JOIN_ANGLE_DEG)))))
            if rng.random() < 0.35:  # a kink at the node: a curve inside the junction
                heading += math.radians(float(rng.uniform(*KINK_DEG))) * float(rng.choice([-1.0, 1.0]))
        length = float(rng.uniform(180.0, 450.0))
        if rng.random() < 0.6:
            radius = float(rng.uniform(*RADIUS_RANGE_M))
            # an S-curve: most arcs after an arc turn the other way
            turn_back = last_curv and rng.random() < 0.7
            sign = -math.copysign(1.0, last_curv) if turn_back else float(rng.choice([-1.0, 1.0]))
            length = min(length, radius * math.radians(40.0))
            curv = sign / radius
        else:
            curv = 0.0
        last_curv = curv
        base, normal, heading = _arc(pos, heading, length, curv)
        pos = base[-1]
        edges.append(_Edge(f"m{i}", lo, hi, float(rng.choice(MAIN_SPEEDS_MPS)), base, normal))
    return width, edges, changes, ramps


def _from_spec(spec: dict):
    width = float(spec.get("width", 3.5))
    lo, hi = 0, int(spec["lanes"])
    heading = math.radians(float(spec.get("heading_deg", 0.0)))
    pos = np.zeros(2)
    edges, changes, ramps = [], [], []
    for i, e in enumerate(spec["edges"]):
        if i > 0:
            change = e.get("change", "none")
            if change not in CHANGES:
                raise ValueError(f"edges[{i}].change: expected one of {', '.join(CHANGES)}, got {change!r}")
            changes.append(change)
            lo += -1 if change in ("add_right", "on_ramp") else 1 if change in ("drop_right", "off_ramp") else 0
            hi += 1 if change == "add_left" else -1 if change == "drop_left" else 0
            if change in ("on_ramp", "off_ramp"):
                ramps.append((change, i, math.radians(float(e.get("angle_deg", 10.0)))))
            heading += math.radians(float(e.get("kink_deg", 0.0)))
        radius = float(e.get("radius_m", 0.0))  # + left, - right, 0 straight
        base, normal, heading = _arc(pos, heading, float(e["length_m"]), 1.0 / radius if radius else 0.0)
        pos = base[-1]
        edges.append(_Edge(f"m{i}", lo, hi, float(e.get("speed_mps", 25.0)), base, normal))
    return width, edges, changes, ramps


def describe(seed: int) -> dict:
    """What network `seed` holds, without building it: the change at each inner main node and
    the lane count of each main edge."""
    _, edges, changes, _ = _draw(np.random.default_rng(seed))
    return {"changes": changes, "lanes": [e.hi - e.lo for e in edges]}


def _write_sources(out: Path, name: str, width: float, edges: list[_Edge], ramps: list[tuple],
                   rng: np.random.Generator) -> dict[str, list[str]]:
    nodes = []
    edge_xml = []
    cons = []

    def node(nid: str, xy) -> None:
        nodes.append(f'    <node id="{nid}" x="{xy[0]:.3f}" y="{xy[1]:.3f}" type="priority"/>')

    for i, e in enumerate(edges):
        # a node on the road's middle where it begins (the junction's shape comes from the edges)
        mid = e.base[0] + e.normal[0] * 0.5 * (e.lo + e.hi) * width
        node(f"n{i}", mid)
    last = edges[-1]
    node(f"n{len(edges)}", last.base[-1] + last.normal[-1] * 0.5 * (last.lo + last.hi) * width)
    for i, e in enumerate(edges):
        shape = e.base + e.normal * (e.hi * width)
        edge_xml.append(f'    <edge id="{e.eid}" from="n{i}" to="n{i + 1}" numLanes="{e.hi - e.lo}" '
                        f'speed="{e.speed:.2f}" width="{width}" shape="{_fmt(shape)}"/>')
    for a, b in zip(edges, edges[1:]):
        for g in range(max(a.lo, b.lo), min(a.hi, b.hi)):
            cons.append(f'    <connection from="{a.eid}" to="{b.eid}" fromLane="{g - a.lo}" toLane="{g - b.lo}"/>')
    routes = {"main": [e.eid for e in edges]}
    for k, (kind, i, angle) in enumerate(ramps):
        length = float(rng.uniform(150.0, 300.0))
        if kind == "on_ramp":
            e = edges[i]  # the edge that starts with the acceleration lane (track e.lo)
            end = e.base[0] + e.normal[0] * ((e.lo + 1) * width)  # the lane's left edge
            heading = math.atan2(-e.normal[0][0], e.normal[0][1]) + angle  # from the right
            d = np.array([math.cos(heading), math.sin(heading)])
            start = end - length * d
            rid = f"on{k}"
            node(f"{rid}_in", start)
            edge_xml.append(f'    <edge id="{rid}" from="{rid}_in" to="n{i}" numLanes="1" speed="{RAMP_SPEED_MPS}" '
                            f'width="{width}" shape="{_fmt(np.array([start, end]))}"/>')
            cons.append(f'    <connection from="{rid}" to="{e.eid}" fromLane="0" toLane="0"/>')
            routes[f"ramp_{k}"] = [rid] + [x.eid for x in edges[i:]]
        else:
            a = edges[i - 1]  # its rightmost lane (track a.lo) leaves
            start = a.base[-1] + a.normal[-1] * ((a.lo + 1) * width)
            heading = math.atan2(-a.normal[-1][0], a.normal[-1][1]) - angle  # to the right
            d = np.array([math.cos(heading), math.sin(heading)])
            end = start + length * d
            rid = f"off{k}"
            node(f"{rid}_out", end)
            edge_xml.append(f'    <edge id="{rid}" from="n{i}" to="{rid}_out" numLanes="1" speed="{RAMP_SPEED_MPS}" '
                            f'width="{width}" shape="{_fmt(np.array([start, end]))}"/>')
            cons.append(f'    <connection from="{a.eid}" to="{rid}" fromLane="0" toLane="0"/>')
            routes[f"exit_{k}"] = [x.eid for x in edges[:i]] + [rid]
    (out / f"{name}.nod.xml").write_text("<nodes>\n" + "\n".join(nodes) + "\n</nodes>\n")
    (out / f"{name}.edg.xml").write_text("<edges>\n" + "\n".join(edge_xml) + "\n</edges>\n")
    (out / f"{name}.con.xml").write_text("<connections>\n" + "\n".join(cons) + "\n</connections>\n")
    return routes


def generate(seed: int, out_dir: str | Path, name: str = "gen", spec: dict | None = None) -> GeneratedNet:
    """Draw network `seed`, write its sources, NAME.net.xml and NAME.rou.xml into out_dir.

    With `spec` the main line is given instead of drawn (the seed then draws the ramps' lengths):
    {"lanes": n, "width": m, "heading_deg": deg, "edges": [{"length_m", "radius_m" (+ left,
    - right, 0 straight), "speed_mps", and from the second edge on "change" (one of CHANGES),
    "kink_deg", "angle_deg" (a ramp's)}, ...]}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    width, edges, changes, ramps = _draw(rng, spec)
    routes = _write_sources(out, name, width, edges, ramps, rng)
    cmd = [netconvert_binary(), "--node-files", f"{name}.nod.xml", "--edge-files", f"{name}.edg.xml",
           "--connection-files", f"{name}.con.xml", "--no-turnarounds", "true",
           "--output-file", f"{name}.net.xml"]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=out)
    if done.returncode != 0:
        raise RuntimeError(f"netconvert failed on generated network seed {seed} ({out}):\n{done.stderr.strip()}")
    route_file = out / f"{name}.rou.xml"
    route_file.write_text("<routes>\n" + "".join(f'    <route id="{r}" edges="{" ".join(e)}"/>\n'
                                                 for r, e in routes.items()) + "</routes>\n")
    return GeneratedNet(seed, out / f"{name}.net.xml", route_file, routes, changes, width)


# ---------------------------------------------------------------------- the frame's properties
# Thresholds of the road frame's promises on any network (issue 47): a world point survives
# world -> (s, d) -> world within ROUND_TRIP_M; along a lane's centre, s grows as the distance
# driven (no jump at junctions: STEP_M between samples, JUMP_M off); a lane's centre keeps its d
# (CENTRE_D_M).
ROUND_TRIP_M = 0.01
JUMP_M = 0.05
CENTRE_D_M = 0.05
STEP_M = 0.5


def _dense(points: np.ndarray, step: float = STEP_M) -> np.ndarray:
    out = [points[:1]]
    for p, q in zip(points[:-1], points[1:]):
        n = max(1, int(math.ceil(np.hypot(*(q - p)) / step)))
        out.append(p + (np.arange(1, n + 1) / n)[:, None] * (q - p))
    return np.concatenate(out)


def frame_properties(net_file: str | Path, route: list[str], seed: int = 0) -> dict[str, float]:
    """The worst case of each geometric promise of the road frame of `route` (metres), from
    SUMO's own lane shapes and connections (sumolib), independently of how the frame reads them:

    - round_trip_m: |world -> (s, d) -> world| for points scattered over every lane of the route
      (edges and junction lanes), up to half a lane beyond the road;
    - s_jump_m: |Δs - distance| between samples 0.5 m apart along every lane centre of a route
      edge and every lane -> junction lane -> lane path between consecutive route edges;
      (within a junction lane, see junction_s_m);
    - junction_s_m: |Δs over a junction lane - its SUMO length| (SUMO gives the lanes of a
      junction one length whatever their shapes': in a bend the inner lanes' are shorter);
    - centre_d_m: |d - the lane's track centre| at every vertex and midpoint of the lanes of the
      route's edges; junction_d_m the same on the junction lanes that join them (SUMO shapes
      those lane by lane: in a bend they are not exactly parallel);
    - lane_match: the fraction of the lanes' segment midpoints map-matched to their lane's track.
    """
    import sumolib

    from vcfusion.traffic.roadframe import RoadFrame

    frame = RoadFrame.from_net(net_file, route)
    net = sumolib.net.readNet(str(net_file), withInternal=True)
    rng = np.random.default_rng(seed)
    worst = {"round_trip_m": 0.0, "s_jump_m": 0.0, "junction_s_m": 0.0, "centre_d_m": 0.0, "junction_d_m": 0.0}
    where: dict[str, str] = {}

    def note(key: str, value: float, at: str) -> None:
        if value > worst[key]:
            worst[key], where[key] = value, at
    matched = total = 0
    paths: list[list] = []
    for a, b in zip(route, route[1:] + [None]):
        edge = net.getEdge(a)
        for lane in edge.getLanes():
            paths.append([lane])
            if b is None:
                continue
            for c in lane.getOutgoing():
                if c.getTo().getID() != b:
                    continue
                chain = [lane]
                via = c.getViaLaneID()
                while via:
                    vl = net.getLane(via)
                    chain.append(vl)
                    nxt = [x for x in vl.getOutgoing()]
                    via = nxt[0].getViaLaneID() if nxt and nxt[0].getViaLaneID() else None
                chain.append(c.getToLane())
                paths.append(chain)
    for chain in paths:
        track = frame.track_of[chain[0].getID()]
        # s along the centre line: SUMO spreads each lane's length over its own shape, so between
        # samples s grows by the distance times length / shape length; where one lane hands over to
        # the next (junctions), s must not jump
        prev_end = None
        for ln in chain:
            shape = np.array(ln.getShape())[:, :2]
            pts = _dense(shape)
            step = np.hypot(*np.diff(pts, axis=0).T)
            geo = step.sum()
            s, _ = frame.to_frame(pts[:, 0], pts[:, 1])
            if ln.getID().startswith(":"):
                # a junction lane: SUMO gives the lanes of a junction one length whatever their
                # shapes' (in a bend the inner lanes' shapes are shorter, down to a few cm): over
                # the whole lane s grows by that length, never backwards
                err = max(abs(float(s[-1] - s[0]) - ln.getLength()), float(-np.diff(s).min(initial=0.0)))
                note("junction_s_m", err, f"over {ln.getID()} at s={s[0]:.1f}")
            elif geo > 1e-6:
                err = np.abs(np.diff(s) - step * (ln.getLength() / geo))
                k = int(err.argmax())
                note("s_jump_m", float(err[k]), f"along {ln.getID()} at s={s[k]:.1f}")
            if prev_end is not None:
                gap = float(np.hypot(*(pts[0] - prev_end[1])))
                note("s_jump_m", abs(float(s[0] - prev_end[0])) - gap,
                     f"{prev_ln} > {ln.getID()} at s={s[0]:.1f}")
            prev_end, prev_ln = (float(s[-1]), pts[-1]), ln.getID()
        for ln in chain:
            xy = np.array(ln.getShape())[:, :2]
            mid = 0.5 * (xy[1:] + xy[:-1])  # (a lane's end vertex is where the next piece begins)
            xy = np.concatenate([xy, mid])
            s, d = frame.to_frame(xy[:, 0], xy[:, 1])
            t = frame.track_of.get(ln.getID(), track)
            err = np.abs(d - frame.lane_centre_d(t, s))
            k = int(err.argmax())
            note("junction_d_m" if ln.getID().startswith(":") else "centre_d_m", float(err[k]),
                 f"{ln.getID()} at s={s[k]:.1f}")
            on = frame.lane_of(s[-len(mid):], d[-len(mid):]) == t
            matched += int(on.sum())
            total += len(mid)
            # world points over the lane, up to half a lane either side of it
            dense = _dense(np.array(ln.getShape())[:, :2], 2.0)
            seg = np.diff(dense, axis=0)
            seg = np.vstack([seg, seg[-1:]])
            normal = np.column_stack([-seg[:, 1], seg[:, 0]]) / np.maximum(np.hypot(*seg.T), 1e-9)[:, None]
            off = rng.uniform(-ln.getWidth(), ln.getWidth(), len(dense))
            p = dense + off[:, None] * normal
            ps, pd = frame.to_frame(p[:, 0], p[:, 1])
            wx, wy = frame.to_world(ps, pd)
            err = np.hypot(wx - p[:, 0], wy - p[:, 1])
            k = int(err.argmax())
            note("round_trip_m", float(err[k]), f"near {ln.getID()} at s={ps[k]:.1f}")
    worst["lane_match"] = matched / max(total, 1)
    return {**worst, "where": where}


# s rate and speed agree within this fraction over RATE_WINDOW_S (SUMO moves a vehicle by its
# speed times the step along its lane, and s is SUMO's route position); a vehicle's position
# stays between the road's edges within INSIDE_M
RATE_TOL = 0.02
RATE_WINDOW_S = 1.0
INSIDE_M = 0.05


def sumo_properties(gen: GeneratedNet, end_s: float = 70.0, period_s: float = 2.5, seed: int = 0) -> dict:
    """A short SUMO run (libsumo, in this process) on a generated network: a flow on every route
    for the first half of the run; for every vehicle sample on its own route's lanes (edges and
    junction lanes), seen in that route's frame:

    - rate_err: the worst |Δs / (Σ speed · step) - 1| over windows of RATE_WINDOW_S;
    - outside_m: the worst distance of d beyond the road's edges at s;
    - samples, windows: how many were checked.
    """
    import libsumo

    from vcfusion.traffic.roadframe import RoadFrame

    frames = {r: RoadFrame.from_net(gen.net_file, e) for r, e in gen.routes.items()}
    flows = gen.net_file.parent / f"{gen.net_file.stem.split('.')[0]}.flows.rou.xml"
    flows.write_text(
        "<routes>\n" + "".join(f'    <route id="{r}" edges="{" ".join(e)}"/>\n' for r, e in gen.routes.items())
        + "".join(f'    <flow id="f_{r}" route="{r}" begin="0" end="{end_s / 2}" period="{period_s}" '
                  f'departLane="{"0" if r.startswith("ramp") else "random"}" departSpeed="max"/>\n'
                  for r in gen.routes) + "</routes>\n")
    step = 0.1
    libsumo.start(["sumo", "-n", str(gen.net_file), "-r", str(flows), "--step-length", str(step),
                   "--seed", str(seed), "--no-step-log", "--no-warnings", "--end", str(end_s)])
    rows: dict[str, list] = {}
    try:
        while libsumo.simulation.getTime() < end_s:
            libsumo.simulationStep()
            for vid in libsumo.vehicle.getIDList():
                x, y = libsumo.vehicle.getPosition(vid)
                rows.setdefault(vid, []).append((libsumo.simulation.getTime(), x, y, libsumo.vehicle.getSpeed(vid),
                                                 libsumo.vehicle.getLaneID(vid)))
    finally:
        libsumo.close()
    worst = {"rate_err": 0.0, "outside_m": 0.0, "samples": 0, "windows": 0}
    n = int(round(RATE_WINDOW_S / step))
    for vid, samples in rows.items():
        route = vid[2:].rsplit(".", 1)[0]
        frame = frames[route]
        t, x, y, v = (np.array([r[k] for r in samples]) for k in range(4))
        on = np.array([r[4] in frame.track_of for r in samples])
        s, d = frame.to_frame(x, y)
        right, left = frame.road_bounds(s)
        out = np.maximum(right - d, d - left)[on]
        worst["samples"] += int(on.sum())
        if out.size:
            worst["outside_m"] = max(worst["outside_m"], float(out.max()))
        for k in range(0, len(t) - n):
            if on[k:k + n + 1].all() and abs(t[k + n] - t[k] - n * step) < 1e-6:
                driven = float(v[k + 1:k + n + 1].sum() * step)
                if driven > 1.0:
                    worst["rate_err"] = max(worst["rate_err"], abs((s[k + n] - s[k]) / driven - 1.0))
                    worst["windows"] += 1
    return worst


# A junction lane stays within its lane's band: its d off the track's centre by at most this
# (SUMO shapes junction lanes one by one; in a kink they are not exactly parallel).
JUNCTION_D_M = 0.2
# Over a junction lane s grows by its SUMO length within this (the border's cut and the lanes'
# shapes are SUMO's to 0.01 m; the lanes of a bent junction are shaped one by one).
JUNCTION_S_M = 0.15


def failed_properties(p: dict) -> list[str]:
    """The promises `frame_properties`' figures break, each with where (empty: all kept)."""
    where = p.get("where", {})
    limits = {"round_trip_m": ROUND_TRIP_M, "s_jump_m": JUMP_M, "junction_s_m": JUNCTION_S_M,
              "centre_d_m": CENTRE_D_M, "junction_d_m": JUNCTION_D_M}
    bad = [f"{k} {p[k]:.3f} > {lim} ({where.get(k, '')})" for k, lim in limits.items() if p[k] > lim]
    if p["lane_match"] < 1.0:
        bad.append(f"lane_match {p['lane_match']:.4f} < 1")
    return bad


def failed_sumo_properties(r: dict) -> list[str]:
    bad = []
    if r["rate_err"] > RATE_TOL:
        bad.append(f"s rate off speed by {100 * r['rate_err']:.2f} % > {100 * RATE_TOL:.0f} %")
    if r["outside_m"] > INSIDE_M:
        bad.append(f"d {r['outside_m']:.3f} m beyond the road > {INSIDE_M} m")
    if r["windows"] == 0:
        bad.append("no vehicle on a route: nothing checked")
    return bad
