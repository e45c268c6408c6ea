"""Trimesh models of the highway and its surroundings (no OpenGL here); vehicles are in
:mod:`vcfusion.render.vehicles`.

The road follows :class:`vcfusion.traffic.network.Road` (lane 0 rightmost): asphalt over the
lanes with slightly darker wheel tracks (the shader adds grain and patches), paved shoulders, a
solid edge line on both sides (0.30 m on the right, 0.15 m on the left), 0.15 m dashes between
lanes (6 m dash, 12 m gap, as on German motorways), guard rails (posts every 4 m and a beam)
beyond the shoulders, reflector posts every 50 m, trees and bushes on the verges, and a grass
ground plane. Every part carries face colours and a material (the colour's alpha byte, see
:mod:`vcfusion.render.materials`).
"""

from __future__ import annotations

import zlib

import numpy as np
import trimesh

from vcfusion.render.materials import ASPHALT, FOLIAGE, GRASS, MATTE, METAL, PAINT_MARK, coloured
from vcfusion.traffic.network import Road

# RGB 0-255.
ASPHALT_RGB = (72, 74, 78)
TRACK_RGB = (64, 66, 70)  # wheel tracks: polished darker
SHOULDER_RGB = (92, 93, 96)
MARKING_RGB = (232, 232, 225)
GRASS_RGB = (84, 116, 60)
RAIL_RGB = (175, 180, 185)
POST_RGB = (110, 112, 116)
DELINEATOR_RGB = (236, 236, 232)
BARK_RGB = (80, 62, 46)
LEAF_RGBS = ((56, 92, 44), (70, 104, 48), (48, 80, 40), (86, 110, 52))
SKY = (0.62, 0.76, 0.92)  # the sky colour about 25 degrees above the horizon (0-1); see vcfusion.render.sky

MARK_Z = 0.02  # paint above the asphalt, against z-fighting
DASH_M, GAP_M = 6.0, 12.0
LINE_W = 0.15
SHOULDER_M = 2.5
RAIL_OFFSET_M = 0.6  # guard rail beyond the shoulder
POST_SPACING_M = 4.0
DELINEATOR_SPACING_M = 50.0
TREE_SPACING_M = 40.0  # one candidate tree site per side every this many metres


def _unit(key: str) -> float:
    """A stable pseudo-random number in [0, 1) for a key."""
    return zlib.crc32(key.encode()) / 2**32


def _box(x0, x1, y0, y1, z0, z1, rgb, material=MATTE) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(x1 - x0, y1 - y0, z1 - z0))
    box.apply_translation(((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2))
    return coloured(box, rgb, material)


def _strip(road: Road, s0: float, s1: float, d0: float, d1: float, z: float, rgb, material=MATTE) -> trimesh.Trimesh:
    """A flat quad on the road frame (s along, d left of the right edge)."""
    xs, ys = road.to_world(np.array([s0, s1, s1, s0]), np.array([d0, d0, d1, d1]))
    verts = np.column_stack([xs, ys, np.full(4, z)])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    # Face normals must point up whatever the road's direction.
    if np.cross(verts[1] - verts[0], verts[2] - verts[0])[2] < 0:
        faces = faces[:, ::-1]
    return coloured(trimesh.Trimesh(verts, faces, process=False), rgb, material)


def _road_box(road: Road, s0, s1, d0, d1, z0, z1, rgb, material=MATTE) -> trimesh.Trimesh:
    return _to_road(road, _box(s0, s1, d0, d1, z0, z1, rgb, material))


def _to_road(road: Road, box: trimesh.Trimesh) -> trimesh.Trimesh:
    """A mesh modelled in the road frame (x = s, y = d) placed in the world."""
    # Road frame -> world: rotate by the road heading about the right road edge's start.
    x0, y0 = road.to_world(0.0, 0.0)
    h = road.heading_rad
    T = np.eye(4)
    T[:2, :2] = [[np.cos(h), -np.sin(h)], [np.sin(h), np.cos(h)]]
    T[:2, 3] = [float(x0), float(y0)]
    # d is to the left (+y of the road frame) so a plain rotation maps (s, d - 0) correctly.
    box.apply_transform(T)
    return box


def ground_mesh(road: Road, margin_m: float = 600.0) -> trimesh.Trimesh:
    """Grass around the road (slightly below it), far enough to meet the horizon haze."""
    return _strip(road, -margin_m, road.length_m + margin_m, -margin_m, road.width_m + margin_m, -0.05, GRASS_RGB, GRASS)


def road_extent(road: Road, margin_m: float = 150.0) -> tuple[float, float]:
    """Range of s covered by the modelled road (beyond the network's ends, so the road never ends in view)."""
    return -margin_m, road.length_m + margin_m


def _tree(s: float, d: float, size: float, leaf_rgb) -> trimesh.Trimesh:
    """A low-poly deciduous tree or bush in the road frame (a trunk and a crown of two blobs)."""
    parts = []
    trunk_h = 0.35 * size
    if size > 2.5:
        trunk = trimesh.creation.cylinder(radius=0.04 * size, height=trunk_h, sections=6)
        trunk.apply_translation((s, d, trunk_h / 2))
        parts.append(coloured(trunk, BARK_RGB, MATTE))
    for dx, dz, rad in ((0.0, 0.62, 0.36), (0.12, 0.8, 0.26)):
        blob = trimesh.creation.icosphere(subdivisions=1, radius=rad * size)
        blob.apply_scale((1.0, 1.0, 0.85))
        blob.apply_translation((s + dx * size, d, dz * size if size > 2.5 else 0.5 * dz * size))
        parts.append(coloured(blob, leaf_rgb, FOLIAGE))
    return trimesh.util.concatenate(parts)


def roadside_mesh(road: Road, s0: float, s1: float) -> list[trimesh.Trimesh]:
    """Reflector posts and trees between s0 and s1, on a global grid (pieces join seamlessly)."""
    parts = []
    Wr = road.width_m
    for side, d_post in ((-1.0, -SHOULDER_M - RAIL_OFFSET_M - 0.35), (1.0, Wr + SHOULDER_M + RAIL_OFFSET_M + 0.35)):
        for s in np.arange(np.ceil(s0 / DELINEATOR_SPACING_M) * DELINEATOR_SPACING_M, s1, DELINEATOR_SPACING_M):
            parts.append(_road_box(road, s - 0.06, s + 0.06, d_post - 0.06, d_post + 0.06, 0.0, 1.0, DELINEATOR_RGB))
            parts.append(_road_box(road, s - 0.065, s + 0.065, d_post - 0.065, d_post + 0.065, 0.75, 0.92, (20, 20, 20)))
        for k in range(int(np.ceil(s0 / TREE_SPACING_M)), int(np.ceil(s1 / TREE_SPACING_M))):
            key = f"{k}/{side}"
            if _unit(key + "/skip") < 0.25:
                continue
            s = k * TREE_SPACING_M + TREE_SPACING_M * 0.8 * _unit(key + "/s")
            if not s0 <= s < s1:
                continue
            edge = 0.0 if side < 0 else Wr
            d = edge + side * (SHOULDER_M + 6.0 + 25.0 * _unit(key + "/d"))
            size = 2.0 + 8.0 * _unit(key + "/size")
            leaf = LEAF_RGBS[int(4 * _unit(key + "/leaf"))]
            parts.append(_to_road(road, _tree(s, d, size, leaf)))
    return parts


def road_mesh(road: Road, s0: float, s1: float) -> trimesh.Trimesh:
    """The road between s0 and s1: asphalt, shoulders, markings, guard rails, roadside objects (one mesh)."""
    Wr, lw = road.width_m, road.lane_width_m
    parts = [
        _strip(road, s0, s1, -SHOULDER_M, 0.0, 0.0, SHOULDER_RGB, ASPHALT),
        _strip(road, s0, s1, Wr, Wr + SHOULDER_M, 0.0, SHOULDER_RGB, ASPHALT),
        _strip(road, s0, s1, 0.05, 0.05 + 2 * LINE_W, MARK_Z, MARKING_RGB, PAINT_MARK),  # right edge line (wide)
        _strip(road, s0, s1, Wr - 0.05 - LINE_W, Wr - 0.05, MARK_Z, MARKING_RGB, PAINT_MARK),  # left edge line
    ]
    # Each lane: darker wheel tracks (0.6 m wide, centred 1.2 m either side of the lane centre).
    for lane in range(road.num_lanes):
        d0 = lane * lw
        cuts = [d0, d0 + 0.3, d0 + 0.9, d0 + lw / 2 - 0.45, d0 + lw / 2 + 0.45, d0 + lw - 0.9, d0 + lw - 0.3, d0 + lw]
        for k in range(len(cuts) - 1):
            rgb = TRACK_RGB if k in (1, 5) else ASPHALT_RGB
            parts.append(_strip(road, s0, s1, cuts[k], cuts[k + 1], 0.0, rgb, ASPHALT))
    # Dashes and posts are laid on a global grid so adjacent pieces join seamlessly.
    period = DASH_M + GAP_M
    for lane in range(1, road.num_lanes):
        d = lane * lw
        for s in np.arange(np.ceil(s0 / period) * period, s1, period):
            parts.append(_strip(road, s, min(s + DASH_M, s1), d - LINE_W / 2, d + LINE_W / 2, MARK_Z, MARKING_RGB,
                                PAINT_MARK))
    for d_rail, side in ((-SHOULDER_M - RAIL_OFFSET_M, -1.0), (Wr + SHOULDER_M + RAIL_OFFSET_M, 1.0)):
        # Beam facing the road, posts behind it.
        parts.append(_road_box(road, s0, s1, d_rail - 0.05, d_rail + 0.05, 0.45, 0.78, RAIL_RGB, METAL))
        for s in np.arange(np.ceil(s0 / POST_SPACING_M) * POST_SPACING_M, s1, POST_SPACING_M):
            dp = d_rail + side * 0.12
            parts.append(_road_box(road, s - 0.06, s + 0.06, dp - 0.06, dp + 0.06, 0.0, 0.72, POST_RGB))
    parts += roadside_mesh(road, s0, s1)
    return trimesh.util.concatenate(parts)
