"""The ego camera at the exit (scenarios/exit.yaml with an ego on the main line): the exit lane
goes on as the exit's own road (no taper, no rails in the gore), and every unoccluded vehicle's
true GNSS point projects inside its ground-truth box while vehicles change into and out of the
deceleration lane and leave by the exit."""

import pytest

from scenario_files import SCENARIOS, write_scenario
from support.camera_runs import check_anchors_and_cuboids, rendered, simulate
from vcfusion.render.meshes import road_layouts
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
    sc, states = simulate(exit_with_ego(tmp_path), 8.0)
    anchors, _ = check_anchors_and_cuboids(rendered(sc, states))
    assert anchors >= 10 and len(states) >= 12
