"""The ego camera on curved and multi-edge roads (issue 19): real SUMO traffic, real renders.

On scenarios/curved.yaml and on scenarios/onramp.yaml with an ego added (the merge with its
acceleration lane ahead): every unoccluded vehicle's true GNSS point projects inside its
ground-truth box from the instance map, and that box agrees with its projected 3D cuboid; the
markings, the rails and the ramp are where the road frame says.
"""

import math

import numpy as np
import pytest

from scenario_files import SCENARIOS, write_scenario
from support.camera_runs import check_anchors_and_cuboids, rendered, simulate
from vcfusion.records import VehicleStates
from vcfusion.render.camera import project_points
from vcfusion.render.meshes import MARK_Z
from vcfusion.render.gt_boxes import ground_truth_boxes
from vcfusion.render.renderer import EgoCameraRenderer, camera_road
from vcfusion.scenario import load_scenario

def onramp_with_ego(tmp_path, depart_pos_m=560.0, lane=1):
    """scenarios/onramp.yaml with an ego on the main line before the merge, camera on."""
    text = (SCENARIOS / "onramp.yaml").read_text().replace("../sumo_net", "NET_DIR")
    ego = (f"ego:\n  vtype: ego\n  lane: {lane}\n  depart_pos_m: {depart_pos_m}\n  speed_mps: 20.0\n"
           "  desired_speed_mps: 22.0\n  trip_distance_m: 600.0\n\nvision:\n  enabled: true\n\n")
    return load_scenario(write_scenario(tmp_path, text.replace("vehicles:", ego + "vehicles:", 1), "onramp_ego.yaml"))


def curved_with_camera(depart_pos_m=380.0):
    sc = load_scenario(SCENARIOS / "curved.yaml")
    return sc.model_copy(update={"ego": sc.ego.model_copy(update={"depart_pos_m": depart_pos_m}),
                                 "vision": sc.vision.model_copy(update={"enabled": True})})


@pytest.fixture(scope="module")
def curved_frames():
    sc, states = simulate(curved_with_camera(), 6.0)
    return sc, rendered(sc, states)


@pytest.fixture(scope="module")
def onramp_frames(tmp_path_factory):
    sc, states = simulate(onramp_with_ego(tmp_path_factory.mktemp("onramp")), 6.0)
    return sc, rendered(sc, states)


def test_anchors_in_boxes_and_cuboids_on_the_curved_road(curved_frames):
    sc, frames = curved_frames
    # the ego drives into the left curve: its camera turns with it
    ego = [t.heading[t.index_of("ego")] for t, _, _ in frames]
    assert max(ego) - min(ego) > math.radians(3)
    anchors, cuboids = check_anchors_and_cuboids(frames)
    assert anchors >= 10 and cuboids >= 5, (anchors, cuboids)


def test_anchors_in_boxes_and_cuboids_at_the_merge(onramp_frames):
    sc, frames = onramp_frames
    anchors, cuboids = check_anchors_and_cuboids(frames)
    assert anchors >= 10 and cuboids >= 5, (anchors, cuboids)


def test_the_camera_draws_the_ego_route(tmp_path):
    sc = onramp_with_ego(tmp_path)
    assert camera_road(sc).route == ("main_in", "accel", "main_out")
    ramp_ego = sc.model_copy(update={"ego": sc.ego.model_copy(update={"route": ["ramp", "accel", "main_out"]})})
    assert camera_road(ramp_ego).route == ("ramp", "accel", "main_out")


def only_ego(road, s, d, time=0.0):
    """A state with the ego alone at (s, d) of the road, heading along it."""
    x, y = road.to_world(s, d)
    one = lambda v: np.array([float(v)])  # noqa: E731
    return VehicleStates(time=time, ids=("ego",), vtype=("ego",), vclass=("passenger",), x=one(x), y=one(y),
                         z=one(0.0), heading=one(road.heading(s, d)), speed=one(0.0), accel=one(0.0),
                         lane=np.zeros(1, np.int16), lateral_offset=one(0.0), length=one(4.6), width=one(1.8),
                         height=one(1.5))


def pixel(frame, road, s, d, z=0.0):
    x, y = road.to_world(s, d)
    p = project_points(np.array([[float(x), float(y), z]]), frame.K, frame.T_world_to_camera, frame.width,
                       frame.height)
    assert p.in_image[0]
    r, c = p.pixel_index()
    return int(r[0]), int(c[0]), float(p.depth[0])


def brightness(frame, rc):
    """The brightest grey of the pixel and its row neighbours (a line a few pixels wide)."""
    return float(frame.rgb[rc[0], max(rc[1] - 1, 0):rc[1] + 2].mean(axis=-1).max())


def surface(frame, road, rc):
    """(s, d, z) of the surface seen at a pixel (from its depth)."""
    r, c = rc[0], rc[1]
    K, T, z = frame.K, frame.T_world_to_camera, float(frame.depth[r, c])
    p_cam = np.array([(c - K[0, 2]) / K[0, 0] * z, (r - K[1, 2]) / K[1, 1] * z, z])
    x, y, zw = T[:3, :3].T @ (p_cam - T[:3, 3])
    s, d = road.to_frame(x, y)
    return float(s), float(d), float(zw)


def test_markings_and_rails_follow_the_curve():
    sc = curved_with_camera()
    road = camera_road(sc)
    cam = sc.camera.model_copy(update={"width_px": 640, "height_px": 480})
    with EgoCameraRenderer(road, cam) as renderer:
        s_ego = 800.0  # on the left curve (c12)
        d_ego = float(road.lane_centre_d(1, s_ego))
        frame = renderer.render(only_ego(road, s_ego, d_ego))
        boundary = float(road.lane_bounds(1, s_ego)[1])  # between lanes 1 and 2
        period = 18.0  # 6 m dashes, 12 m gaps on a global grid of s
        k = math.ceil((s_ego + 12.0) / period)
        dash = pixel(frame, road, k * period + 3.0, boundary, MARK_Z)
        gap = pixel(frame, road, k * period + 12.0, boundary, MARK_Z)
        assert brightness(frame, dash) > brightness(frame, gap) + 60
        # the solid left edge line, 20 m ahead on the curve, and the asphalt beside it
        left = float(road.road_bounds(s_ego + 20.0)[1])
        assert brightness(frame, pixel(frame, road, s_ego + 20.0, left - 0.125, MARK_Z)) > \
            brightness(frame, pixel(frame, road, s_ego + 20.0, left - 1.0)) + 60
        # the left guard rail's beam (0.45-0.78 m high, 3.1 m beyond the edge): its depth is the rail's
        r, c, depth = pixel(frame, road, s_ego + 20.0, left + 3.1 - 0.05, z=0.6)
        assert abs(frame.depth[r, c] - depth) < 0.5


def test_acceleration_lane_and_ramp_are_drawn(tmp_path):
    sc = onramp_with_ego(tmp_path)
    road = camera_road(sc)
    cam = sc.camera.model_copy(update={"width_px": 640, "height_px": 480})
    with EgoCameraRenderer(road, cam) as renderer:
        # the ego in the right main lane (track 1) just before the acceleration lane begins
        s_ego = 690.0
        frame = renderer.render(only_ego(road, s_ego, float(road.lane_centre_d(1, s_ego))))
        boundary = float(road.lane_bounds(0, 750.0)[1])  # acceleration lane | main line
        period = 12.0  # the block marking: 6 m dashes, 6 m gaps
        k = math.ceil((s_ego + 15.0) / period)
        dash = pixel(frame, road, k * period + 3.0, boundary, MARK_Z)
        gap = pixel(frame, road, k * period + 9.0, boundary, MARK_Z)
        assert brightness(frame, dash) > brightness(frame, gap) + 60
        # the acceleration lane is asphalt at ground level, its right edge a solid line
        for s in (k * period + 3.0, k * period + 9.0):
            lane0 = pixel(frame, road, s, float(road.lane_centre_d(0, s)))
            seen = surface(frame, road, lane0)
            assert abs(seen[2]) < 0.03 and abs(seen[1] - road.lane_centre_d(0, s)) < 0.3
            assert brightness(frame, pixel(frame, road, s, 0.2, MARK_Z)) > brightness(frame, lane0) + 60
        # where it ends (946 m) the acceleration lane narrows over 60 m: halfway, its right edge
        # line is 1.75 m further left, with asphalt left of it and none right of it
        frame = renderer.render(only_ego(road, 955.0, float(road.lane_centre_d(1, 955.0))))
        s = 976.0
        assert road.lane_end_ahead(0, 900.0) == pytest.approx(946.0)
        line = pixel(frame, road, s, 1.75 + 0.2, MARK_Z)
        inside = surface(frame, road, pixel(frame, road, s, 2.8))
        assert abs(inside[2]) < 0.03 and abs(inside[1] - 2.8) < 0.3
        assert brightness(frame, line) > brightness(frame, pixel(frame, road, s, 2.8)) + 60
        assert brightness(frame, pixel(frame, road, 1010.0, 0.2, MARK_Z)) < 140  # beyond the taper: no line
    with EgoCameraRenderer(road, cam) as renderer:
        # before the merge: the ramp's lane runs beside the main line, right of a solid line
        s_ego = 630.0
        frame = renderer.render(only_ego(road, s_ego, float(road.lane_centre_d(1, s_ego))))
        s = 650.0
        ramp = pixel(frame, road, s, 1.75)  # where track 0 will be: the ramp's asphalt
        seen = surface(frame, road, ramp)
        assert abs(seen[2]) < 0.03 and abs(seen[1] - 1.75) < 0.3
        rgb = frame.rgb[ramp[0], ramp[1]].astype(int)
        assert rgb.max() < 140 and rgb[1] - rgb[0] < 12  # grey asphalt: not paint, not grass
        line = pixel(frame, road, s, 3.5 + 0.05 + 0.15, MARK_Z)  # the main line's right edge line (0.30 m)
        assert brightness(frame, line) > brightness(frame, ramp) + 60


def test_curved_road_identification_with_the_oracle_detector(tmp_path):
    """Real renders of curved.yaml (the ego through the left curve), the oracle detector's boxes
    and the joint matcher: most visible targets identified (IoU >= 0.5 with their own box)."""
    from vcfusion.detection.detectors import OracleDetector
    from vcfusion.fusion.stage import RenderedFrameSources
    from vcfusion.studies.identification import Condition, accuracy_at, run_identification_study

    sc = curved_with_camera()
    sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": 8.0})})
    sources = RenderedFrameSources()
    try:
        rows = run_identification_study(sc, [0], sources, {"oracle": OracleDetector()}, tmp_path,
                                        conditions=[Condition(0.0, sc.v2c.gnss_noise_std_m)], progress=False)
    finally:
        sources.close()
    joint = rows[rows["method"] == "joint"]
    assert len(joint) >= 150  # target-frames
    acc = accuracy_at(joint, 0.5)["accuracy"].iloc[0]
    print(f"joint matcher, oracle boxes, curved.yaml seed 0: {acc:.3f} of {len(joint)} target-frames at IoU 0.5")
    assert acc >= 0.9, acc


def test_a_vehicle_behind_the_guard_rail_is_partly_hidden():
    """Off a straight road the road's objects can hide vehicles: the ground truth counts it."""
    sc = curved_with_camera()
    road = camera_road(sc)
    ego = only_ego(road, 800.0, float(road.lane_centre_d(2, 800.0)))
    s, d = 825.0, float(road.road_bounds(825.0)[1]) + 2.5 + 0.6 + 1.2  # on the verge, behind the left rail
    x, y = road.to_world(s, d)
    other = VehicleStates(time=0.0, ids=("ego", "verge"), vtype=("ego", "car"), vclass=("passenger", "passenger"),
                          x=np.array([ego.x[0], float(x)]), y=np.array([ego.y[0], float(y)]), z=np.zeros(2),
                          heading=np.array([ego.heading[0], float(road.heading(s, d))]), speed=np.zeros(2),
                          accel=np.zeros(2), lane=np.zeros(2, np.int16), lateral_offset=np.zeros(2),
                          length=np.array([4.6, 4.6]), width=np.array([1.8, 1.8]), height=np.array([1.5, 1.5]))
    with EgoCameraRenderer(road, sc.camera.model_copy(update={"width_px": 640, "height_px": 480})) as renderer:
        frame = renderer.render(other)
        gt = ground_truth_boxes(frame, other, renderer)
        j = gt.vehicle_ids.index("verge")
        assert 0.2 < gt.visible_fraction[j] < 0.9 and gt.full_pixels[j] > gt.pixels[j]
        assert gt.full_pixels[j] == renderer.silhouette("verge").sum()


def test_an_exit_lane_leaves_without_a_taper_an_ending_lane_tapers(tmp_path):
    """The road builder (no OpenGL): a lane that leaves the route onto an exit continues as the
    exit's road; the acceleration lane, which ends, narrows over TAPER_M."""
    from vcfusion.render.meshes import TAPER_M, road_layouts
    from vcfusion.traffic.network import build_network, read_road

    (tmp_path / "t.nod.xml").write_text(
        '<nodes><node id="a" x="0" y="0" type="priority"/><node id="b" x="500" y="0" type="priority"/>'
        '<node id="c" x="1000" y="0" type="priority"/><node id="x" x="900" y="-150" type="priority"/></nodes>')
    (tmp_path / "t.edg.xml").write_text(
        '<edges><edge id="e1" from="a" to="b" numLanes="4" speed="25" width="3.5"/>'
        '<edge id="e2" from="b" to="c" numLanes="3" speed="25" width="3.5"/>'
        '<edge id="exit" from="b" to="x" numLanes="1" speed="20" width="3.5"/></edges>')
    (tmp_path / "t.con.xml").write_text(
        "<connections>" + "".join(f'<connection from="e1" to="e2" fromLane="{i}" toLane="{i - 1}"/>' for i in (1, 2, 3))
        + '<connection from="e1" to="exit" fromLane="0" toLane="0"/></connections>')
    road = read_road(build_network(tmp_path, "t"), ["e1", "e2"])
    assert np.isfinite(road.lane_end_ahead(0, 100.0))  # track 0 leaves the route at b
    layouts = road_layouts(road)
    assert [lay.name for lay in layouts] == ["", "exit/"]
    assert not (layouts[0].cover == 2).any()  # no taper: the lane goes on as the exit
    assert layouts[0].near[:, 0].any() and layouts[1].near[:, 1].any()  # no rails in the gore

    onramp = road_layouts(read_road(SCENARIOS.parent / "sumo_net" / "onramp.net.xml", ["main_in", "accel", "main_out"]))
    route = onramp[0]
    taper = route.cover[0] == 2
    assert taper.any()
    s_taper = route.grid[np.append(taper, False)]
    assert s_taper.min() == pytest.approx(946.0) and s_taper.max() < 946.0 + TAPER_M


@pytest.mark.parametrize("net, route, from_ramp", [
    ("onramp.net.xml", ["main_in", "accel", "main_out"], False), ("onramp.net.xml", ["ramp", "accel", "main_out"], True),
    ("osm_example.net.xml", ["10", "11-AddedOnRampEdge", "11"], False),
    ("osm_example.net.xml", ["20", "11-AddedOnRampEdge", "11"], True),
], ids=["onramp-main", "onramp-ramp", "osm-main", "osm-ramp"])
def test_only_the_acceleration_lane_gets_the_block_marking(net, route, from_ramp):
    """The road builder (no OpenGL). On a route that starts on the ramp the main line's lanes begin
    where the ramp joins them, and every lane counted as auxiliary: block markings between the main
    lanes. The acceleration lane (track 0) is the only auxiliary lane on either route."""
    from vcfusion.render.meshes import road_layouts
    from vcfusion.traffic.network import read_road

    road = read_road(SCENARIOS.parent / "sumo_net" / net, route)
    assert (road.lane_spans(1)[0, 0] > 0) == from_ramp  # from the ramp, the main lanes begin along the route
    assert road_layouts(road)[0].auxiliary == [True, False, False, False]
