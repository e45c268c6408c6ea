"""Which detected box belongs to which cloud twin.

Four matchers, from the paper's baseline to its future work:

- :func:`match_baseline` (RGB camera only, the paper's baseline): the boxes that contain the twin's
  anchor point (its GNSS point projected into the image, eq. 1-3); one -> that box; none -> no
  match. The paper picks the target box "if the anchor point is pinpointed exclusively in one
  detected bounding box"; when the anchor lies in several (Fig. 3) "the system cannot identify
  which one is the correct target vehicle". All an RGB-only pipeline can then go by is the
  detector's own output: the most confident of the candidates (what a YOLO-style list sorted by
  confidence yields first); with an exact tie (e.g. the oracle's scores, all 1.0) nothing singles
  one out and there is no match. No image geometry is used.
- :func:`match_baseline_centre` (RGB only, our stronger image-only heuristic, reported as
  ``baseline_centre``): several candidates -> the box whose centre is nearest the anchor. The paper
  does not use it; we keep it because on our renders it is hard to beat (the anchor is the body
  centre, which projects near the centre of its own box), so nothing is hidden.
- :func:`match_paper` (Algorithm 2, RGB + depth): the same candidates; one -> that box; several ->
  the box whose depth distance (Algorithm 1) differs least, in absolute value, from the distance
  the GNSS position gives (``D_g``); none -> no match (the paper is silent; we return ``None``).
  Candidates without a valid depth (``nan``) are skipped; if no candidate has one, the baseline
  rule decides. ``D_g`` (:func:`match_all_paper`, ``gnss_distance``) is by default the camera-Z of
  the face of the twin that the camera sees (its GNSS point moved half its reported length along
  its heading): Algorithm 1 samples the lower quarter of the box so that it measures "the
  backside of detected vehicles", in camera-Z (a depth image), so that is what it is compared
  with. Our GNSS point is the body centre (records.gnss_antenna_points); compared raw
  (``gnss_distance='range'``, Euclidean distance to the GNSS point) every depth looks half a
  vehicle length too near and, for a car right in front of a truck, the truck's box (whose lower
  quarter is the car's rear) wins. ``'range'`` and ``'z'`` (camera-Z of the GNSS point) remain.
  All take an optional ``fallback_radius_px`` (off by default): with no containing box, the box
  whose edge is nearest the anchor within that radius is taken.
- :class:`JointMatcher` (better): all twins in view are assigned to boxes at once (Hungarian,
  ``scipy.optimize.linear_sum_assignment``) on a cost built from
  (a) the overlap between the box and the twin's expected box (its 3-D cuboid from the cloud's
      position, heading, length, width, height, projected into the image), or the part of that
      box that nearer twins' expected boxes leave visible (:func:`visible_boxes`), whichever is
      larger: a box around the visible part of a partly hidden vehicle is its box,
  (b) the anchor-to-box distance (for an anchor hidden behind a nearer twin, the distance of the
      visible part's centre), and
  (c) the disagreement between the box's depth and the expected depth of the vehicle face the
      camera sees (GNSS point = body centre, records.gnss_antenna_points; the depth samples lie on the rear (or front) face,
      half a vehicle length nearer; with a noisy depth sensor, what the sensor reads there, in a
      sigma widened by the sensor's own error, :meth:`JointMatcher._expected_depth`; samples
      clearly nearer than the twin, a vehicle in front of it, left out where enough remain:
      :func:`_unoccluded_depth_err`),
  with gates on overlap and depth. Before that, each twin's cloud state is extrapolated from the
  time it was measured to the camera's timestamp (latency compensation, constant velocity along
  the heading).

Boxes are (N, 4) float arrays x1, y1, x2, y2 in pixels; anchors are (u, v) pixels.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
from scipy.optimize import linear_sum_assignment

from vcfusion.records import GNSS_HEIGHT_FRACTION, TwinStates

NO_MATCH = -1
DEPTH_QUANTILES = (0.1, 0.3, 0.5, 0.7, 0.9)


# ---------------------------------------------------------------------------------------------
# box geometry


def as_boxes(boxes) -> np.ndarray:
    b = np.asarray(boxes, dtype=np.float64)
    if b.size == 0:
        return np.zeros((0, 4))
    if b.ndim != 2 or b.shape[1] != 4:
        raise ValueError(f"boxes: expected an (N, 4) array of x1, y1, x2, y2, got shape {b.shape}")
    return b


def point_in_boxes(point, boxes) -> np.ndarray:
    """Mask of the boxes that contain the point (edges included)."""
    b = as_boxes(boxes)
    u, v = float(point[0]), float(point[1])
    return (b[:, 0] <= u) & (u <= b[:, 2]) & (b[:, 1] <= v) & (v <= b[:, 3])


def point_to_box_distance(point, boxes) -> np.ndarray:
    """Pixel distance from the point to each box (0 inside)."""
    b = as_boxes(boxes)
    u, v = float(point[0]), float(point[1])
    dx = np.maximum.reduce([b[:, 0] - u, np.zeros(len(b)), u - b[:, 2]])
    dy = np.maximum.reduce([b[:, 1] - v, np.zeros(len(b)), v - b[:, 3]])
    return np.hypot(dx, dy)


def _intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise intersection areas of (N, 4) and (M, 4) boxes, (N, M)."""
    ix = np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0])
    iy = np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1])
    return np.clip(ix, 0, None) * np.clip(iy, 0, None)


def box_iou(a, b) -> np.ndarray:
    """Pairwise IoU, (len(a), len(b))."""
    a, b = as_boxes(a), as_boxes(b)
    inter = _intersection(a, b)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a[:, None] + area_b[None, :] - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, inter / union, 0.0)


def box_inside_share(a, b) -> np.ndarray:
    """Pairwise share of each box of `a` that lies inside each box of `b`, (len(a), len(b)); 0 for an
    empty box of `a`."""
    a, b = as_boxes(a), as_boxes(b)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(area_a[:, None] > 0, _intersection(a, b) / area_a[:, None], 0.0)


def _fallback(anchor, boxes: np.ndarray, radius_px: float | None) -> int | None:
    if radius_px is None or len(boxes) == 0:
        return None
    dist = point_to_box_distance(anchor, boxes)
    best = int(np.argmin(dist))
    return best if dist[best] <= radius_px else None


def _nearest_centre(anchor, boxes: np.ndarray, candidates: np.ndarray) -> int:
    centres = np.stack([(boxes[candidates, 0] + boxes[candidates, 2]) / 2,
                        (boxes[candidates, 1] + boxes[candidates, 3]) / 2], axis=1)
    d = np.hypot(centres[:, 0] - anchor[0], centres[:, 1] - anchor[1])
    return int(candidates[int(np.argmin(d))])


# ---------------------------------------------------------------------------------------------
# the paper's matchers (one twin at a time)


def _most_confident(scores, candidates: np.ndarray) -> int | None:
    """The candidate with the strictly highest detector score; None on a tie (or without scores)."""
    if scores is None:
        return None
    s = np.asarray(scores, dtype=np.float64).reshape(-1)[candidates]
    best = np.flatnonzero(s == np.nanmax(s)) if np.isfinite(s).any() else candidates
    return int(candidates[int(best[0])]) if len(best) == 1 else None


def _check_scores(scores, n: int):
    if scores is not None and len(np.asarray(scores).reshape(-1)) != n:
        raise ValueError(f"scores: expected one detector score per box ({n}), got {len(np.asarray(scores).reshape(-1))}")


def match_baseline(anchor, boxes, scores=None, fallback_radius_px: float | None = None) -> int | None:
    """The paper's RGB-only baseline: index of the chosen box, or None.

    One box contains the anchor -> it; several -> the one with the strictly highest detector score
    (``scores``, aligned with ``boxes``), None on a tie or without scores; none -> None (or the
    fallback)."""
    b = as_boxes(boxes)
    _check_scores(scores, len(b))
    candidates = np.flatnonzero(point_in_boxes(anchor, b))
    if len(candidates) == 0:
        return _fallback(anchor, b, fallback_radius_px)
    if len(candidates) == 1:
        return int(candidates[0])
    return _most_confident(scores, candidates)


def match_baseline_centre(anchor, boxes, fallback_radius_px: float | None = None) -> int | None:
    """RGB-only, nearest box centre among the boxes containing the anchor (our heuristic)."""
    b = as_boxes(boxes)
    candidates = np.flatnonzero(point_in_boxes(anchor, b))
    if len(candidates) == 0:
        return _fallback(anchor, b, fallback_radius_px)
    if len(candidates) == 1:
        return int(candidates[0])
    return _nearest_centre(anchor, b, candidates)


def match_paper(anchor, boxes, box_depths, gnss_distance: float,
                fallback_radius_px: float | None = None, scores=None) -> int | None:
    """Algorithm 2 (distance matching): index of the chosen box, or None.

    ``box_depths`` are the distances of Algorithm 1 (aligned with ``boxes``); ``gnss_distance`` is
    the twin's distance from the camera given by its GNSS position (``D_g``); ``scores`` (the
    detector's) only serve the baseline rule when no candidate has a depth.
    """
    b = as_boxes(boxes)
    _check_scores(scores, len(b))
    depths = np.asarray(box_depths, dtype=np.float64).reshape(-1)
    if len(depths) != len(b):
        raise ValueError(f"box_depths: expected one distance per box ({len(b)}), got {len(depths)}")
    candidates = np.flatnonzero(point_in_boxes(anchor, b))
    if len(candidates) == 0:
        return _fallback(anchor, b, fallback_radius_px)
    if len(candidates) == 1:
        return int(candidates[0])
    diff = np.abs(depths[candidates] - gnss_distance)
    if not np.isfinite(diff).any():
        return _most_confident(scores, candidates)
    return int(candidates[int(np.nanargmin(diff))])


# ---------------------------------------------------------------------------------------------
# camera and twin geometry


@dataclass(frozen=True)
class CameraView:
    """What the matchers need to know of the camera at one frame.

    ``project`` maps world points (N, 3) to pixels (N, 2) and camera-Z depths (N,) (OpenCV camera
    frame: x right, y down, z forward); the renderer's camera model supplies it.
    """

    project: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
    position: np.ndarray  # camera centre in the world frame (3,)
    width: int
    height: int
    time: float  # timestamp of the image (s, simulation clock)
    # pinhole intrinsics (3, 3) and OpenCV extrinsics (4, 4); the depth-guided box refinement
    # back-projects pixels with them (None for a camera known only by its projection)
    K: np.ndarray | None = None
    T_world_to_camera: np.ndarray | None = None


@dataclass(frozen=True)
class TwinProjection:
    """Each twin as the camera would see it (aligned with the twins' ids)."""

    anchor: np.ndarray  # (N, 2) GNSS antenna projected, px
    anchor_z: np.ndarray  # (N,) camera-Z of the antenna, m
    gnss_range: np.ndarray  # (N,) Euclidean camera-to-antenna distance, m (D_g taken raw)
    expected_box: np.ndarray  # (N, 4) projected cuboid (clipped at the near plane), clipped to the image
    face_z: np.ndarray  # (N,) camera-Z of the face nearest the camera (what depth sees; Alg. 2's D_g), m
    in_view: np.ndarray  # (N,) bool: in front of the camera and overlapping the image


def extrapolate_twins(twins: TwinStates, to_time: float, use_accel: bool = False) -> TwinStates:
    """Each twin moved from its ``measured_time`` to ``to_time`` along its heading.

    Constant speed by default (position + speed * heading * dt); with ``use_accel`` the reported
    acceleration is added (speed not allowed to turn negative).
    """
    dt = to_time - np.asarray(twins.measured_time, dtype=np.float64)
    speed = np.asarray(twins.speed, dtype=np.float64)
    if use_accel:
        accel = np.asarray(twins.accel, dtype=np.float64)
        # stop at zero speed rather than drive backwards
        t_stop = np.where(accel < 0, np.minimum(dt, -speed / np.where(accel < 0, accel, -1.0)), dt)
        travel = speed * t_stop + 0.5 * accel * t_stop**2
    else:
        travel = speed * dt
    heading = np.asarray(twins.heading, dtype=np.float64)
    return replace(
        twins,
        x=np.asarray(twins.x) + travel * np.cos(heading),
        y=np.asarray(twins.y) + travel * np.sin(heading),
        measured_time=np.full(len(twins), float(to_time)),
    )


def body_points(x, y, z_ground, heading, length, width, height, along, across, up) -> np.ndarray:
    """World points (N, P, 3) on each vehicle's box: ``along`` / ``across`` its length / width from the
    footprint centre (x, y, z_ground) and ``up`` its height from the ground, as fractions, (P,) for
    every vehicle or (N, P) per vehicle."""
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    dl = np.asarray(along) * np.asarray(length)[:, None]
    dw = np.asarray(across) * np.asarray(width)[:, None]
    dz = np.asarray(up) * np.asarray(height)[:, None]
    cx = np.asarray(x)[:, None] + dl * c - dw * s
    cy = np.asarray(y)[:, None] + dl * s + dw * c
    cz = np.asarray(z_ground)[:, None] + dz
    return np.stack(np.broadcast_arrays(cx, cy, cz), axis=-1)


CORNER_FRACTIONS = np.array([[sl, sw, sh] for sl in (-0.5, 0.5) for sw in (-0.5, 0.5) for sh in (0.0, 1.0)])
# the box's 12 edges: corner pairs that differ in one of length, width, height (bits 4, 2, 1 of the index)
CUBOID_EDGES = np.array([(i, i | bit) for bit in (4, 2, 1) for i in range(8) if not i & bit])


def cuboid_corners(x, y, z_ground, heading, length, width, height) -> np.ndarray:
    """World corners (N, 8, 3) of each vehicle's box; (x, y, z_ground) is the footprint centre."""
    return body_points(x, y, z_ground, heading, length, width, height, *CORNER_FRACTIONS.T)


def _in_image(uv: np.ndarray, camera: CameraView) -> np.ndarray:
    # pixel-centre convention (pixel (0, 0) is centred on (0, 0)): the image spans [-0.5, W - 0.5]
    return ((uv[..., 0] >= -0.5) & (uv[..., 0] <= camera.width - 0.5)
            & (uv[..., 1] >= -0.5) & (uv[..., 1] <= camera.height - 0.5))


def _clipped_cuboid_pixels(corners: np.ndarray, camera: CameraView, near: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 20, 2) of each box clipped at the plane camera-Z = near, and which of them are
    points of the clipped box (N, 20): its corners in front of the plane, and the points where its
    edges cross it. A vehicle beside the camera (a truck alongside, its rear behind the camera) is
    in view with the part of it in front."""
    n = len(corners)
    uv, cz = camera.project(corners.reshape(-1, 3))
    uv, cz = np.asarray(uv, float).reshape(n, 8, 2), np.asarray(cz, float).reshape(n, 8)
    a, b = CUBOID_EDGES.T
    za, zb = cz[:, a], cz[:, b]
    crosses = (za - near) * (zb - near) < 0
    t = np.where(crosses, (near - za) / np.where(crosses, zb - za, 1.0), 0.0)
    cut = corners[:, a] + t[..., None] * (corners[:, b] - corners[:, a])
    cut_uv, _ = camera.project(cut.reshape(-1, 3))
    points = np.concatenate([uv, np.asarray(cut_uv, float).reshape(n, len(a), 2)], axis=1)
    valid = np.concatenate([cz > near, crosses], axis=1) & np.isfinite(points).all(axis=2)
    return points, valid


def _outline_pixels(ground, heading, length, width, height, camera: CameraView,
                    t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, P, 2) and camera-Z (N, P) of points of each vehicle's footprint outline a quarter
    of its height up (where Algorithm 1 samples): both sides at the fractions `t` of the length
    (-0.5 rear .. 0.5 front), rear and front at the same fractions of the width."""
    k = len(t)
    along = np.r_[t, t, np.full(k, -0.5), np.full(k, 0.5)]
    across = np.r_[np.full(k, -0.5), np.full(k, 0.5), t, t]
    pts = body_points(*ground.T, heading, length, width, height, along, across, np.full(4 * k, 0.25))
    uv, cz = camera.project(pts.reshape(-1, 3))
    return np.asarray(uv, float).reshape(len(ground), -1, 2), np.asarray(cz, float).reshape(len(ground), -1)


def _nearest_in_view_z(ground, heading, length, width, height, camera: CameraView, default: np.ndarray,
                       samples: int = 16) -> np.ndarray:
    """Camera-Z of the nearest point in the image of each vehicle's outline a quarter of its height
    up (where Algorithm 1 samples), or ``default`` where none of it is in view."""
    uv, cz = _outline_pixels(ground, heading, length, width, height, camera, (np.arange(samples) + 0.5) / samples - 0.5)
    seen = _in_image(uv, camera) & (cz > 0)
    return np.where(seen.any(axis=1), np.where(seen, cz, np.inf).min(axis=1), default)


def outline_depth_in_columns(twins: TwinStates, camera: CameraView, boxes, samples: int = 16) -> np.ndarray:
    """Per twin i and box boxes[i] (x1, y1, x2, y2 px; nan where none), the camera-Z of the nearest
    point of the twin's footprint outline, a quarter of its height up (where Algorithm 1 samples),
    that projects into the box's columns: the depth the part of the vehicle the box shows should
    have. A car seen at an angle whose rear is hidden shows its side or front, metres deeper than
    its rear face (the matcher's ``face_z``). (N,) m; nan where no outline point falls in the box's
    columns or no box is given."""
    n = len(twins)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if len(b) != n:
        raise ValueError(f"boxes: expected one box (or nan) per twin ({n}), got {len(b)}")
    out = np.full(n, np.nan)
    if n == 0:
        return out
    height = np.asarray(twins.height, dtype=np.float64)
    ground = np.stack([twins.x, twins.y, np.asarray(twins.z, dtype=np.float64) - GNSS_HEIGHT_FRACTION * height],
                      axis=1).astype(np.float64)
    uv, cz = _outline_pixels(ground, np.asarray(twins.heading, dtype=np.float64),
                             np.asarray(twins.length, dtype=np.float64), np.asarray(twins.width, dtype=np.float64),
                             height, camera, np.arange(samples + 1) / samples - 0.5)  # corners included
    u = uv[..., 0]
    with np.errstate(invalid="ignore"):
        inside = (u >= b[:, None, 0]) & (u <= b[:, None, 2]) & (cz > 0)
    z = np.where(inside, cz, np.inf).min(axis=1)
    return np.where(np.isfinite(z), z, np.nan)


def project_twins(twins: TwinStates, camera: CameraView, min_z: float = 0.5) -> TwinProjection:
    """Anchors, GNSS distances, expected boxes and expected face depths of the twins."""
    n = len(twins)
    antenna = np.stack([twins.x, twins.y, twins.z], axis=1).astype(np.float64)
    if n == 0:
        z0 = np.zeros(0)
        return TwinProjection(np.zeros((0, 2)), z0, z0, np.zeros((0, 4)), z0, np.zeros(0, bool))
    anchor, anchor_z = camera.project(antenna)
    gnss_range = np.linalg.norm(antenna - np.asarray(camera.position)[None, :], axis=1)
    height = np.asarray(twins.height, dtype=np.float64)
    length = np.asarray(twins.length, dtype=np.float64)
    width = np.asarray(twins.width, dtype=np.float64)
    heading = np.asarray(twins.heading, dtype=np.float64)
    ground = antenna - np.stack([np.zeros(n), np.zeros(n), GNSS_HEIGHT_FRACTION * height], axis=1)  # footprint centre
    corners = cuboid_corners(*ground.T, heading, length, width, height)
    points, valid = _clipped_cuboid_pixels(corners, camera, min_z)
    in_front = valid.any(axis=1)
    # out-of-view twins get an empty box, never nan
    lo = np.where(valid[..., None], points, np.inf).min(axis=1)
    hi = np.where(valid[..., None], points, -np.inf).max(axis=1)
    box = np.where(in_front[:, None], np.concatenate([lo, hi], axis=1), 0.0)
    box[:, [0, 2]] = np.clip(box[:, [0, 2]], -0.5, camera.width - 0.5)
    box[:, [1, 3]] = np.clip(box[:, [1, 3]], -0.5, camera.height - 0.5)
    overlaps = (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])
    # The face the camera sees: the rear if the vehicle drives away from the camera, else the front;
    # taken a quarter of the height up, where Algorithm 1 samples (lower quarter of the box).
    direction = np.stack([np.cos(heading), np.sin(heading), np.zeros(n)], axis=1)
    away = np.einsum("ij,ij->i", direction, ground - np.asarray(camera.position)[None, :]) > 0
    face = body_points(*ground.T, heading, length, width, height, np.where(away, -0.5, 0.5)[:, None], 0.0, 0.25)[:, 0]
    face_uv, face_z = camera.project(face)
    face_z = np.asarray(face_z, float).copy()
    # A vehicle cut by the image border (beside the camera, close) may show only its side: the face
    # point then lies off the image, and depth sees the nearest part of the side that is in view.
    off = in_front & (~_in_image(np.asarray(face_uv), camera) | (face_z <= min_z))
    if off.any():
        face_z[off] = _nearest_in_view_z(ground[off], heading[off], length[off], width[off], height[off], camera,
                                         face_z[off])
    anchor = np.asarray(anchor, float)
    in_view = in_front & overlaps & (np.asarray(anchor_z) > min_z) & np.isfinite(anchor).all(axis=1)
    return TwinProjection(anchor, np.asarray(anchor_z, float), gnss_range, box, np.asarray(face_z, float), in_view)


def visible_boxes(proj: TwinProjection, grid: int = 16) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The part of each twin's expected box that nearer twins' expected boxes leave visible.

    Returns (visible, anchor_hidden, hidden_share): (N, 4) the bounding box of the cells of a ``grid`` x ``grid``
    raster of the expected box that no nearer twin (smaller face depth) covers -- the whole
    expected box when nothing hides it, an empty box (zeros) when all of it is hidden --, (N,)
    whether the anchor cannot be seen: it lies inside a nearer twin's expected box, or off the image
    (a vehicle cut by the image border: the expected box is clipped to the image, the anchor is
    not), and (N,) the share of the cells hidden. Twins out of view hide nothing.
    """
    e = proj.expected_box
    n = len(e)
    visible = e.copy()
    u, v = proj.anchor[:, 0], proj.anchor[:, 1]
    anchor_hidden = proj.in_view & ~((e[:, 0] <= u) & (u <= e[:, 2]) & (e[:, 1] <= v) & (v <= e[:, 3]))
    hidden_share = np.zeros(n)
    if n < 2:
        return visible, anchor_hidden, hidden_share
    depth = np.where(proj.in_view, proj.face_z, np.inf)
    t = (np.arange(grid) + 0.5) / grid
    for i in np.flatnonzero(proj.in_view):
        nearer = np.flatnonzero(depth < depth[i])
        if len(nearer) == 0:
            continue
        k = nearer[(e[nearer, 0] < e[i, 2]) & (e[nearer, 2] > e[i, 0]) & (e[nearer, 1] < e[i, 3]) & (e[nearer, 3] > e[i, 1])]
        if len(k) == 0:
            continue
        anchor_hidden[i] |= bool(point_in_boxes(proj.anchor[i], e[k]).any())
        us = e[i, 0] + t * (e[i, 2] - e[i, 0])
        vs = e[i, 1] + t * (e[i, 3] - e[i, 1])
        hid_u = (e[k, None, 0] <= us[None, :]) & (us[None, :] <= e[k, None, 2])  # (K, grid)
        hid_v = (e[k, None, 1] <= vs[None, :]) & (vs[None, :] <= e[k, None, 3])
        hidden = (hid_v[:, :, None] & hid_u[:, None, :]).any(axis=0)  # (grid v, grid u)
        hidden_share[i] = hidden.mean()
        if hidden.all():
            visible[i] = 0.0
            continue
        rows, cols = np.flatnonzero(~hidden.all(axis=1)), np.flatnonzero(~hidden.all(axis=0))
        cu, cv = (e[i, 2] - e[i, 0]) / grid, (e[i, 3] - e[i, 1]) / grid
        visible[i] = [e[i, 0] + cols[0] * cu, e[i, 1] + rows[0] * cv, e[i, 0] + (cols[-1] + 1) * cu,
                      e[i, 1] + (rows[-1] + 1) * cv]
    return visible, anchor_hidden, hidden_share


# ---------------------------------------------------------------------------------------------
# the per-frame drivers for all twins


def match_all_baseline(proj: TwinProjection, boxes, scores=None, fallback_radius_px: float | None = None,
                       rule: str = "score") -> np.ndarray:
    """Baseline box index per twin (NO_MATCH where none or out of view). ``rule``: 'score' (the
    paper's baseline, :func:`match_baseline`) or 'centre' (:func:`match_baseline_centre`)."""
    if rule not in ("score", "centre"):
        raise ValueError(f"rule: expected 'score' or 'centre', got {rule!r}")
    out = np.full(len(proj.anchor), NO_MATCH)
    for i in np.flatnonzero(proj.in_view):
        if rule == "score":
            j = match_baseline(proj.anchor[i], boxes, scores, fallback_radius_px)
        else:
            j = match_baseline_centre(proj.anchor[i], boxes, fallback_radius_px)
        out[i] = NO_MATCH if j is None else j
    return out


GNSS_DISTANCES = ("face", "range", "z")


def gnss_distances(proj: TwinProjection, gnss_distance: str = "face") -> np.ndarray:
    """``D_g`` per twin: 'face' (camera-Z of the face the camera sees, from the GNSS position,
    heading and length; what Algorithm 1 measures), 'range' (Euclidean camera-to-GNSS-point
    distance) or 'z' (camera-Z of the GNSS point)."""
    if gnss_distance not in GNSS_DISTANCES:
        raise ValueError(f"gnss_distance: expected one of {GNSS_DISTANCES}, got {gnss_distance!r}")
    return {"face": proj.face_z, "range": proj.gnss_range, "z": proj.anchor_z}[gnss_distance]


def match_all_paper(proj: TwinProjection, boxes, box_depths, fallback_radius_px: float | None = None,
                    gnss_distance: str = "face", scores=None) -> np.ndarray:
    """Algorithm 2 box index per twin (NO_MATCH where none or out of view); ``D_g`` per
    :func:`gnss_distances`."""
    dg = gnss_distances(proj, gnss_distance)
    out = np.full(len(proj.anchor), NO_MATCH)
    for i in np.flatnonzero(proj.in_view):
        j = match_paper(proj.anchor[i], boxes, box_depths, float(dg[i]), fallback_radius_px, scores)
        out[i] = NO_MATCH if j is None else j
    return out


class TwinPositionFilter:
    """Smooths each twin's GNSS position over its reports (the paper's future work: a location
    estimate that keeps identification accurate under GNSS error).

    Per twin, a fixed-gain (alpha) filter with the reported motion as the prediction: the last
    estimate is moved by speed * heading * (time between reports), then pulled towards the new
    report by ``alpha``. The reported heading includes a lane change's lateral motion, so the
    prediction follows it; the gain only has to remove the white GNSS error (its std shrinks by
    sqrt(alpha / (2 - alpha)), 0.38 at alpha 0.25). A twin unseen for ``reset_after_s`` or
    jumping by more than ``reset_jump_m`` starts again from its report. Only x, y are filtered.
    """

    def __init__(self, alpha: float = 0.25, reset_after_s: float = 1.0, reset_jump_m: float = 8.0):
        if not 0.0 < alpha <= 1.0:
            raise ValueError(f"alpha: expected 0 < alpha <= 1, got {alpha}")
        self.alpha = alpha
        self.reset_after_s = reset_after_s
        self.reset_jump_m = reset_jump_m
        self._state: dict[str, tuple[float, float, float]] = {}  # id -> (measured_time, x, y)

    def update(self, twins: TwinStates) -> TwinStates:
        x = np.asarray(twins.x, dtype=np.float64).copy()
        y = np.asarray(twins.y, dtype=np.float64).copy()
        for i, vid in enumerate(twins.ids):
            t = float(twins.measured_time[i])
            prev = self._state.get(vid)
            if prev is not None and prev[0] == t:  # the same report again: keep its estimate
                x[i], y[i] = prev[1], prev[2]
                continue
            if prev is not None and 0.0 < t - prev[0] <= self.reset_after_s:
                dt = t - prev[0]
                px = prev[1] + twins.speed[i] * dt * np.cos(twins.heading[i])
                py = prev[2] + twins.speed[i] * dt * np.sin(twins.heading[i])
                if np.hypot(x[i] - px, y[i] - py) <= self.reset_jump_m:
                    x[i] = px + self.alpha * (x[i] - px)
                    y[i] = py + self.alpha * (y[i] - py)
            self._state[vid] = (t, float(x[i]), float(y[i]))
        return replace(twins, x=x, y=y)


@dataclass(frozen=True)
class JointMatcherParams:
    latency_compensation: bool = True
    use_accel: bool = False
    # GNSS position smoothing over the reports (a stateful filter: one matcher per run); None = off
    smoothing_alpha: float | None = 0.25
    face_offset: bool = True  # compare depth to the visible face, not to the antenna
    w_overlap: float = 1.0  # weight of (1 - IoU(expected box, box))
    w_anchor: float = 0.5  # weight of the anchor's distance outside the box (in box diagonals)
    w_depth: float = 1.0  # weight of the depth disagreement (in sigmas, capped at depth_gate)
    w_hidden: float = 1.0  # weight of the share of the twin's expected box that nearer twins hide
    depth_sigma_rel: float = 0.05  # depth disagreement scale: rel * expected depth + abs
    depth_sigma_abs_m: float = 1.0
    depth_gate: float = 4.0  # pairs further apart than this many sigmas are not allowed
    # a measured depth within this many sigmas of the twin's costs nothing, the penalty rising from
    # there to depth_gate at the gate: between two boxes whose depths both agree within the twin's
    # own error the overlap decides, not the noise (curve seeds 3104, 1185, 2045, 3090, tuned-on:
    # wrong highlight episodes 23 -> 17, development identification 98.8 -> 98.4 % at 0.5; 1 sigma
    # gave 14 wrong but 97.7 %). A box without depth keeps its neutral one-sigma penalty
    depth_tolerance_sigmas: float = 0.5
    overlap_gate: float = 0.05  # pairs with less IoU and the anchor outside the box are not allowed
    # cost of leaving a twin without a box (6: only pairs near the dearest allowed one, 1 overlap +
    # 0.5 anchor + 4 depth + 1 hidden = 6.5, lose to it); None: every twin with an allowed box gets one
    miss_cost: float | None = 6.0
    hidden_within: float = 0.9  # a twin hidden whole by nearer ones: boxes with this share of their
    # area inside its expected box are allowed (the visible-part overlap cannot gate them)
    weak_cost: float = 2.5  # a first-round pair dearer than this that a hidden-whole twin also wants
    # is decided again together with the hidden twins (JointMatcher.assign)

    def __post_init__(self):
        if self.depth_gate <= 0 or self.depth_sigma_abs_m <= 0 or self.depth_sigma_rel < 0:
            raise ValueError("depth_gate and depth_sigma_abs_m must be > 0, depth_sigma_rel >= 0")
        if not 0 <= self.depth_tolerance_sigmas < self.depth_gate:
            raise ValueError(f"depth_tolerance_sigmas: expected 0 <= tolerance < depth_gate ({self.depth_gate}), "
                             f"got {self.depth_tolerance_sigmas}")
        if not 0 < self.hidden_within <= 1:
            raise ValueError(f"hidden_within: expected a share in (0, 1], got {self.hidden_within}")


@dataclass(frozen=True)
class JointMatch:
    """One frame's joint assignment (:meth:`JointMatcher.match_details`), aligned with the twins."""

    choice: np.ndarray  # (N,) box index per twin, NO_MATCH where unassigned
    projection: TwinProjection  # the twins as the matcher saw them: GNSS-smoothed, moved on by their latency
    hidden_share: np.ndarray  # (N,) share of each twin's outline nearer twins' outlines hide (visible_boxes)
    # (N,) disagreement of the chosen box's measured depth (its outline's surface where known, else
    # the best quantile of its lower-quarter samples) with the twin's expected face depth, in the
    # matcher's sigmas (depth_sigma_rel * depth + depth_sigma_abs_m, combined with the depth sensor's
    # error there when it has one: JointMatcher._expected_depth); inf: no box or no depth
    depth_sigmas: np.ndarray
    # (N,) the chosen box's lower-quarter depth samples fit a clearly nearer twin too (the box would
    # be allowed without depth support, JointMatcher._depth_of_nearer_twin)
    depth_of_nearer: np.ndarray
    # (N,) depth_sigmas is the depth of the surface drawing the chosen box's outline
    # (box_refine.box_surface_depths), not the samples' best quantile
    depth_on_surface: np.ndarray
    # (N,) the same measured depth's disagreement, in the same sigmas, with the part of the twin the
    # chosen box's columns show: the nearest point of its footprint outline a quarter of its height up
    # that projects into them (outline_depth_in_columns); inf: no box, no depth or no such point. A car
    # seen at an angle, its rear hidden by the car in front, shows its side or front, metres deeper
    # than the face the matcher compares
    shown_depth_sigmas: np.ndarray | None = None


# Least share of a box's lower-quarter depth samples that must lie no nearer than a twin's depth
# gate (JointMatcherParams.depth_gate sigmas in front of its expected face) for the box's depth to be
# read on those samples alone when it is compared with that twin (_unoccluded_depth_err): the samples
# nearer than that are a vehicle in front of the twin, hiding the lower part of the box. Cause: a
# truck turned 20-28 degrees at 30-35 m behind a car 8 m ahead (curved.yaml seed 2045, ego standing):
# its whole box's lower quarter was half the car (7.6 m) and half the truck (28-35 m), its best
# quantile read 29.9 m against a face at 28.0 m (0.8 sigma), and a box on the truck's upper part
# alone (0.0 sigma, IoU 0.34-0.49 with the truck's visible box) took the twin in 16 of its 46 AR
# updates from 79.5 to 84.0 s; read on the truck's samples, 6 (the frames replayed offline).
# A quarter: a box whose lower quarter is mostly a nearer vehicle stays read as it is (that vehicle's
# box, or one that `_depth_of_nearer_twin` lets be neither confirmed nor excluded by depth).
MIN_UNOCCLUDED_SAMPLE_SHARE = 0.25


def _tolerant_depth_penalty(err: np.ndarray, tolerance: float, gate: float) -> np.ndarray:
    """Depth cost of a disagreement of `err` sigmas: 0 up to `tolerance`, rising linearly to `gate`
    at the gate and capped there (tolerance 0: the disagreement itself, capped)."""
    return np.clip((np.asarray(err, np.float64) - tolerance) * (gate / (gate - tolerance)), 0.0, gate)


def _unoccluded_depth_err(samples: np.ndarray, expected: np.ndarray, sigma: np.ndarray, gate: float) -> np.ndarray:
    """(N, D) depth disagreement, in sigmas, of each box with each twin, read on the box's
    lower-quarter samples that lie no nearer than `gate` sigmas in front of the twin's expected
    depth (its best DEPTH_QUANTILES quantile over them, numpy's linear quantile); inf where fewer
    than MIN_UNOCCLUDED_SAMPLE_SHARE of the box's valid samples are left, or where none was dropped
    (the ordinary reading then stands). `samples` (D, n) m, nan where invalid; `expected`,
    `sigma` (N,) m."""
    ordered = np.sort(samples, axis=1)  # nan last
    n_valid = np.isfinite(ordered).sum(axis=1)  # (D,)
    cut = expected - gate * sigma  # (N,) nearer than this: the vehicle in front
    # (N, D) samples nearer than the cut: the index of each twin's first kept one in the ordered samples
    with np.errstate(invalid="ignore"):
        first = (ordered[None, :, :] < cut[:, None, None]).sum(axis=2)
    n_kept = n_valid[None, :] - first
    usable = (first > 0) & (n_kept >= MIN_UNOCCLUDED_SAMPLE_SHARE * n_valid[None, :])  # some dropped, enough left
    out = np.full(usable.shape, np.inf)
    if not usable.any():
        return out
    i, j = np.nonzero(usable)
    pos = first[i, j, None] + np.asarray(DEPTH_QUANTILES)[None, :] * (n_kept[i, j, None] - 1)  # (K, q)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, n_valid[j, None] - 1)
    rows = ordered[j]  # (K, n)
    q = np.take_along_axis(rows, lo, axis=1)
    q = q + (pos - lo) * (np.take_along_axis(rows, hi, axis=1) - q)
    out[i, j] = (np.abs(q - expected[i, None]) / sigma[i, None]).min(axis=1)
    return out


class JointMatcher:
    """Joint (Hungarian) assignment of all twins in view to detected boxes."""

    def __init__(self, params: JointMatcherParams = JointMatcherParams()):
        self.params = params
        self.filter = TwinPositionFilter(params.smoothing_alpha) if params.smoothing_alpha is not None else None

    def cost_matrix(self, proj: TwinProjection, boxes, box_depths, surface_depths=None,
                    depth_noise=None) -> tuple[np.ndarray, np.ndarray]:
        """(cost, allowed) over (twins, boxes)."""
        return self._cost_terms(proj, boxes, box_depths, surface_depths, depth_noise)[:2]

    def _cost_terms(self, proj: TwinProjection, boxes, box_depths,
                    surface_depths=None, depth_noise=None) -> tuple[np.ndarray, ...]:
        """(cost, allowed) over (twins, boxes), (N,) whether each twin is hidden whole (the
        assignment's second round; computed here with the rest of :func:`visible_boxes`), and over
        (twins, boxes) the depth disagreement the cost compares, in sigmas (uncapped; inf where the
        box has no depth), whether the box's depth is a clearly nearer twin's
        (:meth:`_depth_of_nearer_twin`), (D,) whether that disagreement is the surface drawing the
        box's outline (else the best quantile of its lower-quarter samples), (D, q) the depths it
        was measured on (that surface's depth where known, else the samples' quantiles), and (N,)
        each twin's depth sigma (:meth:`_expected_depth`)."""
        p = self.params
        b = as_boxes(boxes)
        depths = np.asarray(box_depths, dtype=np.float64)
        n, m = len(proj.anchor), len(b)
        if depths.ndim == 1:
            depths = depths[:, None]
        samples = depths if depths.shape[1] > 1 else None  # Algorithm 1's raw samples, (D, n)
        if depths.shape[0] != m:
            raise ValueError(f"box_depths: expected one distance (or one row of samples) per box ({m}), "
                             f"got shape {depths.shape}")
        # With the raw samples of Algorithm 1 (D, n), a box agrees with a twin if a good share of its
        # samples does: the depth error is the best over the samples' 10..90% quantiles. A box whose
        # lower quarter is partly hidden behind a nearer vehicle then still matches its own twin.
        if depths.shape[1] > 1 and m:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # all-nan rows (sky) give nan quantiles
                depths = np.nanquantile(depths, DEPTH_QUANTILES, axis=1).T  # (D, 5)
        # A partly hidden vehicle's box covers only its visible part, which may not hold its anchor
        # (e.g. a car whose centre a nearer truck hides): the box is compared with the visible part
        # of the twin's expected box too, and a hidden anchor is replaced by that part's centre.
        visible, anchor_hidden, hidden_share = visible_boxes(proj)
        iou = (np.maximum(box_iou(proj.expected_box, b), box_iou(visible, b)) if n and m else np.zeros((n, m)))
        anchors = np.where(anchor_hidden[:, None], (visible[:, :2] + visible[:, 2:]) / 2, proj.anchor)
        anchor_dist = np.zeros((n, m))
        inside = np.zeros((n, m), bool)
        diag = np.hypot(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]) if m else np.zeros(0)
        for i in range(n):
            anchor_dist[i] = point_to_box_distance(anchors[i], b) / np.maximum(diag, 1.0)
            # a hidden anchor's stand-in (the visible part's centre) admits no box by lying in it: a
            # car all but beyond the image's side (expected box 0.8 px wide at the border) took the
            # box of the car beside it, which the stand-in lay in, and pushed that car off its box
            if not anchor_hidden[i]:
                inside[i] = point_in_boxes(anchors[i], b)
        expected, sigma = self._expected_depth(proj, depth_noise)
        sigma = sigma[:, None]
        with np.errstate(invalid="ignore"):
            err_q = np.abs(depths[None, :, :] - expected[:, None, None]) / sigma[:, :, None]  # (N, D, q)
        err_q = np.where(np.isfinite(err_q), err_q, np.inf)
        depth_err = err_q.min(axis=2) if err_q.shape[2] else np.full((n, m), np.inf)
        if samples is not None and n and m:
            depth_err = np.minimum(depth_err, _unoccluded_depth_err(samples, expected, sigma[:, 0], p.depth_gate))
        depth_known = np.isfinite(depth_err)
        # A box without valid depth neither helps nor is excluded: a neutral one-sigma penalty.
        depth_err = np.where(depth_known, depth_err, 1.0)
        # A box whose sampled lower quarter lies on a clearly nearer twin (inside its expected box,
        # at its depth) measured that twin, not the vehicles behind it: for those its depth cannot
        # confirm a match but does not exclude one either (e.g. a far car whose lower part a nearer
        # one hides): allowed at the largest depth penalty, so any twin whose depth does agree wins.
        of_nearer = (self._depth_of_nearer_twin(proj, b, depth_err, expected, sigma) if n > 1 and m
                     else np.zeros((n, m), bool))
        measured_err = np.where(depth_known, depth_err, np.inf)
        depth_err = np.where(of_nearer, np.minimum(depth_err, p.depth_gate), depth_err)
        # where the depth image tells which surface draws a box's outline, the cost compares that
        # surface's depth (box_refine.box_surface_depths): the samples' best quantile also fits a
        # vehicle of which the box shows a sliver. The gate stays with the samples: a surface
        # wrongly found must not forbid a pair the samples allow
        cost_err = depth_err
        on_surface = np.zeros(m, bool)
        if surface_depths is not None and m:
            surface = np.asarray(surface_depths, dtype=np.float64)
            if surface.shape != (m,):
                raise ValueError(f"surface_depths: expected one depth (or nan) per box ({m}), got shape {surface.shape}")
            with np.errstate(invalid="ignore"):
                surface_err = np.abs(surface[None, :] - expected[:, None]) / sigma
            cost_err = np.where(np.isfinite(surface_err), surface_err, depth_err)
            measured_err = np.where(np.isfinite(surface_err), surface_err, measured_err)
            on_surface = np.isfinite(surface)
            depths = np.where(on_surface[:, None], surface[:, None], depths)
        cost_known = depth_known | on_surface[None, :]
        depth_penalty = np.where(cost_known, _tolerant_depth_penalty(cost_err, p.depth_tolerance_sigmas, p.depth_gate),
                                 np.minimum(cost_err, p.depth_gate))
        # the more of a twin nearer twins hide, the less likely it has a box of its own: a box wanted
        # by a mostly hidden twin and a visible one goes to the visible one
        cost = (p.w_overlap * (1.0 - iou) + p.w_anchor * np.minimum(anchor_dist, 1.0)
                + p.w_depth * depth_penalty + p.w_hidden * hidden_share[:, None])
        cost = np.nan_to_num(cost, nan=10.0, posinf=10.0)  # twins out of view (nan anchors) are gated below
        allowed = ((iou >= p.overlap_gate) | inside) & (depth_err <= p.depth_gate)
        # a twin that nearer twins' expected boxes hide whole has no visible part to overlap a box
        # with, yet a roof above the car in front or a corner beside it often shows (the expected
        # boxes are coarser than the vehicles): a box lying within its expected box is allowed too
        hidden_whole = hidden_share >= 1.0  # every cell of visible_boxes' raster covered
        whole = np.flatnonzero(hidden_whole)
        if len(whole) and m:
            allowed[whole] |= ((depth_err[whole] <= p.depth_gate)
                               & (box_inside_share(b, proj.expected_box[whole]).T >= p.hidden_within))
        allowed &= proj.in_view[:, None]
        return cost, allowed, hidden_whole, measured_err, of_nearer, on_surface, depths, sigma[:, 0]

    def _expected_depth(self, proj: TwinProjection, depth_noise=None) -> tuple[np.ndarray, np.ndarray]:
        """(N,) the depth each twin's box should measure (its face, or its anchor without
        face_offset) and (N,) the depth sigma there, m: the matcher's own (depth_sigma_rel * depth +
        depth_sigma_abs_m: the twin's GNSS, latency and shape error) combined in quadrature with the
        depth sensor's error at that depth (`depth_noise`, vcfusion.fusion.road.DepthNoise, of the depth
        the samples were read from; None or exact: no sensor term, the matcher's sigma as it is)."""
        p = self.params
        expected = proj.face_z if p.face_offset else proj.anchor_z
        sigma = p.depth_sigma_rel * expected + p.depth_sigma_abs_m
        if depth_noise is not None and not depth_noise.exact:
            # what the sensor reads there (a stereo pair's far depth reads nearer, DepthNoise.reading),
            # with its error at that depth
            expected = depth_noise.reading(expected)
            with np.errstate(invalid="ignore"):
                sensor = np.asarray(depth_noise.sigma(np.maximum(expected, 0.0)), np.float64)
            sigma = np.where(np.isfinite(sensor), np.hypot(sigma, sensor), sigma)
        return expected, sigma

    def _depth_of_nearer_twin(self, proj: TwinProjection, boxes: np.ndarray, depth_err: np.ndarray,
                              expected: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """(N, D) mask: box j's depth agrees with a twin k that is nearer than twin i by more than
        i's depth gate and whose expected box holds >= 80 % of box j's lower quarter, while box j is
        not k's own box (IoU with k's expected box < 0.5: else a far twin would take the box of a
        near one). `expected` (N,), `sigma` (N, 1): each twin's expected depth and its sigma, m
        (:meth:`_expected_depth`)."""
        gate = self.params.depth_gate
        lower = boxes.copy()
        lower[:, 1] = boxes[:, 3] - 0.25 * (boxes[:, 3] - boxes[:, 1])
        # (K, D): twin k covers box j's sampled area and box j's depth is twin k's
        explains = ((box_inside_share(lower, proj.expected_box).T >= 0.8) & (depth_err <= gate)
                    & proj.in_view[:, None] & (box_iou(proj.expected_box, boxes) < 0.5))
        nearer = expected[None, :] < (expected[:, None] - gate * sigma)  # (I, K): k clearly nearer than i
        return (nearer.astype(np.int64) @ explains.astype(np.int64)) > 0

    def match(self, twins: TwinStates, boxes, box_depths, camera: CameraView, surface_depths=None,
              depth_noise=None) -> np.ndarray:
        """Box index per twin (NO_MATCH where unassigned), aligned with ``twins.ids``.

        ``box_depths``: Algorithm 1's distance per box (D,), or better its raw samples (D, n)
        (:func:`vcfusion.fusion.depth_eval.sample_box_depths`). ``surface_depths``: (D,) the depth of
        the surface drawing each box's outline, nan where unknown
        (:func:`vcfusion.fusion.box_refine.box_surface_depths`); None: none known. ``depth_noise``: the
        error of the depth the samples were read from (vcfusion.fusion.road.DepthNoise; the depth step's
        DepthView.noise), which widens the depth sigma (:meth:`_expected_depth`); None: exact depth."""
        return self.match_details(twins, boxes, box_depths, camera, surface_depths, depth_noise).choice

    def match_details(self, twins: TwinStates, boxes, box_depths, camera: CameraView,
                      surface_depths=None, depth_noise=None) -> "JointMatch":
        """:meth:`match`'s choice with what it was decided on (:class:`JointMatch`): the twins as
        the matcher projects them (GNSS-smoothed, moved on by their latency) and each chosen box's
        depth agreement."""
        if self.filter is not None:
            twins = self.filter.update(twins)
        if self.params.latency_compensation:
            twins = extrapolate_twins(twins, camera.time, self.params.use_accel)
        proj = project_twins(twins, camera)
        choice, (_, _, _, depth_err, of_nearer, on_surface, depths, depth_sigma) = self._assign(
            proj, boxes, box_depths, surface_depths, depth_noise)
        n = len(choice)
        rows, cols = np.flatnonzero(choice != NO_MATCH), choice[choice != NO_MATCH]
        sigmas, nearer, surface = np.full(n, np.inf), np.zeros(n, bool), np.zeros(n, bool)
        shown = np.full(n, np.inf)
        if len(rows):
            sigmas[rows], nearer[rows], surface[rows] = depth_err[rows, cols], of_nearer[rows, cols], on_surface[cols]
            # the same measured depths against the part of the twin the box's columns show
            chosen = np.full((n, 4), np.nan)
            chosen[rows] = as_boxes(boxes)[cols]
            column_z = outline_depth_in_columns(twins, camera, chosen)[rows]
            if depth_noise is not None and not depth_noise.exact:
                column_z = depth_noise.reading(column_z)
            sigma = depth_sigma[rows]
            with np.errstate(invalid="ignore"):
                err = np.abs(depths[cols] - column_z[:, None]) / sigma[:, None]
            err = np.where(np.isfinite(err), err, np.inf).min(axis=1) if depths.shape[1] else np.full(len(rows), np.inf)
            shown[rows] = err
        return JointMatch(choice, proj, visible_boxes(proj)[2], sigmas, nearer, surface, shown)

    def assign(self, proj: TwinProjection, boxes, box_depths, surface_depths=None, depth_noise=None) -> np.ndarray:
        """Box index per twin (NO_MATCH where unassigned), in two rounds: first the twins with a
        visible part, then, from the boxes they left, the twins that nearer twins' expected boxes hide
        whole. Why: such a twin rarely has a box (a roof line above the car in front at most), yet in
        one joint assignment it took a visible twin's box at a cost under ``miss_cost`` and pushed that
        twin onto a worse box, because the two costs together were lower than one twin going without
        (e.g. 3.7 + 1.8 < 0.2 + 6).

        A first-round pair dearer than ``weak_cost`` whose box a hidden twin is also allowed goes into
        the second round with the hidden twins: a far car in a chain, visible by a corner, otherwise kept
        the box of the car in front of it at 5.97 (just under ``miss_cost``), which that car, hidden but
        for its roof, fitted at 2.03."""
        return self._assign(proj, boxes, box_depths, surface_depths, depth_noise)[0]

    def _assign(self, proj: TwinProjection, boxes, box_depths, surface_depths=None, depth_noise=None):
        """:meth:`assign`'s choice and the cost terms it was made on (:meth:`_cost_terms`)."""
        terms = self._cost_terms(proj, boxes, box_depths, surface_depths, depth_noise)
        cost, allowed, hidden_whole = terms[:3]
        out = np.full(len(proj.anchor), NO_MATCH)
        if cost.size == 0:
            return out, terms
        out[~hidden_whole] = self._assign_once(cost[~hidden_whole], allowed[~hidden_whole])
        if hidden_whole.any():
            matched = np.flatnonzero(out != NO_MATCH)
            wanted = allowed[hidden_whole].any(axis=0)  # (D,) boxes some hidden twin may take
            weak = matched[(cost[matched, out[matched]] > self.params.weak_cost) & wanted[out[matched]]]
            out[weak] = NO_MATCH
            second = hidden_whole.copy()
            second[weak] = True
            free = np.ones(cost.shape[1], bool)
            free[out[out != NO_MATCH]] = False
            out[second] = self._assign_once(cost[second], allowed[second] & free[None, :])
        return out, terms

    def _assign_once(self, cost: np.ndarray, allowed: np.ndarray) -> np.ndarray:
        """One Hungarian assignment of (twins, boxes) cost under the allowed mask."""
        out = np.full(len(cost), NO_MATCH)
        if cost.size == 0 or not allowed.any():
            return out
        big = 1e6
        cost = np.where(allowed, cost, big)
        m = cost.shape[1]
        if self.params.miss_cost is not None:
            # one "no box" column per twin: without it, the assignment must give a box to every twin
            # it can, so a mostly hidden twin takes a box at any cost and pushes the box's own
            # vehicle onto a worse one, and that one onto the next
            cost = np.hstack([cost, np.where(np.eye(len(cost), dtype=bool), self.params.miss_cost, big)])
        rows, cols = linear_sum_assignment(cost)
        for i, j in zip(rows, cols):
            if j < m and allowed[i, j]:
                out[i] = j
        return out
