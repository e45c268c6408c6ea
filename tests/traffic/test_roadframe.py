"""The road frame of a route (vcfusion.traffic.roadframe) against the straight Road and SUMO itself."""

import subprocess
import xml.etree.ElementTree as ET

import libsumo
import numpy as np
import pytest
import sumolib

from scenario_files import REPO
from vcfusion.traffic.network import read_road
from vcfusion.traffic.roadframe import RoadFrame, RouteError

NETS = REPO / "sumo_net"
HIGHWAY = NETS / "highway.net.xml"
CURVED = NETS / "curved.net.xml"
ONRAMP = NETS / "onramp.net.xml"
CURVED_ROUTE = ["c01", "c12", "c23", "c34", "c45"]
MAIN_ROUTE = ["main_in", "accel", "main_out"]
RAMP_ROUTE = ["ramp", "accel", "main_out"]
# imported from the hand-written OpenStreetMap extract by build-net (netconvert's --ramps.guess
# added the acceleration lane as the edge "11-AddedOnRampEdge")
OSM = NETS / "osm_example.net.xml"
OSM_MAIN_ROUTE = ["10", "11-AddedOnRampEdge", "11"]
OSM_RAMP_ROUTE = ["20", "11-AddedOnRampEdge", "11"]
ROUTES = [(CURVED, CURVED_ROUTE), (ONRAMP, MAIN_ROUTE), (ONRAMP, RAMP_ROUTE), (OSM, OSM_MAIN_ROUTE), (OSM, OSM_RAMP_ROUTE)]
ROUTE_IDS = ["curved", "onramp-main", "onramp-ramp", "osm-main", "osm-ramp"]


@pytest.fixture(scope="module")
def frames() -> dict:
    return {(net.name, tuple(route)): RoadFrame.from_net(net, route) for net, route in ROUTES}


def frame_of(frames, net, route) -> RoadFrame:
    return frames[(net.name, tuple(route))]


def sumo_route_starts(net_file, route) -> dict[str, float]:
    """Independently of the frame: where each route edge and each junction lane the route's
    lanes pass through begins, in SUMO's lane lengths (sumolib)."""
    net = sumolib.net.readNet(str(net_file), withInternal=True)
    starts, s = {}, 0.0
    for a, b in zip(route, route[1:] + [None]):
        edge = net.getEdge(a)
        starts[a] = s
        s += edge.getLength()
        if b is None:
            break
        vias = [c.getViaLaneID() for lane in edge.getLanes() for c in lane.getOutgoing()
                if c.getTo().getID() == b and c.getViaLaneID()]
        lengths = {net.getLane(v).getLength() for v in vias}
        assert len(lengths) == 1, f"junction lanes {a}->{b} of different lengths: {lengths}"
        for v in vias:
            starts[net.getLane(v).getEdge().getID()] = s
        s += lengths.pop()
    starts["__end__"] = s
    return starts


def test_straight_network_is_todays_road():
    """On the shipped single-edge highway the frame (its default route) gives what Road gives:
    s, d, lane, world position, heading, lane centres."""
    road, frame = read_road(HIGHWAY), RoadFrame.from_net(HIGHWAY)
    assert frame.route == (road.edge_id,)
    assert frame.num_tracks == road.num_lanes and frame.length_m == road.length_m
    rng = np.random.default_rng(1)
    # on the road, beside it and beyond both ends
    x = rng.uniform(-300.0, road.length_m + 300.0, 500)
    y = rng.uniform(-40.0, 30.0, 500)
    s, d = frame.to_frame(x, y)
    want_s, want_d = road.to_road_frame(x, y)
    np.testing.assert_allclose(s, want_s, rtol=0, atol=1e-9)
    np.testing.assert_allclose(d, want_d, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(frame.lane_of(s, d), road.lane_of(s, d))
    s_, d_, lane_ = frame.locate(x, y)
    np.testing.assert_array_equal(lane_, road.lane_of(s, d))
    wx, wy = frame.to_world(want_s, want_d)
    rx, ry = road.to_world(want_s, want_d)
    np.testing.assert_allclose(wx, rx, atol=1e-9)
    np.testing.assert_allclose(wy, ry, atol=1e-9)
    np.testing.assert_allclose(frame.heading(s, d), road.heading_rad, atol=1e-12)
    for lane in range(road.num_lanes):
        assert frame.lane_centre_d(lane, 100.0) == pytest.approx(float(road.lane_centre_d(lane)), abs=1e-12)
        assert frame.track_of[f"{road.edge_id}_{lane}"] == lane
        assert np.isinf(frame.lane_end_ahead(lane, 50.0))


@pytest.mark.parametrize(("net", "route"), ROUTES, ids=ROUTE_IDS)
def test_round_trip_to_one_centimetre(frames, net, route):
    """(s, d) -> world -> (s, d) and world -> (s, d) -> world, on the road and around it, across
    edges and junctions, curves and the acceleration lane."""
    frame = frame_of(frames, net, route)
    rng = np.random.default_rng(2)
    s = rng.uniform(-30.0, frame.length_m + 30.0, 4000)
    d = rng.uniform(-6.0, frame.max_width_m + 6.0, 4000)
    x, y = frame.to_world(s, d)
    s2, d2 = frame.to_frame(x, y)
    np.testing.assert_allclose(s2, s, rtol=0, atol=0.01)
    np.testing.assert_allclose(d2, d, rtol=0, atol=0.01)
    # world points scattered around every lane shape of the route (SUMO's own geometry)
    shapes = np.concatenate([sumolib.net.readNet(str(net)).getEdge(e).getLanes()[0].getShape() for e in route])
    px = np.repeat(shapes[:, 0], 20) + rng.uniform(-12.0, 12.0, 20 * len(shapes))
    py = np.repeat(shapes[:, 1], 20) + rng.uniform(-12.0, 12.0, 20 * len(shapes))
    s3, d3 = frame.to_frame(px, py)
    x3, y3 = frame.to_world(s3, d3)
    assert np.hypot(x3 - px, y3 - py).max() < 0.01


@pytest.mark.parametrize(("net", "route"), ROUTES, ids=ROUTE_IDS)
def test_lane_shapes_are_lines_of_constant_d(frames, net, route):
    """Every vertex of every lane (edges and junction lanes) of the route lies at its track's
    centre, is map-matched to its track, and has s within the lane's own extent."""
    frame = frame_of(frames, net, route)
    sumo = sumolib.net.readNet(str(net), withInternal=True)
    checked = 0
    for lane_id, track in frame.track_of.items():
        lane = sumo.getLane(lane_id)
        xy = np.array(lane.getShape())
        s, d = frame.to_frame(xy[:, 0], xy[:, 1])
        # junction lanes begin where their incoming edge ends, which may be off the route (a ramp)
        tolerance = 0.1 if lane_id.startswith(":") else 0.02
        np.testing.assert_allclose(d, frame.lane_centre_d(track, s), atol=tolerance, err_msg=lane_id)
        mid = 0.5 * (xy[1:] + xy[:-1])  # a lane's end vertex is where the next piece begins
        assert (frame.lane_of(*frame.to_frame(mid[:, 0], mid[:, 1])) == track).all(), lane_id
        start, slack = frame.route_position(lane_id, 0.0), 0.5 if lane_id.startswith(":") else 0.3
        assert start - slack <= s.min() and s.max() <= start + lane.getLength() + slack, lane_id
        checked += 1
    assert checked >= 3 * len(route)


@pytest.mark.parametrize(("net", "route"), ROUTES, ids=ROUTE_IDS)
def test_s_is_sumos_route_position_and_continuous_across_edges(frames, net, route):
    """s = (SUMO's lane lengths of the route before the edge) + lane position, edge after edge:
    the edge starts agree with sumolib's lengths, and SUMO's own lane-position -> world
    conversion (libsumo convert2D) maps back to that s on every lane, up to each edge's end."""
    frame = frame_of(frames, net, route)
    want = sumo_route_starts(net, route)
    for name, start in want.items():
        if name != "__end__":
            assert frame.edge_start_s[name] == pytest.approx(start, abs=1e-9), name
    assert frame.length_m == pytest.approx(want["__end__"], abs=1e-9)
    sumo = sumolib.net.readNet(str(net))
    libsumo.start(["sumo", "-n", str(net), "--no-step-log", "--begin", "0", "--end", "1"])
    try:
        for edge in route:
            length = sumo.getEdge(edge).getLength()
            middle = 0.5 * (len(sumo.getEdge(edge).getLanes()) - 1)
            for lane in sumo.getEdge(edge).getLanes():
                pos = np.linspace(0.0, length, 40)
                xy = np.array([libsumo.simulation.convert2D(edge, float(p), lane.getIndex()) for p in pos])
                s, d = frame.to_frame(xy[:, 0], xy[:, 1])
                # SUMO spreads each lane's length over that lane's own shape (the frame: over the
                # middle of the road), and cuts the lanes of an edge at junctions a few cm apart. On
                # an edge that is part straight, part curved, lanes beside the middle thus disagree
                # with each other by up to their offset times the edge's turn
                turn = np.abs(np.diff(np.unwrap(np.arctan2(*np.diff(np.array(lane.getShape()), axis=0).T[::-1])))).sum()
                offset = abs(lane.getIndex() - middle) * lane.getWidth()
                np.testing.assert_allclose(s, want[edge] + pos, atol=0.25 + offset * turn / 2, err_msg=lane.getID())
                assert (np.diff(s) > 0).all()
                assert (frame.lane_of(s, d)[:-1] == frame.track_of[lane.getID()]).all()  # the end: next piece
    finally:
        libsumo.close()
    # continuity: along every lane -> junction lane -> lane path between consecutive route edges
    # (SUMO's own connections), s grows without a jump and d stays at the lane's centre
    sumo_int = sumolib.net.readNet(str(net), withInternal=True)
    paths = 0
    for a, b in zip(route, route[1:]):
        for lane in sumo_int.getEdge(a).getLanes():
            for c in lane.getOutgoing():
                if c.getTo().getID() != b:
                    continue
                chain = [lane, sumo_int.getLane(c.getViaLaneID()), c.getToLane()]
                pts = np.concatenate([np.array(ln.getShape()) for ln in chain])
                dense = np.concatenate([np.linspace(p, q, 2 + int(np.hypot(*(q - p)) / 0.5))
                                        for p, q in zip(pts[:-1], pts[1:])])
                step = np.hypot(*np.diff(dense, axis=0).T)  # <= 0.5 m
                s, d = frame.to_frame(dense[:, 0], dense[:, 1])
                ds = np.diff(s)
                # s never goes back and never jumps (SUMO's lengths differ from the shapes' by <1 %
                # on the curves, and by a few cm on junction lanes)
                assert (ds >= -1e-9).all() and (ds <= 1.01 * step + 0.1).all(), lane.getID()
                np.testing.assert_allclose(d, frame.lane_centre_d(frame.track_of[lane.getID()], s), atol=0.03)
                paths += 1
    assert paths >= len(route) - 1


@pytest.mark.parametrize(("net", "route"), ROUTES, ids=ROUTE_IDS)
def test_sumo_lane_position_inverts_route_position(frames, net, route):
    """Placing a vehicle at (track, s) gives the SUMO lane and position whose s it is."""
    frame = frame_of(frames, net, route)
    for edge in route:
        for lane_id in [lid for lid in frame.track_of if lid.rsplit("_", 1)[0] == edge]:
            for pos in (0.0, 10.0, 55.5):
                s = float(frame.route_position(lane_id, pos))
                assert frame.sumo_lane_position(frame.track_of[lane_id], s) == (lane_id, pytest.approx(pos))
    with pytest.raises(ValueError, match="inside junction lane"):
        frame.sumo_lane_position(frame.track_of[f"{route[1]}_0"], frame.edge_start_s[route[1]] - 0.05)
    with pytest.raises(ValueError, match="does not exist"):
        frame.sumo_lane_position(frame.num_tracks, 1.0)


def test_tracks_stable_across_edges_from_sumos_connections(frames):
    """A lane that continues keeps its track: every SUMO connection between consecutive route
    edges joins lanes of one track, except where a lane ends or joins; the main line keeps its
    lanes' d range through the merge."""
    main = frame_of(frames, ONRAMP, MAIN_ROUTE)
    ramp = frame_of(frames, ONRAMP, RAMP_ROUTE)
    sumo = sumolib.net.readNet(str(ONRAMP))
    for frame in (main, ramp):
        for a, b in zip(frame.route, frame.route[1:]):
            for lane in sumo.getEdge(a).getLanes():
                for c in lane.getOutgoing():
                    if c.getTo().getID() == b:
                        assert frame.track_of[lane.getID()] == frame.track_of[c.getToLane().getID()]
    # the main line's three lanes are tracks 1..3 on all three edges; the ramp's lane is track 0
    for i in range(3):
        assert main.track_of[f"main_in_{i}"] == main.track_of[f"accel_{i + 1}"] == main.track_of[f"main_out_{i}"] == i + 1
    assert main.track_of["accel_0"] == ramp.track_of["ramp_0"] == ramp.track_of["accel_0"] == 0
    # one track, one d range along the main line (the acceleration lane added to its right moves nothing)
    s = np.linspace(0.0, main.length_m, 200)
    for t in (1, 2, 3):
        right, left = main.lane_bounds(t, s)
        np.testing.assert_allclose(right, 3.5 * t)
        np.testing.assert_allclose(left, 3.5 * (t + 1))
    # a straight line along the middle of main_in's lane 0 stays in track 1 through merge and drop
    y = np.mean([p[1] for p in sumo.getLane("main_in_0").getShape()])
    x = np.linspace(1.0, 1799.0, 900)
    assert (main.lane_of(*main.to_frame(x, np.full_like(x, y))) == 1).all()


def test_lane_drop_is_a_lane_that_ends(frames):
    """The acceleration lane exists from the merge to the drop; ahead of any s on it, it ends
    where SUMO's edge ends; the main line's lanes run to the route's end."""
    main = frame_of(frames, ONRAMP, MAIN_ROUTE)
    accel = sumolib.net.readNet(str(ONRAMP)).getEdge("accel")
    accel_start = main.edge_start_s["accel"]
    accel_end = accel_start + accel.getLength()
    merge_start = main.edge_start_s[":merge_0"]
    assert main.lane_spans(0).tolist() == [[pytest.approx(merge_start), pytest.approx(accel_end)]]
    s = np.array([100.0, accel_start + 1.0, accel_start + 200.0, accel_end - 0.5, accel_end + 2.0, 1500.0])
    assert main.lane_count(s).tolist() == [3, 4, 4, 4, 3, 3]
    assert main.lane_exists(0, s).tolist() == [False, True, True, True, False, False]
    ends = main.lane_end_ahead(0, s)
    assert np.isnan(ends[[0, 4, 5]]).all()
    np.testing.assert_allclose(ends[1:4], accel_end)
    assert np.isinf(main.lane_end_ahead(np.array([1, 2, 3]), 800.0)).all()
    # ahead of the merge, the acceleration lane is a lane that begins there
    np.testing.assert_allclose(main.lane_start_ahead(0, np.array([100.0, accel_start + 1.0])), [merge_start, np.inf])
    # a point on the acceleration lane is lane 0; the same d past the drop is off the road
    x, y = main.to_world(np.array([accel_start + 100.0, accel_end + 30.0]), main.lane_centre_d(0, accel_start + 100.0))
    assert main.lane_of(*main.to_frame(x, y)).tolist() == [0, -1]
    # the ramp's route: its lane (track 0) ends at the same place; the main lanes start at the merge
    ramp = frame_of(frames, ONRAMP, RAMP_ROUTE)
    assert ramp.lane_end_ahead(0, 10.0) == pytest.approx(ramp.edge_start_s["accel"] + accel.getLength())
    assert ramp.lane_spans(1)[0, 0] == pytest.approx(ramp.edge_start_s[":merge_0"])
    assert ramp.lane_count(np.array([10.0, ramp.edge_start_s["accel"] + 10.0])).tolist() == [1, 4]


def test_fcd_positions_on_the_curved_highway_are_on_their_lanes(tmp_path, frames):
    """A short SUMO run on the curved five-edge highway (libsumo, --fcd-output): every recorded
    front-bumper position maps to the centre of its SUMO lane's track, s agrees with SUMO's lane
    position along the route, and the heading SUMO reports (the back-to-front direction of the
    vehicle) is the frame's chord from s - length to s at that d."""
    frame = frame_of(frames, CURVED, CURVED_ROUTE)
    routes = tmp_path / "r.rou.xml"
    routes.write_text(
        '<routes><vType id="car" length="4.6" sigma="0.5" lcSpeedGain="2"/>'
        f'<route id="r" edges="{" ".join(CURVED_ROUTE)}"/>'
        '<flow id="f" type="car" route="r" begin="0" end="40" period="1.5" departLane="random" departSpeed="max"/>'
        '</routes>')
    fcd = tmp_path / "fcd.xml"
    libsumo.start(["sumo", "-n", str(CURVED), "-r", str(routes), "--fcd-output", str(fcd), "--seed", "3",
                   "--no-step-log", "--end", "110"])
    try:
        while libsumo.simulation.getTime() < 110:
            libsumo.simulationStep()
    finally:
        libsumo.close()
    rows = [(float(v.get("x")), float(v.get("y")), float(v.get("angle")), v.get("lane"), float(v.get("pos")))
            for ts in ET.parse(fcd).getroot().iter("timestep") for v in ts.iter("vehicle")]
    assert len(rows) > 1000
    lanes = {r[3] for r in rows}
    assert {f"{e}_{i}" for e in CURVED_ROUTE for i in range(3)} <= lanes  # every lane of every edge
    x, y, angle = (np.array([r[k] for r in rows]) for k in range(3))
    track = np.array([frame.track_of[r[3]] for r in rows])
    s, d, lane = frame.locate(x, y)
    np.testing.assert_array_equal(lane, track)
    np.testing.assert_allclose(d, frame.lane_centre_d(track, s), atol=0.02)  # fcd prints 2 decimals
    np.testing.assert_allclose(s, [frame.route_position(r[3], r[4]) for r in rows], atol=0.25)
    yaw = np.radians(90.0 - angle)
    bx, by = frame.to_world(s - 4.6, d)
    chord = np.arctan2(y - by, x - bx)
    assert np.degrees(np.abs(np.angle(np.exp(1j * (yaw - chord))))).max() < 0.2
    # and the lane's own direction at the bumper, within the 2-degree steps of the curves' shapes
    along = np.degrees(np.abs(np.angle(np.exp(1j * (yaw - frame.heading(s, d))))))
    assert along.max() < 2.5


def test_merging_ramp_vehicles_in_the_main_line_frame(tmp_path, frames):
    """A SUMO run on the on-ramp network, main-line and ramp traffic (libsumo, --fcd-output and
    --lanechange-output), seen in the main line's frame: every position on the main line's lanes
    maps to its lane's track at its centre; on the ramp, before the merge, a vehicle is on none of
    the main line's lanes; every ramp vehicle merges (SUMO's reason: strategic) from the
    acceleration lane, track 0, into track 1, at an s where the frame has both lanes."""
    frame = frame_of(frames, ONRAMP, MAIN_ROUTE)
    routes = tmp_path / "r.rou.xml"
    routes.write_text(
        '<routes><vType id="car" length="4.6" sigma="0.5"/>'
        f'<route id="main" edges="{" ".join(MAIN_ROUTE)}"/><route id="ramp" edges="{" ".join(RAMP_ROUTE)}"/>'
        '<flow id="m" type="car" route="main" begin="0" end="60" vehsPerHour="3600" departLane="random" departSpeed="max"/>'
        '<flow id="r" type="car" route="ramp" begin="0" end="60" vehsPerHour="900" departLane="0" departSpeed="max"/>'
        '</routes>')
    fcd, changes = tmp_path / "fcd.xml", tmp_path / "lc.xml"
    libsumo.start(["sumo", "-n", str(ONRAMP), "-r", str(routes), "--fcd-output", str(fcd), "--seed", "2",
                   "--lanechange-output", str(changes), "--no-step-log", "--end", "150"])
    try:
        while libsumo.simulation.getTime() < 150:
            libsumo.simulationStep()
    finally:
        libsumo.close()
    rows = [(float(v.get("x")), float(v.get("y")), v.get("lane"), v.get("id"))
            for ts in ET.parse(fcd).getroot().iter("timestep") for v in ts.iter("vehicle")]
    x, y = (np.array([r[k] for r in rows]) for k in range(2))
    s, d, lane = frame.locate(x, y)
    on_main = np.array([r[2] in frame.track_of for r in rows])
    track = np.array([frame.track_of.get(r[2], -1) for r in rows])
    np.testing.assert_array_equal(lane[on_main], track[on_main])
    np.testing.assert_allclose(d[on_main], frame.lane_centre_d(track[on_main], s[on_main]), atol=0.02)
    on_ramp = np.array([r[2] == "ramp_0" for r in rows])
    assert on_ramp.sum() > 100 and (lane[on_ramp] == -1).all()
    merges = [c for c in ET.parse(changes).getroot().iter("change") if c.get("from") == "accel_0" and c.get("id").startswith("r.")]
    ramp_ids = {r[3] for r in rows if r[3].startswith("r.")}
    assert sorted(c.get("id") for c in merges) == sorted(ramp_ids) and len(ramp_ids) > 10  # each once
    for c in merges:
        assert "strategic" in c.get("reason")
        assert frame.track_of[c.get("from")] == 0 and frame.track_of[c.get("to")] == 1
        at = frame.route_position(c.get("from"), float(c.get("pos")))
        assert frame.lane_exists(np.array([0, 1]), at).all()


def test_route_errors_name_the_problem(tmp_path):
    with pytest.raises(RouteError, match=r"onramp.net.xml: route\[1\]: unknown edge 'nope'") as err:
        RoadFrame.from_net(ONRAMP, ["main_in", "nope"])
    assert (err.value.where, err.value.detail) == ("route[1]", "unknown edge 'nope'")  # for a scenario's own field
    with pytest.raises(RouteError, match=r"route\[1\]: edges 'main_in' and 'main_out' do not connect"):
        RoadFrame.from_net(ONRAMP, ["main_in", "main_out"])
    with pytest.raises(RouteError, match="not one chain of edges"):
        RoadFrame.from_net(ONRAMP)  # the ramp makes the network branch: a route is needed
    assert RoadFrame.from_net(CURVED).route == tuple(CURVED_ROUTE)  # one chain: its route by default
    from vcfusion.traffic.network import netconvert_binary

    subprocess.run([netconvert_binary(), "-n", str(NETS / "highway.nod.xml"), "-e", str(NETS / "highway.edg.xml"),
                    "-t", str(NETS / "highway.typ.xml"), "--lefthand", "-o", str(tmp_path / "lh.net.xml")],
                   check=True, capture_output=True)
    with pytest.raises(RouteError, match="left-hand-traffic network"):
        RoadFrame.from_net(tmp_path / "lh.net.xml")


def test_osm_import_keeps_the_motorway_and_its_acceleration_lane(frames):
    """The OpenStreetMap extract imports as the motorway and its on-ramp only (the residential
    street is dropped); along the main carriageway the guessed acceleration lane is track 0 and
    ends, the three motorway lanes run through as tracks 1..3."""
    sumo = sumolib.net.readNet(str(OSM))
    assert {e.getID() for e in sumo.getEdges()} == {"10", "11-AddedOnRampEdge", "11", "20"}
    frame = frame_of(frames, OSM, OSM_MAIN_ROUTE)
    assert [frame.track_of[f"10_{i}"] for i in range(3)] == [1, 2, 3]
    assert [frame.track_of[f"11_{i}"] for i in range(3)] == [1, 2, 3]
    accel_start = frame.edge_start_s["11-AddedOnRampEdge"]
    accel_end = accel_start + sumo.getEdge("11-AddedOnRampEdge").getLength()
    assert frame.lane_end_ahead(0, accel_start + 10.0) == pytest.approx(accel_end)
    assert frame.lane_count(np.array([accel_start - 50.0, accel_start + 50.0, accel_end + 50.0])).tolist() == [3, 4, 3]


def test_every_network_builds_reproducibly(tmp_path, capsys):
    """build-net rebuilds each committed network (plain XML and the OSM extract) to the same content."""
    from vcfusion.traffic.network import build_networks, network_names

    assert network_names(NETS) == ["curved", "exit", "highway", "onramp", "osm_example"]
    for source in NETS.iterdir():
        if not source.name.endswith(".net.xml"):
            (tmp_path / source.name).write_text(source.read_text())
    built = build_networks(tmp_path)

    def body(path):  # the header comment carries a timestamp
        text = path.read_text()
        return text[text.index("<net "):]

    assert [p.name for p in built] == [f"{n}.net.xml" for n in network_names(NETS)]
    for path in built:
        assert body(path) == body(NETS / path.name), path.name
    # built again, nothing changes, and the command says so (it printed "built" for every file)
    from vcfusion.commands import main

    (tmp_path / "highway.edg.xml").write_text((tmp_path / "highway.edg.xml").read_text().replace(
        "</edges>", "<!-- touched -->\n</edges>"))  # a comment: the same network
    capsys.readouterr()
    assert main(["build-net", "--net-dir", str(tmp_path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == [f"up to date {tmp_path / n}.net.xml" for n in network_names(NETS)]


def test_equal_frames_compare_equal(frames):
    """Value semantics, so per-record caches keyed by the frame survive each stage reading the net."""
    a = RoadFrame.from_net(CURVED)
    assert a == frame_of(frames, CURVED, CURVED_ROUTE) and hash(a) == hash(frame_of(frames, CURVED, CURVED_ROUTE))
    assert a != frame_of(frames, ONRAMP, MAIN_ROUTE)


def _two_edge_network(tmp_path, lanes: tuple[int, int], connections=None, second_shape=None):
    """A two-edge network built by netconvert (build_network) in tmp_path: edge e1 (x 0..500)
    then e2 (x 500..1000), lanes of 3.5 m spread right of the edges' shapes."""
    from vcfusion.traffic.network import build_network

    (tmp_path / "t.nod.xml").write_text(
        '<nodes><node id="a" x="0" y="0" type="priority"/><node id="b" x="500" y="0" type="priority"/>'
        '<node id="c" x="1000" y="0" type="priority"/></nodes>')
    shape = f' shape="{second_shape}"' if second_shape else ""
    (tmp_path / "t.edg.xml").write_text(
        f'<edges><edge id="e1" from="a" to="b" numLanes="{lanes[0]}" speed="25" width="3.5"/>'
        f'<edge id="e2" from="b" to="c" numLanes="{lanes[1]}" speed="25" width="3.5"{shape}/></edges>')
    if connections is not None:
        (tmp_path / "t.con.xml").write_text(
            "<connections>" + "".join(f'<connection from="e1" to="e2" fromLane="{i}" toLane="{j}"/>'
                                      for i, j in connections) + "</connections>")
    return build_network(tmp_path, "t")


def test_lane_drops_and_merges_follow_sumos_connections(tmp_path):
    """Which lanes continue is decided by the connections (most agree), ties by the geometry."""
    # netconvert's own 3 -> 2: the right lane has no successor (it drops), the others shift down
    (tmp_path / "right").mkdir()
    frame = RoadFrame.from_net(_two_edge_network(tmp_path / "right", (3, 2)))
    assert [frame.track_of[f"e1_{i}"] for i in range(3)] == [0, 1, 2]
    assert [frame.track_of[f"e2_{i}"] for i in range(2)] == [1, 2]
    assert frame.lane_end_ahead(0, 100.0) == pytest.approx(frame.edge_start_s["e1"] + 496.0)
    assert np.isinf(frame.lane_end_ahead(np.array([1, 2]), 100.0)).all()
    # a zipper 2 -> 1 (both lanes feed the one lane): a tie, the lane that lines up continues
    (tmp_path / "zip").mkdir()
    frame = RoadFrame.from_net(_two_edge_network(tmp_path / "zip", (2, 1), [(0, 0), (1, 0)]))
    assert frame.track_of["e2_0"] == frame.track_of["e1_1"] == 1
    assert frame.lane_spans(0)[:, 1].max() < frame.edge_start_s["e2"]
    # the left lane ends, merging into the middle one (2 of 3 connections keep their index), with
    # the second edge's lanes lined up with the first's right two
    (tmp_path / "left").mkdir()
    frame = RoadFrame.from_net(_two_edge_network(tmp_path / "left", (3, 2), [(0, 0), (1, 1), (2, 1)],
                                                 second_shape="500,-3.5 1000,-3.5"))
    assert [frame.track_of[f"e2_{i}"] for i in range(2)] == [0, 1]
    assert frame.lane_count(np.array([100.0, 800.0])).tolist() == [3, 2]
    assert frame.lane_end_ahead(2, 100.0) < frame.edge_start_s["e2"]
    # lanes that keep their index although the edge narrows: SUMO's junction lanes swerve, the
    # frame follows them: each lane keeps its track and d range after the junction, and inside it
    # (S-shaped lanes shifted sideways, not offset along their normals: up to 0.8 m off the lane's
    # centre in the swerve's middle, still inside the lane)
    (tmp_path / "swerve").mkdir()
    net = _two_edge_network(tmp_path / "swerve", (3, 2), [(0, 0), (1, 1)])
    frame = RoadFrame.from_net(net)
    assert [frame.track_of[f"e2_{i}"] for i in range(2)] == [0, 1]
    sumo = sumolib.net.readNet(str(net), withInternal=True)
    for lane_id in (":b_0_0", ":b_0_1", "e2_0", "e2_1"):
        xy = np.array(sumo.getLane(lane_id).getShape())
        xy = np.concatenate([xy, 0.5 * (xy[1:] + xy[:-1])])
        s, d = frame.to_frame(xy[:, 0], xy[:, 1])
        track = frame.track_of[lane_id]
        if lane_id.startswith(":"):
            assert (frame.lane_of(s, d) == track).all()
        else:  # 2 cm off at the first vertex, where the miter bisects the swerve's end
            np.testing.assert_allclose(d, frame.lane_centre_d(track, s), atol=0.03)
    # without junction lanes (netconvert --no-internal-links) nothing joins the two: refused
    from vcfusion.traffic.network import netconvert_binary

    subprocess.run([netconvert_binary(), "-n", "t.nod.xml", "-e", "t.edg.xml", "-x", "t.con.xml",
                    "--no-internal-links", "-o", "flat.net.xml"], cwd=tmp_path / "swerve", check=True,
                   capture_output=True)
    # (the message names the cause: it told of a jump in the lane geometry)
    with pytest.raises(RouteError, match=r"no junction lanes join 'e1' to 'e2' \(a network built with "
                       r"--no-internal-links\?\) and their lanes lie \d+\.\d\d m apart"):
        RoadFrame.from_net(tmp_path / "swerve" / "flat.net.xml")


def test_records_cache_a_frame_like_a_road(frames):
    """A RoadFrame can stand where the records take a road: road_frame(frame) is its to_frame,
    computed once per record."""
    from vcfusion.records import VehicleStates

    frame = frame_of(frames, CURVED, CURVED_ROUTE)
    n = 3
    x, y = frame.to_world(np.array([100.0, 600.0, 1300.0]), np.array([1.75, 5.25, 8.75]))
    truth = VehicleStates(time=0.0, ids=tuple("abc"), vtype=("car",) * n, vclass=("passenger",) * n, x=x, y=y,
                          z=np.zeros(n), heading=np.zeros(n), speed=np.ones(n), accel=np.zeros(n),
                          lane=np.zeros(n, np.int16), lateral_offset=np.zeros(n), length=np.full(n, 4.5),
                          width=np.full(n, 1.8), height=np.full(n, 1.5))
    s, d = truth.road_frame(frame)
    np.testing.assert_allclose(s, [100.0, 600.0, 1300.0], atol=1e-9)
    np.testing.assert_allclose(d, [1.75, 5.25, 8.75], atol=1e-9)
    assert truth.road_frame(RoadFrame.from_net(CURVED))[0] is s  # an equal frame: no recomputation


def test_a_lane_drop_on_centre_spread_edges_as_osm_imports_them(tmp_path):
    """OpenStreetMap roads come as centre-spread edges: where a motorway drops from 3 lanes to 2, the
    lanes that continue swerve half a lane sideways in the junction. Each piece offset along its own
    end normal left 0.5 m between them and the route was refused; offset along the bend's miter,
    the lanes are lines of constant d on both sides, and the junction lanes stay in their tracks."""
    from vcfusion.traffic.network import build_network

    (tmp_path / "t.nod.xml").write_text('<nodes><node id="a" x="0" y="0"/><node id="b" x="500" y="0"/>'
                                        '<node id="c" x="1000" y="0"/></nodes>')
    (tmp_path / "t.edg.xml").write_text(
        '<edges><edge id="e1" from="a" to="b" numLanes="3" speed="33" width="3.5" spreadType="center"/>'
        '<edge id="e2" from="b" to="c" numLanes="2" speed="33" width="3.5" spreadType="center"/></edges>')
    net = build_network(tmp_path, "t")
    frame = RoadFrame.from_net(net)
    assert frame.max_join_gap_m < 0.2
    sumo = sumolib.net.readNet(str(net), withInternal=True)
    for lane_id, track in frame.track_of.items():
        xy = np.array(sumo.getLane(lane_id).getShape())
        if lane_id.startswith(":"):
            mid = 0.5 * (xy[1:] + xy[:-1])
            assert (frame.lane_of(*frame.to_frame(mid[:, 0], mid[:, 1])) == track).all(), lane_id
        else:
            s, d = frame.to_frame(xy[:, 0], xy[:, 1])
            np.testing.assert_allclose(d, frame.lane_centre_d(track, s), atol=0.05, err_msg=lane_id)
