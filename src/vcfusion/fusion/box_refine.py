"""Depth-guided box refinement: snap each detected box to the vehicle surface the depth image shows.

Why: the detector sees a 320x240 RGB image, so its boxes of small or crowded vehicles are a few
pixels off, and a car straight ahead in a chain gets a box that swallows the car behind it (the
paper's Fig. 3). The camera also gives depth at full resolution, where a vehicle is a connected
surface standing on the road, separated from the next vehicle by a jump in depth.

Per detected box (pixel-centre convention, as everywhere in the fusion stage):
1. A search window: the box grown by ``margin`` of its size on each side (at least 3 px).
2. Object pixels: a valid depth whose back-projected point stands more than ``min_height_m``
   above the road. The renderer's world is flat with the road at world z = 0, so the height
   follows from the camera's intrinsics and pose alone (no ground fit).
3. Candidate surface depths: the ``candidates`` most populated 4 % log-depth bins of the object
   pixels in the box's core (its central half in each direction).
4. For each candidate depth z0, the object pixels from ``0.3 * band_m`` (+3 % of z0) nearer to
   ``band_m`` (+3 %) farther than z0, split into 4-connected segments twice: as they are, and cut
   at depth jumps (the farther pixel of each neighbour pair whose depths differ by more than
   ``jump_m`` + ``jump_rel`` of the depth removed, then given back to a neighbour on their own
   surface: :func:`_restore_outlines`, as for the proposals). Why both: a near car touches, in the
   image, the side of a truck or the car beside it that lies within its band, and only the cut
   separates them; but a surface whose depth runs steeply across the view (a far truck's side, each
   column a jump from the next) has no neighbour on its surface to take its pixels back, and only the
   band keeps it whole. The cut takes a pixel off each occluded outline, and every pixel of a strip a
   nearer vehicle leaves 1-2 px wide: without giving them back a small far box lost a pixel a side
   and a hidden vehicle's box its lower part. Also, once per box, the
   object pixels of the window cut at depth jumps (given back the same way) without any band:
   a surface whole, however deep it runs (the side of a truck in the next lane spans 15 m). A
   segment's box is the span of its rows and columns holding at least ``support`` of its fullest
   row / column (so a rail or a sliver of road does not widen it).
5. Of the segments touching the core, the one whose box overlaps the detected box most replaces
   it, when that IoU reaches ``min_iou``; otherwise the detected box is kept (and counted as kept).
   A segment that spans a depth jump and is wider across the view than any vehicle
   (``pair_width_m``; two trucks side by side a few metres apart in depth share a band) gives way to
   the best jump-free one no wider that still overlaps the box by ``pair_min_iou``: a box over the
   pair then holds one of them, and the other is proposed.
   A left or right side the snap moved inward over the segment's own surface (the window's surfaces
   whole go on past it without a depth jump) is given back up to the detector's side
   (``surface_sides``, :func:`_surface_sides`): a band's cut can split one vehicle where no depth
   jump does.
   How high that segment's top stands (``RefinedBoxes.top_m``) lets the fusion stage correct the
   class: a car box standing as high as a truck is a truck (``fuse.depth_step``).

Then vehicles the detector missed (a car mostly hidden behind another, a far car in a chain) are
proposed from the depth image alone (``depth_proposals``): the object pixels of the whole image
cut at depth jumps into segments (the pixels the cut removed, a hidden vehicle's outline next to
the nearer one, go back to their own surface's segment); a segment that stands as high as a car
roof, is wider than a post (than a vehicle, when it stands on the road higher than a truck: tree
trunks; the top of a truck seen over the car in front rests on that car instead), whose top does
not go on upward (tree crowns and poles cut at the height cap), that does not stand on a narrow
stem under its middle with nothing nearer beside it (a tree lower than the cap) and that no
confident box explains becomes a box (a truck when it stands higher than a car); its box reaches
down over the same surface to where the refinement's object pixels end (bumper and tyres). A box the
refinement could not snap to any segment is not confirmed by depth and explains only the segments it
overlaps, not those it merely holds. A box's surface is that of the segment drawing its outline
(:func:`outline_segments`), else its core's median; that segment itself is the box's only by overlap.

Last (``join_fragments``), each box grows over its own segments of that segmentation whole (the one
most of its core shows, and the one drawing its outline: where the detector's box was too small, the
refinement kept a part of the vehicle), and a vehicle that a nearer one cuts into pieces (its roof
above the nearer car, a corner beside it) gets one box over all of them: a segment at a box's
surface depth, near it, that no other box owns, joins the box when what lies between them is mostly
nearer and all together are no wider than a vehicle.

A depth step that does not need a perfect world (``road``, the gates): the heights above are
measured above the road plane fitted to each depth image (vcfusion.fusion.road; the nominal pose's
flat road where the fit fails, counted), and with a sensor's noise (a DepthNoise) the depth is
median-filtered first, the object pixels' height threshold grows by ``noise_k`` sigma of the
height's noise, and a box (or proposal) whose depth is too noisy to tell one surface from the next,
or whose core holds too little measured depth, keeps the detector's box: it is *gated*, and counted
(``RefinedBoxes.gated``; fuse.depth_step's counts), never silently. Holes are filled first where
the sensor leaves them between two measurements (:func:`fill_scan_gaps`): a stereo pair's along its
rows (the occlusion band left of a nearer surface with the farther depth), a LiDAR scan's between
its returns (the road's along the fitted plane); on a scan a box crossed by too few of its rows is
gated, and a side of a snapped box that ends where the scan sees nothing is the detector's.

The band is one vehicle deep: a car behind another in the same lane is at least a car length plus
the gap farther away, so it falls outside the band of the car in front. Depth quality sets what
this can do: it was tuned on the renderer's exact depth (docs: components/fusion.md, "Depth step",
for the rules, the folders that chose each value and the limits).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numba
import numpy as np

# the renderer's flat world: the road surface lies at world z = 0
ROAD_Z_M = 0.0


@dataclass(frozen=True)
class ProposalParams:
    """Vehicles the detector missed, proposed from the depth image alone (module docstring)."""
    min_height_m: float = 0.3  # object pixels: above the road by more than this (no markings, kerbs)
    # and below BoxRefineParams.max_height_m (tree crowns, gantries)
    max_top_continuing: float = 0.3  # a segment whose top outline goes on, as the same surface,
    # above max_height_m over more than this share is part of a tree, a pole or a bridge
    min_pixels: int = 30  # px; a far car partly hidden shows as few (the roof line of a car behind
    # the next one, 20 x 5 px at 30 m); chosen on the jam development seeds (30 vs 40: +1 target)
    min_top_m: float = 1.0  # the segment's top stands at least this high (a car's roof line; rails are lower)
    min_top_truncated_m: float = 0.8  # ... or this high when the image's side cuts it (_min_top)
    min_width_m: float = 0.15  # m; wider than reflector posts (0.12 m): a car mostly hidden behind
    # another shows a sliver as narrow as this (6 px at 19 m is 0.249 m); jam development seeds
    # 3240-3479: 8 of 28 targets without a box were slivers of 0.12-0.25 m
    min_tall_width_m: float = 0.8  # a segment standing as high as a truck: wider than this (tree trunks)
    max_overlap: float = 0.6  # IoU; a segment whose box overlaps a detected box more than this is
    # that box's (at 0.5 a whole car's segment overlapping a box that held a part of it, or the car and
    # a sliver of road, by 0.51-0.55 got no box of its own; jam development 95.2 -> 95.6 %; 0.7 the same)
    behind_m: float = 1.0  # m; ... as is one mostly inside a box, unless this far behind the box's
    # surface (a car 1-3 m behind a nearer one is its own; jam development 89.1 % at 3 m, 89.8 % at 1 m)
    score: float = 0.3  # the proposals' score; detected boxes at least this confident explain segments
    max_stem_share: float = 0.25  # a segment whose lowest quarter of rows is one run narrower than
    # this share of its widest row stands on a stem: a tree
    # the fragments of a vehicle that a nearer one cuts in two join its box (join_fragments): a segment
    fragment_depth_m: float = 0.5  # at the box's surface depth (within this + 3 %),
    fragment_gap: float = 0.5  # no farther from the box than this share of the box's larger side
    fragment_gap_m: float = 0.75  # or than this at the box's surface depth (a car's roof corner seen
    # beside a nearer truck, 14 px wide at 13 m, and its lower corner 17 px below: the share alone
    # kept them apart; on the development folders 0.5 m joined 3 more targets' pieces, 0.75 m 6, 1 m 4),
    fragment_hidden: float = 0.5  # with at least this share of the pixels between them nearer (the cut),
    max_width_m: float = 2.7  # and the two together no wider than a vehicle seen from behind, across
    # the camera's view (each side at its own depth: a car's flank seen at an angle adds only what it
    # adds across the view; development seeds 9000-9609, exact depth: 2 targets more, none lost)
    merge_same_segment: bool = True  # on noiseless depth, a proposal whose segment draws a snapped
    # box's outline, of the box's class, while the box reaches below the segment's lowest row on its
    # surface, is that box's vehicle: the box takes the proposal's sides (merge_same_segment; under
    # stereo noise the segment can end short of its car or join the next: 2 development targets lost)
    merge_below_px: float = 2.0  # px; reaching below by more than this (development cases: 7-11 px;
    # a LiDAR proposal of a car's lower half, ending where the box ends, is another car's: 0 px)
    join_truck_fragments: bool = True  # on noiseless depth, truck boxes that share columns and whose
    # cores show one segment, their union within that segment's extent, are one truck's fragments:
    # the best-scored takes the union, the others go (join_truck_fragments; curved seed 5020 at 57.7 s:
    # the CNN's two boxes on one truck at IoU 0.40 / 0.69 with it, their union 0.90). Curve seen seeds
    # 5000-5020, 5030 and 5123 (tuned-on, study fusion arm): wrong highlight episodes 24 -> 17, missed 7 ->
    # 11; development identification, exact depth, 98.4 % with and without it


@dataclass(frozen=True)
class BoxRefineParams:
    margin: float = 0.4  # search window: the box grown by this share of its width / height per side
    # (whole surfaces need room; jam development 89.8 % at 0.25, 91.1 % at 0.4, 90.8 % at 0.45)
    min_height_m: float = 0.05  # above the road by more than this: an object pixel (tyres included)
    band_m: float = 4.0  # depth band of one vehicle's visible surface (see the module docstring)
    candidates: int = 3  # surface depths tried per box
    support: float = 0.03  # rows / columns with less than this share of the fullest one are trimmed
    # (at 0.05 a sliver's last rows, 1 px of a 24 px row, were cut off its box; 0.02 loses 2 jam
    # development targets; 0 keeps the stray pixels of rails and road and breaks most boxes)
    min_iou: float = 0.3  # a segment replaces the box only when its box overlaps the box this much
    pair_width_m: float = 3.0  # a segment across a depth jump laterally wider than any vehicle (2.55 m)
    pair_min_iou: float = 0.5  # is two side by side: a jump-free one, narrower, overlapping the box at
    # least this much replaces it
    jump_m: float = 0.5  # depth discontinuity between neighbours: more than this (+ jump_rel of the
    jump_rel: float = 0.045  # depth, m per m: at 100 m 5 m, so the cars of a far chain come apart;
    # far_chain development 98.0 % at 0.05, 99.0 % at 0.045; 0.035 splits a truck's side seen at a
    # grazing angle); the refinement's cut segments, the proposals and the fragments all use it
    truck_top_m: float = 2.6  # a segment whose top stands higher than this (cars: <= 2 m) is a truck,
    max_height_m: float = 4.5  # unless it stands higher than this (no vehicle does: trees, poles, gantries)
    duplicate_iou: float = 0.7  # the detector's NMS IoU, applied again to the trucks after boxes
    # became trucks
    proposals: ProposalParams | None = ProposalParams()  # None: refine the detected boxes only
    # A depth step that does not need a perfect world (vcfusion.fusion.road; the module docstring's
    # last part). Heights above the road fitted to each depth image ("from_depth") or above the
    # nominal pose's flat road ("flat", exact where depth and pose are: a scenario's fusion.road
    # "auto" picks it there, vcfusion.fusion.stage.road_model)
    road: str = "flat"
    # noisy dense depth (a sensor's DepthNoise; a LiDAR scan is not filtered, fuse.depth_view): a 5 x 5
    # median first (sigma about 0.25 of a pixel's for Gaussian noise, 1.2533 / 5; 0.3 assumed), then
    # object pixels stand noise_k sigma of their height's noise above min_height_m, and a box or
    # segment whose depth's sigma exceeds gate_noise of the depth-jump threshold there (jump_m +
    # jump_rel z) keeps the detector's box (gated)
    denoise_px: int = 5
    denoise_passes: int = 1
    denoise_sigma_share: float = 0.3
    noise_k: float = 3.0
    gate_noise: float = 0.5
    # a box whose core holds less than this share of measured depth (holes, a sparse LiDAR) keeps the
    # detector's box, and an image with less than this share keeps every box and has no depth
    # proposals (gated); a scan's gaps are filled first (scan_fill_px: filled from the nearest return
    # alone the boxes snapped worse than the detector's, 58.9 vs 72.1 % on the development folders)
    gate_valid_share: float = 0.3
    # a sparse scan (less than gate_valid_share measured) first has its gaps filled between returns at
    # most this many pixels apart (down a column, along a row; px): fill_scan_gaps. A 64-beam scan's
    # rows lie 3-4 px apart at f = 457 px and its returns 1-2 px apart along a row; development
    # folders, LiDAR + 0.3 deg: 72.1 % kept sparse (every box gated), 86.0 % filled and then median-
    # filtered, 91.5 % filled (a filled scan is not median-filtered: fuse.depth_view). None: kept sparse
    scan_fill_px: tuple[int, int] | None = (6, 2)
    # a scan's return within this of the fitted road (m, + noise_k sigma of its height's noise) is the
    # road's: two such returns bound a gap filled along the plane (nearest-return fill of the road: 56.6 %
    # on the development folders, the road between two beams 0.1-0.3 m above the plane)
    scan_road_m: float = 0.1
    # on a scan, a side of a snapped box where the depth ends unmeasured (more than this share of the
    # two rows / columns outside it nan) is the detector's: the surface may go on unseen (a truck 9 m
    # ahead above the highest beam, +2 deg; development folders, LiDAR + 0.3 deg: 65.1 % without, 84.5 %
    # with, at scan_min_rows 3)
    unmeasured_share: float = 0.5
    scan_min_rows: int = 5  # a box whose core's columns hold fewer of a scan's returns than this (median
    # over its columns) is gated: its outline lies between the scan's rows (development folders, LiDAR
    # and 0.3 deg, the filled scan median-filtered: 84.5 % at 3, 86.0 % at 5, 86.8 % at 7)
    # a box the noise gate keeps as detected (gate_noise: a stereo car beyond about 34 m) has its sides
    # placed from the image instead by a small CNN on an RGB crop around it (vcfusion.fusion.far_boxes):
    # "shipped" the package's far_box_head.pt, a path another weights file, None keeps the detector's
    # box. Boxes gated for too little measured depth or too few scan rows keep it (development folders,
    # LiDAR + 0.3 deg: 91.5 % keeping them, 90.7 % with the head on them)
    box_head: str | None = "shipped"
    # a left / right side the snap moved inward over its own surface (no depth jump) is given back, up
    # to the detector's side (_surface_sides; development folders and seeds 9100-9109 / 9200-9209, exact
    # depth: 367 -> 369 of 379 targets)
    surface_sides: bool = True
    # on noisy dense depth (stereo, ToF; not a scan), a left / right side the snap moved outward of the
    # detector's box ends where the segment's column medians leave the depth at the detector's side by
    # more than the jump threshold (_grown_sides; development seeds 9000-9609, stereo + 0.3 deg: 5 snapped
    # boxes more at IoU 0.7 with their target, none fewer; the SUMO identification study's 2 targets)
    grown_sides: bool = True
    # on noisy dense depth, a side the snap moved inward by at least this share of the detector's box
    # (width for left / right, height for top / bottom) is the detector's where more than
    # unmeasured_share of the two rows / columns beyond it are holes (_unmeasured_sides, as on a scan):
    # a truck's textureless panel 5-9 m ahead is a hole wider than hole_fill_px, and its box lost a
    # third of its height or width to it (development seeds 9000-9609, stereo + 0.3 deg: 4 snapped boxes
    # more at IoU 0.7, none fewer; at 0.1 the same; every side moved, whatever the share: 5 more, 4
    # fewer, the top of a far car against the unmatched sky). 0: off
    hole_side_share: float = 0.2
    hole_fill_px: int = 16  # px; stereo depth (DepthNoise.c > 0): holes up to this wide filled along rows
    # (fill_scan_gaps, occlusion bands with the farther depth; development folders, stereo + 0.3 deg:
    # 81.4 % without, 82.9 % at 16 px, 82.2 % at 48 px)

    def __post_init__(self):
        for name, low, high in (("margin", 0.0, 2.0), ("support", 0.0, 1.0), ("min_iou", 0.0, 1.0),
                                ("pair_min_iou", 0.0, 1.0), ("unmeasured_share", 0.0, 1.0)):
            v = getattr(self, name)
            if not low <= v <= high:
                raise ValueError(f"{name}: expected a value in [{low}, {high}], got {v}")
        if self.pair_width_m <= 0:
            raise ValueError(f"pair_width_m: expected a positive width, got {self.pair_width_m}")
        if self.scan_fill_px is not None and (len(self.scan_fill_px) != 2 or min(self.scan_fill_px) < 0):
            raise ValueError(f"scan_fill_px: expected None or two gap widths >= 0 (px), got {self.scan_fill_px}")
        if self.hole_fill_px < 0 or self.scan_min_rows < 0 or self.scan_road_m < 0:
            raise ValueError("hole_fill_px, scan_min_rows, scan_road_m: expected values >= 0, got "
                             f"{self.hole_fill_px}, {self.scan_min_rows}, {self.scan_road_m}")
        if self.band_m <= 0 or self.candidates < 1:
            raise ValueError(f"band_m and candidates: expected positive values, got {self.band_m}, {self.candidates}")


@dataclass(frozen=True)
class RefinedBoxes:
    boxes: np.ndarray  # (N, 4) x1, y1, x2, y2: refined where `refined`, else the detected box
    refined: np.ndarray  # (N,) bool
    top_m: np.ndarray  # (N,) height above the road of the refined segment's top (95th percentile), nan if not refined
    gated: np.ndarray | None = None  # (N,) bool: depth could not support a decision (kept as detected)
    noisy: np.ndarray | None = None  # (N,) bool: gated because the depth's noise there exceeds gate_noise


def _box_iou(a: np.ndarray, b: np.ndarray) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def _core(box: np.ndarray, x0: int, y0: int) -> tuple[slice, slice]:
    """Rows and columns of the box's central half in each direction, in an array whose pixel
    (0, 0) is image pixel (x0, y0)."""
    w, h = box[2] - box[0], box[3] - box[1]
    return (slice(max(int(box[1] + 0.25 * h) - y0, 0), max(int(np.ceil(box[3] - 0.25 * h)) - y0 + 1, 0)),
            slice(max(int(box[0] + 0.25 * w) - x0, 0), max(int(np.ceil(box[2] - 0.25 * w)) - x0 + 1, 0)))


class _Heights:
    """Height above the road of the point seen at each pixel: camera-Z times a term linear in the
    pixel coordinates, minus a constant (the world-z row of the inverse pose and intrinsics)."""

    def __init__(self, K: np.ndarray, T_world_to_camera: np.ndarray):
        K = np.asarray(K, float)
        T = np.asarray(T_world_to_camera, float)
        if K.shape != (3, 3) or T.shape != (4, 4):
            raise ValueError(f"camera: expected K (3, 3) and T_world_to_camera (4, 4), got {K.shape} and {T.shape}")
        up = T[:3, 2]  # world z axis in camera coordinates (third column of R)
        ray = up @ np.linalg.inv(K)  # world-z component of the ray through (u, v, 1), per unit camera-Z
        self.per_u, self.per_v, self.const = (float(x) for x in ray)
        self.offset = float(up @ T[:3, 3]) + ROAD_Z_M

    def noise_margin(self, z: np.ndarray, noise, k: float):
        """k sigma of the height's noise at depth z (0 for exact depth): sigma_z(z) h / z, h the
        camera's height above the road (the slope of a road point's height in its depth)."""
        if noise is None or noise.exact:
            return np.float32(0.0)
        cam_h = max(-self.offset, 0.5)
        return np.float32(k) * noise.sigma(z) * np.float32(cam_h) / np.maximum(z, np.float32(1.0))

    def window(self, z: np.ndarray, x0: int, y0: int) -> np.ndarray:
        h, w = z.shape
        u = np.arange(x0, x0 + w, dtype=np.float32) * np.float32(self.per_u)
        v = np.arange(y0, y0 + h, dtype=np.float32) * np.float32(self.per_v) + np.float32(self.const)
        return z * (v[:, None] + u[None, :]) - np.float32(self.offset)


def _farther(a, b, jump_m: float, jump_rel: float):
    """Whether depth a lies behind depth b by a jump: more than jump_m + jump_rel of the depth (the
    one definition of a depth discontinuity for the refinement and the proposals)."""
    return a > b * np.float32(1 + jump_rel) + np.float32(jump_m)


def _same_surface(a, b, jump_m: float, jump_rel: float):
    """Whether depths a and b belong to one surface: no jump either way."""
    return ~_farther(a, b, jump_m, jump_rel) & ~_farther(b, a, jump_m, jump_rel)


def _jump_free(z: np.ndarray, valid: np.ndarray, jump_m: float, jump_rel: float) -> np.ndarray:
    """False at the farther pixel of each 4-neighbour pair whose depths jump (:func:`_farther`; no
    depth counts as infinitely far, so a vehicle keeps its outline against the sky). One compiled
    pass (:func:`_jump_free_kernel`)."""
    z = np.asarray(z, np.float32)
    valid = np.asarray(valid, np.bool_)
    if z.shape != valid.shape or z.ndim != 2:
        raise ValueError(f"z, valid: expected one 2-D shape, got {z.shape} and {valid.shape}")
    keep = np.empty(z.shape, np.bool_)
    _jump_free_kernel(z, valid, np.float32(jump_m), np.float32(1 + jump_rel), keep)
    return keep


@numba.njit(cache=True)
def _jump_free_kernel(z, valid, jump_m, one_plus_rel, keep):
    """_jump_free per pixel: not farther (a > b (1 + jump_rel) + jump_m, in float32) than any of its
    4-neighbours, a pixel without depth reading inf."""
    H, W = z.shape
    inf = np.float32(np.inf)
    for y in range(H):
        for x in range(W):
            a = z[y, x] if valid[y, x] else inf
            k = True
            for d in range(4):
                ny, nx = y, x
                if d == 0:
                    ny = y - 1
                elif d == 1:
                    ny = y + 1
                elif d == 2:
                    nx = x - 1
                else:
                    nx = x + 1
                if ny < 0 or ny >= H or nx < 0 or nx >= W:
                    continue
                b = z[ny, nx] if valid[ny, nx] else inf
                if a > b * one_plus_rel + jump_m:
                    k = False
                    break
            keep[y, x] = k


@numba.njit(cache=True)
def _label_boxes(labels, n):
    """(n, 4) row start, row stop, column start, column stop of each label 1..n in `labels` (as
    scipy.ndimage.find_objects' slices; -1 where a label holds no pixel), in one pass."""
    out = np.full((n, 4), -1, np.int64)
    H, W = labels.shape
    for y in range(H):
        for x in range(W):
            k = labels[y, x]
            if k < 1 or k > n:
                continue
            b = out[k - 1]
            if b[0] < 0:
                b[0], b[1], b[2], b[3] = y, y + 1, x, x + 1
            else:
                b[1] = y + 1  # rows come in order
                if x < b[2]:
                    b[2] = x
                if x + 1 > b[3]:
                    b[3] = x + 1
    return out


def _restore_outlines(labels: np.ndarray, removed: np.ndarray, z: np.ndarray, jump_m: float,
                      jump_rel: float) -> np.ndarray:
    """Segment labels with the pixels the cut removed given back: each removed pixel (the farther of
    a jumping pair, so the outline of a vehicle a nearer one hides) takes the label of a 4-neighbour
    on its own surface (no jump either way), pass after pass until no pixel changes, so a strip of
    them (the lower part of a truck seen 1-2 px wide between two nearer vehicles, where every pixel
    is the farther one of some pair) goes back to its surface whole, not one pixel deep. Without
    this a sliver of a hidden car, 12 px wide, loses a pixel on each hidden side and its box misses
    IoU 0.7 with the true one. Each pass reads the labels the previous one left; of several
    neighbours, right, left, below, above is the order of preference."""
    z = np.asarray(z, np.float32)
    if labels.shape != removed.shape or labels.shape != z.shape:
        raise ValueError(f"labels, removed, z: expected one shape, got {labels.shape}, {removed.shape}, {z.shape}")
    return _restore_kernel(labels, np.asarray(removed, np.bool_), z, np.float32(jump_m), np.float32(1 + jump_rel))


@numba.njit(cache=True)
def _restore_kernel(labels, removed, z, jump_m, one_plus_rel):
    """_restore_outlines compiled: the pixels to give back in row-major order, each with its
    neighbours on its own surface (right, left, below, above; -1: off the image or off its surface),
    then passes that each read the labels the previous one left (all found, then all written)."""
    H, W = labels.shape
    out = labels.copy()
    n = 0
    for y in range(H):
        for x in range(W):
            if removed[y, x] and labels[y, x] == 0:
                n += 1
    pending = np.empty(n, np.int64)
    neighbours = np.full((n, 4), -1, np.int64)
    k = 0
    for y in range(H):
        for x in range(W):
            if not (removed[y, x] and labels[y, x] == 0):
                continue
            pending[k] = y * W + x
            a = z[y, x]
            for d in range(4):
                ny, nx = y, x
                if d == 0:
                    nx = x + 1
                elif d == 1:
                    nx = x - 1
                elif d == 2:
                    ny = y + 1
                else:
                    ny = y - 1
                if ny < 0 or ny >= H or nx < 0 or nx >= W:
                    continue
                b = z[ny, nx]
                if not (a > b * one_plus_rel + jump_m) and not (b > a * one_plus_rel + jump_m):
                    neighbours[k, d] = ny * W + nx
            k += 1
    flat = out.reshape(-1)
    found = np.zeros(n, out.dtype)
    left = np.arange(n)
    while len(left):
        given = 0
        for j in range(len(left)):
            i = left[j]
            f = 0
            for d in range(4):
                q = neighbours[i, d]
                if q >= 0 and flat[q] > 0:
                    f = flat[q]
                    break
            found[i] = f
            if f > 0:
                given += 1
        if given == 0:
            break
        rest = np.empty(len(left) - given, np.int64)
        r = 0
        for j in range(len(left)):
            i = left[j]
            if found[i] > 0:
                flat[pending[i]] = found[i]
            else:
                rest[r] = i
                r += 1
        left = rest
    return out


def _join_across_outlines(labels: np.ndarray, z: np.ndarray, jump_m: float, jump_rel: float) -> np.ndarray:
    """Segment labels with the segments that touch as one surface made one (each takes the lowest
    label among them). Why: the cut removes the farther pixel of every jumping pair, so where a
    vehicle shows 1-2 px wide beside a nearer one every pixel of that strip goes, and its parts above
    and below become two segments; :func:`_restore_outlines` gives each pixel back to one neighbour's
    segment but does not join the two (a car's sliver beside a nearer car lost its lower third)."""
    z = np.asarray(z, np.float32)
    if labels.shape != z.shape or labels.ndim != 2:
        raise ValueError(f"labels, z: expected one 2-D shape, got {labels.shape} and {z.shape}")
    return _join_pairs(labels, _touching_pairs(labels, z, np.float32(jump_m), np.float32(1 + jump_rel)))


def _join_pairs(labels: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Labels with every pair of labels (a 2 x n array) joined into one: each group of labels
    linked by pairs takes its lowest label, so labels in no pair keep their number."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if not pairs.shape[1]:
        return labels
    n = int(labels.max()) + 1
    graph = coo_matrix((np.ones(pairs.shape[1]), (pairs[0], pairs[1])), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    lowest = np.full(n, n)
    np.minimum.at(lowest, component, np.arange(n))
    return lowest[component][labels]


@numba.njit(cache=True)
def _touching_pairs(labels, z, jump_m, one_plus_rel):
    """(2, N) the label pairs of 4-neighbour pixels in two different segments on one surface (no
    jump either way, :func:`_same_surface`), each pair of labels once (the smaller first)."""
    H, W = labels.shape
    seen = set()
    out = []
    for y in range(H):
        for x in range(W):
            a = labels[y, x]
            if a <= 0:
                continue
            za = z[y, x]
            for d in range(2):
                ny, nx = (y + 1, x) if d == 0 else (y, x + 1)
                if ny >= H or nx >= W:
                    continue
                b = labels[ny, nx]
                if b <= 0 or b == a:
                    continue
                zb = z[ny, nx]
                if za > zb * one_plus_rel + jump_m or zb > za * one_plus_rel + jump_m:
                    continue
                lo, hi = (a, b) if a < b else (b, a)
                key = np.int64(lo) * np.int64(2 ** 31) + np.int64(hi)
                if key not in seen:
                    seen.add(key)
                    out.append((np.int64(lo), np.int64(hi)))
    pairs = np.empty((2, len(out)), np.int64)
    for i in range(len(out)):
        pairs[0, i], pairs[1, i] = out[i]
    return pairs


def _components(mask: np.ndarray) -> np.ndarray:
    """4-connected segment labels of a mask (0: not in it)."""
    return cv2.connectedComponents(mask.astype(np.uint8), connectivity=4)[1]


def _segment_box(sel: np.ndarray, support: float, x0: int, y0: int) -> np.ndarray:
    """The box (pixel-centre convention) from the first to the last column, and row, of mask `sel`
    holding at least `support` of the fullest one's pixels; `sel`'s pixel (0, 0) is image pixel
    (x0, y0). One compiled pass (:func:`_segment_box_kernel`)."""
    sel = np.ascontiguousarray(sel, np.bool_)
    if sel.ndim != 2 or not sel.size:
        raise ValueError(f"segment mask: expected a non-empty 2-D mask, got shape {sel.shape}")
    return _segment_box_kernel(sel, float(support), int(x0), int(y0))


@numba.njit(cache=True)
def _segment_box_kernel(sel, support, x0, y0):
    """_segment_box: column and row pixel counts, each compared with support x its maximum (float64,
    as the array expressions cols >= support * cols.max() compare them)."""
    H, W = sel.shape
    cols = np.zeros(W, np.int64)
    rows = np.zeros(H, np.int64)
    for y in range(H):
        for x in range(W):
            if sel[y, x]:
                cols[x] += 1
                rows[y] += 1
    out = np.empty(4, np.float64)
    for counts, lo, hi, origin in ((cols, 0, 2, x0), (rows, 1, 3, y0)):
        thr = support * np.float64(counts.max())
        first, last = -1, -1
        for i in range(len(counts)):
            if np.float64(counts[i]) >= thr:
                if first < 0:
                    first = i
                last = i
        out[lo] = np.float64(origin + first) - 0.5
        out[hi] = np.float64(origin + last) + 0.5
    return out


def _lateral_extent(sel: np.ndarray, z: np.ndarray, x0: int, K: np.ndarray, support: float) -> float:
    """How wide a segment is across the camera's view, in metres: camera X of its leftmost and
    rightmost columns (those :func:`_segment_box` keeps) at their median depths. Unlike image width x
    depth, the side of a vehicle in the next lane, which runs away from the camera, adds nothing."""
    cols = sel.sum(axis=0)
    xs = np.flatnonzero(cols >= support * cols.max())
    ends = []
    for c in (xs[0], xs[-1]):
        ends.append((x0 + c - K[0, 2]) * float(np.median(z[sel[:, c], c])) / K[0, 0])
    return ends[1] - ends[0]


def gate_by_noise(z_m: float, noise, params: BoxRefineParams) -> bool:
    """Whether depth of this noise at z_m cannot tell one surface from the next: its sigma exceeds
    ``gate_noise`` of the depth-jump threshold there."""
    if noise is None or noise.exact:
        return False
    return float(noise.sigma(z_m)) > params.gate_noise * (params.jump_m + params.jump_rel * z_m)


def refine_boxes(boxes: np.ndarray, depth: np.ndarray, K: np.ndarray, T_world_to_camera: np.ndarray,
                 params: BoxRefineParams = BoxRefineParams(), noise=None,
                 returns: np.ndarray | None = None) -> RefinedBoxes:
    """Each box snapped to the depth segment that explains it best (module docstring); with
    ``noise`` (vcfusion.fusion.road.DepthNoise of `depth`), a box depth cannot decide is gated.
    ``returns``: (H, W) bool, the pixels a scan measured when `depth` is a scan with its gaps filled
    (:func:`fill_scan_gaps`): a box crossed by fewer than ``scan_min_rows`` of the scan's rows is
    gated, and a side of a snapped box that ends where the scan measured nothing is the detector's
    (:func:`_unmeasured_sides`)."""
    boxes = np.asarray(boxes, float).reshape(-1, 4)
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth: expected a 2-D depth image (H, W), got shape {depth.shape}")
    heights = _Heights(K, T_world_to_camera)
    K = np.asarray(K, float)
    H, W = depth.shape
    out = boxes.copy()
    refined = np.zeros(len(boxes), bool)
    top_m = np.full(len(boxes), np.nan)
    gated = np.zeros(len(boxes), bool)
    noisy = np.zeros(len(boxes), bool)
    p = params
    # with a noisy sensor, each box's median measured depth in its core (nan: none): what the noise
    # gate tests, and the depth of the boxes beside a grown side (_grown_sides)
    box_z = np.full(len(boxes), np.nan)
    if noise is not None and not noise.exact:
        depth32 = np.asarray(depth, np.float32)
        for k, b in enumerate(boxes):
            if b[2] > b[0] and b[3] > b[1]:
                zc = depth32[_core(b, 0, 0)]
                zc = zc[np.isfinite(zc) & (zc > 0)]
                box_z[k] = float(np.median(zc)) if zc.size else np.nan
    # a dense image whose error grows with range (stereo, ToF): the median-filtered, hole-filled depth
    # the two side rules below are for; exact depth and a LiDAR scan (range noise alone) never reach them
    dense_noisy = noise is not None and (noise.b > 0 or noise.c > 0) and returns is None
    for i, b in enumerate(boxes):
        w, h = b[2] - b[0], b[3] - b[1]
        if not (w > 0 and h > 0):
            continue
        mx, my = max(p.margin * w, 3.0), max(p.margin * h, 3.0)
        x0, y0 = max(0, int(np.floor(b[0] - mx))), max(0, int(np.floor(b[1] - my)))
        x1, y1 = min(W, int(np.ceil(b[2] + mx)) + 1), min(H, int(np.ceil(b[3] + my)) + 1)
        if x1 <= x0 or y1 <= y0:
            continue
        z = depth[y0:y1, x0:x1].astype(np.float32)
        core = _core(b, x0, y0)  # at least one pixel
        if np.isnan(z[core]).mean() > 1 - p.gate_valid_share:  # no measurement (holes, a sparse scan)
            gated[i] = True
            continue
        if returns is not None:
            # a box crossed by too few of the scan's rows: its outline lies between them, unseen
            core_returns = returns[y0:y1, x0:x1][core]
            if not core_returns.size or np.median(core_returns.sum(axis=0)) < p.scan_min_rows:
                gated[i] = True
                continue
        valid = np.isfinite(z) & (z > 0)
        if np.isfinite(box_z[i]) and gate_by_noise(float(box_z[i]), noise, p):
            gated[i] = noisy[i] = True  # too noisy at this depth to tell one surface from the next
            continue
        z = np.where(valid, z, np.float32(0))
        height = heights.window(z, x0, y0)
        obj = valid & (height > p.min_height_m + heights.noise_margin(z, noise, p.noise_k))
        core_z = z[core][obj[core]]
        if core_z.size < 3:
            continue
        jump_free = _jump_free(z, valid, p.jump_m, p.jump_rel)
        log_z = np.log(core_z)
        edges = np.arange(log_z.min(), log_z.max() + 0.05, 0.04)
        hist, edges = np.histogram(log_z, bins=edges)
        jump = ~jump_free
        segmentations = []  # (labels, cut at depth jumps) per way of splitting the window's object pixels
        for j in np.argsort(-hist, kind="stable")[: p.candidates]:
            if hist[j] == 0:
                break
            z0 = float(np.exp(edges[j]))
            band = obj & (z > z0 - 0.3 * p.band_m - 0.03 * z0) & (z < z0 + p.band_m + 0.03 * z0)
            segmentations.append((_components(band), False))
            cut = band & jump_free
            if (band > cut).any():
                segmentations.append((_restore_outlines(_components(cut), band & ~cut, z, p.jump_m, p.jump_rel), True))
        # and the surfaces whole, however deep (the side of a truck in the next lane runs 15 m away)
        whole = obj & jump_free
        segmentations.append((_restore_outlines(_components(whole), obj & ~whole, z, p.jump_m, p.jump_rel), True))
        # (IoU with the detected box, segment box, (rows, columns) of the window holding the segment,
        # its mask there, cut at depth jumps): each segment's mask within its bounding box only
        candidates = []
        whole_window = (slice(None), slice(None))
        for labels, is_cut in segmentations:
            in_core = np.unique(labels[core])
            in_core = in_core[in_core > 0]
            if not in_core.size:
                continue
            # with support 0 every column of the window counts (_segment_box): the whole window then
            regions = _label_boxes(labels, int(in_core[-1])) if p.support > 0 else None
            for label in in_core:
                r = whole_window
                if regions is not None:
                    r0, r1, c0, c1 = regions[label - 1]
                    r = (slice(int(r0), int(r1)), slice(int(c0), int(c1)))
                sel = labels[r] == label
                candidate = _segment_box(sel, p.support, x0 + (r[1].start or 0), y0 + (r[0].start or 0))
                iou = _box_iou(candidate, b)
                if iou > p.min_iou:
                    candidates.append((iou, candidate, r, sel, is_cut))
        best = best_sel = None
        if candidates:
            candidates.sort(key=lambda c: -c[0])  # stable: of equal overlaps, the first found
            _, best, best_r, best_sel, best_is_cut = candidates[0]
            # a box over two vehicles side by side (two trucks in neighbouring lanes a few metres
            # apart in depth, inside one band) snaps best to the pair: when that segment spans a depth
            # jump and is wider than any vehicle, a jump-free segment no wider that still explains the
            # box takes its place, and the other vehicle, no longer inside a box, becomes a proposal.
            # Jump-free, because a car mid lane change, seen at an angle, is 3-4 m across the view
            # with its side, one surface: its wheels and mirrors must not pass for a second vehicle
            if (_spans_jump(best_sel, best_is_cut, jump[best_r])
                    and _lateral_extent(best_sel, z[best_r], x0 + (best_r[1].start or 0), K, p.support)
                    > p.pair_width_m):
                for iou, candidate, r, sel, is_cut in candidates[1:]:
                    if iou < p.pair_min_iou:
                        break
                    if (not _spans_jump(sel, is_cut, jump[r])
                            and _lateral_extent(sel, z[r], x0 + (r[1].start or 0), K, p.support) <= p.pair_width_m):
                        best, best_r, best_sel = candidate, r, sel
                        break
        if best is not None:
            if p.surface_sides:
                best = _surface_sides(best, b, best_r, best_sel, segmentations[-1][0], x0, y0, p.support)
            if p.grown_sides and dense_noisy:
                best = _grown_sides(best, b, best_r, best_sel, z, x0, y0, p.jump_m, p.jump_rel,
                                    np.delete(boxes, i, axis=0), np.delete(box_z, i))
            if returns is not None:
                best = _unmeasured_sides(best, b, np.isnan(depth[y0:y1, x0:x1]), x0, y0, p.unmeasured_share)
            elif p.hole_side_share > 0 and dense_noisy:
                # noisy dense depth: a side moved inward by hole_side_share of the box or more, where
                # the depth beyond it is holes (a textureless panel the pair could not match)
                best = _unmeasured_sides(best, b, np.isnan(depth[y0:y1, x0:x1]), x0, y0, p.unmeasured_share,
                                         p.hole_side_share)
            out[i] = best
            refined[i] = True
            top_m[i] = float(np.percentile(height[best_r][best_sel], 95))
    return RefinedBoxes(out, refined, top_m, gated, noisy)


def _surface_sides(best: np.ndarray, detected: np.ndarray, best_r: tuple[slice, slice], best_sel: np.ndarray,
                   whole: np.ndarray, x0: int, y0: int, support: float) -> np.ndarray:
    """The snapped box with a left or right side it moved inward over its own surface given back, up
    to the detector's side: where the snapped side lies inside the detector's box and the surface the
    snapped segment belongs to (its segment among the window's surfaces whole, `whole`, cut only at
    depth jumps) goes on beyond it. A band's cut can split one vehicle where no depth jump does (the
    flank of a car seen at an angle above a nearer car's roof, cut off its rear face, which then
    overlapped the detector's box a little more than the car whole did: its box lost a fifth of its
    width); the depth does not support that, and the detector's side stands, or the surface's own side
    where it ends before the detector's. Left and right only: the same rule for the top and bottom
    sides cost a target on the development seeds (a car 34 m ahead whose bottom it gave back 4 px)
    and gained none. `best_r`, `best_sel`: the
    snapped segment's rows and columns in the window and its mask there; `whole`'s pixel (0, 0) is
    image pixel (x0, y0)."""
    left, right = best[0] - detected[0] >= 1.0, detected[2] - best[2] >= 1.0  # moved inward
    if not (left or right):
        return best
    labels = whole[best_r][best_sel]
    labels = labels[labels > 0]
    if not labels.size:
        return best
    surface = _segment_box(whole == np.bincount(labels).argmax(), support, x0, y0)
    out = best.copy()
    if left and best[0] - surface[0] >= 1.0:  # the left side moved right, over its own surface
        out[0] = max(detected[0], surface[0])
    if right and surface[2] - best[2] >= 1.0:  # the right side moved left, over its own surface
        out[2] = min(detected[2], surface[2])
    return out


def _grown_sides(best: np.ndarray, detected: np.ndarray, best_r: tuple[slice, slice], best_sel: np.ndarray,
                 z: np.ndarray, x0: int, y0: int, jump_m: float, jump_rel: float,
                 others: np.ndarray | None = None, others_z: np.ndarray | None = None) -> np.ndarray:
    """The snapped box with a left or right side that the snap moved outward of the detector's box drawn
    back to where the snapped segment's depth leaves that at the detector's side: each column is the
    segment's median depth down it, the reference is the last column inside the detector's side, and
    going outward the first column whose median lies more than the depth-jump threshold (jump_m +
    jump_rel z) from the reference ends the side before it; never inside the detector's side. Nor does
    it go past the near side of another of the detector's boxes beside it (`others`, the other boxes;
    `others_z`, their cores' median depths) that stands at the reference's depth within the same
    threshold: two vehicles side by side at one depth (two trucks stopped abreast) are one surface to
    depth, two to the detector. On noisy depth the 5 x 5 median and the hole fill bridge a jump between
    two surfaces with intermediate depths, each step below the threshold from its neighbour, and the
    pixel-level segment runs on over the next vehicle or a barrier; a column's median has the noise
    averaged out, and a fixed reference does not drift along a ramp. `best_r`, `best_sel`: the segment's
    rows and columns in the search window `z` (whose pixel (0, 0) is image pixel (x0, y0)) and its mask
    there."""
    out = best.copy()
    zs = np.where(best_sel, z[best_r], np.nan)
    origin = x0 + (best_r[1].start or 0)  # image column of best_sel's column 0
    n = zs.shape[1]
    filled = best_sel.any(axis=0)
    column = np.full(n, np.nan)
    column[filled] = np.nanmedian(zs[:, filled], axis=0)
    inner = (int(np.clip(np.ceil(detected[0] - origin), 0, n - 1)),  # the detector's box's outermost
             int(np.clip(np.floor(detected[2] - origin), 0, n - 1)))  # columns, left and right
    for side, step, start in ((0, -1, inner[0]), (2, 1, inner[1])):
        if (best[side] - detected[side]) * step < 1.0:  # not moved outward by a pixel or more
            continue
        ref, last, j = column[start], start, start + step
        if not np.isfinite(ref):
            continue
        while 0 <= j < n:
            if np.isfinite(column[j]):
                if abs(column[j] - ref) > jump_m + jump_rel * min(column[j], ref):
                    break
                last = j
            j += step
        edge = origin + last + 0.5 * step
        if others is not None and len(others):
            # another of the detector's boxes beside this one, on the side grown (its centre beyond the
            # detector's side, rows shared over half the smaller height): the side ends at its near side
            centre = 0.5 * (others[:, 0] + others[:, 2])
            shared = np.minimum(others[:, 3], detected[3]) - np.maximum(others[:, 1], detected[1])
            beside = shared >= 0.5 * np.minimum(others[:, 3] - others[:, 1], detected[3] - detected[1])
            beside &= np.abs(others_z - ref) <= jump_m + jump_rel * np.minimum(others_z, ref)
            if step < 0:
                near = others[beside & (centre < detected[0]), 2]
                edge = max(edge, near.max()) if near.size else edge
            else:
                near = others[beside & (centre > detected[2]), 0]
                edge = min(edge, near.min()) if near.size else edge
        out[side] = min(max(edge, best[0]), detected[0]) if step < 0 else max(min(edge, best[2]), detected[2])
    return out


def _unmeasured_sides(best: np.ndarray, detected: np.ndarray, hole: np.ndarray, x0: int, y0: int,
                      share: float, min_inward: float | None = None) -> np.ndarray:
    """The snapped box with each side where depth ends in a hole taken from the detector's box: when
    more than ``share`` of the two pixel rows (columns) just outside a side, across the box, measured
    nothing (nan: beyond a LiDAR's highest beam, a stereo hole), the surface may go on there unseen
    (a near truck's upper half above a 64-beam scan's +2 deg). `hole`: the search window's nan mask,
    whose pixel (0, 0) is image pixel (x0, y0). ``min_inward``: only sides the snap moved inward of
    the detector's by at least this share of the detector's box (its width for left / right, its
    height for top / bottom); None: every side."""
    out = best.copy()
    if min_inward is None:
        inward = np.ones(4, bool)
    else:
        w, h = detected[2] - detected[0], detected[3] - detected[1]
        inward = (best - detected) * np.array([1, 1, -1, -1]) >= min_inward * np.array([w, h, w, h])
    Hh, Ww = hole.shape
    c0, c1 = max(int(best[0] + 0.5) - x0, 0), min(int(best[2] + 0.5) - x0, Ww)
    r0, r1 = max(int(best[1] + 0.5) - y0, 0), min(int(best[3] + 0.5) - y0, Hh)
    if c1 <= c0 or r1 <= r0:
        return out
    strips = ((1, hole[max(r0 - 2, 0):r0, c0:c1]), (3, hole[r1:r1 + 2, c0:c1]),
              (0, hole[r0:r1, max(c0 - 2, 0):c0]), (2, hole[r0:r1, c1:c1 + 2]))
    for side, strip in strips:
        if inward[side] and strip.size and strip.mean() > share:
            out[side] = detected[side]
    return out


def _spans_jump(sel: np.ndarray, is_cut: bool, jump: np.ndarray) -> bool:
    """Whether a candidate segment holds a depth jump; a cut segment holds none (the pixels given back
    to it are its own outline, each the farther of a jumping pair whose partner lies outside it)."""
    return not is_cut and bool((sel & jump).any())


def _surface_depth(z: np.ndarray, obj: np.ndarray, box: np.ndarray, y0: int) -> float:
    """Median depth of the object pixels in a box's core (arrays starting at image row y0); inf if none."""
    core = _core(box, 0, y0)
    depths = z[core][obj[core]]
    return float(np.median(depths)) if depths.size else np.inf


def _beyond_outline(sel: np.ndarray, x: int, y: int, rows_away: int, n_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """Image rows and columns ``rows_away`` rows below (> 0) or above (< 0) each pixel of a segment's
    lower (resp. upper) outline, those inside rows 0..n_rows-1. `sel` is the segment's mask in its
    bounding box, whose pixel (0, 0) is image pixel (x, y)."""
    shifted = np.zeros_like(sel)
    if rows_away > 0:
        shifted[:-1] = sel[1:]  # the pixel below is in the segment
    else:
        shifted[1:] = sel[:-1]  # the pixel above is
    rows, cols = np.nonzero(sel & ~shifted)
    rows, cols = rows + y + rows_away, cols + x
    inside = (rows >= 0) & (rows < n_rows)
    return rows[inside], cols[inside]


def _nearer_object(rows: np.ndarray, cols: np.ndarray, z: np.ndarray, obj: np.ndarray, depth_m: float,
                   jump_m: float, jump_rel: float) -> np.ndarray:
    """Per pixel (rows, cols): an object pixel nearer than a segment at depth_m by a depth jump."""
    return obj[rows, cols] & _farther(np.float32(depth_m), z[rows, cols], jump_m, jump_rel)


def _seen_over_nearer(sel: np.ndarray, x: int, y: int, z: np.ndarray, obj: np.ndarray, depth_m: float,
                      jump_m: float, jump_rel: float) -> bool:
    """Whether most of a segment's lower outline rests on a nearer object: the top of a truck seen
    over the vehicle in front of it, not a trunk standing on the ground. The object is looked for two
    rows below the outline: one row may still be the segment's own pixel that the cut removed, where
    :func:`_restore_outlines` found no neighbour of its surface to give it back to."""
    rows, cols = _beyond_outline(sel, x, y, 2, z.shape[0])
    if not len(rows):
        return False
    return bool(_nearer_object(rows, cols, z, obj, depth_m, jump_m, jump_rel).mean() > 0.5)


def _continues_above(sel: np.ndarray, x: int, y: int, z: np.ndarray, valid: np.ndarray, height: np.ndarray,
                     max_height_m: float, jump_m: float, jump_rel: float) -> float:
    """Share of a segment's top outline whose upper neighbour is the same surface (no depth jump
    either way) standing higher than any vehicle: a tree crown or a pole cut at the height cap."""
    rows, cols = _beyond_outline(sel, x, y, -1, z.shape[0])
    if not len(rows):
        return 0.0
    same = valid[rows, cols] & _same_surface(z[rows, cols], z[rows + 1, cols], jump_m, jump_rel)
    return float((same & (height[rows, cols] >= max_height_m)).mean())


def _on_a_stem(sel: np.ndarray, x: int, y: int, z: np.ndarray, obj: np.ndarray, depth_m: float, share: float,
               jump_m: float, jump_rel: float, stem_rows: float = 0.25) -> bool:
    """Whether a segment stands on one narrow stem: each of its lowest rows (``stem_rows`` of them, at
    least two) is a single run of pixels narrower than ``share`` of its widest row, under the middle
    of it, with nothing nearer beside it (a tree's trunk under its crown; a vehicle stands on its
    full width, and what nearer ones leave of it runs down one side of them or between them)."""
    rows = np.flatnonzero(sel.any(axis=1))
    n = max(2, int(round(stem_rows * len(rows))))
    if len(rows) < 2 * n:
        return False
    widths = sel.sum(axis=1)
    low = sel[rows[-n:]]
    runs = low[:, 0].astype(int) + (low[:, 1:] & ~low[:, :-1]).sum(axis=1)
    if not (np.all(runs == 1) and np.all(widths[rows[-n:]] <= share * widths.max())):
        return False
    # under the middle of the crown (what shows of a car beside a nearer one runs down one side)
    cols = np.arange(sel.shape[1])
    widest = sel[int(np.argmax(widths))]
    crown = cols[widest].mean()
    stem = (low * cols).sum() / low.sum()
    if abs(stem - crown) > 0.2 * widths.max():
        return False
    # the pixels just left and right of the stem: a gap between nearer vehicles shows a vehicle, not a trunk
    r = rows[-n:]
    first, last = np.argmax(low, axis=1), low.shape[1] - 1 - np.argmax(low[:, ::-1], axis=1)
    side_r = np.r_[r, r] + y
    side_c = np.r_[first - 1, last + 1] + x
    inside = (side_c >= 0) & (side_c < z.shape[1])
    side_r, side_c = side_r[inside], side_c[inside]
    return bool(len(side_r) == 0 or _nearer_object(side_r, side_c, z, obj, depth_m, jump_m, jump_rel).mean() < 0.5)


@dataclass(frozen=True)
class ObjectSegments:
    """The object pixels of a whole depth image cut at depth jumps into 4-connected segments (what
    the proposals and the fragments work on), on the image rows ``y_lo`` onward that hold any."""

    z: np.ndarray  # (h, W) camera-Z, 0 where no depth
    valid: np.ndarray  # (h, W) bool: a depth
    obj: np.ndarray  # (h, W) bool: an object pixel (between the proposals' min height and max_height_m)
    height: np.ndarray  # (h, W) height above the road, m
    labels: np.ndarray  # (h, W) segment label, 0 = none
    areas: np.ndarray  # pixels per label
    regions: list  # per label from 1, its (rows, columns) slices (scipy.ndimage.find_objects)
    y_lo: int  # image row of row 0
    # per (label, percentile), a segment's face and far-end depths (_near_far): the fragments and the
    # matcher both ask, for mostly the same segments, each vision tick
    faces: dict = field(default_factory=dict, repr=False, compare=False)

    @cached_property
    def present(self) -> np.ndarray:
        """The labels that hold pixels (joining segments across outlines leaves gaps), ascending."""
        return np.array([k for k, r in enumerate(self.regions, start=1) if r is not None], int)

    @cached_property
    def present_boxes(self) -> np.ndarray:
        """(len(present), 4) the boxes of :attr:`present`."""
        return self.boxes(self.present)

    def boxes(self, labels) -> np.ndarray:
        """(N, 4) image boxes (pixel-centre convention) around the whole of each of these labels."""
        regions = [self.regions[k - 1] for k in labels]
        return np.array([[r[1].start, r[0].start + self.y_lo, r[1].stop, r[0].stop + self.y_lo] for r in regions],
                        float).reshape(-1, 4) - 0.5


def object_segments(depth: np.ndarray, K: np.ndarray, T_world_to_camera: np.ndarray,
                    refine: BoxRefineParams = BoxRefineParams(), noise=None) -> ObjectSegments | None:
    """The image's object pixels cut into segments (module docstring); None when it holds none
    (``noise``: the depth's DepthNoise, raising the object pixels' height threshold)."""
    params = refine.proposals
    if params is None:
        raise ValueError("depth segments: the proposals are switched off (BoxRefineParams.proposals is None)")
    z = np.asarray(depth, np.float32)
    if z.ndim != 2:
        raise ValueError(f"depth: expected a 2-D depth image (H, W), got shape {z.shape}")
    heights = _Heights(K, T_world_to_camera)
    # the rows holding depth only (and the row above them: what stands above a top): one compiled
    # pass gives each pixel's depth (0 where none), validity, height and whether it is an object pixel
    lo, hi, z, valid, height, obj = _object_pixels(z, heights, refine.noise_k, noise, params.min_height_m,
                                                   refine.max_height_m)
    if hi <= lo:
        return None
    rows = np.flatnonzero(obj.any(axis=1))
    if not len(rows):
        return None
    # only the rows holding object pixels (the sky and the road ahead hold none)
    y_lo, y_hi = int(rows[0]) + lo, int(rows[-1]) + 1 + lo
    y_lo = max(y_lo - 1, 0)  # and the row above them: what stands above a segment's top
    a, b = y_lo - lo, y_hi - lo
    obj, height, z, valid = obj[a:b], height[a:b], z[a:b], valid[a:b]
    # cut at depth jumps: the farther pixel of each jumping neighbour pair leaves the mask
    keep = obj & _jump_free(z, valid, refine.jump_m, refine.jump_rel)
    labels = _restore_outlines(_components(keep), obj & ~keep, z, refine.jump_m, refine.jump_rel)
    # what no neighbour on its surface took back is a segment of its own, not left out: a vehicle seen
    # 1 px wide between nearer things (every pixel the farther one of a jumping pair), e.g. the piece
    # of a sliver below a mirror of the car beside it, which then joins its box (join_fragments)
    islands = obj & (labels == 0)
    if islands.any():
        labels = np.where(islands, _components(islands) + labels.max(), labels)
    labels = _join_across_outlines(labels, z, refine.jump_m, refine.jump_rel)
    regions = [None if b[0] < 0 else (slice(int(b[0]), int(b[1])), slice(int(b[2]), int(b[3])))
               for b in _label_boxes(labels, int(labels.max()))]  # as scipy.ndimage.find_objects gives them
    return ObjectSegments(z, valid, obj, height, labels, np.bincount(labels.ravel()), regions, y_lo)


def _object_pixels(z: np.ndarray, heights: _Heights, noise_k: float, noise, min_height_m: float,
                   max_height_m: float):
    """(lo, hi, z, valid, height, obj) on image rows lo..hi (from the row above the first holding a
    depth to the last holding one; hi <= lo: none): the depth with 0 where none, whether measured
    (finite, > 0), the height above the road (_Heights.window) and whether an object pixel (measured,
    higher than min_height_m + noise_k sigma of the height's noise (_Heights.noise_margin), lower
    than max_height_m), in their float32 arithmetic."""
    H, W = z.shape
    lo, hi = _depth_rows(z)
    if hi <= lo:
        return lo, hi, None, None, None, None
    noisy = noise is not None and not noise.exact
    a, b, c = (noise.a, noise.b, noise.c) if noisy else (0.0, 0.0, 0.0)
    f32 = np.float32
    zw = np.empty((hi - lo, W), np.float32)
    valid = np.empty((hi - lo, W), np.bool_)
    height = np.empty((hi - lo, W), np.float32)
    obj = np.empty((hi - lo, W), np.bool_)
    _object_kernel(z, lo, f32(heights.per_u), f32(heights.per_v), f32(heights.const), f32(heights.offset), noisy,
                   f32(noise_k), f32(a), f32(b), f32(c), f32(max(-heights.offset, 0.5)), f32(min_height_m),
                   f32(max_height_m), zw, valid, height, obj)
    return lo, hi, zw, valid, height, obj


@numba.njit(cache=True)
def _depth_rows(z):
    """(lo, hi): from the row above the first row holding a measured pixel (finite, > 0) to the last
    such row + 1; (0, 0) when there is none."""
    H, W = z.shape
    first, last = -1, -1
    for y in range(H):
        for x in range(W):
            d = z[y, x]
            if np.isfinite(d) and d > 0:
                if first < 0:
                    first = y
                last = y
                break
    if first < 0:
        return 0, 0
    return max(first - 1, 0), last + 1


@numba.njit(cache=True)
def _object_kernel(z, lo, per_u, per_v, const, offset, noisy, k, a, b, c, cam_h, min_h, max_h, zw, valid, height, obj):
    """object_segments' per-pixel work on rows lo.. (see _object_pixels), as _Heights.window and
    noise_margin compute it: height = z (v per_v + const + u per_u) - offset; the threshold
    min_h + k sigma_z(z) cam_h / max(z, 1), sigma_z = (a + b z) + (c z) z, when noisy."""
    one, zero = np.float32(1.0), np.float32(0.0)
    for r in range(zw.shape[0]):
        y = lo + r
        v = np.float32(y) * per_v + const
        for x in range(zw.shape[1]):
            d = z[y, x]
            ok = np.isfinite(d) and d > 0
            if not ok:
                d = zero
            h = d * (v + np.float32(x) * per_u) - offset
            thr = min_h
            if noisy:
                thr = min_h + k * ((a + b * d) + (c * d) * d) * cam_h / max(d, one)
            zw[r, x], valid[r, x], height[r, x] = d, ok, h
            obj[r, x] = ok and h > thr and h < max_h


def _min_top(params: ProposalParams, refine: BoxRefineParams, truncated: bool, width_m: float,
             depths: np.ndarray) -> float:
    """How high a segment's top must stand to be proposed: ``params.min_top_m`` (a car's roof line;
    rails are lower), or ``params.min_top_truncated_m`` for one cut by the image's side that is no
    wider than a vehicle and no deeper than one (``refine.band_m`` between its 10th and 90th
    percentiles). Why: of a car alongside the camera only its front corner shows at the image's
    side, bonnet and wing, 0.8-1.0 m high; a guard rail cut by the side is as high but runs tens of
    metres away from the camera (on 454 frames of `curved.yaml`, 0.7 m gave 864 false boxes without
    the width and depth rule, 11 with it)."""
    if truncated and width_m <= params.max_width_m:
        spread = np.percentile(depths, 90) - np.percentile(depths, 10)
        if spread <= refine.band_m:
            return params.min_top_truncated_m
    return params.min_top_m


def _lowest_row_on_its_surface(sel: np.ndarray, x: int, y: int, depth: np.ndarray, heights: _Heights,
                               min_height_m: float, jump_m: float, jump_rel: float) -> int:
    """The lowest image row a segment reaches when each of its columns is followed down from its
    lowest pixel over the same surface (no depth jump from the pixel above) while the pixels stand
    more than ``min_height_m`` above the road. `sel` is the segment's mask in its bounding box, whose
    pixel (0, 0) is image pixel (x, y). Why: the proposals' object pixels stand 0.3 m above the road
    (no kerbs or markings), so a proposed vehicle's box stopped above its bumper and tyres, which the
    ground truth spans: 17 px for a car 8 m ahead."""
    cols = np.flatnonzero(sel.any(axis=0))
    rows = y + sel.shape[0] - 1 - np.argmax(sel[::-1, cols], axis=0)  # each column's lowest pixel
    row0 = int(rows.min())
    if row0 >= depth.shape[0] - 1:
        return int(rows.max())
    f32 = np.float32
    return row0 + _walk_down(np.asarray(depth[row0:], np.float32), (x + cols).astype(np.int64),
                             (rows - row0).astype(np.int64), f32(heights.per_u), f32(heights.per_v),
                             f32(heights.const), f32(heights.offset), f32(min_height_m), row0, f32(jump_m),
                             f32(1 + jump_rel))


@numba.njit(cache=True)
def _walk_down(z, cols, start, per_u, per_v, const, offset, min_height, row0, jump_m, one_plus_rel):
    """_lowest_row_on_its_surface's walk, compiled: each column of `cols` followed down from its row
    `start` (rows of `z`, whose row 0 is image row row0) while the next pixel stands more than
    min_height above the road (_Heights.window's float32 arithmetic; no depth counts as 0) and lies
    on the same surface as the last; the lowest row reached."""
    H = z.shape[0]
    lowest = 0
    for j in range(len(cols)):
        c = cols[j]
        u = np.float32(c) * per_u
        r = start[j]
        za = z[r, c]
        if not (np.isfinite(za) and za > 0):
            za = np.float32(0.0)
        while r + 1 < H:
            zn = z[r + 1, c]
            if not (np.isfinite(zn) and zn > 0):
                zn = np.float32(0.0)
            v = np.float32(row0 + r + 1) * per_v + const
            if not (zn * (v + u) - offset > min_height):
                break
            if zn > za * one_plus_rel + jump_m or za > zn * one_plus_rel + jump_m:
                break
            r += 1
            za = zn
        if r > lowest:
            lowest = r
    return lowest


def depth_proposals(depth: np.ndarray, K: np.ndarray, T_world_to_camera: np.ndarray, boxes: np.ndarray,
                    refine: BoxRefineParams = BoxRefineParams(), segments: ObjectSegments | None = None,
                    snapped: np.ndarray | None = None, noise=None, with_labels: bool = False):
    """Boxes of depth segments standing on the road that no detected box explains: (M, 4) boxes and
    (M,) bool is_truck (``refine.proposals``; segments trimmed with ``refine.support``), and with
    ``with_labels`` (M,) the label in ``segments`` of the segment each was proposed from. ``segments``:
    the image's :func:`object_segments`, when already computed. ``snapped``: per box, whether the
    refinement snapped it to a depth segment (:attr:`RefinedBoxes.refined`; None: all were). A box
    that found no segment to snap to (one over two trucks and the car in front of them) is not
    confirmed by depth: a segment lying inside it is not explained by it, only one overlapping it."""
    from vcfusion.fusion.matching import box_inside_share, box_iou

    params = refine.proposals
    if segments is None:
        segments = object_segments(depth, K, T_world_to_camera, refine, noise)
    if segments is None:
        return (np.zeros((0, 4)), np.zeros(0, bool)) + ((np.zeros(0, int),) if with_labels else ())
    z, valid, obj, height, labels, areas, y_lo = (segments.z, segments.valid, segments.obj, segments.height,
                                                  segments.labels, segments.areas, segments.y_lo)
    fx = float(np.asarray(K, float)[0, 0])
    heights = _Heights(K, T_world_to_camera)
    out, trucks, from_label = [], [], []
    existing = np.asarray(boxes, float).reshape(-1, 4)
    snapped = np.ones(len(existing), bool) if snapped is None else np.asarray(snapped, bool)
    if snapped.shape != (len(existing),):
        raise ValueError(f"snapped: expected one flag per box ({len(existing)}), got shape {snapped.shape}")
    surface, outline_label = _box_surfaces(existing, segments, refine)
    for label, region in enumerate(segments.regions, start=1):
        if region is None or areas[label] < params.min_pixels:
            continue
        y, x = region[0].start, region[1].start
        h, w = region[0].stop - y, region[1].stop - x
        sel = labels[y:y + h, x:x + w] == label
        box = _segment_box(sel, refine.support, x, y + y_lo)
        # explained by a box: overlapping it, or mostly inside it and not clearly behind its surface
        # (a vehicle peeking over or beside a nearer one lies inside the nearer one's box), unless
        # it stands clearly in front of the box's surface (nearer by a depth jump): then the box
        # measured a farther vehicle and this segment is the one in front (Fig. 3 at range)
        seg_z = z[y:y + h, x:x + w][sel]
        depth_m = float(np.median(seg_z))
        if gate_by_noise(depth_m, noise, refine):
            continue  # depth this noisy cannot tell a vehicle's surface: no proposal
        iou = box_iou(box[None], existing)[0]
        not_in_front = ~_farther(surface, np.float32(depth_m), refine.jump_m, refine.jump_rel)
        if np.any((iou > params.max_overlap) & not_in_front):
            continue
        top = float(np.percentile(height[y:y + h, x:x + w][sel], 95))
        width_m = (box[2] - box[0]) * depth_m / fx
        is_truck = top > refine.truck_top_m
        min_width = params.min_width_m
        # cut by the image's side, a truck's side shows as narrow as a trunk: its width is unknown
        truncated = box[0] <= 0.0 or box[2] >= z.shape[1] - 1.0
        if is_truck and width_m < params.min_tall_width_m and not truncated and not _seen_over_nearer(
                sel, x, y, z, obj, depth_m, refine.jump_m, refine.jump_rel):
            min_width = params.min_tall_width_m  # standing on the ground as tall as this: a trunk or a pole
        if top < _min_top(params, refine, truncated, width_m, seg_z) or width_m < min_width:
            continue
        # (the segment drawing a box's outline is that box's only by overlap: a box over a truck's L
        # and the top of the car hiding the rest holds the truck's segment but fits it at IoU 0.55)
        inside = box_inside_share(box[None], existing)[0]
        if np.any((inside > 0.5) & snapped & not_in_front & (depth_m < surface + params.behind_m)
                  & (outline_label != label)):
            continue
        if _continues_above(sel, x, y, z, valid, height, refine.max_height_m, refine.jump_m,
                            refine.jump_rel) > params.max_top_continuing:
            continue  # a tree crown or a pole cut at the height cap, not a vehicle's roof
        if _on_a_stem(sel, x, y, z, obj, depth_m, params.max_stem_share, refine.jump_m, refine.jump_rel):
            continue  # a tree lower than the cap: a crown on a trunk
        # down to where the refinement's object pixels end (its bumper and tyres), as a detected box snaps
        box[3] = max(box[3], _lowest_row_on_its_surface(sel, x, y + y_lo, depth, heights, refine.min_height_m,
                                                        refine.jump_m, refine.jump_rel) + 0.5)
        out.append(box)
        trucks.append(is_truck)
        from_label.append(label)
    return (np.array(out, float).reshape(-1, 4), np.array(trucks, bool)) + (
        (np.array(from_label, int),) if with_labels else ())


def merge_same_segment(boxes: np.ndarray, box_trucks: np.ndarray, snapped: np.ndarray, proposals: np.ndarray,
                       proposal_trucks: np.ndarray, segments: ObjectSegments,
                       below_px: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Boxes that describe one vehicle twice after the depth step, made one: a proposal (the box of a
    segment no box explains, down to the lowest row on the segment's surface) whose segment also draws
    the outline of a snapped box of the same class (truck or not), while the box reaches more than
    ``below_px`` below the proposal, is that box's vehicle, and the proposal fits its surface (the box
    reached rows of something else); the box takes the proposal's sides and the proposal is dropped.
    A proposal of the other class (a truck's L above the car in front of it), or one ending where the
    box ends (a part of another car), stays its own box. Returns the boxes (a copy) and, per proposal,
    whether it is kept. One proposal per box: the one overlapping it most."""
    from vcfusion.fusion.matching import box_iou

    boxes = np.asarray(boxes, float).reshape(-1, 4).copy()
    proposals = np.asarray(proposals, float).reshape(-1, 4)
    keep = np.ones(len(proposals), bool)
    if not len(boxes) or not len(proposals):
        return boxes, keep
    box_label = np.where(np.asarray(snapped, bool), outline_segments(boxes, segments), 0)
    prop_label = outline_segments(proposals, segments)
    iou = box_iou(boxes, proposals)
    same = ((box_label[:, None] == prop_label[None, :]) & (prop_label[None, :] > 0)
            & (np.asarray(box_trucks, bool)[:, None] == np.asarray(proposal_trucks, bool)[None, :])
            & (boxes[:, 3, None] > proposals[None, :, 3] + below_px))
    iou = np.where(same, iou, 0.0)
    for j in np.argsort(-iou.max(axis=1)):
        cand = np.flatnonzero((iou[j] > 0) & keep)
        if len(cand):
            p = cand[iou[j, cand].argmax()]
            boxes[j] = proposals[p]
            keep[p] = False
    return boxes, keep


def _box_between(a: np.ndarray, b: np.ndarray, y_lo: int, shape: tuple[int, int]) -> tuple[slice, slice, np.ndarray]:
    """Rows, columns (arrays starting at image row y_lo) of the box around a and b, and the mask of
    its pixels inside neither: what lies between them."""
    u = np.r_[np.minimum(a[:2], b[:2]), np.maximum(a[2:], b[2:])]
    r0, r1 = min(max(int(u[1] + 0.5) - y_lo, 0), shape[0]), min(max(int(u[3] + 0.5) - y_lo, 0), shape[0])
    c0, c1 = min(max(int(u[0] + 0.5), 0), shape[1]), min(max(int(u[2] + 0.5), 0), shape[1])
    between = np.ones((r1 - r0, c1 - c0), bool)
    for x in (a, b):
        between[max(int(x[1] + 0.5) - y_lo - r0, 0):max(int(x[3] + 0.5) - y_lo - r0, 0),
                max(int(x[0] + 0.5) - c0, 0):max(int(x[2] + 0.5) - c0, 0)] = False
    return slice(r0, r1), slice(c0, c1), between


def _union_if_within(box: np.ndarray, ends: tuple[float, float], other: np.ndarray, other_ends: tuple[float, float],
                     max_width_m: float, K: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """The box around both and the depths of its left and right sides, when it is no wider than
    ``max_width_m`` across the camera's view; else ``box`` and ``ends`` unchanged. ``ends`` and
    ``other_ends``: camera-Z (m) at the left and right side of each (:func:`_lateral_width`)."""
    u = np.r_[np.minimum(box[:2], other[:2]), np.maximum(box[2:], other[2:])]
    left = other_ends[0] if other[0] < box[0] else ends[0]
    right = other_ends[1] if other[2] > box[2] else ends[1]
    if _lateral_width(u[0], left, u[2], right, K) <= max_width_m:
        return u, (left, right)
    return box, ends


def _lateral_width(u_left: float, z_left: float, u_right: float, z_right: float, K: np.ndarray) -> float:
    """How wide a box is across the camera's view, m: camera X of its right side at depth z_right
    minus that of its left side at z_left (image columns u, pixel-centre convention). At one depth
    this is the image width times depth over the focal length; a side that a segment running away
    from the camera draws (a car's flank seen at an angle, beside or above a nearer car) sits at its
    own depth, so the flank adds to the width only what it adds across the view."""
    fx, cx = float(K[0, 0]), float(K[0, 2])
    return ((u_right - cx) * z_right - (u_left - cx) * z_left) / fx


def _end_depths(segments: "ObjectSegments", label: int) -> tuple[float, float]:
    """Median camera-Z (m) of a segment's pixels in its leftmost and rightmost columns."""
    r = segments.regions[label - 1]
    sel = segments.labels[r] == label
    z = segments.z[r]
    cols = np.flatnonzero(sel.any(axis=0))
    return (float(np.median(z[:, cols[0]][sel[:, cols[0]]])), float(np.median(z[:, cols[-1]][sel[:, cols[-1]]])))


def join_fragments(boxes: np.ndarray, owners: np.ndarray, segments: ObjectSegments | None, K: np.ndarray,
                   refine: BoxRefineParams = BoxRefineParams(), noise=None,
                   outline: np.ndarray | None = None) -> np.ndarray:
    """Each box grown over its own segment whole and over the other fragments of its vehicle: (N, 4)
    boxes.

    The refinement snaps a box to the segment of its search window that overlaps the detected box
    most; when the detector's box was too small (a car half hidden at 30-45 m), that is a part of the
    vehicle. So a box first grows over the whole-image segments that most of its core shows and that
    draws its outline (:func:`outline_segments`), each when it stands at the box's surface depth, is
    not another owner box's segment and the two together are no wider than a vehicle.

    Then its other fragments: a vehicle partly hidden by a nearer one can show in pieces (its roof
    above the nearer car and a corner beside it); the detector and the refinement box one piece, the
    ground truth spans all. A segment joins a box when it stands at the box's surface depth (that of
    the segment drawing the box's outline, :func:`box_surface_depths`, else its core's median), lies
    near it (``fragment_gap`` of the box's size or ``fragment_gap_m`` at its depth), is not the own
    segment of one of the ``owners`` boxes (IoU > 0.5; an (N,) mask: the boxes the fusion uses),
    what lies between the two is mostly nearer (the piece of the nearer vehicle that cuts them apart)
    and all together are no wider than a vehicle (a car beside it at the same depth in the next lane
    is a lane width away). Wide across the camera's view (:func:`_lateral_width`): each side of the
    union at its own depth, a segment's side at the median depth of its outermost column, the box's
    at its surface depth (with a noisy sensor's depth, ``noise``, every side at the box's surface
    depth: one column of it is too noisy to place a side; stereo + 0.3 deg, seeds 9000-9009: 1
    target lost measuring each side at its own depth). A fragment stands at the box's surface depth
    when its nearest part (10th percentile of its depths) does, as the box's surface is measured:
    the piece of a car beyond a nearer object can show its flank running away, whose median lies
    metres behind. With ``noise`` (the depth's DepthNoise), a box whose surface lies where the
    depth is too noisy to tell one surface from the next (:func:`gate_by_noise`) does not grow: the
    gate that kept it as detected holds here too. ``outline``: (N,) per box, the label of the segment
    known to draw it (a depth proposal's own segment, :func:`depth_proposals` ``with_labels``), 0
    where it is found by overlap: a proposal's box reaches down over its surface below the segment
    (its bumper and tyres) and can overlap its own segment by less than IoU 0.5, and the median of
    its core then reads the nearer vehicle that hides the rest of it (a car's roof line seen above
    the car in front would take the front car's depth, and its other fragments be looked for there)."""
    from vcfusion.fusion.matching import box_inside_share, box_iou

    params = refine.proposals
    boxes = np.asarray(boxes, float).reshape(-1, 4)
    if params is None:
        raise ValueError("join_fragments: the proposals are switched off (BoxRefineParams.proposals is None)")
    if segments is None or not len(boxes):
        return boxes
    z, obj, y_lo = segments.z, segments.obj, segments.y_lo
    # any segment, however small: what shows of a truck through the gap under a nearer car, or beside
    # its outline, is 1-3 px: the ground truth spans them, and a box that stopped above them missed
    # IoU 0.7 (a 4-px minimum lost 3 targets on the development folders)
    labels, seg_box = segments.present, segments.present_boxes
    if not len(labels):
        return boxes
    # mean depth per segment, all at once: a first, loose sift (the test itself takes the median; the
    # mean of a segment with a little of something farther at its edge lies off it)
    seg_mean = (np.bincount(segments.labels.ravel(), weights=z.ravel(), minlength=len(segments.areas))[labels]
                / segments.areas[labels])
    owned = box_iou(seg_box, boxes[owners]) > 0.5 if owners.any() else np.zeros((len(labels), 0), bool)
    owner_index = np.flatnonzero(owners)
    fx = float(np.asarray(K, float)[0, 0])
    index_of = np.full(len(segments.areas), -1)  # image label -> k (a place in `labels`), -1 for none
    index_of[labels] = np.arange(len(labels))
    medians: dict[int, float] = {}

    def median_depth(k):  # of segment k (boxes share segments: computed once)
        if k not in medians:
            r = segments.regions[labels[k] - 1]
            medians[k] = float(np.median(z[r][segments.labels[r] == labels[k]]))
        return medians[k]

    ends_of: dict[int, tuple[float, float]] = {}

    exact = noise is None or noise.exact

    def end_depths(k, surface):  # of segment k's left and right columns (computed once)
        if not exact:  # one column of a noisy sensor's depth: the box's surface depth for both
            return surface, surface
        if k not in ends_of:
            ends_of[k] = _end_depths(segments, int(labels[k]))
        return ends_of[k]

    K = np.asarray(K, float)
    out = boxes.copy()
    surfaces, outline_label = _box_surfaces(boxes, segments, refine, outline)
    for i, b in enumerate(boxes):
        surface = surfaces[i]
        if not np.isfinite(surface) or gate_by_noise(surface, noise, refine):
            continue
        tolerance = params.fragment_depth_m + 0.03 * surface
        ends = (surface, surface)  # the depths of the grown box's left and right sides
        others = owned[:, owner_index != i].any(axis=1)
        grown = b.copy()
        # first the box's own segment whole: the refinement chose within a window around the detected
        # box and by overlap with it, so a detected box that was too small keeps part of its vehicle
        # out. Its own: the one most of its core shows, and the one drawing its outline (a car's box
        # that stopped short above the nearer car in front of its lower half shows that car most)
        core = _core(b, 0, y_lo)
        core_labels = index_of[segments.labels[core][obj[core]]]
        core_labels = core_labels[core_labels >= 0]
        own = {int(np.bincount(core_labels).argmax())} if core_labels.size else set()
        if outline_label[i]:
            own.add(int(index_of[outline_label[i]]))
        for k in own:
            if not others[k] and abs(median_depth(k) - surface) <= tolerance:
                grown, ends = _union_if_within(grown, ends, seg_box[k], end_depths(k, surface), params.max_width_m, K)
        side = max(b[2] - b[0], b[3] - b[1])
        gap = np.maximum.reduce([seg_box[:, 0] - b[2], b[0] - seg_box[:, 2],
                                 seg_box[:, 1] - b[3], b[1] - seg_box[:, 3]])
        inside = box_inside_share(seg_box, b[None])[:, 0] >= 0.9
        reach = max(params.fragment_gap * side, params.fragment_gap_m * fx / surface)
        near = (gap <= reach) & ~inside & ~others
        for k in np.flatnonzero(near & (np.abs(seg_mean - surface) <= 2 * tolerance + 1.0)):
            if abs(_near_far(segments, int(labels[k]))[0] - surface) > tolerance:  # its face
                continue
            rows, cols, between = _box_between(b, seg_box[k], y_lo, z.shape)
            if not between.any():
                continue  # touching the box: its own segment (above), or one the refinement did not want
            nearer = _nearer_object(*np.nonzero(between), z[rows, cols], obj[rows, cols], surface,
                                    refine.jump_m, refine.jump_rel)
            if nearer.mean() >= params.fragment_hidden:
                grown, ends = _union_if_within(grown, ends, seg_box[k], end_depths(k, surface), params.max_width_m, K)
        out[i] = grown
    return out


def outline_segments(boxes: np.ndarray, segments: ObjectSegments, min_iou: float = 0.5) -> np.ndarray:
    """Per box, the label of the segment drawing its outline: the one of ``segments`` whose bounding
    box overlaps the box most, when by IoU >= ``min_iou``; 0 where none does. (N,) int."""
    from vcfusion.fusion.matching import box_iou

    boxes = np.asarray(boxes, float).reshape(-1, 4)
    present = segments.present
    if not len(boxes) or not len(present):
        return np.zeros(len(boxes), int)
    iou = box_iou(boxes, segments.present_boxes)
    best = iou.argmax(axis=1)
    return np.where(iou[np.arange(len(boxes)), best] >= min_iou, present[best], 0)


# a segment is a box's surface only where at least this share of its bounding box lies inside the box:
# a car in front and a car entering beside it made one segment (IoU 0.67 with the front car's box, a
# third outside it) whose face became that box's surface, and the front car took the truck's box behind
# it (curve seed 3104 from 68.7 s, tuned-on); 0.8 leaves a whole vehicle's segment (inside its box but
# for the box's rounding) its surface; the figures that kept it: docs/components/guidance-loop.md
MIN_SURFACE_INSIDE_SHARE = 0.8


def box_surface_depths(boxes: np.ndarray, segments: ObjectSegments | None,
                       refine: BoxRefineParams = BoxRefineParams(), min_iou: float = 0.5,
                       face_percentile: float = 10.0) -> np.ndarray:
    """Per box, the depth of the surface that draws its outline: (N,) camera-Z, m, nan where unknown.

    That surface is the segment of ``segments`` (the image's :func:`object_segments`) whose bounding
    box overlaps the box most, when by IoU >= ``min_iou``; its depth is the ``face_percentile``
    percentile of the segment's depths (the face nearest the camera, what the matcher's expected
    depth is). Why: Algorithm 1's samples of a partly hidden vehicle's box read the nearer vehicle
    in front of it, and the matcher takes the best of their quantiles, so a near car's box that
    shows a sliver of the truck behind it fits the truck's depth as well as its own, and the two
    twins swapped boxes on a 0.02 difference in cost. Unknown (nan) where no segment explains the
    box, or where that segment runs deeper than one vehicle's band (``refine.band_m`` between its
    10th and 90th percentiles): far away a car a few metres in front of a truck is within one depth
    jump of it (0.5 m + 4.5 % of the depth), and their joint segment's face is the car's. Unknown
    too where less than :data:`MIN_SURFACE_INSIDE_SHARE` of the segment's bounding box lies in the box:
    the segment then holds more than the box's vehicle (a car beside it, within one depth jump), and
    its face may be the other's."""
    boxes = np.asarray(boxes, float).reshape(-1, 4)
    if segments is None or not len(boxes):
        return np.full(len(boxes), np.nan)
    outline = outline_segments(boxes, segments, min_iou)
    drawn = np.flatnonzero(outline)
    if len(drawn):
        from vcfusion.fusion.matching import box_inside_share

        inside = box_inside_share(segments.boxes(outline[drawn]), boxes[drawn]).diagonal()
        outline[drawn[inside < MIN_SURFACE_INSIDE_SHARE]] = 0
    return _face_depths(outline, segments, refine, face_percentile)


def _face_depths(outline: np.ndarray, segments: ObjectSegments, refine: BoxRefineParams,
                 face_percentile: float = 10.0) -> np.ndarray:
    """Per label of ``outline`` (:func:`outline_segments`; 0: none), its segment's face depth as
    :func:`box_surface_depths` defines it; nan for 0."""
    out = np.full(len(outline), np.nan)
    for j in np.flatnonzero(outline):
        near, far = _near_far(segments, int(outline[j]), face_percentile)
        out[j] = near if far - near <= refine.band_m else np.nan
    return out


def _near_far(segments: ObjectSegments, label: int, face_percentile: float = 10.0) -> tuple[float, float]:
    """The ``face_percentile`` and 100 - ``face_percentile`` percentiles of a segment's depths, m: its
    face (the nearest part, as a box's surface is measured) and its far end; computed once per
    segmentation (boxes share segments, and calls share the segmentation)."""
    key = (label, face_percentile)
    if key not in segments.faces:
        r = segments.regions[label - 1]
        near, far = np.percentile(segments.z[r][segments.labels[r] == label], [face_percentile, 100 - face_percentile])
        segments.faces[key] = (float(near), float(far))
    return segments.faces[key]


def _box_surfaces(boxes: np.ndarray, segments: ObjectSegments, refine: BoxRefineParams,
                  known: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per box, its surface depth and the label of the segment drawing its outline (0: none), as the
    proposals and the fragments take them: that segment's face depth (as the matcher does), else the
    median of the box's core (inf where it holds no object pixel), which a nearer car in front of part
    of the box, or beside a sliver, can hold. ``known``: (N,) labels of segments known to draw boxes
    (0: found by overlap, :func:`outline_segments`)."""
    outline = outline_segments(boxes, segments)
    if known is not None:
        known = np.asarray(known, int)
        if known.shape != outline.shape:
            raise ValueError(f"outline: expected one label per box ({len(outline)}), got shape {known.shape}")
        outline = np.where(known > 0, known, outline)
    surface = _face_depths(outline, segments, refine)
    for j in np.flatnonzero(~np.isfinite(surface)):
        surface[j] = _surface_depth(segments.z, segments.obj, boxes[j], segments.y_lo)
    return surface, outline


def fill_scan_gaps(depth: np.ndarray, max_gap_px: int, jump_m: float, jump_rel: float, axis: int = 0,
                   on_road: np.ndarray | None = None, occlusion_side: str | None = None) -> np.ndarray:
    """A sparse scan's depth (nan where no return lands) with the gaps between returns filled along
    ``axis`` (0: down each column, 1: along each row), where two returns at most ``max_gap_px + 1``
    pixels apart bound the gap: linearly in inverse depth between them (exact on a plane) when they
    lie on one surface (no depth jump, :func:`_same_surface`) or both on the road (``on_road``, (H, W)
    bool: returns within the road's noise of the fitted road; far down the road two beams' returns
    lie metres apart), else each pixel takes the nearer return's depth (the edge between two surfaces
    half-way between the returns). A gap wider than that, or open at the image's edge, stays nan.
    ``inf`` (a return with nothing within range) counts as a return. ``occlusion_side="left"`` (along
    rows of a stereo pair's left image): a gap whose right end is nearer than its left by a depth
    jump is the band the right camera could not see behind the nearer surface's left edge, and takes
    the farther depth whole. One compiled pass along each line (:func:`_fill_lines`)."""
    if occlusion_side not in (None, "left"):
        raise ValueError(f"occlusion_side: expected None or 'left', got {occlusion_side!r}")
    if axis not in (0, 1):
        raise ValueError(f"axis: expected 0 (columns) or 1 (rows), got {axis}")
    z = np.asarray(depth, np.float32)
    if z.ndim != 2:
        raise ValueError(f"depth: expected a 2-D depth image (H, W), got shape {z.shape}")
    if on_road is not None and np.shape(on_road) != z.shape:
        raise ValueError(f"on_road: expected a mask of the depth's shape {z.shape}, got {np.shape(on_road)}")
    out = z.copy()
    road = np.zeros((0, 0), np.bool_) if on_road is None else np.asarray(on_road, np.bool_)
    along = out
    if axis == 0:  # down the columns: the same pass on the transposed views
        z, along, road = z.T, out.T, road.T
    _fill_lines(z, along, road, on_road is not None, int(max_gap_px), np.float32(jump_m),
                np.float32(1 + jump_rel), occlusion_side == "left")
    return out


@numba.njit(cache=True, error_model="numpy")
def _fill_lines(z, out, on_road, use_road, max_gap_px, jump_m, one_plus_rel, occlusion_left):
    """fill_scan_gaps along each row of `z` into `out` (float32 arithmetic as _farther's): a gap of at
    most max_gap_px pixels between two returns (not nan) is filled, pixel p at t = (p - a) / (b - a)
    of the way from return a to return b."""
    H, W = z.shape
    half = np.float32(0.5)
    one = np.float32(1.0)
    for r in range(H):
        prev = -1
        for c in range(W):
            zb = z[r, c]
            if np.isnan(zb):
                continue
            if prev >= 0 and 1 < c - prev <= max_gap_px + 1:
                za = z[r, prev]
                finite = np.isfinite(za) and np.isfinite(zb)
                same = (finite and za > 0 and zb > 0 and not za > zb * one_plus_rel + jump_m
                        and not zb > za * one_plus_rel + jump_m)
                if use_road and finite and on_road[r, prev] and on_road[r, c]:
                    same = True
                far_left = za > zb * one_plus_rel + jump_m
                inv_a = one / za
                step = one / zb - inv_a
                for p in range(prev + 1, c):
                    t = np.float32((p - prev) / (c - prev))
                    if same:
                        out[r, p] = one / (inv_a + t * step)
                    elif occlusion_left and far_left:
                        out[r, p] = za
                    elif t <= half:
                        out[r, p] = za
                    else:
                        out[r, p] = zb
            prev = c


def on_road_mask(depth: np.ndarray, K: np.ndarray, T_world_to_camera: np.ndarray, noise,
                 refine: BoxRefineParams = BoxRefineParams()) -> np.ndarray:
    """(H, W) bool: the measured pixels within ``refine.scan_road_m`` (+ ``noise_k`` sigma of their
    height's noise) of the road whose z = 0 plane `T_world_to_camera` defines (a fitted road's pose).
    One compiled pass (:func:`_road_kernel`), in _Heights' float32 arithmetic."""
    heights = _Heights(K, T_world_to_camera)
    z = np.asarray(depth, np.float32)
    if z.ndim != 2:
        raise ValueError(f"depth: expected a 2-D depth image (H, W), got shape {z.shape}")
    noisy = noise is not None and not noise.exact
    a, b, c = (noise.a, noise.b, noise.c) if noisy else (0.0, 0.0, 0.0)
    out = np.zeros(z.shape, np.bool_)
    f32 = np.float32
    _road_kernel(z, f32(heights.per_u), f32(heights.per_v), f32(heights.const), f32(heights.offset),
                 f32(refine.scan_road_m), noisy, f32(refine.noise_k), f32(a), f32(b), f32(c),
                 f32(max(-heights.offset, 0.5)), out)
    return out


@numba.njit(cache=True)
def _road_kernel(z, per_u, per_v, const, offset, tolerance, noisy, k, a, b, c, cam_h, out):
    """on_road_mask per pixel: |height| < tolerance (+ k sigma_z(z) cam_h / max(z, 1) when noisy),
    height = z (v per_v + const + u per_u) - offset, as _Heights.window and noise_margin compute them."""
    H, W = z.shape
    one = np.float32(1.0)
    for y in range(H):
        v = np.float32(y) * per_v + const
        for x in range(W):
            d = z[y, x]
            if not np.isfinite(d):
                continue
            h = d * (v + np.float32(x) * per_u) - offset
            tol = tolerance
            if noisy:
                sigma = (a + b * d) + (c * d) * d
                tol = tolerance + k * sigma * cam_h / max(d, one)
            out[y, x] = abs(h) < tol


def warm_kernels() -> None:
    """Load the depth step's compiled kernels (numba's cache) for the argument types a frame uses,
    with tiny inputs: a forked worker that imports this first fuses its first frame without the
    load (vcfusion.worker_preload)."""
    z = np.full((3, 4), np.nan, np.float32)
    z[:, 0] = z[:, 3] = 10.0
    road = np.ones(z.shape, bool)
    fill_scan_gaps(z, 2, 0.5, 0.045, 1)
    fill_scan_gaps(z, 2, 0.5, 0.045, 0)
    fill_scan_gaps(z, 2, 0.5, 0.045, 0, road)
    fill_scan_gaps(z, 2, 0.5, 0.045, 1, road, "left")
    labels = _components(road)
    _restore_outlines(labels, ~road, np.zeros(z.shape, np.float32), 0.5, 0.045)
    _label_boxes(labels, 1)
    _label_boxes(labels.astype(np.int64), 1)
    _join_across_outlines(labels, np.zeros(z.shape, np.float32), 0.5, 0.045)
    _jump_free(z, road, 0.5, 0.045)
    _segment_box(road, 0.3, 0, 0)
    eye = np.eye(4)
    on_road_mask(z, np.eye(3), eye, None)
    _object_pixels(z, _Heights(np.eye(3), eye), 3.0, None, 0.3, 4.5)
    _lowest_row_on_its_surface(road[:1], 0, 0, z, _Heights(np.eye(3), eye), 0.05, 0.5, 0.045)


def core_segment(box: np.ndarray, segments: ObjectSegments) -> int:
    """The label of the segment holding at least half of the segment pixels in a box's core (its
    central half in each direction, :func:`_core`; pixels of no segment, the road or the sky, do
    not count); 0 where none does or the core holds no segment."""
    labels = segments.labels[_core(box, 0, segments.y_lo)]
    labels = labels[labels > 0]
    if not labels.size:
        return 0
    values, counts = np.unique(labels, return_counts=True)
    return int(values[counts.argmax()]) if counts.max() >= 0.5 * labels.size else 0


def join_truck_fragments(boxes: np.ndarray, scores: np.ndarray, is_truck: np.ndarray,
                         segments: ObjectSegments, slack_px: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Truck boxes that box one truck in pieces, made one: the boxes (a copy), the best-scored
    fragment of each truck holding the union, and (N,) whether each box is kept.

    A detector can box a truck seen at an angle twice, front and back half, at an IoU with each
    other below its suppression. Two truck boxes are one truck's fragments when at least half of
    each one's core shows the same depth segment (:func:`core_segment`), they share columns, and
    their union lies within that segment's box (``slack_px`` either side): a second truck at
    another depth is another segment, and a box reaching beyond the segment shows something else.
    Fragments join the best-scored box of their segment one by one, each while the union still fits."""
    boxes = np.array(boxes, dtype=float)
    keep = np.ones(len(boxes), bool)
    by_segment: dict[int, list[int]] = {}
    for i in np.flatnonzero(np.asarray(is_truck, bool)):
        label = core_segment(boxes[i], segments)
        if label > 0:
            by_segment.setdefault(label, []).append(int(i))
    for label, members in by_segment.items():
        if len(members) < 2:
            continue
        extent = segments.boxes([label])[0] + np.array([-slack_px, -slack_px, slack_px, slack_px])
        members.sort(key=lambda i: -float(scores[i]))
        union = boxes[members[0]]
        for j in members[1:]:
            b = boxes[j]
            if min(union[2], b[2]) <= max(union[0], b[0]):
                continue  # no columns in common
            joined = np.r_[np.minimum(union[:2], b[:2]), np.maximum(union[2:], b[2:])]
            if np.all(joined[:2] >= extent[:2]) and np.all(joined[2:] <= extent[2:]):
                union, keep[j] = joined, False
        boxes[members[0]] = union
    return boxes, keep
