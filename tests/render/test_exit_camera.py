"""The ego camera at the exit (scenarios/exit.yaml with an ego on the main line): the exit lane
goes on as the exit's own road (no taper, no rails in the gore), and every unoccluded vehicle's
true GNSS point projects inside its ground-truth box while vehicles change into and out of the
deceleration lane and leave by the exit."""

import pytest

from scenario_files import SCENARIOS, write_scenario
from vcfusion.cosim import CoSimulation
from vcfusion.driver.idm import IdmController
from vcfusion.records import gnss_antenna_points
from vcfusion.render.camera import project_points
from vcfusion.render.gt_boxes import ground_truth_boxes
from vcfusion.render.meshes import road_layouts
from vcfusion.render.renderer import EgoCameraRenderer
from vcfusion.scenario import load_scenario
from vcfusion.traffic.network import read_road


def exit_with_ego(tmp_path):
    text = (SCENARIOS / "exit.yaml").read_text().replace("../sumo_net", "NET_DIR")
    ego = ("ego:\n  vtype: ego\n  lane: 1\n  depart_pos_m: 720.0\n  speed_mps: 20.0\n"
           "  desired_speed_mps: 22.0\n  trip_distance_m: 600.0\n\nvision:\n  enabled: true\n\n")
    return load_scenario(write_scenario(tmp_path, text.replace("vehicles:", ego + "vehicles:", 1), "exit_ego.yaml"))


def test_the_exit_lane_goes_on_as_the_exit():
    """The road builder (no OpenGL): the deceleration lane (track 0) leaves the route at the gore
    as the exit's road, so it does not taper; the exit is drawn in its own layout."""
    road = read_road(SCENARIOS.parent / "sumo_net" / "exit.net.xml", ["main_in", "decel", "main_out"])
    layouts = road_layouts(road)
    assert [lay.name for lay in layouts] == ["", "exit/"]
    assert not (layouts[0].cover == 2).any()


@pytest.mark.slow
def test_anchors_in_boxes_at_the_exit(tmp_path):
    sc = exit_with_ego(tmp_path)
    sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": 8.0}),
                               "camera": sc.camera.model_copy(update={"width_px": 640, "height_px": 480})})
    states = []

    class Collect:
        table = "collect"

        def __call__(self, tick):
            if "ego" in tick.truth.ids and abs(tick.time * 2 - round(tick.time * 2)) < 1e-6:
                states.append(tick.truth)  # every 0.5 s

    CoSimulation(sc, 0, controller=IdmController.for_scenario(sc), hooks=[Collect()]).run()
    anchors = 0
    with EgoCameraRenderer.for_scenario(sc) as renderer:
        for truth in states:
            frame = renderer.render(truth)
            gt = ground_truth_boxes(frame, truth, renderer)
            index = {vid: i for i, vid in enumerate(truth.ids)}
            for j, vid in enumerate(gt.vehicle_ids):
                if not (gt.visible_fraction[j] >= 0.999 and gt.truncation[j] == 0.0 and gt.pixels[j] >= 30):
                    continue
                i = index[vid]
                point = gnss_antenna_points(truth.x[i:i + 1], truth.y[i:i + 1], truth.z[i:i + 1],
                                            truth.height[i:i + 1])
                u, v = project_points(point, frame.K, frame.T_world_to_camera, frame.width, frame.height).uv[0]
                x1, y1, x2, y2 = gt.box[j]
                assert x1 <= u < x2 and y1 <= v < y2, (vid, frame.time, (u, v), gt.box[j])
                anchors += 1
    assert anchors >= 10 and len(states) >= 12
