"""The look of the camera (issue 18): vehicle models true to SUMO's sizes and closed, materials and
sky shared with the shader, contact shadows that are ground (not vehicle), and render presets that
change only the RGB image."""

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from vcfusion.render import materials, sky, vehicles
from vcfusion.scenario import CameraConfig, load_scenario
from vcfusion.traffic.network import read_road

SHADERS = Path(vehicles.__file__).parent / "shaders"
CAR_SIZES = [(4.6, 1.8, 1.5), (4.0, 1.7, 1.45), (5.2, 2.0, 1.9)]  # SUMO's passenger default first
TRUCK_SIZES = [(12.0, 2.5, 3.6), (16.5, 2.55, 4.0), (7.1, 2.4, 2.4), (4.5, 2.1, 2.8), (3.6, 1.9, 2.4)]  # and short ones


def _models():
    for shape in vehicles.CAR_SHAPES:
        for size in CAR_SIZES:
            yield shape, size, vehicles.car_mesh(shape, *size, (120, 20, 20))
    for shape in vehicles.TRUCK_SHAPES:
        for size in TRUCK_SIZES:
            yield shape, size, vehicles.truck_mesh(shape, *size, (200, 200, 200), (60, 90, 140))


@pytest.mark.parametrize("shape, size, mesh", list(_models()), ids=lambda v: str(v) if not isinstance(v, trimesh.Trimesh) else "")
def test_every_model_spans_the_sumo_box_and_is_closed(shape, size, mesh):
    L, W, H = size
    np.testing.assert_allclose(mesh.bounds, [[-L / 2, -W / 2, 0.0], [L / 2, W / 2, H]], atol=0.01)
    # Every part (body, tyre, lamp, ...) is a closed solid with outward faces.
    parts = mesh.split(only_watertight=False)
    assert len(parts) >= 10
    volume = 0.0
    for part in parts:
        part.merge_vertices()
        assert part.is_watertight and part.is_winding_consistent and part.volume > 0
        volume += part.volume
    assert volume > 0.3 * L * W * H  # the body fills its box
    kinds = set(materials.face_materials(mesh))
    assert {materials.PAINT, materials.GLASS, materials.LAMP, materials.METAL, materials.SHADOW} <= kinds


def test_car_shapes_differ_and_the_style_is_stable():
    roofs = {}
    for shape in vehicles.CAR_SHAPES:
        m = vehicles.car_mesh(shape, 4.6, 1.8, 1.5, (1, 2, 3))
        tops = m.vertices[m.vertices[:, 2] > 1.45]
        roofs[shape] = (tops[:, 0].min(), tops[:, 0].max())
    assert len({tuple(np.round(v, 2)) for v in roofs.values()}) == len(vehicles.CAR_SHAPES)
    assert roofs["van"][1] - roofs["van"][0] > roofs["saloon"][1] - roofs["saloon"][0] + 1.0  # the van's long roof
    a = vehicles.vehicle_style("veh7", "passenger", 4.6, 1.8, 1.5)
    assert a[0] in vehicles.CAR_SHAPES
    # stable across processes: Python's string hash differs with PYTHONHASHSEED, the style must not
    code = ("from vcfusion.render import vehicles; "
            "print(vehicles.vehicle_style('veh7', 'passenger', 4.6, 1.8, 1.5))")
    for hash_seed in ("1", "2"):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                             env={**os.environ, "PYTHONHASHSEED": hash_seed}).stdout.strip()
        assert out == repr(a)
    assert vehicles.vehicle_style("veh7", "truck", 12, 2.5, 3.6)[0] in vehicles.TRUCK_SHAPES
    shapes = {vehicles.vehicle_style(f"v{i}", "passenger", 4.6, 1.8, 1.5)[0] for i in range(40)}
    assert shapes == set(vehicles.CAR_SHAPES)


def _glsl_consts(pattern, text):
    return {m.group(1): m.group(2) for m in re.finditer(pattern, text)}


def test_shader_constants_match_python():
    frag = (SHADERS / "lambert.frag").read_text()
    vert = (SHADERS / "lambert.vert").read_text()
    ids = {k: int(v) for k, v in _glsl_consts(r"const int MAT_(\w+) = (\d+);", frag).items()}
    assert ids == {name: mid for mid, name in materials.NAMES.items()}
    assert int(_glsl_consts(r"const int MAT_(SHADOW) = (\d+);", vert)["SHADOW"]) == materials.SHADOW
    assert float(_glsl_consts(r"const float (SHADOW_Z) = ([\d.]+);", vert)["SHADOW_Z"]) == vehicles.SHADOW_Z
    vec3 = {k: [float(x) for x in v.split(",")] for k, v in _glsl_consts(r"const vec3 (\w+) = vec3\(([^)]*)\)", frag).items()}
    np.testing.assert_allclose(vec3["HORIZON"], sky.HORIZON)
    np.testing.assert_allclose(vec3["ZENITH"], sky.ZENITH)


def test_sky_gradient():
    c = sky.sky_colour(np.array([0.0, 0.39, 1.0]))
    np.testing.assert_allclose(c[0], sky.HORIZON, atol=1e-6)
    np.testing.assert_allclose(c[1], sky.SKY, atol=0.01)
    np.testing.assert_allclose(c[2], sky.ZENITH, atol=1e-6)
    assert (np.diff(sky.sky_colour(np.linspace(0, 1, 50))[:, 0]) <= 1e-6).all()  # deeper blue upwards


# -- renders -----------------------------------------------------------------------------------------

from test_render import LANE2, SCENE, SCENARIO, states  # noqa: E402


@pytest.fixture(scope="module")
def road():
    return read_road(load_scenario(SCENARIO).network)


def _render(road, preset, scene, size=(320, 240)):
    from vcfusion.render.renderer import EgoCameraRenderer

    with EgoCameraRenderer(road, CameraConfig(width_px=size[0], height_px=size[1], render_preset=preset)) as r:
        return r.render(states(scene, time=3.0))


def test_presets_give_identical_depth_and_instances(road):
    fast, quality = _render(road, "fast", SCENE), _render(road, "quality", SCENE)
    np.testing.assert_array_equal(fast.depth, quality.depth)
    np.testing.assert_array_equal(fast.instances, quality.instances)
    assert fast.vehicle_ids == quality.vehicle_ids
    diff = np.abs(fast.rgb.astype(int) - quality.rgb.astype(int))
    assert diff.mean() > 0.5  # supersampling and noise changed the colours
    assert np.abs(fast.rgb.mean() - quality.rgb.mean()) < 8  # but not the picture
    # The sky is painted with the gradient: paler towards the horizon than at the top.
    column = 20
    horizon = np.flatnonzero(np.isinf(fast.depth[:, column]))[-1]
    assert int(fast.rgb[horizon - 2, column, 0]) > int(fast.rgb[0, column, 0]) + 15


def test_contact_shadow_darkens_the_road_but_is_no_vehicle(road):
    from vcfusion.render.scene import SUN_AZIMUTH_DEG, SUN_ELEVATION_DEG

    car = ("lead", "passenger", 118.0, LANE2, 0.0, 4.6, 1.8, 1.5)
    ego = SCENE[0]
    with_car = _render(road, "fast", [ego, car])
    empty = _render(road, "fast", [ego])
    # Ground point beside the car, on the side away from the sun, within the shadow of its body.
    az, el = np.radians(SUN_AZIMUTH_DEG), np.radians(SUN_ELEVATION_DEG)
    away = -np.array([np.cos(az), np.sin(az)])
    reach = 0.6 * 1.5 / np.tan(el)
    point = np.array([118.0 + away[0] * reach, LANE2 + np.sign(away[1]) * (0.9 + 0.5 * reach)])
    from vcfusion.render.camera import project_points

    p = project_points(np.array([[*point, 0.0]]), with_car.K, with_car.T_world_to_camera, 320, 240)
    assert p.in_image.all()
    r, c = (v[0] for v in p.pixel_index())
    assert with_car.instances[r, c] == -1  # the shadow is ground
    assert with_car.rgb[r, c].mean() < 0.75 * empty.rgb[r, c].mean()
    # no shadow pixel carries the car's code: its pixels lie within its projected 3D box, while
    # the shadow reaches beyond that box's image on the side away from the sun
    k = with_car.vehicle_ids.index("lead")
    corners = np.array([[118.0 + sx * 2.3, LANE2 + sy * 0.9, z] for sx in (-1, 1) for sy in (-1, 1) for z in (0.0, 1.5)])
    cu = project_points(corners, with_car.K, with_car.T_world_to_camera, 320, 240).uv[:, 0]
    cols = np.argwhere(with_car.instances == k)[:, 1]
    assert len(cols) > 200 and cu.min() - 1 <= cols.min() and cols.max() <= cu.max() + 1
    assert (c < cu.min() - 1) or (c > cu.max() + 1)  # the checked shadow pixel is outside the box's image
