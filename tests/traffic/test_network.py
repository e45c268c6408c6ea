import numpy as np
import sumolib

from scenario_files import REPO
from vcfusion.traffic.network import build_network, read_road

NET = REPO / "sumo_net" / "highway.net.xml"


def test_road_matches_sumolib_lane_shapes():
    road = read_road(NET)
    net = sumolib.net.readNet(str(NET))
    edge = net.getEdge(road.edge_id)
    assert road.num_lanes == len(edge.getLanes()) == 3
    assert road.length_m == edge.getLength()
    for lane in edge.getLanes():
        (x0, y0), (x1, y1) = lane.getShape()[0], lane.getShape()[-1]
        s, d = road.to_road_frame(np.array([x0, x1]), np.array([y0, y1]))
        np.testing.assert_allclose(d, road.lane_centre_d(lane.getIndex()), atol=1e-9)
        np.testing.assert_allclose(s, [0.0, road.length_m], atol=1e-9)
        assert road.lane_of(s, d).tolist() == [lane.getIndex()] * 2


def test_road_frame_round_trip():
    road = read_road(NET)
    s = np.array([0.0, 10.0, 1999.0])
    d = np.array([0.2, 5.0, 10.4])
    x, y = road.to_world(s, d)
    s2, d2 = road.to_road_frame(x, y)
    np.testing.assert_allclose(s2, s)
    np.testing.assert_allclose(d2, d)
    assert road.lane_of(s[:2], np.array([-0.1, 10.6])).tolist() == [-1, -1]


def test_build_reproduces_committed_network(tmp_path):
    for suffix in ("nod", "edg", "typ"):
        (tmp_path / f"highway.{suffix}.xml").write_text((REPO / "sumo_net" / f"highway.{suffix}.xml").read_text())
    built = build_network(tmp_path)

    def body(path):  # the header comment carries a timestamp and paths
        text = path.read_text()
        return text[text.index("<net "):]

    assert body(built) == body(NET)


def test_records_keep_their_road_frame_and_selections_carry_it():
    """VehicleStates/TwinStates.road_frame equals Road.to_road_frame, is computed once per record
    (also for an equal copy of the road), is carried into selections, and a record with moved
    positions (dataclasses.replace) gets its own."""
    from dataclasses import replace

    from vcfusion.records import VehicleStates

    road = read_road(NET)
    n = 4
    x, y = road.to_world(np.array([10.0, 50.0, 90.0, 130.0]), np.array([1.6, 4.8, 8.0, 4.8]))
    truth = VehicleStates(time=0.0, ids=tuple("abcd"), vtype=("car",) * n, vclass=("passenger",) * n, x=x, y=y,
                          z=np.zeros(n), heading=np.zeros(n), speed=np.ones(n), accel=np.zeros(n),
                          lane=np.zeros(n, np.int16), lateral_offset=np.zeros(n), length=np.full(n, 4.5),
                          width=np.full(n, 1.8), height=np.full(n, 1.5))
    s, d = truth.road_frame(road)
    want_s, want_d = road.to_road_frame(x, y)
    np.testing.assert_array_equal(s, want_s)
    np.testing.assert_array_equal(d, want_d)
    assert truth.road_frame(read_road(NET))[0] is s  # an equal Road: no recomputation
    sub = truth.select([3, 1])
    assert sub.__dict__["_road_frame"][1].tolist() == want_s[[3, 1]].tolist()
    np.testing.assert_array_equal(sub.road_frame(road)[1], want_d[[3, 1]])
    moved = replace(truth, x=truth.x + 5.0)
    np.testing.assert_allclose(moved.road_frame(road)[0] - s, 5.0 * road.direction[0])


def test_elevation_is_found_in_a_netconvert_network_and_gone_after_flatten(tmp_path):
    """netconvert carries the nodes' z into the lane shapes; the camera refuses such a network
    until `netconvert --flatten` removes it (the command the error names)."""
    import subprocess

    import pytest

    from vcfusion.traffic.network import NetworkFileError, netconvert_binary, network_elevation, require_flat_network

    (tmp_path / "hill.nod.xml").write_text(
        '<nodes><node id="a" x="0" y="0" z="0"/><node id="b" x="500" y="0" z="12.5"/>'
        '<node id="c" x="1000" y="0" z="0"/></nodes>')
    (tmp_path / "hill.edg.xml").write_text(
        '<edges><edge id="up" from="a" to="b" numLanes="2" speed="30"/>'
        '<edge id="down" from="b" to="c" numLanes="2" speed="30"/></edges>')
    hill = build_network(tmp_path, "hill")
    z, lane = network_elevation(hill)
    assert z == pytest.approx(12.5) and lane.startswith((":b", "up", "down"))
    with pytest.raises(NetworkFileError, match=r"lies 12\.50 m off z = 0.*--flatten"):
        require_flat_network(hill)
    flat = tmp_path / "flat.net.xml"
    subprocess.run([netconvert_binary(), "-s", str(hill), "--flatten", "-o", str(flat)], check=True, capture_output=True)
    assert network_elevation(flat) == (0.0, "")
    require_flat_network(flat)
    assert network_elevation(NET) == (0.0, "")  # the shipped networks are flat
    for name in ("curved", "onramp"):
        assert network_elevation(REPO / "sumo_net" / f"{name}.net.xml") == (0.0, "")


def test_a_run_on_a_network_with_elevation_says_movestar_is_zero_grade(tmp_path):
    """SUMO drives a network with elevation; the run's metrics say that MOVESTAR's rates ignore it
    (its spec is zero grade) instead of passing them off as the road's. A flat network's run
    carries no such field."""
    from scenario_files import lifted_highway, write_scenario

    from vcfusion.metrics.run_metrics import format_run_metrics
    from vcfusion.run import build_cosimulation
    from vcfusion.scenario import load_scenario

    def run_on(network: str, name: str):
        text = (f"name: t\nnetwork: {network}\nvehicle_types: NET_DIR/vtypes.add.xml\nsimulation: {{max_time_s: 2.0}}\n"
                "ego: {lane: 2, depart_pos_m: 50, speed_mps: 19}\n"
                "vehicles: [{name: car, count: 1, vtype: car, lanes: [1], pos_m: [80, 120]}]\n")
        return build_cosimulation(load_scenario(write_scenario(tmp_path, text, name)), 0).run()

    lifted_highway(tmp_path, 7.5)
    lifted = run_on("hill.net.xml", "hill.yaml")
    assert lifted.summary["network_max_height_m"] == 7.5
    assert "zero grade, but this network has elevation (lanes up to 7.5 m off z = 0)" in format_run_metrics(lifted.summary)
    flat = run_on("NET_DIR/highway.net.xml", "flat.yaml")
    assert "network_max_height_m" not in flat.summary and "zero grade" not in format_run_metrics(flat.summary)


def test_an_edge_whose_length_is_set_apart_from_its_geometry_follows_sumos_positions(tmp_path):
    # `length="600"` on 500 m of straight geometry: SUMO's positions run to 600 m, and so must s
    # (the closed-form Road measured the geometry: s = 250 where SUMO says 300)
    import libsumo

    (tmp_path / "n.nod.xml").write_text('<nodes><node id="a" x="0" y="0"/><node id="b" x="500" y="0"/></nodes>')
    (tmp_path / "n.edg.xml").write_text('<edges><edge id="e" from="a" to="b" numLanes="3" speed="25" width="3.5" '
                                        'length="600"/></edges>')
    net = build_network(tmp_path, "n")
    road = read_road(net)
    libsumo.start(["sumo", "-n", str(net), "--no-step-log", "--no-warnings"])
    try:
        edge, pos, lane = libsumo.simulation.convertRoad(250.0, -5.25)
    finally:
        libsumo.close()
    s, d = road.to_frame(250.0, -5.25)
    assert road.length_m == 600.0 and float(s) == pos == 300.0 and int(road.lane_of(s, d)) == lane == 1


def test_the_compiled_frame_conversion_gives_the_numpy_expressions_doubles():
    """Float64 vectors (every tick's vehicles and twins, strided views included) go through one
    compiled call: bit for bit the arithmetic of the expression on any other input (lists,
    scalars), which the straight-road runs were recorded with."""
    road = read_road(REPO / "sumo_net" / "highway.net.xml")
    x0, y0, dx, dy, nx, ny, width = road._frame
    rng = np.random.default_rng(4)
    for scale in (1e-3, 1.0, 1e3, 1e6):
        block = rng.uniform(-1.0, 1.0, (40, 7)) * scale
        pairs = ((block[:, 1].copy(), block[:, 2].copy()), (block[:, 1], block[:, 2]), (block[:0, 1], block[:0, 2]))
        for x, y in pairs:  # contiguous, strided views (a twin snapshot's columns), empty
            s, d = road.to_frame(x, y)
            rel_x, rel_y = np.array(x.tolist()) - x0, np.array(y.tolist()) - y0
            assert s.dtype == d.dtype == np.float64 and s.shape == x.shape
            assert np.array_equal(s, rel_x * dx + rel_y * dy)
            assert np.array_equal(d, (rel_x * nx + rel_y * ny) + width)
            s_list, d_list = road.to_frame(x.tolist(), y.tolist())
            assert np.array_equal(s, s_list) and np.array_equal(d, d_list)
    s, d = road.to_frame(np.float32([250.0]), np.float32([-5.25]))  # other types keep NumPy's rules
    assert s.dtype == np.float32
