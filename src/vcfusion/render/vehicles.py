"""Vehicle models generated in code (trimesh, no OpenGL): saloon, hatchback, SUV, van; rigid truck, semi-trailer.

Every model is in the vehicle frame (origin at the footprint centre on the ground, x forward, y
left, z up) and its bounding box is exactly the SUMO vehicle's length x width x height (tested to
1 cm), so a vehicle is placed with its VehicleStates pose alone.

Car bodies are *lofted*: a cross-section ring (sill, rounded lower corners, shoulder, tumblehome
greenhouse, roof) is swept along x through stations whose heights and widths follow the shape's
side profile (bumper, sloped hood, windscreen, roof, rear window, boot), with wheel arches cut
by raising the underside around the axles. Faces between stations get paint or glass by where
they lie (windscreen, side windows between the pillars, rear window), so the shader's specular
paint and sky-reflecting glass apply. Tyres, rims, lamps, number plates, mirrors and a grille
are separate closed parts; the whole model is closed (watertight once coincident vertices are
merged, tested).

Each model also carries a *contact shadow*: a footprint box that the vertex shader flattens onto
the ground along the sun direction (a planar projected shadow), drawn just above the road paint
with instance code 0. So a shadow follows any heading at no extra pass, and never counts as
vehicle pixels.

Materials travel in the face colour's alpha byte (see :mod:`vcfusion.render.materials`).
"""

from __future__ import annotations

import zlib

import numpy as np
import trimesh

from vcfusion.render.materials import GLASS, LAMP, MATTE, METAL, PAINT, SHADOW, coloured

TYRE = (24, 24, 26)
RIM = (170, 172, 178)
HUB = (60, 62, 66)
TRIM = (28, 28, 30)  # black plastic: bumpers, pillars' trim, grille, mirror arms
GLASS_TINT = (26, 32, 40)
TAIL_LIGHT = (190, 18, 16)
HEAD_LIGHT = (235, 235, 225)
INDICATOR = (230, 130, 20)
PLATE = (236, 236, 228)
PLATE_TEXT = (30, 30, 34)
CHASSIS = (38, 38, 42)
FRAME = (120, 122, 128)  # box bodies' rear door frame

# Car paints seen on European roads (silver, grey, black, white dominate), as a stable function of the id.
BODY_COLOURS = (
    (190, 192, 196), (120, 124, 130), (22, 22, 26), (235, 235, 235), (40, 60, 120), (150, 20, 24),
    (200, 200, 205), (70, 72, 78), (245, 245, 242), (30, 80, 60), (100, 30, 30), (180, 150, 110),
)
CAB_COLOURS = ((235, 235, 235), (200, 30, 30), (30, 70, 150), (245, 245, 245), (40, 40, 44), (230, 180, 30))
CARGO_COLOURS = ((236, 236, 236), (215, 212, 200), (60, 90, 140), (170, 40, 40), (200, 200, 205))

CAR_SHAPES = ("saloon", "hatchback", "suv", "van")
TRUCK_SHAPES = ("rigid", "semi")
TRUCK_CLASSES = ("truck", "trailer", "bus", "coach", "delivery")

SHADOW_Z = 0.03  # above the road paint (0.02): the shadow darkens markings too
PLATE_W, PLATE_H = 0.52, 0.11  # EU number plate


def stable_index(key: str, n: int) -> int:
    """Stable across runs and processes (unlike Python's hash)."""
    return zlib.crc32(key.encode()) % n


def _box(x0, x1, y0, y1, z0, z1, rgb, material=MATTE) -> trimesh.Trimesh:
    """An axis-aligned box between two corners given in any order (mirrored parts swap them)."""
    (x0, x1), (y0, y1), (z0, z1) = sorted((x0, x1)), sorted((y0, y1)), sorted((z0, z1))
    box = trimesh.creation.box(extents=(x1 - x0, y1 - y0, z1 - z0))
    box.apply_translation(((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2))
    return coloured(box, rgb, material)


def _disc(x, y, z, radius, thickness, rgb, material, sections=16) -> trimesh.Trimesh:
    """A cylinder with its axis along y (wheels, rims)."""
    cyl = trimesh.creation.cylinder(radius=radius, height=thickness, sections=sections)
    cyl.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    cyl.apply_translation((x, y, z))
    return coloured(cyl, rgb, material)


def wheel(x, y_outer, radius, width, side: float) -> list[trimesh.Trimesh]:
    """Tyre whose outer face is at |y| = y_outer, a metal rim and a dark hub on that face."""
    yc = side * (y_outer - width / 2)
    return [
        _disc(x, yc, radius, radius, width, TYRE, MATTE, 12),
        _disc(x, side * (y_outer - 0.012), radius, 0.64 * radius, 0.03, RIM, METAL, 10),
        _disc(x, side * (y_outer - 0.004), radius, 0.22 * radius, 0.014, HUB, MATTE, 8),
    ]


def contact_shadow(length, width, height) -> trimesh.Trimesh:
    """A closed box over the footprint, 0.8 x the height, of the SHADOW material.

    The vertex shader projects it along the sun onto the plane SHADOW_Z above the vehicle's
    ground (a planar projected shadow): what is drawn is the shadow of that box, for any heading.
    """
    return _box(-length / 2 + 0.15, length / 2 - 0.15, -width / 2 + 0.03, width / 2 - 0.03, SHADOW_Z, 0.8 * height,
                (0, 0, 0), SHADOW)


# -- cars ---------------------------------------------------------------------------------------------

# Side profiles, u = x / length from the rear (-0.5) to the front (+0.5), heights / vehicle height.
# top: roof / bonnet / boot centreline; zones: (u0, u1) of the rear window, roof and windscreen;
# side: (u0, u1) of the side glass; pillars: u of the B (and C) pillars between side windows.
PROFILES = {
    "saloon": dict(
        top=[(-0.5, 0.50), (-0.485, 0.61), (-0.45, 0.65), (-0.30, 0.67), (-0.13, 0.97), (-0.09, 1.0),
             (0.06, 1.0), (0.10, 0.975), (0.27, 0.66), (0.42, 0.60), (0.48, 0.56), (0.5, 0.47)],
        belt=0.60, bottom=0.12, rear_window=(-0.30, -0.10), roof=(-0.10, 0.09), windscreen=(0.09, 0.27),
        side=(-0.215, 0.215), pillars=(0.0,), lamp_z=(0.52, 0.60), tumble=0.80),
    "hatchback": dict(
        top=[(-0.5, 0.56), (-0.49, 0.82), (-0.47, 0.95), (-0.43, 1.0), (0.03, 1.0), (0.08, 0.975),
             (0.27, 0.64), (0.43, 0.58), (0.48, 0.55), (0.5, 0.47)],
        belt=0.60, bottom=0.12, rear_window=(-0.5, -0.43), roof=(-0.43, 0.07), windscreen=(0.07, 0.27),
        side=(-0.40, 0.215), pillars=(-0.05, -0.30), lamp_z=(0.58, 0.68), tumble=0.80),
    "suv": dict(
        top=[(-0.5, 0.58), (-0.49, 0.86), (-0.47, 0.97), (-0.44, 1.0), (0.11, 1.0), (0.15, 0.975),
             (0.30, 0.71), (0.44, 0.66), (0.48, 0.63), (0.5, 0.55)],
        belt=0.64, bottom=0.15, rear_window=(-0.5, -0.44), roof=(-0.44, 0.14), windscreen=(0.14, 0.30),
        side=(-0.41, 0.25), pillars=(-0.04, -0.28), lamp_z=(0.60, 0.70), tumble=0.84),
    "van": dict(
        top=[(-0.5, 0.60), (-0.495, 0.93), (-0.48, 1.0), (0.20, 1.0), (0.25, 0.96), (0.40, 0.70),
             (0.46, 0.64), (0.49, 0.60), (0.5, 0.52)],
        belt=0.58, bottom=0.13, rear_window=(-0.5, -0.45), roof=(-0.45, 0.24), windscreen=(0.24, 0.41),
        side=(-0.44, 0.36), pillars=(0.12, -0.17), lamp_z=(0.50, 0.66), tumble=0.88),
}

# Ring segments, bottom centre -> +y side -> roof centre (then mirrored): what each segment is.
_SEG = ("under", "under", "lower", "lower", "lower", "sill", "window", "edge", "roof", "roof")


def _ring(zb, zbelt, ztop, wb, wg, wt, rb, rr) -> np.ndarray:
    """Cross-section (y, z) points of one station, closed; P = 20 points, same order every station."""
    zside = zbelt - 0.3 * (zbelt - zb - rb)
    half = [
        (0.0, zb), (wb - rb, zb), (wb - 0.3 * rb, zb + 0.3 * rb), (wb, zb + rb), (wb, zside),
        (0.985 * wb, zbelt), (wg, zbelt + 0.25 * rr), (wt, ztop - rr), (wt - 0.6 * rr, ztop - 0.22 * rr),
        (0.5 * wt, ztop - 0.02 * rr), (0.0, ztop),
    ]
    half = np.array(half)
    other = half[1:-1][::-1] * [-1.0, 1.0]
    return np.vstack([half, other])  # 11 + 9 = 20


def _loft(xs: np.ndarray, rings: np.ndarray) -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray]:
    """Closed mesh through rings (S, P, 2) at stations xs; returns (mesh, station index, segment index) per face."""
    S, P, _ = rings.shape
    verts = np.column_stack([np.repeat(xs, P), rings[:, :, 0].ravel(), rings[:, :, 1].ravel()])
    i, j = np.meshgrid(np.arange(S - 1), np.arange(P), indexing="ij")
    i, j = i.ravel(), j.ravel()
    a, b = i * P + j, i * P + (j + 1) % P
    c, d = (i + 1) * P + (j + 1) % P, (i + 1) * P + j
    faces = np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    station = np.r_[i, i]
    seg = np.r_[j, j]
    # End caps: fans around each end ring's centroid.
    caps, cap_station = [], []
    for k, end in ((0, 0), (S - 1, S - 2)):
        centre = len(verts)
        verts = np.vstack([verts, [xs[k], *rings[k].mean(axis=0)]])
        ring = k * P + np.arange(P)
        nxt = np.roll(ring, -1)
        # The two ends face opposite ways: opposite fan windings.
        caps.append(np.column_stack([np.full(P, centre), nxt, ring] if k == 0 else [np.full(P, centre), ring, nxt]))
        cap_station.append(np.full(P, -1 if k == 0 else S - 1))
    faces = np.vstack([faces, *caps])
    station = np.r_[station, *cap_station]
    seg = np.r_[seg, np.full(2 * P, -1)]
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if mesh.volume < 0:
        mesh.invert()
    return mesh, station, seg


def _stations(L: float, axles: list[float], arch_r: float) -> np.ndarray:
    xs = list(np.linspace(-L / 2, L / 2, 21))
    for xa in axles:
        xs += list(xa + arch_r * np.array([-1.02, -0.98, -0.6, 0.0, 0.6, 0.98, 1.02]))
    return np.unique(np.clip(np.round(xs, 5), -L / 2, L / 2))


def car_mesh(shape: str, length: float, width: float, height: float, paint) -> trimesh.Trimesh:
    """A passenger car of one of CAR_SHAPES, exactly length x width x height."""
    p = PROFILES[shape]
    L, W, H = length, width, height
    r = min(0.33, 0.205 * H)  # tyre radius
    tyre_w = min(0.22, 0.12 * W)
    mirror_out = 0.075
    wb_max = W / 2 - mirror_out  # body half-width; the mirrors reach W / 2
    front_axle, rear_axle = L / 2 - 0.19 * L, -L / 2 + 0.21 * L
    arch_r = 1.18 * r
    xs = _stations(L - 0.03, [front_axle, rear_axle], arch_r)  # body 1.5 cm short of each end: lamps, plates
    u = xs / L
    top = np.interp(u, *zip(*p["top"])) * H
    belt = np.minimum(p["belt"] * H, top - 0.05 * H)
    bottom = np.full_like(u, p["bottom"] * H)
    bottom += np.clip((np.abs(u) - 0.40) / 0.1, 0, 1) * 0.10 * H  # bumpers higher than the sills
    for xa in (front_axle, rear_axle):
        dx = np.abs(xs - xa)
        inside = dx < arch_r
        bottom[inside] = np.maximum(bottom[inside], r + np.sqrt(arch_r ** 2 - dx[inside] ** 2) * 0.92)
    # Plan view: corners rounded at both ends.
    end = np.clip((np.abs(u) - 0.40) / 0.10, 0, 1)
    wb = wb_max * (1 - 0.12 * end ** 2)
    greenhouse = np.clip((top - belt - 0.05 * H) / (0.3 * H), 0, 1)  # 0 on bonnet and boot, 1 under the roof
    wt = wb * (1 - (1 - p["tumble"]) * greenhouse) - 0.02
    wg = wb * (1 - 0.04 * greenhouse) - 0.01
    rb = np.minimum(0.06 * H, 0.45 * (belt - bottom))
    rr = np.minimum(0.05 * H, 0.45 * (top - belt))
    rings = np.stack([_ring(*args) for args in zip(bottom, belt, top, wb, wg, wt, rb, rr)])
    body, station, seg = _loft(xs, rings)

    # Materials per face from where it lies.
    u_face = np.where(station >= 0, (u[np.clip(station, 0, len(u) - 1)] + u[np.clip(station + 1, 0, len(u) - 1)]) / 2,
                      -0.5)
    u_face[station == len(u) - 1] = 0.5
    half_seg = np.where(seg >= 10, 19 - seg, seg)  # mirror index onto the +y half
    name = np.array([_SEG[k] if k >= 0 else "cap" for k in np.clip(half_seg, -1, 9)])
    name[seg < 0] = "cap"
    material = np.full(len(body.faces), PAINT)
    rgb = np.tile(np.asarray(paint, np.uint8), (len(body.faces), 1))

    def zone(lo_hi):
        return (u_face > lo_hi[0]) & (u_face < lo_hi[1])

    glass = np.zeros(len(body.faces), bool)
    glass |= zone(p["windscreen"]) & (name == "roof")
    glass |= zone(p["rear_window"]) & (name == "roof")
    side = zone(p["side"]) & (name == "window")
    for pu in p["pillars"]:
        side &= np.abs(u_face - pu) > 0.018
    glass |= side
    material[glass] = GLASS
    rgb[glass] = GLASS_TINT
    under = name == "under"
    rgb[under] = CHASSIS
    material[under] = MATTE
    body = coloured(body, rgb, material)

    parts = [body]
    for xa in (front_axle, rear_axle):
        for s in (1.0, -1.0):
            parts += wheel(xa, wb_max - 0.02, r, tyre_w, s)
    # Lamps, plates and bumpers reach the full length.
    lz0, lz1 = p["lamp_z"][0] * H, p["lamp_z"][1] * H
    xr, xf = -L / 2, L / 2
    for s in (1.0, -1.0):
        parts.append(_box(xr, xr + 0.3, s * 0.5 * wb_max, s * 0.95 * wb_max, lz0, lz1, TAIL_LIGHT, LAMP))
        parts.append(_box(xf - 0.3, xf, s * 0.58 * wb_max, s * 0.92 * wb_max, 0.50 * H, 0.56 * H, HEAD_LIGHT, LAMP))
        # Mirrors at the windscreen's foot, reaching the full width.
        xm = p["windscreen"][1] * L - 0.05
        zm = p["belt"] * H + 0.04
        parts.append(_box(xm - 0.12, xm, s * (wb_max - 0.1), s * W / 2, zm, zm + 0.13, paint, PAINT))
    plate_z = 0.27 * H
    parts.append(_box(xr, xr + 0.2, -PLATE_W / 2, PLATE_W / 2, plate_z, plate_z + PLATE_H, PLATE))
    parts.append(_box(xf - 0.2, xf, -PLATE_W / 2, PLATE_W / 2, 0.22 * H, 0.22 * H + PLATE_H, PLATE))
    parts.append(_box(xr + 0.005, xr + 0.2, -0.45 * wb_max, 0.45 * wb_max, 0.12 * H + 0.06, 0.19 * H + 0.04, TRIM))
    parts.append(_box(xf - 0.2, xf - 0.005, -0.5 * wb_max, 0.5 * wb_max, 0.36 * H, 0.47 * H, TRIM))  # grille
    parts.append(contact_shadow(L, W, H))
    return trimesh.util.concatenate(parts)


# -- trucks ----------------------------------------------------------------------------------------------


def _rounded_block(x0, x1, half_w, z0, z1, rgb, material, bevel=0.06) -> trimesh.Trimesh:
    """A box with bevelled vertical and top edges (convex hull of three inset boxes)."""
    pts = []
    for dx, dy, dz in ((0, bevel, bevel), (bevel, 0, bevel), (bevel, bevel, 0)):
        for x in (x0 + dx, x1 - dx):
            for y in (-half_w + dy, half_w - dy):
                for z in (z0, z1 - dz):
                    pts.append((x, y, z))
    return coloured(trimesh.convex.convex_hull(np.array(pts)), rgb, material)


def truck_mesh(shape: str, length: float, width: float, height: float, cab_rgb, cargo_rgb) -> trimesh.Trimesh:
    """Rigid lorry (cab + box body) or tractor + box semi-trailer, exactly length x width x height."""
    L, W, H = length, width, height
    r = min(0.52, 0.145 * H)
    hw = W / 2 - 0.06  # the mirrors reach W / 2
    cab_len = min(2.3, 0.25 * L)
    cab_top = min(H - 0.05, max(2.6, 0.85 * H))
    xf, xr = L / 2, -L / 2
    x_cab = xf - cab_len
    floor = 2.0 * r  # the cargo floor: below vcfusion.render.check.BODY_POINT_HEIGHT x height, with margin
    parts = []
    # Cab: body-coloured block, large windscreen, side windows, grille, bumper, lamps, mirrors.
    parts.append(_rounded_block(x_cab, xf - 0.03, hw, 0.55 * r + 0.25, cab_top, cab_rgb, PAINT, 0.12))
    parts.append(_box(xf - 0.06, xf - 0.01, -0.44 * W, 0.44 * W, 0.58 * cab_top, 0.9 * cab_top, GLASS_TINT, GLASS))
    for s in (1.0, -1.0):
        parts.append(_box(xf - 1.0, xf - 0.25, s * (hw - 0.02), s * (hw + 0.005), 0.6 * cab_top, 0.88 * cab_top,
                          GLASS_TINT, GLASS))
        parts.append(_box(xf - 0.35, xf - 0.02, s * (hw - 0.01), s * W / 2, 0.55 * cab_top, 0.72 * cab_top, TRIM))
        parts.append(_box(xf - 0.1, xf, s * 0.32 * W, s * 0.44 * W, 1.05 * r, 1.05 * r + 0.2, HEAD_LIGHT, LAMP))
    parts.append(_box(xf - 0.1, xf - 0.005, -0.3 * W, 0.3 * W, 1.3 * r, 0.5 * cab_top, TRIM))  # grille
    parts.append(_box(xf - 0.15, xf, -hw, hw, 0.45 * r, 1.0 * r, TRIM))  # bumper
    parts.append(_box(xf - 0.1, xf, -PLATE_W / 2, PLATE_W / 2, 0.55 * r, 0.55 * r + PLATE_H, PLATE))
    # Cargo: a box body (rigid) or a semi-trailer with a gap behind the cab.
    gap = 0.25 if shape == "rigid" else 0.6
    box_front = x_cab - gap
    # The box's rear face is 3 cm in: the door frame, bars and markings stand proud of it (no z-fighting).
    parts.append(_rounded_block(xr + 0.03, box_front, W / 2 - 0.065, floor, H, cargo_rgb, MATTE, 0.05))
    parts.append(_box(xr + 0.3, box_front, -0.4 * W, 0.4 * W, 0.9 * r, floor, CHASSIS))  # chassis rails
    # Rear doors: two leaves with a seam, hinges and lock bars (thin trim), a rear underrun bar and lamps.
    parts.append(_box(xr, xr + 0.03, -0.025, 0.025, floor + 0.05, H - 0.08, TRIM))
    for y in (-0.36 * W, -0.12 * W, 0.12 * W, 0.36 * W):
        parts.append(_box(xr, xr + 0.03, y - 0.035, y + 0.035, floor + 0.15, H - 0.15, (90, 92, 96), METAL))
    parts.append(_box(xr, xr + 0.15, -0.45 * W, 0.45 * W, 0.5 * r, 0.5 * r + 0.12, TRIM))  # underrun bar
    # Rear door frame (grey metal) and the red retro-reflective contour marking around the rear outline.
    hb = W / 2 - 0.065
    for y0, y1, z0, z1 in ((-hb, -hb + 0.1, floor, H), (hb - 0.1, hb, floor, H), (-hb, hb, H - 0.1, H),
                           (-hb, hb, floor, floor + 0.12)):
        parts.append(_box(xr + 0.005, xr + 0.045, y0, y1, z0, z1, FRAME, METAL))
    for y0, y1, z0, z1 in ((-hb + 0.01, -hb + 0.09, floor + 0.15, H - 0.15), (hb - 0.09, hb - 0.01, floor + 0.15, H - 0.15),
                           (-hb + 0.01, hb - 0.01, H - 0.09, H - 0.01), (-hb + 0.01, hb - 0.01, floor + 0.02, floor + 0.1)):
        parts.append(_box(xr, xr + 0.04, y0, y1, z0, z1, TAIL_LIGHT, LAMP))
    for s in (1.0, -1.0):  # mudflaps behind the last axle
        parts.append(_box(xr + 0.5, xr + 0.53, s * (W / 2 - 0.08), s * (W / 2 - 0.75), 0.12, 2 * r + 0.05, TRIM))
    for s in (1.0, -1.0):
        parts.append(_box(xr, xr + 0.12, s * 0.28 * W, s * 0.44 * W, 0.5 * r + 0.14, 0.5 * r + 0.3, TAIL_LIGHT, LAMP))
        parts.append(_box(xr, xr + 0.12, s * 0.2 * W, s * 0.27 * W, 0.5 * r + 0.14, 0.5 * r + 0.3, INDICATOR, LAMP))
    parts.append(_box(xr, xr + 0.16, -PLATE_W / 2, PLATE_W / 2, 0.5 * r - 0.13, 0.5 * r - 0.13 + PLATE_H, PLATE))
    # Wheels: steer axle under the cab, two (rigid) or three (semi) axles at the back, twin tyres.
    axles = [xf - 0.55 * cab_len]
    rear = [xr + 2.2, xr + 3.5] if shape == "rigid" else [x_cab - 0.9, xr + 1.6, xr + 2.9, xr + 4.2]
    # a short truck (a user's vtype under ~5 m) has room for fewer axles: one that would put its wheel
    # beyond the body made the model longer than the vehicle
    axles += [xa for xa in rear if xr + r <= xa <= xf - r and abs(xa - axles[0]) >= 2 * r + 0.05]
    tw = 0.3
    for k, xa in enumerate(axles):
        for s in (1.0, -1.0):
            parts += wheel(xa, W / 2 - 0.07, r, tw, s)
            if k > 0:
                parts.append(_disc(xa, s * (W / 2 - 0.07 - tw - 0.02 - tw / 2), r, r, tw, TYRE, MATTE, 12))
    parts.append(contact_shadow(L, W, H))
    return trimesh.util.concatenate(parts)


# -- choice ------------------------------------------------------------------------------------------------


def vehicle_style(vehicle_id: str, vclass: str, length: float, width: float, height: float) -> tuple:
    """Shape and colours of a vehicle (a stable function of its id); vehicles with the same style share one mesh."""
    dims = (round(float(length), 3), round(float(width), 3), round(float(height), 3))
    if vclass in TRUCK_CLASSES:
        return (TRUCK_SHAPES[stable_index(vehicle_id + "/shape", len(TRUCK_SHAPES))], *dims,
                stable_index(vehicle_id, len(CAB_COLOURS)), stable_index(vehicle_id + "/cargo", len(CARGO_COLOURS)))
    return (CAR_SHAPES[stable_index(vehicle_id + "/shape", len(CAR_SHAPES))], *dims,
            stable_index(vehicle_id, len(BODY_COLOURS)))


def vehicle_mesh(style: tuple) -> trimesh.Trimesh:
    shape, length, width, height = style[:4]
    if shape in TRUCK_SHAPES:
        return truck_mesh(shape, length, width, height, CAB_COLOURS[style[4]], CARGO_COLOURS[style[5]])
    return car_mesh(shape, length, width, height, BODY_COLOURS[style[4]])
