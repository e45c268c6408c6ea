"""Real renders under OSMesa (no GPU, no display): images, projection, depth, boxes, COCO export."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from vcfusion.records import VehicleStates
from vcfusion.scenario import CameraConfig, load_scenario
from vcfusion.traffic.network import read_road
from vcfusion.render import meshes
from vcfusion.render.camera import project_points
from vcfusion.render.gt_boxes import ground_truth_boxes
from vcfusion.render.renderer import EgoCameraRenderer

SCENARIO = Path("scenarios/accident.yaml")


def states(rows, time=1.0):
    """rows: (id, vclass, x, y, yaw, length, width, height)."""
    cols = list(zip(*rows))
    n = len(rows)
    f = lambda k: np.array(cols[k], dtype=float)  # noqa: E731
    return VehicleStates(time=time, ids=tuple(cols[0]), vtype=tuple(cols[1]), vclass=tuple(cols[1]),
                         x=f(2), y=f(3), z=np.zeros(n), heading=f(4), speed=np.zeros(n), accel=np.zeros(n),
                         lane=np.zeros(n, dtype=np.int16), lateral_offset=np.zeros(n),
                         length=f(5), width=f(6), height=f(7))


@pytest.fixture(scope="module")
def renderer():
    sc = load_scenario(SCENARIO)
    with EgoCameraRenderer(read_road(sc.network), CameraConfig(width_px=320, height_px=240)) as r:
        yield r


LANE2, LANE1 = -1.75, -5.25
SCENE = [
    ("ego", "passenger", 100.0, LANE2, 0.0, 4.6, 1.8, 1.5),
    ("lead", "passenger", 125.0, LANE2, 0.0, 4.6, 1.8, 1.5),
    ("hidden", "passenger", 140.0, LANE2 - 0.9, 0.0, 4.6, 1.8, 1.5),  # right behind 'lead': partly occluded
    ("truck", "truck", 150.0, LANE1, 0.02, 12.0, 2.5, 3.6),
    ("behind", "passenger", 80.0, LANE1, 0.0, 4.6, 1.8, 1.5),  # behind the camera
]


def body_and_rear(truth, i, frac=0.35):
    c, s = math.cos(truth.heading[i]), math.sin(truth.heading[i])
    z = truth.z[i] + frac * truth.height[i]
    body = np.array([truth.x[i], truth.y[i], z])
    rear = body - np.array([c, s, 0.0]) * truth.length[i] / 2
    return body, rear


def test_frame_images_and_id_mapping(renderer):
    truth = states(SCENE)
    frame = renderer.render(truth)
    assert frame.rgb.shape == (240, 320, 3) and frame.rgb.dtype == np.uint8
    assert frame.depth.dtype == np.float32 and frame.instances.dtype == np.int32
    assert "ego" not in frame.vehicle_ids and "behind" not in frame.vehicle_ids
    seen = {frame.vehicle_ids[k] for k in np.unique(frame.instances) if k >= 0}
    assert seen == {"lead", "hidden", "truck"}
    assert np.isinf(frame.depth[0]).all() and (frame.instances[0] == -1).all()  # sky row
    assert np.isfinite(frame.depth[-1]).all() and (frame.instances[-1] == -1).all()  # road row
    # The sky colour, and a road that is darker than the sky.
    np.testing.assert_allclose(frame.rgb[0, 0] / 255.0, meshes.SKY, atol=0.02)
    assert frame.rgb[-1].mean() < frame.rgb[0].mean()


def test_projection_lands_in_mask_and_depth_matches(renderer):
    truth = states(SCENE)
    frame = renderer.render(truth)
    for vid in ("lead", "truck"):
        i = truth.index_of(vid)
        body, rear = body_and_rear(truth, i)
        p = project_points(np.array([body, rear]), frame.K, frame.T_world_to_camera, frame.width, frame.height)
        assert p.in_image.all()
        rows, cols = p.pixel_index()
        k = frame.vehicle_ids.index(vid)
        assert frame.instances[rows[0], cols[0]] == k
        assert frame.instances[rows[1], cols[1]] == k
        assert abs(frame.depth[rows[1], cols[1]] - p.depth[1]) < 0.1


def test_moving_a_vehicle_moves_its_pixels(renderer):
    a = renderer.render(states(SCENE))
    moved = [r if r[0] != "lead" else ("lead", "passenger", 125.0, LANE1, 0.0, 4.6, 1.8, 1.5) for r in SCENE]
    b = renderer.render(states(moved))
    ka, kb = a.vehicle_ids.index("lead"), b.vehicle_ids.index("lead")
    ca = np.argwhere(a.instances == ka)[:, 1].mean()
    cb = np.argwhere(b.instances == kb)[:, 1].mean()
    assert cb > ca + 20  # moved right (lane 1 is right of lane 2)
    # a vehicle that leaves the state disappears from the scene
    c = renderer.render(states([r for r in SCENE if r[0] != "truck"]))
    assert "truck" not in c.vehicle_ids and "truck" not in renderer.traffic.nodes


def test_ground_truth_boxes(renderer):
    truth = states(SCENE)
    frame = renderer.render(truth)
    boxes = ground_truth_boxes(frame, truth, renderer)
    by_id = {vid: j for j, vid in enumerate(boxes.vehicle_ids)}
    lead, hidden, truck = by_id["lead"], by_id["hidden"], by_id["truck"]
    assert boxes.visible_fraction[lead] == 1.0 and boxes.truncation[lead] == 0.0
    assert 0.0 < boxes.visible_fraction[hidden] < 0.9  # behind 'lead' in the same lane
    assert boxes.full_pixels[hidden] > boxes.pixels[hidden]
    assert boxes.vclass[truck] == "truck"
    # The box holds exactly the mask's extent.
    k = frame.vehicle_ids.index("lead")
    r, c = np.nonzero(frame.instances == k)
    np.testing.assert_allclose(boxes.box[lead], [c.min() - 0.5, r.min() - 0.5, c.max() + 0.5, r.max() + 0.5])
    assert boxes.pixels[lead] == len(r)
    assert abs(boxes.median_depth[lead] - (25.0 - 2.3 - 0.6)) < 0.5  # its rear, 25 m ahead less half lengths and the mount


def area(b):
    return (b[2] - b[0]) * (b[3] - b[1])


def silhouette_box(renderer, vehicle_id):
    """The box (pixel-centre convention) around the vehicle drawn alone: the renderer's own second pass."""
    rows, cols = np.nonzero(renderer.silhouette(vehicle_id))
    return np.array([cols.min() - 0.5, rows.min() - 0.5, cols.max() + 0.5, rows.max() + 0.5])


def test_the_visible_share_agrees_with_the_vehicle_drawn_alone(renderer):
    """The outline (projected 3D box) holds the vehicle's silhouette drawn alone (the renderer's own
    second pass, an independent reference); an unoccluded car's visible box covers most of it, a
    car straight behind another showing a sliver less than MIN_VISIBLE_SHARE, as the silhouette's
    box says too."""
    from vcfusion.metrics.highlights import MIN_VISIBLE_SHARE

    scene = [SCENE[0], SCENE[1], ("sliver", "passenger", 140.0, LANE2 - 0.6, 0.0, 4.6, 1.8, 1.5)]
    truth = states(scene)
    frame = renderer.render(truth)
    boxes = ground_truth_boxes(frame, truth, renderer)
    for vid in ("lead", "sliver"):
        j = boxes.vehicle_ids.index(vid)
        alone = silhouette_box(renderer, vid)
        out = boxes.outline[j]
        assert out[0] <= alone[0] + 1 and out[1] <= alone[1] + 1 and out[2] >= alone[2] - 1 and out[3] >= alone[3] - 1
        assert boxes.visible_share[j] == pytest.approx(area(boxes.patch[j]) / area(out))
        np.testing.assert_array_equal(boxes.patch[j], boxes.box[j])  # each shows as one patch
        if vid == "lead":
            assert boxes.visible_fraction[j] == 1.0 and boxes.visible_share[j] > 0.75
        else:
            assert boxes.visible_fraction[j] < 0.2
            assert boxes.visible_share[j] < MIN_VISIBLE_SHARE and area(boxes.box[j]) / area(alone) < MIN_VISIBLE_SHARE


def test_a_car_beside_the_camera_leaving_the_frame_shows_most_of_its_outline(renderer):
    """The outline is the box around the projected 3D box's part inside the image: for an
    unoccluded car leaving the frame beside the camera it holds the car drawn alone (the renderer's
    second pass) and the car covers most of it; the box around the whole projection, clipped to
    the image, would span the image's height and put the share near the sliver floor."""
    from vcfusion.metrics.highlights import MIN_VISIBLE_SHARE
    from vcfusion.render.gt_boxes import box_corners, projected_box_polygon

    for x in (106.0, 105.0, 104.0):
        truth = states([SCENE[0], ("side", "passenger", x, LANE1, 0.0, 4.6, 1.8, 1.5)])
        frame = renderer.render(truth)
        boxes = ground_truth_boxes(frame, truth, renderer)
        j = boxes.vehicle_ids.index("side")
        alone = silhouette_box(renderer, "side")
        out = boxes.outline[j]
        assert out[0] <= alone[0] + 1 and out[1] <= alone[1] + 1 and out[2] >= alone[2] - 1 and out[3] >= alone[3] - 1
        assert boxes.truncation[j] > 0.5 and boxes.visible_fraction[j] == 1.0
        assert boxes.visible_share[j] > 0.7
        hull = projected_box_polygon(box_corners(x, LANE1, 0.0, 0.0, 4.6, 1.8, 1.5), frame.K, frame.T_world_to_camera,
                                     0.3)
        lo, hi = hull.min(axis=0), hull.max(axis=0)
        whole = (max(lo[0], -0.5), max(lo[1], -0.5), min(hi[0], frame.width - 0.5), min(hi[1], frame.height - 0.5))
        assert area(whole) > 1.15 * area(out)
    assert area(boxes.box[j]) / area(whole) < 2.5 * MIN_VISIBLE_SHARE  # x = 104: 0.44 by the whole projection


def test_truncation_at_image_border(renderer):
    near_side = [SCENE[0], ("side", "passenger", 106.0, LANE1, 0.0, 4.6, 1.8, 1.5)]
    truth = states(near_side)
    frame = renderer.render(truth)
    boxes = ground_truth_boxes(frame, truth, renderer)
    j = boxes.vehicle_ids.index("side")
    assert 0.2 < boxes.truncation[j] < 1.0
    assert boxes.box[j][2] == frame.width - 0.5  # touches the right border


def test_shader_sky_matches_scene_sky():
    src = (Path(meshes.__file__).parent / "shaders" / "lambert.frag").read_text()
    values = [float(v) for v in re.search(r"const vec3 SKY = vec3\(([^)]*)\)", src).group(1).split(",")]
    np.testing.assert_allclose(values, meshes.SKY)


def _short(scenario, seconds, **camera):
    return scenario.model_copy(update={
        "simulation": scenario.simulation.model_copy(update={"max_time_s": seconds}),
        "camera": scenario.camera.model_copy(update=camera)})


def test_render_dataset_end_to_end(tmp_path):
    """Real SUMO run -> frames -> COCO; checked independently from the exported files."""
    from pycocotools.coco import COCO

    from vcfusion.render.check import check_dataset
    from vcfusion.render.export import render_dataset

    sc = _short(load_scenario("scenarios/overlap.yaml"), 6.0, width_px=320, height_px=240)
    out = tmp_path / "ds"
    counts = render_dataset(sc, [0], every=10, out=out, progress=False)
    assert counts["images"] == 6 and counts["annotations"] > 0
    assert not list(tmp_path.glob("*.tmp-writing*"))
    stats = check_dataset(out)
    assert stats["anchor_max_abs_diff_px"] < 1e-6
    assert stats["unoccluded_vehicles"] >= 5 and stats["body_point_in_mask_rate"] >= 0.99
    assert stats["rear_depth_checks"] >= 10 and stats["rear_depth_max_abs_err_m"] < 0.1
    coco = COCO(str(out / "annotations.json"))
    assert len(coco.getImgIds()) == 6
    image = coco.loadImgs(coco.getImgIds()[0])[0]
    assert np.array(image["camera"]["K"]).shape == (3, 3)
    assert np.array(image["camera"]["T_world_to_camera"]).shape == (4, 4)
    assert {"pair_near0", "pair_far0"} <= {v["vehicle_id"] for v in image["vehicles"]}
    ann = coco.loadAnns(coco.getAnnIds(imgIds=[image["id"]]))
    assert all("vehicle_id" in a for a in ann)
    # The RLE mask's area is the annotation's area.
    assert all(int(coco.annToMask(a).sum()) == a["area"] for a in ann)
    with pytest.raises(FileExistsError):
        render_dataset(sc, [0], every=10, out=out, progress=False)


@pytest.mark.slow
def test_render_in_workers_writes_the_folder_one_process_writes(tmp_path):
    """`vcfusion render --workers 2`: the seeds run in two processes and their records merge in seed
    order: the same annotations byte for byte and the same images as one process (which reuses one
    renderer for every seed)."""
    from vcfusion.render.export import render_dataset

    sc = _short(load_scenario("scenarios/overlap.yaml"), 4.0, width_px=320, height_px=240)
    for workers in (1, 2):
        render_dataset(sc, [2, 0, 1], every=10, out=tmp_path / f"w{workers}", progress=False, workers=workers)
    one, two = tmp_path / "w1", tmp_path / "w2"
    assert (one / "annotations.json").read_bytes() == (two / "annotations.json").read_bytes()
    data = json.loads((one / "annotations.json").read_text())
    assert [im["seed"] for im in data["images"]] == [2] * 4 + [0] * 4 + [1] * 4  # the order asked for
    for kind in ("rgb", "depth", "instances"):
        names = sorted(p.name for p in (one / kind).iterdir())
        assert len(names) == 12 and names == sorted(p.name for p in (two / kind).iterdir())
        assert all((one / kind / n).read_bytes() == (two / kind / n).read_bytes() for n in names)


@pytest.mark.parametrize("workers", ["1", "2"])
def test_a_seed_sumo_refuses_is_one_error_line_in_workers_too(tmp_path, capsys, workers):
    """In worker processes a failing seed raised a RuntimeError with the worker's traceback; one
    process printed SUMO's refusal on one line and exited with 1. Now both do the same."""
    from scenario_files import REFUSED_DEPARTURE, write_scenario

    from vcfusion.commands import main

    ego = "ego: {vtype: ego, lane: 1, depart_pos_m: 20.0, speed_mps: 20.0, trip_distance_m: 200.0}\n"
    scenario = write_scenario(tmp_path, REFUSED_DEPARTURE + ego)
    rc = main(["render", str(scenario), "--seeds", "0-1", "--every", "5", "--out", str(tmp_path / "ds"),
               "--workers", workers])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1, err
    assert err[0].startswith("error: ") and "SUMO could not insert 'b0'" in err[0]
    assert not list(tmp_path.glob("ds*"))


def test_vision_enabled_run_puts_frames_on_ticks():
    from vcfusion.cosim import CoSimulation
    from vcfusion.run import build_cosimulation

    sc = _short(load_scenario(SCENARIO), 1.0, width_px=160, height_px=120)
    sc = sc.model_copy(update={"vision": sc.vision.model_copy(update={"enabled": True, "every_ticks": 2})})
    cosim = build_cosimulation(sc, 0)
    frames = []

    class Grab:
        table = "grab"
        needs = ("frame",)

        def __call__(self, tick):
            if tick.frame is not None:
                frames.append(tick.frame)

    cosim = CoSimulation(sc, 0, controller=cosim.controller, hooks=cosim.hooks + [Grab()])
    result = cosim.run()
    assert len(frames) == len(result.tables["camera"]) == 5
    assert frames[0].rgb.shape == (120, 160, 3)


def test_sumo_vehicle_classes_map_to_the_camera_categories():
    from vcfusion.records import VEHICLE_CATEGORIES as CATEGORIES
    from vcfusion.render.coco import category_id

    assert [category_id(c) for c in CATEGORIES] == list(range(1, len(CATEGORIES) + 1))  # fixed ids
    assert category_id("evehicle") == category_id("private") == category_id("passenger") == 1
    assert category_id("moped") == category_id("motorcycle")
    with pytest.raises(ValueError, match="vehicle class 'bicycle' has no COCO category"):
        category_id("bicycle")


def test_depth_beyond_the_png_formats_range_reads_as_no_depth():
    # uint16 centimetres reach 655.35 m; a far plane set further must not write 655.35 m for 700 m
    from vcfusion.render.coco import depth_to_png16

    png = depth_to_png16(np.array([599.0, 655.35, 700.0, 999.0, np.inf, 0.0]))
    assert png.tolist() == [59900, 65535, 0, 0, 0, 0]


def test_a_vehicle_cut_by_the_image_border_is_listed_as_a_twin(renderer):
    # a truck alongside, its centre 3.4 m ahead of the camera and right of the image: its cab is
    # in view, its GNSS point is not; listed only where the point projects into the image, it was
    # no twin, and eval-detector's identification left it out (the hard, truncated cases)
    from vcfusion.render.coco import vehicle_anchors

    truth = states([SCENE[0], ("truck", "truck", 104.0, LANE1, 0.0, 12.0, 2.5, 3.6), SCENE[1], SCENE[4]])
    frame = renderer.render(truth)
    listed = {v["vehicle_id"]: v for v in vehicle_anchors(frame, truth, "ego")}
    assert "truck" in frame.vehicle_ids and set(listed) == {"truck", "lead"}  # 'behind' is behind the camera
    assert listed["truck"]["in_image"] is False and listed["truck"]["anchor_uv"][0] > 319.5
    assert listed["truck"]["visible"] and listed["lead"]["in_image"] is True


@pytest.mark.parametrize("preset", ["fast", "quality"])
def test_the_lean_forward_pass_draws_pyrenders_frames_bit_for_bit(preset, monkeypatch):
    # The renderer sets the camera and light uniforms once per program and frame, with each
    # uniform's location asked once and undeclared ones skipped, and its own draw order and poses
    # computed once a frame; pyrender's own pass sets every uniform before every primitive. Same
    # draws, same values: the same images.
    from pyrender.shader_program import ShaderProgram

    from vcfusion.render.renderer import _CameraProgram

    sc = load_scenario(SCENARIO)
    truth = states([*SCENE, ("c", "passenger", 110.0, LANE1, 0.0, 4.0, 1.7, 1.4),
                    ("b", "truck", 125.0, LANE1, 0.0, 12.0, 2.5, 3.6)])
    frames, drawn = [], []
    for lean in (True, False):
        r = EgoCameraRenderer(read_road(sc.network), CameraConfig(width_px=320, height_px=240, render_preset=preset))
        try:
            if not lean:
                del r._gl._forward_pass, r._gl._update_context  # pyrender's methods again
                monkeypatch.setattr(_CameraProgram, "set_uniform", ShaderProgram.set_uniform)  # and its uniforms
            frames.append(r.render(truth))
            drawn.append((r._gl._forward_pass.__qualname__, _CameraProgram.set_uniform.__qualname__))
        finally:
            r.close()
    lean_frame, pyrender_frame = frames
    assert drawn == [("_lean_forward_pass.<locals>.forward_pass", "_CameraProgram.set_uniform"),
                     ("Renderer._forward_pass", "ShaderProgram.set_uniform")]
    assert lean_frame.vehicle_ids == pyrender_frame.vehicle_ids and len(lean_frame.vehicle_ids) >= 3
    assert np.array_equal(lean_frame.rgb, pyrender_frame.rgb)
    assert np.array_equal(lean_frame.depth, pyrender_frame.depth)
    assert np.array_equal(lean_frame.instances, pyrender_frame.instances)


def test_a_uniform_the_shader_does_not_declare_is_skipped_and_a_bad_value_refused():
    sc = load_scenario(SCENARIO)
    r = EgoCameraRenderer(read_road(sc.network), CameraConfig(width_px=160, height_px=120))
    try:
        r.render(states(SCENE))
        program = next(iter(r._gl._program_cache._program_cache.values()))  # one of the frame's programs
        program._bind()
        program.set_uniform("material.metallic_factor", 0.5)  # pyrender's PBR factor: not in our shader
        assert program._locations["material.metallic_factor"] == -1
        program.set_uniform("M", np.eye(4))
        assert program._locations["M"] >= 0
        with pytest.raises(TypeError, match="uniform M: expected an array, a float or an int, got list"):
            program.set_uniform("M", [[1.0, 0.0], [0.0, 1.0]])
        program._unbind()
    finally:
        r.close()


def test_vehicles_that_come_and_go_between_frames_are_drawn_as_by_a_fresh_renderer():
    # the context is updated only when the scene's meshes change: a vehicle added after the first
    # frame, and one removed, must show as a renderer that never saw the earlier frame draws them
    sc = load_scenario(SCENARIO)
    camera = CameraConfig(width_px=320, height_px=240)
    late = ("c", "passenger", 110.0, LANE1, 0.0, 4.0, 1.7, 1.4)
    sequence = [states(SCENE), states([*SCENE, late]), states([SCENE[0], late])]
    kept = EgoCameraRenderer(read_road(sc.network), camera)
    try:
        frames = [kept.render(truth) for truth in sequence]
    finally:
        kept.close()
    assert "c" not in frames[0].vehicle_ids and "c" in frames[1].vehicle_ids and "c" in frames[2].vehicle_ids
    for truth, frame in zip(sequence[1:], frames[1:]):
        fresh = EgoCameraRenderer(read_road(sc.network), camera)
        try:
            alone = fresh.render(truth)
        finally:
            fresh.close()
        assert frame.vehicle_ids == alone.vehicle_ids
        assert np.array_equal(frame.rgb, alone.rgb) and np.array_equal(frame.depth, alone.depth)
        assert np.array_equal(frame.instances, alone.instances)
