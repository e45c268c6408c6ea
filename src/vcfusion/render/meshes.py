"""Low-poly trimesh models of the highway and its vehicles (no OpenGL here).

Vehicle meshes are in the vehicle frame: origin at the footprint centre on the ground, x forward,
y left, z up, spanning exactly length x width x height, so a vehicle is placed with its
VehicleStates pose (footprint centre, yaw) alone. Every part carries face colours; the renderer
draws flat-shaded faces.

The road follows :class:`vcfusion.traffic.network.Road` (lane 0 rightmost): asphalt over the
lanes, paved shoulders, a solid edge line on both sides, dashed lines between lanes (6 m dash,
12 m gap, as on German motorways), guard rails (posts every 4 m and a beam) beyond the shoulders,
and a grass ground plane.
"""

from __future__ import annotations

import zlib

import numpy as np
import trimesh

from vcfusion.traffic.network import Road

# RGBA 0-255.
ASPHALT = (72, 74, 78, 255)
SHOULDER = (96, 97, 100, 255)
MARKING = (235, 235, 228, 255)
GRASS = (86, 122, 62, 255)
RAIL = (182, 186, 190, 255)
POST = (120, 122, 126, 255)
GLASS = (38, 48, 62, 255)
TYRE = (22, 22, 24, 255)
RIM = (150, 150, 155, 255)
TAIL_LIGHT = (200, 20, 20, 255)
HEAD_LIGHT = (245, 240, 215, 255)
CHASSIS = (40, 40, 44, 255)
SKY = (0.62, 0.76, 0.92)  # background colour (0-1), used by the renderer

# Distinct body colours; a vehicle's colour is a stable function of its id.
BODY_COLOURS = (
    (200, 30, 35), (30, 70, 170), (200, 200, 205), (245, 245, 245), (30, 30, 34),
    (235, 185, 20), (25, 120, 60), (230, 110, 20), (110, 30, 120), (20, 150, 170),
    (120, 20, 25), (90, 95, 100),
)
CARGO_COLOURS = ((235, 235, 235), (210, 205, 190), (60, 90, 140), (170, 40, 40))

TRUCK_CLASSES = ("truck", "trailer", "bus", "coach", "delivery")

MARK_Z = 0.02  # paint above the asphalt, against z-fighting
DASH_M, GAP_M = 6.0, 12.0
LINE_W = 0.15
SHOULDER_M = 2.5
RAIL_OFFSET_M = 0.6  # guard rail beyond the shoulder
POST_SPACING_M = 4.0


def colour_index(vehicle_id: str, n: int) -> int:
    """Stable across runs and processes (unlike Python's hash)."""
    return zlib.crc32(vehicle_id.encode()) % n


def _coloured(mesh: trimesh.Trimesh, rgba) -> trimesh.Trimesh:
    mesh.visual.face_colors = np.tile(np.asarray(rgba, dtype=np.uint8), (len(mesh.faces), 1))
    return mesh


def _box(x0, x1, y0, y1, z0, z1, rgba) -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(x1 - x0, y1 - y0, z1 - z0))
    box.apply_translation(((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2))
    return _coloured(box, rgba)


def _wheel(x, y, radius, width, rgba=TYRE) -> trimesh.Trimesh:
    tyre = trimesh.creation.cylinder(radius=radius, height=width, sections=12)
    tyre.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    tyre.apply_translation((x, y, radius))
    _coloured(tyre, rgba)
    # A rim disc slightly proud of the tyre's outer face makes the wheel read as a wheel.
    rim = trimesh.creation.cylinder(radius=radius * 0.55, height=0.02, sections=10)
    rim.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    rim.apply_translation((x, y + np.sign(y) * (width / 2 + 0.005), radius))
    return trimesh.util.concatenate([tyre, _coloured(rim, RIM)])


def _cabin(x_rear_low, x_front_low, x_rear_top, x_front_top, half_w_low, half_w_top, z0, z1,
           body_rgba) -> trimesh.Trimesh:
    """Greenhouse: a convex frustum; glass on the sides, body colour on the roof."""
    pts = np.array([
        [x_rear_low, -half_w_low, z0], [x_rear_low, half_w_low, z0],
        [x_front_low, -half_w_low, z0], [x_front_low, half_w_low, z0],
        [x_rear_top, -half_w_top, z1], [x_rear_top, half_w_top, z1],
        [x_front_top, -half_w_top, z1], [x_front_top, half_w_top, z1],
    ])
    hull = trimesh.convex.convex_hull(pts)
    colours = np.tile(np.asarray(GLASS, dtype=np.uint8), (len(hull.faces), 1))
    colours[hull.face_normals[:, 2] > 0.9] = body_rgba
    hull.visual.face_colors = colours
    return hull


def car_mesh(length: float, width: float, height: float, body_rgb) -> trimesh.Trimesh:
    """Passenger car: body, glass cabin with roof, four wheels, tail and head lights."""
    body = (*body_rgb, 255)
    L, W, H = length, width, height
    r = min(0.33, 0.22 * H)
    sill = 0.55 * r
    belt = 0.58 * H
    parts = [
        _box(-L / 2, L / 2, -W / 2, W / 2, sill, belt, body),
        _cabin(-0.36 * L, 0.22 * L, -0.28 * L, 0.02 * L, 0.47 * W, 0.40 * W, belt, H, body),
    ]
    axle = L / 2 - max(0.75, 0.18 * L)
    for x in (axle, -axle):
        for y in (W / 2 - 0.11, -(W / 2 - 0.11)):
            parts.append(_wheel(x, y, r, 0.22))
    lamp_z0, lamp_z1 = belt - 0.2, belt - 0.05
    for y in (W / 2 - 0.3, -(W / 2 - 0.3)):
        parts.append(_box(-L / 2 - 0.02, -L / 2 + 0.01, y - 0.2, y + 0.2, lamp_z0, lamp_z1, TAIL_LIGHT))
        parts.append(_box(L / 2 - 0.01, L / 2 + 0.02, y - 0.2, y + 0.2, lamp_z0, lamp_z1, HEAD_LIGHT))
    mesh = trimesh.util.concatenate(parts)
    return mesh


def truck_mesh(length: float, width: float, height: float, cab_rgb, cargo_rgb) -> trimesh.Trimesh:
    """Lorry: cab with windscreen in front, box body behind, chassis, three axles."""
    cab, cargo = (*cab_rgb, 255), (*cargo_rgb, 255)
    L, W, H = length, width, height
    r = min(0.5, 0.14 * H)
    cab_len = min(2.3, 0.3 * L)
    cab_top = min(H, max(2.2, 0.82 * H))
    x_cab = L / 2 - cab_len
    parts = [
        _box(-L / 2 + 0.3, x_cab, -0.42 * W, 0.42 * W, 0.8 * r, 2.0 * r, CHASSIS),
        _box(-L / 2, x_cab - 0.15, -W / 2, W / 2, 2.0 * r, H, cargo),
        _box(x_cab, L / 2, -W / 2, W / 2, 0.8 * r, cab_top, cab),
        # Windscreen and side windows of the cab (slightly proud of the cab's faces).
        _box(L / 2 - 0.01, L / 2 + 0.02, -0.45 * W, 0.45 * W, 0.62 * cab_top, 0.92 * cab_top, GLASS),
        _box(L / 2 - 0.9, L / 2 - 0.1, -W / 2 - 0.02, W / 2 + 0.02, 0.62 * cab_top, 0.92 * cab_top, GLASS),
    ]
    for x in (L / 2 - 0.6 * cab_len, -L / 2 + 2.6, -L / 2 + 1.4):
        for y in (W / 2 - 0.2, -(W / 2 - 0.2)):
            parts.append(_wheel(x, y, r, 0.35))
    for y in (W / 2 - 0.3, -(W / 2 - 0.3)):
        parts.append(_box(-L / 2 - 0.02, -L / 2 + 0.01, y - 0.2, y + 0.2, 1.3 * r, 1.3 * r + 0.15, TAIL_LIGHT))
        parts.append(_box(L / 2 - 0.01, L / 2 + 0.02, y - 0.25, y + 0.25, 1.2 * r, 1.2 * r + 0.18, HEAD_LIGHT))
    return trimesh.util.concatenate(parts)


def vehicle_style(vehicle_id: str, vclass: str, length: float, width: float, height: float) -> tuple:
    """Shape and colours of a vehicle; vehicles with the same style share one mesh."""
    dims = (round(float(length), 3), round(float(width), 3), round(float(height), 3))
    if vclass in TRUCK_CLASSES:
        return ("truck", *dims, colour_index(vehicle_id, len(BODY_COLOURS)),
                colour_index(vehicle_id + "/cargo", len(CARGO_COLOURS)))
    return ("car", *dims, colour_index(vehicle_id, len(BODY_COLOURS)))


def vehicle_mesh(style: tuple) -> trimesh.Trimesh:
    kind, length, width, height = style[:4]
    if kind == "truck":
        return truck_mesh(length, width, height, BODY_COLOURS[style[4]], CARGO_COLOURS[style[5]])
    return car_mesh(length, width, height, BODY_COLOURS[style[4]])


def _strip(road: Road, s0: float, s1: float, d0: float, d1: float, z: float, rgba) -> trimesh.Trimesh:
    """A flat quad on the road frame (s along, d left of the right edge)."""
    xs, ys = road.to_world(np.array([s0, s1, s1, s0]), np.array([d0, d0, d1, d1]))
    verts = np.column_stack([xs, ys, np.full(4, z)])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    # Face normals must point up whatever the road's direction.
    if np.cross(verts[1] - verts[0], verts[2] - verts[0])[2] < 0:
        faces = faces[:, ::-1]
    return _coloured(trimesh.Trimesh(verts, faces, process=False), rgba)


def _road_box(road: Road, s0, s1, d0, d1, z0, z1, rgba) -> trimesh.Trimesh:
    box = _box(s0, s1, d0, d1, z0, z1, rgba)
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
    return _strip(road, -margin_m, road.length_m + margin_m, -margin_m, road.width_m + margin_m, -0.05, GRASS)


def road_extent(road: Road, margin_m: float = 150.0) -> tuple[float, float]:
    """Range of s covered by the modelled road (beyond the network's ends, so the road never ends in view)."""
    return -margin_m, road.length_m + margin_m


def road_mesh(road: Road, s0: float, s1: float) -> trimesh.Trimesh:
    """The road between s0 and s1: asphalt, shoulders, markings, guard rails (one mesh)."""
    Wr = road.width_m
    parts = [
        _strip(road, s0, s1, 0.0, Wr, 0.0, ASPHALT),
        _strip(road, s0, s1, -SHOULDER_M, 0.0, 0.0, SHOULDER),
        _strip(road, s0, s1, Wr, Wr + SHOULDER_M, 0.0, SHOULDER),
        _strip(road, s0, s1, 0.05, 0.05 + 2 * LINE_W, MARK_Z, MARKING),  # right edge line (wide)
        _strip(road, s0, s1, Wr - 0.05 - LINE_W, Wr - 0.05, MARK_Z, MARKING),  # left edge line
    ]
    # Dashes and posts are laid on a global grid so adjacent pieces join seamlessly.
    period = DASH_M + GAP_M
    for lane in range(1, road.num_lanes):
        d = lane * road.lane_width_m
        for s in np.arange(np.ceil(s0 / period) * period, s1, period):
            parts.append(_strip(road, s, min(s + DASH_M, s1), d - LINE_W / 2, d + LINE_W / 2, MARK_Z, MARKING))
    for d_rail, side in ((-SHOULDER_M - RAIL_OFFSET_M, -1.0), (Wr + SHOULDER_M + RAIL_OFFSET_M, 1.0)):
        # Beam facing the road, posts behind it.
        parts.append(_road_box(road, s0, s1, d_rail - 0.05, d_rail + 0.05, 0.45, 0.78, RAIL))
        for s in np.arange(np.ceil(s0 / POST_SPACING_M) * POST_SPACING_M, s1, POST_SPACING_M):
            dp = d_rail + side * 0.12
            parts.append(_road_box(road, s - 0.06, s + 0.06, dp - 0.06, dp + 0.06, 0.0, 0.72, POST))
    return trimesh.util.concatenate(parts)
