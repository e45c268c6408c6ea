"""Camera runs on real SUMO traffic for the render tests: simulate a scenario with the driver model,
keep the ground truth every 0.5 s, render each state and check that every unoccluded vehicle's true
GNSS point projects inside its ground-truth box (and, where large, that the box agrees with the
projected 3-D cuboid)."""

from vcfusion.cosim import CoSimulation
from vcfusion.driver.idm import IdmController
from vcfusion.fusion.matching import box_iou
from vcfusion.records import gnss_antenna_points
from vcfusion.render.camera import project_points
from vcfusion.render.gt_boxes import box_corners, ground_truth_boxes, projected_box_polygon
from vcfusion.render.renderer import EgoCameraRenderer

SIZE = dict(width_px=640, height_px=480)


def simulate(sc, seconds):
    sc = sc.model_copy(update={"simulation": sc.simulation.model_copy(update={"max_time_s": seconds}),
                               "camera": sc.camera.model_copy(update=SIZE)})
    states = []

    class Collect:
        table = "collect"

        def __call__(self, tick):
            if "ego" in tick.truth.ids and abs(tick.time * 2 - round(tick.time * 2)) < 1e-6:
                states.append(tick.truth)  # every 0.5 s

    CoSimulation(sc, 0, controller=IdmController.for_scenario(sc), hooks=[Collect()]).run()
    return sc, states


def rendered(sc, states):
    """(truth, frame, ground-truth boxes) per state; the boxes taken right after each render."""
    out = []
    with EgoCameraRenderer.for_scenario(sc) as renderer:
        for truth in states:
            frame = renderer.render(truth)
            out.append((truth, frame, ground_truth_boxes(frame, truth, renderer)))
    return out


def check_anchors_and_cuboids(frames):
    """Counts (anchors checked, cuboid boxes checked) over the frames; asserts every check."""
    anchors = cuboids = 0
    for truth, frame, gt in frames:
        index = {vid: i for i, vid in enumerate(truth.ids)}
        for j, vid in enumerate(gt.vehicle_ids):
            if not (gt.visible_fraction[j] >= 0.999 and gt.truncation[j] == 0.0 and gt.pixels[j] >= 30):
                continue
            i = index[vid]
            anchor = gnss_antenna_points(truth.x[i:i + 1], truth.y[i:i + 1], truth.z[i:i + 1], truth.height[i:i + 1])
            p = project_points(anchor, frame.K, frame.T_world_to_camera, frame.width, frame.height)
            x1, y1, x2, y2 = gt.box[j]
            u, v = p.uv[0]
            assert x1 <= u < x2 and y1 <= v < y2, (vid, frame.time, (u, v), gt.box[j])
            anchors += 1
            if gt.pixels[j] >= 200:
                corners = box_corners(truth.x[i], truth.y[i], truth.z[i], truth.heading[i], truth.length[i],
                                      truth.width[i], truth.height[i])
                hull = projected_box_polygon(corners, frame.K, frame.T_world_to_camera, 0.3)
                cuboid = (*(hull.min(axis=0)), *(hull.max(axis=0)))
                assert float(box_iou([gt.box[j]], [cuboid])[0, 0]) >= 0.8, (vid, frame.time, gt.box[j], cuboid)
                cuboids += 1
    return anchors, cuboids
