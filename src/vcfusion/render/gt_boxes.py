"""Ground-truth 2D boxes of the vehicles in a frame, from its instance map.

For every vehicle with at least one visible pixel:
- ``box``: the box around its *visible* pixels, (x1, y1, x2, y2) in the camera's pixel
  convention (integer coordinates at pixel centres), so its edges lie on half-integers and a
  pixel coordinate (u, v) is inside iff x1 <= u < x2 and y1 <= v < y2;
- ``visible_fraction``: visible pixels / pixels of the vehicle drawn alone (same pose, nothing
  in front of it), both counted inside the image; 1 = unoccluded. The vehicle is only redrawn
  alone when another vehicle nearer the camera overlaps its projected 3D box. On a straight road
  nothing else can hide a vehicle on it (the camera looks along the road, rails and trees are
  beside it): the fraction is then 1 without a redraw. On other roads a rail or a tree on the
  inside of a curve can: there one more pass draws the vehicles without the road, and a vehicle
  that shows more pixels in it than in the frame is partly hidden by the road's objects;
- ``truncation``: fraction of the projected 3D bounding box (length x width x height, clipped
  at the near plane) that lies outside the image (KITTI's notion; 0 = fully inside);
- ``median_depth``: median camera Z of its visible pixels (what a depth camera measures);
- ``outline``: the box around the part of its projected 3D bounding box (clipped at the near
  plane) that lies inside the image: where the whole vehicle would be with nothing in front of it
  (for a car beside the camera, the box around all of the projection, clipped, would span the
  image's height);
- ``patch``: the box around its largest 8-connected patch of visible pixels: the part of it a
  person sees (pixels scattered between the wheels of a nearer truck are not a view of the car);
  ``box`` where it shows as one patch;
- ``visible_share``: the patch's area over the outline's (the CityPersons benchmark's visibility,
  visible box over full box; 1 where it comes out larger): how much of the vehicle's extent in the
  image nearer objects leave, without a second render.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from vcfusion.records import VehicleStates

# The 12 edges of a box whose corners are indexed by bits (x, y, z) = (i & 1, i >> 1 & 1, i >> 2 & 1).
_BOX_EDGES = [(a, a | bit) for bit in (1, 2, 4) for a in range(8) if not a & bit]


@dataclass(frozen=True)
class GroundTruthBoxes:
    """Struct-of-arrays: one row per vehicle seen in a frame."""

    vehicle_ids: tuple[str, ...]
    vclass: tuple[str, ...]
    instance: np.ndarray  # (N,) value of the vehicle in Frame.instances
    box: np.ndarray  # (N, 4) x1, y1, x2, y2 (pixel-centre convention: edges on half-integers)
    pixels: np.ndarray  # (N,) visible pixels
    full_pixels: np.ndarray  # (N,) pixels of the vehicle drawn alone (inside the image)
    visible_fraction: np.ndarray  # (N,)
    truncation: np.ndarray  # (N,)
    median_depth: np.ndarray  # (N,) metres
    outline: np.ndarray  # (N, 4) x1, y1, x2, y2 around the projected 3D box's part inside the image
    patch: np.ndarray  # (N, 4) x1, y1, x2, y2 around the largest 8-connected patch of visible pixels
    visible_share: np.ndarray  # (N,) area of `patch` / area of `outline`, at most 1

    def __len__(self) -> int:
        return len(self.vehicle_ids)


def box_corners(x: float, y: float, z: float, yaw: float, length: float, width: float, height: float) -> np.ndarray:
    """(8, 3) world corners of a vehicle's bounding box (footprint centre, yaw)."""
    bits = np.arange(8)
    local = np.column_stack([((bits & 1) - 0.5) * length, ((bits >> 1 & 1) - 0.5) * width, (bits >> 2 & 1) * height])
    c, s = np.cos(yaw), np.sin(yaw)
    return np.column_stack([x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1],
                            z + local[:, 2]])


def projected_box_polygon(corners_world: np.ndarray, K: np.ndarray, T: np.ndarray, near: float) -> np.ndarray | None:
    """Convex hull (M, 2) in pixels of a 3D box clipped at the plane Z = near; None if all behind."""
    pc = corners_world @ T[:3, :3].T + T[:3, 3]
    pts = [p for p in pc if p[2] >= near]
    for a, b in _BOX_EDGES:
        za, zb = pc[a, 2], pc[b, 2]
        if (za - near) * (zb - near) < 0:
            t = (near - za) / (zb - za)
            pts.append(pc[a] + t * (pc[b] - pc[a]))
    if len(pts) < 3:
        return None
    pts = np.array(pts)
    uv = (pts @ K.T)[:, :2] / pts[:, 2:3]
    return cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)


def outline_in_image(hull: np.ndarray | None, width: int, height: int) -> tuple[float, np.ndarray]:
    """The truncation of a projected 3D box's hull (share of its area outside the image; 1 for
    None) and the box (x1, y1, x2, y2) around its part inside the image (NaN where none is)."""
    none = np.full(4, np.nan)
    if hull is None:
        return 1.0, none
    image = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]],
                     dtype=np.float32)
    hull = np.asarray(hull, dtype=np.float32)
    inside, polygon = cv2.intersectConvexConvex(hull, image)
    if polygon is None or inside <= 0:
        outline = none
    else:
        corners = polygon.reshape(-1, 2)
        outline = np.r_[corners.min(axis=0), corners.max(axis=0)]
    area = cv2.contourArea(hull)
    if area <= 0:
        return 0.0, outline
    # Rounded: the float32 polygon clipping leaves ~1e-8 of noise on boxes fully inside.
    return round(float(np.clip(1.0 - inside / area, 0.0, 1.0)), 6), outline


def largest_patch_box(rows: np.ndarray, cols: np.ndarray) -> tuple[float, float, float, float]:
    """The box (pixel-centre convention) around the largest 8-connected patch of the pixels at
    (`rows`, `cols`); the first in scan order of equal ones."""
    r0, c0 = rows.min(), cols.min()
    h, w = rows.max() - r0 + 1, cols.max() - c0 + 1
    if len(rows) < h * w:  # a filled rectangle is one patch
        mask = np.zeros((h, w), np.uint8)
        mask[rows - r0, cols - c0] = 1
        n, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        if n > 2:
            x, y, bw, bh = stats[1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA])), :4]
            return c0 + x - 0.5, r0 + y - 0.5, c0 + x + bw - 0.5, r0 + y + bh - 0.5
    return c0 - 0.5, r0 - 0.5, c0 + w - 0.5, r0 + h - 0.5


def ground_truth_boxes(frame, truth: VehicleStates, renderer=None, near: float = 0.3) -> GroundTruthBoxes:
    """Boxes of the vehicles seen in `frame` (rendered from `truth`).

    `renderer` (the EgoCameraRenderer that made the frame, still at that state) is needed for the
    visible fraction of vehicles that may be occluded; without it their fraction is NaN.
    """
    inst = frame.instances
    flat = inst.ravel()
    seen = flat >= 0
    counts = np.bincount(flat[seen], minlength=len(frame.vehicle_ids))
    present = np.flatnonzero(counts)
    rows, cols = np.divmod(np.flatnonzero(seen), inst.shape[1])
    labels = flat[seen]
    order = np.argsort(labels, kind="stable")
    labels, rows, cols = labels[order], rows[order], cols[order]
    depths = frame.depth.ravel()[np.flatnonzero(seen)[order]]
    starts = np.searchsorted(labels, present)
    ends = np.searchsorted(labels, present, side="right")

    index = {vid: i for i, vid in enumerate(truth.ids)}
    hulls, near_depth, far_depth = [], [], []
    for k in present:
        i = index[frame.vehicle_ids[k]]
        corners = box_corners(truth.x[i], truth.y[i], truth.z[i], truth.heading[i], truth.length[i], truth.width[i],
                              truth.height[i])
        hulls.append(projected_box_polygon(corners, frame.K, frame.T_world_to_camera, near))
        z = corners @ frame.T_world_to_camera[2, :3] + frame.T_world_to_camera[2, 3]
        near_depth.append(z.min())
        far_depth.append(z.max())
    rects = [None if h is None else (h.min(axis=0), h.max(axis=0)) for h in hulls]
    # pixels per vehicle where only vehicles can hide it (roads other than one straight edge)
    alone_counts = None
    road = getattr(renderer, "road", None)
    if road is not None and not road.is_straight:
        vo = renderer.vehicles_only().ravel()
        alone_counts = np.bincount(vo[vo >= 0], minlength=len(frame.vehicle_ids))

    n = len(present)
    box = np.zeros((n, 4))
    full = np.zeros(n, dtype=np.int64)
    visible_fraction = np.full(n, np.nan)
    truncation = np.zeros(n)
    median_depth = np.zeros(n)
    outline = np.full((n, 4), np.nan)
    patch = np.zeros((n, 4))
    for j, k in enumerate(present):
        r, c = rows[starts[j]:ends[j]], cols[starts[j]:ends[j]]
        box[j] = (c.min() - 0.5, r.min() - 0.5, c.max() + 0.5, r.max() + 0.5)
        patch[j] = largest_patch_box(r, c)
        median_depth[j] = float(np.median(depths[starts[j]:ends[j]]))
        truncation[j], outline[j] = outline_in_image(hulls[j], frame.width, frame.height)
        if _may_be_occluded(j, rects, near_depth, far_depth):
            if renderer is not None:
                full[j] = int(renderer.silhouette(frame.vehicle_ids[k]).sum())
                visible_fraction[j] = min(1.0, counts[k] / full[j]) if full[j] else 0.0
            else:
                full[j] = -1
        elif alone_counts is not None and alone_counts[k] > counts[k]:  # only the road's objects hide it
            full[j] = alone_counts[k]
            visible_fraction[j] = counts[k] / full[j]
        else:
            full[j] = counts[k]
            visible_fraction[j] = 1.0
    vids = tuple(frame.vehicle_ids[k] for k in present)
    return GroundTruthBoxes(
        vehicle_ids=vids, vclass=tuple(truth.vclass[index[v]] for v in vids), instance=present.astype(np.int32),
        box=box, pixels=counts[present], full_pixels=full, visible_fraction=visible_fraction,
        truncation=truncation, median_depth=median_depth, outline=outline, patch=patch,
        visible_share=visible_shares(patch, outline))


def visible_shares(visible_box: np.ndarray, outline: np.ndarray) -> np.ndarray:
    """(N,) area of each visible box over the area of its outline, at most 1 (a visible box can
    reach a pixel past the projected 3D box: mirrors and wheels outside the length x width x
    height box, the pixel grid); 1 where the outline is NaN or empty (no extent to compare with)."""
    v = np.asarray(visible_box, dtype=float).reshape(-1, 4)
    o = np.asarray(outline, dtype=float).reshape(-1, 4)
    area_v = (v[:, 2] - v[:, 0]) * (v[:, 3] - v[:, 1])
    area_o = np.clip(o[:, 2] - o[:, 0], 0, None) * np.clip(o[:, 3] - o[:, 1], 0, None)
    with np.errstate(divide="ignore", invalid="ignore"):  # the empty and NaN outlines' quotients are not used
        return np.minimum(np.where(area_o > 0, area_v / area_o, 1.0), 1.0)


def _may_be_occluded(j: int, rects, near_depth, far_depth) -> bool:
    if rects[j] is None:
        return True
    lo, hi = rects[j]
    for m, other in enumerate(rects):
        if m == j:
            continue
        if other is None:
            return True
        olo, ohi = other
        overlap = (olo[0] < hi[0]) and (lo[0] < ohi[0]) and (olo[1] < hi[1]) and (lo[1] < ohi[1])
        if overlap and near_depth[m] < far_depth[j]:
            return True
    return False
