"""The procedural scene sampler: held-out families are never sampled for training, the recipes
mean what they say, and rendered scenes make a COCO folder the detector tools read."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from vcfusion.detection.scenes import (CAR, FAMILIES, HELD_OUT, TRUCK, CameraMount, PlacedVehicle, SceneRecipe,
                                       held_out_families, is_cut_in, is_far_chain, is_jam, is_truck_occlusion,
                                       occluded_fraction, sample_scene, scene_states)


def _v(vid, lane, rear, kind=CAR, lateral=0.0, yaw=0.0, length=4.5, width=1.8, height=1.5):
    return PlacedVehicle(vid, kind, lane, rear + length / 2, lateral, yaw, length, width, height, 10.0)


def _recipe(*vehicles, ego_lane=1):
    return SceneRecipe("x", 0, 3, 3.5, ego_lane, 500.0, CameraMount(1.4, 0.0, 0.0), tuple(vehicles))


def test_training_sampler_never_emits_a_held_out_configuration():
    stats = {"ego_lane_chain_near": 0, "yawed_towards_ego_elsewhere": 0, "car_behind_truck": 0}
    for seed in range(600):
        r = sample_scene("train", seed)
        assert held_out_families(r) == [], (seed, held_out_families(r))
        assert r.vehicles and all(3.0 <= v.rear_m <= 150.0 for v in r.vehicles)
        # the neighbourhood of each held-out region is sampled (what makes the hold-out a test)
        lane_chain = [v for v in r.vehicles if v.lane == r.ego_lane]
        stats["ego_lane_chain_near"] += any(
            a.rear_m < 60 and 0 <= b.rear_m - a.front_m <= 10 for a in lane_chain for b in lane_chain if b is not a)
        stats["yawed_towards_ego_elsewhere"] += any(
            abs(v.lane - r.ego_lane) == 1 and np.sign(r.ego_lane - v.lane) * v.yaw_rad >= math.radians(2)
            and not 10 <= v.ahead_m <= 20 for v in r.vehicles)
        stats["car_behind_truck"] += any(t.vclass == TRUCK and c.vclass == CAR and c.lane == t.lane and c.ahead_m > t.ahead_m
                                         for t in r.vehicles for c in r.vehicles)
    assert min(stats["ego_lane_chain_near"], stats["yawed_towards_ego_elsewhere"], stats["car_behind_truck"]) >= 15, stats


@pytest.mark.parametrize("family", list(HELD_OUT))
def test_held_out_family_scenes_match_their_recipe(family):
    for seed in range(40):
        r = sample_scene(family, seed)
        assert family in held_out_families(r)
        assert r == sample_scene(family, seed)  # deterministic in (family, seed)
    assert sample_scene(family, 0) != sample_scene(family, 1)


def test_predicates_on_hand_made_recipes():
    chain = [_v("a", 1, 70.0), _v("b", 1, 70.0 + 4.5 + 6.0)]
    assert is_far_chain(_recipe(*chain))
    assert not is_far_chain(_recipe(*chain, ego_lane=0))  # another lane than the ego's
    assert not is_far_chain(_recipe(_v("a", 1, 130.0), _v("b", 1, 140.0)))  # too far
    assert not is_far_chain(_recipe(_v("a", 1, 70.0), _v("b", 1, 70.0 + 4.5 + 12.0)))  # gap > 10 m
    cut = _v("c", 2, 12.0, lateral=-1.0, yaw=-math.radians(4))  # left lane, heading right (towards lane 1)
    assert is_cut_in(_recipe(cut))
    assert not is_cut_in(_recipe(replace(cut, yaw_rad=math.radians(4))))  # leaving towards lane 3
    assert not is_cut_in(_recipe(replace(cut, ahead_m=40.0)))
    jam = [_v(f"{lane}{k}", lane, 4.0 + k * 7.0) for lane in range(3) for k in range(4)]  # gaps 2.5 m
    assert is_jam(_recipe(*jam))
    assert not is_jam(_recipe(*[v for v in jam if v.lane != 0]))
    # a car straight behind a wider, taller truck is fully hidden (not the held-out case); shifted
    # by 2 m it peeks out: seen from the camera (lane 1 centre, 1.4 m up, pitch 0), the truck's near
    # face spans u = +-1.25/25 and the car u = 1.1/46.5 .. 2.9/42 (normalised), the car's height
    # lies within the truck's: (0.05 - 1.1/46.5) / (2.9/42 - 1.1/46.5) = 0.58 of it is covered
    truck = _v("t", 1, 25.0, TRUCK, length=12.0, width=2.5, height=3.6)
    hidden = _v("h", 1, 25.0 + 12.0 + 5.0)
    assert occluded_fraction(hidden, truck, _recipe()) == pytest.approx(1.0)
    assert not is_truck_occlusion(_recipe(truck, hidden))
    peek = replace(hidden, lateral_m=-2.0)  # to the right: u grows to the right, d to the left
    expected = (1.25 / 25 - 1.1 / 46.5) / (2.9 / 42 - 1.1 / 46.5)
    assert occluded_fraction(peek, truck, _recipe()) == pytest.approx(expected, rel=1e-6)
    assert is_truck_occlusion(_recipe(truck, peek))
    assert not is_truck_occlusion(_recipe(replace(truck, ahead_m=60.0), replace(peek, ahead_m=80.0)))


def test_scene_states_place_the_vehicles_on_the_road():
    from scenario_files import REPO
    from vcfusion.traffic.network import read_road

    road = read_road(REPO / "sumo_net" / "highway.net.xml")
    r = sample_scene("train", 3, road.num_lanes, road.lane_width_m)
    truth = scene_states(r, road)
    assert truth.ids[0] == "ego" and len(truth) == len(r.vehicles) + 1
    s, d = truth.road_frame(road)
    cam_s = r.ego_s + r.mount.forward_m
    for k, v in enumerate(r.vehicles, start=1):
        assert s[k] - cam_s == pytest.approx(v.ahead_m)
        assert d[k] == pytest.approx((v.lane + 0.5) * road.lane_width_m + v.lateral_m)
        assert road.lane_of(s[k], d[k] - v.lateral_m) == v.lane


@pytest.mark.slow
def test_rendered_scenes_are_a_coco_folder_with_the_recipe(tmp_path):
    from scenario_files import SCENARIOS
    from vcfusion.detection.detector_train import load_coco_many
    from vcfusion.detection.scenes import render_scenes
    from vcfusion.scenario import load_scenario

    sc = load_scenario(SCENARIOS / "overlap.yaml")
    counts = render_scenes(sc, "cut_in", [0, 1], tmp_path / "cut", progress=False)
    assert counts["images"] == 2 and counts["annotations"] >= 2
    data = json.loads((tmp_path / "cut" / "annotations.json").read_text())
    ds = load_coco_many([tmp_path / "cut"])
    assert len(ds) == 2
    for im in data["images"]:
        recipe = sample_scene("cut_in", im["seed"])
        assert im["family"] == "cut_in" and im["scene"]["vehicles"][0]["vehicle_id"] == recipe.vehicles[0].vehicle_id
        # the camera sits where the jittered mount puts it: height above the road
        T = np.array(im["camera"]["T_world_to_camera"])
        centre = -T[:3, :3].T @ T[:3, 3]
        assert centre[2] == pytest.approx(recipe.mount.height_m)
        seen = {a["vehicle_id"] for a in data["annotations"] if a["image_id"] == im["id"]}
        assert seen <= {v.vehicle_id for v in recipe.vehicles}
        # the cut-in vehicle (10-20 m ahead) is seen
        assert any(v.vehicle_id in seen for v in recipe.vehicles if 10 <= v.ahead_m <= 20)
    with pytest.raises(FileExistsError):
        render_scenes(sc, "cut_in", [0], tmp_path / "cut", progress=False)


@pytest.mark.slow
def test_workers_render_the_same_folder_as_one_process(tmp_path):
    """render-scenes in two processes (two chunks of consecutive seeds, merged in seed order) writes
    the folder one process writes: the same images and byte-identical annotations."""
    from scenario_files import SCENARIOS
    from vcfusion.detection.scenes import _chunks, render_scenes
    from vcfusion.scenario import load_scenario

    sc = load_scenario(SCENARIOS / "overlap.yaml")
    seeds = list(range(3, 15))
    assert len(_chunks(seeds, 2)) == 2
    for workers in (1, 2):
        render_scenes(sc, "truck_occlusion", seeds, tmp_path / f"w{workers}", progress=False, workers=workers)
    one, two = tmp_path / "w1", tmp_path / "w2"
    assert (one / "annotations.json").read_bytes() == (two / "annotations.json").read_bytes()
    data = json.loads((one / "annotations.json").read_text())
    assert [im["seed"] for im in data["images"]] == seeds and len(data["annotations"]) > len(seeds)
    for kind in ("rgb", "depth", "instances"):
        names = sorted(p.name for p in (one / kind).iterdir())
        assert names == sorted(p.name for p in (two / kind).iterdir()) and len(names) == len(seeds)
        assert all((one / kind / n).read_bytes() == (two / kind / n).read_bytes() for n in names)


def test_unknown_family_is_refused():
    with pytest.raises(ValueError, match="family: expected one of train, jam"):
        sample_scene("rain", 0)
    assert FAMILIES[0] == "train"


def test_render_scenes_refuses_a_road_it_cannot_place_scenes_on(tmp_path):
    from scenario_files import write_scenario
    from vcfusion.detection.scenes import render_scenes
    from vcfusion.errors import InputError
    from vcfusion.scenario import load_scenario

    path = write_scenario(tmp_path, "name: c\nnetwork: NET_DIR/curved.net.xml\nvehicle_types: NET_DIR/vtypes.add.xml\n"
                                    "ego: {lane: 1, depart_pos_m: 50, speed_mps: 19}\n")
    with pytest.raises(InputError, match="network: procedural scenes need a straight road"):
        render_scenes(load_scenario(path), "train", [0], tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_render_scenes_works_from_any_folder_with_its_default_scenario(tmp_path):
    """The default --scenario is the shipped scenarios/overlap.yaml, not a path under the working
    directory (from another folder it was 'scenario file not found')."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "vcfusion", "render-scenes", "--family", "jam", "--seeds", "0-0",
                           "--out", "scenes"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "scenes" / "annotations.json").read_text())["images"][0]["family"] == "jam"
