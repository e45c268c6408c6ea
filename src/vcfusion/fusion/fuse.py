"""The vision-cloud fusion stage of a tick: detect, evaluate depth, match twins to boxes, guide.

The renderer plugs in through :class:`FrameSource`: a callable that returns the ego camera's
:class:`CameraFrame` for a tick (or None when there is no camera image at that tick). Everything
here works on those plain arrays, so it is tested with hand-made frames.
"""

from __future__ import annotations

import functools
import time as wallclock
from dataclasses import dataclass, field, replace
from typing import Protocol

import cv2
import numba
import numpy as np

from vcfusion.guidance import GuidancePolicy
from vcfusion.records import GuidanceSet, TwinStates
from vcfusion.fusion.box_refine import (BoxRefineParams, ObjectSegments, RefinedBoxes, box_surface_depths,
                                       depth_proposals, fill_scan_gaps, join_fragments, join_truck_fragments,
                                       merge_same_segment,
                                       object_segments, on_road_mask, refine_boxes)
from vcfusion.fusion.road import DepthNoise, RoadFit, fit_road_plane
from vcfusion.fusion.depth_eval import DepthEvalParams, joint_depth_samples, reduce_depth_samples, sample_box_depths
from vcfusion.detection.detectors import Detections, Detector, OracleDetector, nms
from vcfusion.fusion.matching import (NO_MATCH, CameraView, JointMatcher, box_iou, match_all_baseline, visible_boxes,
                                      match_all_paper, point_in_boxes, project_twins)
from vcfusion.fusion.overlay import Hud, OverlayRecorder, draw_overlay, make_guidance
from vcfusion.metrics.highlights import judge_highlight

# baseline: the paper's RGB-only rule; baseline_centre: our nearest-box-centre heuristic (RGB only);
# paper: Algorithm 2 (RGB + depth); joint: the joint matcher (see matching.py)
METHODS = ("baseline", "baseline_centre", "paper", "joint")


@dataclass(frozen=True)
class CameraFrame:
    """One ego camera frame, as the renderer produces it."""

    time: float  # s, simulation clock (the image's timestamp)
    image: np.ndarray  # (H, W, 3) RGB uint8
    depth: np.ndarray  # (H, W) float32 camera-Z metres; inf or 0 where nothing was hit (sky), nan where
    # the sensor measured nothing (vcfusion.fusion.sensors)
    camera: CameraView
    gt_boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (M, 4) visible vehicles' boxes
    gt_ids: tuple[str, ...] = ()  # vehicle id of each ground-truth box
    # (M, 4) each vehicle's visible box (around its largest patch of pixels, gt_boxes.GroundTruthBoxes.patch)
    # and (M,) the share of its outline (its projected 3D box's part inside the image) it covers: what
    # highlights are judged against (vcfusion.metrics.highlights); None where the source has none (scene
    # folders: gt_boxes, every share 1)
    gt_patches: np.ndarray | None = None
    gt_visible_share: np.ndarray | None = None
    gt_classes: np.ndarray | None = None  # (M,) category ids, for the oracle detector
    # (H, W) index into `instance_ids` of the vehicle seen at each pixel, -1 where none (the
    # renderer's instance map); None when the source has none
    instances: np.ndarray | None = None
    instance_ids: tuple[str, ...] = ()
    depth_noise: DepthNoise = DepthNoise()  # the depth sensor's error (its spec), for the depth step

    @property
    def visible_boxes(self) -> np.ndarray:
        """The boxes highlights are judged against: the visible boxes, or the ground-truth boxes
        where the source has none."""
        return self.gt_boxes if self.gt_patches is None else self.gt_patches


@dataclass(frozen=True)
class DepthView:
    """What the depth step works on for one frame (:func:`depth_view`): the depth (a stereo pair's
    holes and a LiDAR scan's gaps filled, box_refine.fill_scan_gaps; median-filtered when noisy and
    dense, a scan not), the pose whose z = 0 plane is the road, the depth's noise after the filter,
    the road fit, whether the image holds too little measured depth for proposals, and a filled
    scan's own returns."""

    depth: np.ndarray
    T: np.ndarray
    noise: DepthNoise
    road: RoadFit | None
    sparse: bool
    returns: np.ndarray | None = None  # (H, W) bool: a scan's own returns, when its gaps were filled


def depth_view(frame: CameraFrame, refine: BoxRefineParams) -> DepthView:
    """The frame's :class:`DepthView` with `refine`'s settings, computed once per frame."""
    key = (refine.road, refine.scan_fill_px, refine.scan_road_m, refine.hole_fill_px, refine.denoise_px,
           refine.denoise_passes, refine.denoise_sigma_share, refine.gate_valid_share)
    cached = frame.__dict__.get("_depth_view")
    if cached is not None and cached[0] == key:
        return cached[1]
    cam = frame.camera
    depth, noise = frame.depth, frame.depth_noise
    sparse = bool(np.isnan(frame.depth).mean() > 1 - refine.gate_valid_share)
    road = returns = None
    if sparse and refine.scan_fill_px:  # a scan: its gaps between returns filled (box_refine.fill_scan_gaps)
        # the road first, on the returns themselves (a plane needs no dense image), so that the road's
        # returns are filled along the plane
        T = cam.T_world_to_camera
        returns = ~np.isnan(depth)
        if refine.road == "from_depth":
            road = fit_road_plane(depth, cam.K, T, noise)
            T = road.T
        # along each beam's row first (returns a pixel or two apart), then down the columns between beams
        depth = fill_scan_gaps(depth, refine.scan_fill_px[1], refine.jump_m, refine.jump_rel, 1)
        on_road = on_road_mask(depth, cam.K, T, noise, refine)
        depth = fill_scan_gaps(depth, refine.scan_fill_px[0], refine.jump_m, refine.jump_rel, 0, on_road)
        sparse = bool(np.isnan(depth).mean() > 1 - refine.gate_valid_share)
    if not sparse and noise.c > 0 and refine.hole_fill_px:  # stereo: its holes filled along the rows
        depth = fill_scan_gaps(depth, refine.hole_fill_px, refine.jump_m, refine.jump_rel, 1, None, "left")
    # a scan (filled or not) is not median-filtered: its range noise (centimetres) needs no filter, and
    # most of a 5 x 5 window over a filled scan is fill, not measurement; beside a far car's lower half,
    # where the road's depth changes by metres from row to row, the window's median mixes the car's depth
    # with the road's and lands nearer than the road there: object pixels that widen the car's segment
    # by 1-2 px a side (development folders, LiDAR + 0.3 deg: 86.0 % with the median, 91.5 % without)
    if not noise.exact and refine.denoise_px and not sparse and returns is None:
        for _ in range(refine.denoise_passes):
            depth = _median(depth, refine.denoise_px)
        noise = noise.scaled(refine.denoise_sigma_share)
        if frame.depth_noise.mixed_edges:
            depth = _without_flying_pixels(depth, refine)
    if road is None and refine.road == "from_depth":
        road = fit_road_plane(depth, cam.K, cam.T_world_to_camera, noise)
    view = DepthView(depth, road.T if road is not None else cam.T_world_to_camera, noise, road, sparse, returns)
    object.__setattr__(frame, "_depth_view", (key, view))
    return view


def _median(depth: np.ndarray, size: int) -> np.ndarray:
    """A size x size median of a depth image with holes (nan): holes stay holes, and a pixel the
    median takes into a hole (more than half its window missing) becomes one. Filtered on the rows
    within size // 2 of a measurement only: elsewhere every pixel of the window is a hole, and so is
    the median (the sky stays inf)."""
    z = np.asarray(depth, np.float32)
    if z.ndim != 2:
        raise ValueError(f"depth: expected a 2-D depth image (H, W), got shape {z.shape}")
    out, filled, lo = _median_prepare(z, size // 2)
    if len(filled):
        _median_finish(z, cv2.medianBlur(filled, size), lo, out)
    return out


@numba.njit(cache=True)
def _median_prepare(z, reach):
    """(out: inf where z is +inf, nan elsewhere; the rows lo.. within `reach` of a measurement with
    holes as 0, the median's input; lo)."""
    H, W = z.shape
    out = np.empty((H, W), np.float32)
    first, last = H, -1
    for y in range(H):
        for x in range(W):
            d = z[y, x]
            out[y, x] = np.inf if d == np.inf else np.nan
            if np.isfinite(d):
                if y < first:
                    first = y
                last = y
    if last < 0:
        return out, np.zeros((0, W), np.float32), 0
    lo, hi = max(first - reach, 0), min(last + reach + 1, H)
    filled = np.empty((hi - lo, W), np.float32)
    for y in range(lo, hi):
        for x in range(W):
            d = z[y, x]
            filled[y - lo, x] = d if np.isfinite(d) else np.float32(0.0)
    return out, filled, lo


@numba.njit(cache=True)
def _median_finish(z, med, lo, out):
    """out's rows lo.. from the median: inf where z is +inf, nan where z is a hole or the median not
    positive, else the median."""
    for r in range(med.shape[0]):
        y = lo + r
        for x in range(z.shape[1]):
            d = z[y, x]
            if d == np.inf:
                out[y, x] = np.inf
            elif not np.isfinite(d) or med[r, x] <= 0:
                out[y, x] = np.nan
            else:
                out[y, x] = med[r, x]


def warm_depth_kernels() -> None:
    """Load the depth step's compiled kernels (numba's cache) with tiny inputs, so that a forked
    worker's first frame does not (vcfusion.worker_preload)."""
    from vcfusion.fusion.box_refine import warm_kernels
    from vcfusion.fusion.sensors import DepthSensorParams, stereo_depth

    warm_kernels()
    z = np.full((6, 6), np.nan, np.float32)
    z[:, :3] = 10.0
    _median(z, 5)
    stereo_depth(z, 100.0, DepthSensorParams(), np.random.default_rng(0), np.zeros((6, 6, 3), np.uint8))


def _without_flying_pixels(depth: np.ndarray, refine: BoxRefineParams) -> np.ndarray:
    """A noisy sensor's depth with its flying pixels made holes: a pixel whose 3 x 3 neighbourhood
    spans a depth jump (box_refine's jump_m + jump_rel z) and which lies more than half a jump
    from both the nearest and the farthest of it: a mix of two surfaces (a ToF pixel straddling an
    edge, a stereo match across one), which would join them into one segment."""
    z = np.asarray(depth, np.float32)
    finite = np.isfinite(z)
    kernel = np.ones((3, 3), np.uint8)
    near = cv2.erode(np.where(finite, z, np.float32(1e6)), kernel)
    far = cv2.dilate(np.where(finite, z, np.float32(0)), kernel)
    half = np.float32(0.5) * (np.float32(refine.jump_m) + np.float32(refine.jump_rel) * z)
    flying = finite & (far - near > 2 * half) & (z - near > half) & (far - z > half)
    return np.where(flying, np.float32(np.nan), z)


def count_depth_step(stats: dict | None, key: str, n: float = 1) -> None:
    if stats is not None:
        stats[key] = stats.get(key, 0) + n


class FrameSource(Protocol):
    def __call__(self, tick) -> CameraFrame | None: ...


@dataclass
class FusionResult:
    time: float
    twin_ids: tuple[str, ...]
    detections: Detections
    box_depths: np.ndarray  # (D,) Algorithm 1 distances
    choice: dict  # method -> (N,) box index per twin, NO_MATCH where none
    in_view: np.ndarray  # (N,) twins projected into the image (as received) or matched by a method
    timings_s: dict  # stage -> seconds
    # (N,) boxes containing each twin's anchor (0 out of view): >= 2 is the ambiguous case of Fig. 3
    n_anchor_boxes: np.ndarray | None = None
    depth_counts: dict = field(default_factory=dict)  # the depth step's counts (depth_step's `stats`)
    # (N, 4) each twin's whole projected outline (TwinProjection.expected_box) and (N,) the share of
    # it nearer twins' outlines hide (matching.visible_boxes): as the joint matcher projected the twins
    # (GNSS-smoothed, moved on by their latency) when it ran, else as received
    expected_boxes: np.ndarray | None = None
    hidden_share: np.ndarray | None = None
    # (N,) the joint matcher's chosen box's depth disagreement with the twin, in sigmas, and whether
    # the disagreement is the box outline's surface (matching.JointMatch); None when the joint matcher
    # did not run
    depth_sigmas: np.ndarray | None = None
    depth_on_surface: np.ndarray | None = None
    # (N,) the same depth's disagreement with the part of the twin the box's columns show
    # (JointMatch.shown_depth_sigmas); None when the joint matcher did not run
    shown_depth_sigmas: np.ndarray | None = None

    def box_of(self, method: str, i: int):
        j = int(self.choice[method][i])
        return None if j == NO_MATCH else self.detections.boxes[j]


def detect_frame(frame: CameraFrame, detector: Detector, refine: BoxRefineParams | None = None,
                 segments: ObjectSegments | None = None, stats: dict | None = None) -> Detections:
    """The detector's boxes on the frame's image, snapped to the depth image when `refine` is given
    (vcfusion.fusion.box_refine; `segments`: the frame's :func:`frame_segments`, when already
    computed). The oracle's boxes are the truth and are never refined."""
    if isinstance(detector, OracleDetector):
        detector.set_truth(frame.gt_boxes, frame.gt_classes)
        return detector.detect(frame.image)
    detections = detector.detect(frame.image)
    return detections if refine is None else depth_step(frame, detections, refine, segments, stats)


def frame_segments(frame: CameraFrame, refine: BoxRefineParams | None) -> ObjectSegments | None:
    """The frame's depth image cut into object segments (box_refine.object_segments), with `refine`'s
    settings when it has proposals, else the defaults (the matcher reads them with any detector);
    None when the camera has no intrinsics / pose or the image holds no object."""
    cam = frame.camera
    if cam.K is None or cam.T_world_to_camera is None:
        return None
    params = refine if refine is not None and refine.proposals is not None else BoxRefineParams()
    view = depth_view(frame, params)
    if view.sparse:
        return None  # too little measured depth to cut into surfaces
    return object_segments(view.depth, cam.K, view.T, params, view.noise)


def depth_step(frame: CameraFrame, detections: Detections, refine: BoxRefineParams,
               segments: ObjectSegments | None = None, stats: dict | None = None) -> Detections:
    """The detector's boxes snapped to the frame's depth image, relabelled by how high they stand,
    and the vehicles it missed proposed from depth (vcfusion.fusion.box_refine). `segments`: the
    frame's :func:`frame_segments` with these settings, when already computed. `stats` (a dict)
    counts what depth could not decide: boxes_gated (kept as detected, or placed from the image:
    boxes_from_image, of those behind the noise gate when `refine.box_head`), boxes_refined, frames,
    frames_road_fit_failed, frames_without_proposals (too little measured depth), road_fit_ms."""
    cam = frame.camera
    if cam.K is None or cam.T_world_to_camera is None:
        raise ValueError("box refinement: the camera has no intrinsics / pose (CameraView.K, T_world_to_camera)")
    from vcfusion.render.coco import category_id  # the dataset's category ids, as every detector reports

    view = depth_view(frame, refine)
    count_depth_step(stats, "frames")
    if view.road is not None:
        count_depth_step(stats, "frames_road_fit_failed", int(not view.road.ok))
        count_depth_step(stats, "road_fit_ms", view.road.ms)
    if view.sparse:  # too little measured depth to snap boxes to: every box kept as detected
        refined = RefinedBoxes(detections.boxes.copy(), np.zeros(len(detections), bool),
                               np.full(len(detections), np.nan), np.ones(len(detections), bool))
    else:
        refined = refine_boxes(detections.boxes, view.depth, cam.K, view.T, refine, view.noise, view.returns)
    count_depth_step(stats, "boxes_gated", int(refined.gated.sum()))
    if refine.box_head is not None and refined.noisy is not None:
        _place_gated_from_image(frame.image, refined, refine.box_head, stats)
    count_depth_step(stats, "boxes_refined", int(refined.refined.sum()))
    boxes, scores, snapped = refined.boxes, detections.scores, refined.refined
    # depth measures how high a vehicle stands, which a 10 px box at 100 m does not show: a car box
    # whose surface stands higher than any car (and not higher than any vehicle: a tree) is a truck
    tall = (refined.top_m > refine.truck_top_m) & (refined.top_m <= refine.max_height_m)
    relabelled = tall & (detections.classes == category_id("passenger"))
    classes = np.where(relabelled, category_id("truck"), detections.classes)
    if relabelled.any():
        # the detector's suppression within a class, again for the class that gained boxes (it may
        # have seen one truck as a truck and as a car at one place); on the detector's boxes, not
        # the refined ones: at 90 m a car and the truck right behind it are one depth surface, both
        # boxes snap to it, and the car must keep its box
        trucks = np.flatnonzero(classes == category_id("truck"))
        keep = np.ones(len(boxes), bool)
        keep[trucks] = False
        keep[trucks[nms(detections.boxes[trucks], scores[trucks], refine.duplicate_iou)]] = True
        boxes, scores, classes, snapped = boxes[keep], scores[keep], classes[keep], snapped[keep]
    if refine.proposals is not None and view.sparse:
        count_depth_step(stats, "frames_without_proposals")  # too little measured depth: none proposed
    elif refine.proposals is not None:
        if segments is None:
            segments = object_segments(view.depth, cam.K, view.T, refine, view.noise)
        confident = scores >= refine.proposals.score
        new, is_truck, new_labels = depth_proposals(view.depth, cam.K, view.T, boxes[confident], refine,
                                                    segments, snapped[confident], view.noise, with_labels=True)
        # only on noiseless depth: a noisy sensor's segment can end short of its own car or join the
        # next one, and is no better than the detector's sides (stereo, development: 2 targets lost)
        if refine.proposals.merge_same_segment and view.noise.exact and segments is not None:
            merged, kept = merge_same_segment(boxes[confident], classes[confident] == category_id("truck"),
                                              snapped[confident], new, is_truck, segments,
                                              refine.proposals.merge_below_px)
            count_depth_step(stats, "boxes_merged", int((~kept).sum()))
            boxes = boxes.copy()
            boxes[confident] = merged
            new, is_truck, new_labels = new[kept], is_truck[kept], new_labels[kept]
        new_scores = _proposal_scores(new, boxes[~confident], scores[~confident], refine.proposals.score)
        boxes, scores = np.vstack([boxes, new]), np.r_[scores, new_scores]
        classes = np.r_[classes, np.where(is_truck, category_id("truck"), category_id("passenger"))]
        # a proposal's surface is that of the segment it was proposed from
        outline = np.r_[np.zeros(len(boxes) - len(new), int), new_labels]
        boxes = join_fragments(boxes, scores >= refine.proposals.score, segments, cam.K, refine, view.noise, outline)
        # only on noiseless depth, as merge_same_segment: a noisy segment can join the next vehicle
        if refine.proposals.join_truck_fragments and view.noise.exact and segments is not None and len(boxes) > 1:
            boxes, kept = join_truck_fragments(boxes, scores, classes == category_id("truck"), segments)
            count_depth_step(stats, "truck_fragments_joined", int((~kept).sum()))
            boxes, scores, classes = boxes[kept], scores[kept], classes[kept]
    return Detections.of(boxes, scores, classes)


def _place_gated_from_image(image: np.ndarray, refined: RefinedBoxes, weights: str, stats: dict | None) -> None:
    """The sides of the boxes the noise gate kept from the image (vcfusion.fusion.far_boxes.BoxHead),
    in place; counted as boxes_from_image. Boxes taller than the head's training range keep the
    detector's sides."""
    head = _box_head(weights)
    b = refined.boxes
    pick = np.flatnonzero(refined.noisy & (b[:, 3] - b[:, 1] <= head.max_height_px))
    count_depth_step(stats, "boxes_from_image", len(pick))
    if len(pick):
        h, w = image.shape[:2]
        moved = head.refine(image, b[pick])
        moved[:, [0, 2]] = moved[:, [0, 2]].clip(-0.5, w - 0.5)
        moved[:, [1, 3]] = moved[:, [1, 3]].clip(-0.5, h - 0.5)
        b[pick] = moved


@functools.lru_cache(maxsize=4)
def _box_head(weights: str):
    """The far-box head `weights` names ("shipped": the package's, else a weights file), found and
    loaded once a process, not once a frame."""
    from vcfusion.fusion.far_boxes import BoxHead, default_box_head_path

    return BoxHead.load(default_box_head_path() if weights == "shipped" else weights)


def _proposal_scores(proposals: np.ndarray, weak_boxes: np.ndarray, weak_scores: np.ndarray,
                     base: float) -> np.ndarray:
    """A depth proposal scores `base` (the proposals' operating score) plus the best score of a
    detection below it that covers the proposal (IoU >= 0.5): where the detector saw something too,
    the proposal is likelier a vehicle (a bush or a sign standing on the road side never has one).
    Only a detector run below the operating threshold (the COCO evaluation) has such detections; the
    proposals are kept either way, only their rank changes."""
    out = np.full(len(proposals), base, np.float32)
    if len(proposals) and len(weak_boxes):
        covers = box_iou(proposals, weak_boxes) >= 0.5
        out += np.where(covers, weak_scores[None, :], 0.0).max(axis=1).astype(np.float32)
    return out


def fuse_frame(frame: CameraFrame, twins: TwinStates, detector: Detector, rng: np.random.Generator,
               depth_params: DepthEvalParams = DepthEvalParams(), joint: JointMatcher | None = None,
               methods=METHODS, fallback_radius_px: float | None = None,
               refine: BoxRefineParams | None = None, segments: ObjectSegments | None = None) -> FusionResult:
    """Run every requested matcher on one frame for the given twins (boxes refined by depth when
    `refine` is given). `segments`: the frame's :func:`frame_segments`, when already computed."""
    timings = {}
    t0 = wallclock.perf_counter()
    if segments is None and ("joint" in methods or (refine is not None and refine.proposals is not None)):
        segments = frame_segments(frame, refine)
    depth_counts: dict = {}
    detections = detect_frame(frame, detector, refine, segments, depth_counts)
    t1 = wallclock.perf_counter()
    # the matchers read the depth as the depth step does (median-filtered when the sensor is noisy)
    view = depth_view(frame, refine or BoxRefineParams()) if not frame.depth_noise.exact else None
    depth = view.depth if view is not None else frame.depth
    samples = sample_box_depths(depth, detections.boxes, rng, depth_params)
    depths = reduce_depth_samples(samples, depth_params.reducer)  # Algorithm 1
    t2 = wallclock.perf_counter()
    timings["detect"], timings["depth"] = t1 - t0, t2 - t1
    choice = {}
    # the paper's matchers use the twins as received (no latency compensation)
    proj = project_twins(twins, frame.camera)
    if "baseline" in methods:
        choice["baseline"] = match_all_baseline(proj, detections.boxes, detections.scores, fallback_radius_px)
    if "baseline_centre" in methods:
        choice["baseline_centre"] = match_all_baseline(proj, detections.boxes, None, fallback_radius_px, rule="centre")
    if "paper" in methods:
        choice["paper"] = match_all_paper(proj, detections.boxes, depths, fallback_radius_px,
                                          scores=detections.scores)
    if "joint" in methods:
        joint_samples = joint_depth_samples(depth, detections.boxes, samples, depth_params.th)
        surface = box_surface_depths(detections.boxes, segments, refine or BoxRefineParams())
        # the depth term's sigma widened by the error of the depth the samples were read from
        joint_match = (joint or JointMatcher()).match_details(twins, detections.boxes, joint_samples, frame.camera,
                                                              surface, view.noise if view is not None else None)
        choice["joint"] = joint_match.choice
    timings["match"] = wallclock.perf_counter() - t2
    n_anchor_boxes = np.zeros(len(twins), np.int64)
    for i in np.flatnonzero(proj.in_view):
        n_anchor_boxes[i] = int(point_in_boxes(proj.anchor[i], detections.boxes).sum()) if len(detections) else 0
    # in view: projected into the image as received, or matched (the joint matcher projects the
    # twins moved on by their latency: a stale report can lie behind the camera, its vehicle not)
    in_view = proj.in_view | np.any([c != NO_MATCH for c in choice.values()], axis=0) if choice else proj.in_view
    if "joint" in methods:
        # the overlay's rules (drawable_box) judge the outlines the matcher decided on, not the noisier
        # reports as received: a near car's raw GNSS error (0.3 m, ~10 px at 10 m) made its outline
        # hide a visible car the matcher had found
        return FusionResult(frame.time, twins.ids, detections, depths, choice, in_view, timings, n_anchor_boxes,
                            depth_counts, joint_match.projection.expected_box, joint_match.hidden_share,
                            depth_sigmas=joint_match.depth_sigmas, depth_on_surface=joint_match.depth_on_surface,
                            shown_depth_sigmas=joint_match.shown_depth_sigmas)
    return FusionResult(frame.time, twins.ids, detections, depths, choice, in_view, timings, n_anchor_boxes,
                        depth_counts, proj.expected_box, visible_boxes(proj)[2])


def _finite_or_none(value) -> float | None:
    v = float(value)
    return v if np.isfinite(v) and v > 0 else None



# A twin whose projected outline nearer twins hide by at least this share (the joint matcher's
# visible_boxes raster, twin data only; 1.0: hidden whole, the matcher's own second-round case)
# gets no box drawn: its vehicle shows a sliver at most, and the box it was matched to is mostly
# another vehicle's (curved.yaml seed 0: cars queued behind the accident at 150-165 m, 8-35 px of
# them visible, took boxes on the stopped trucks and on the cars in front of them).
MAX_HIDDEN_SHARE_DRAWN = 1.0
# A matched box more than this many times the area of the twin's whole projected outline is not
# drawn: it cannot be the twin's vehicle (its visible part is at most its outline; GNSS noise and
# detector slack move a box by a fraction of it). Cause: a mostly hidden far car's twin took a
# stopped truck's box or a fragment of it (curved.yaml seed 0: a truck's 15 x 21 px box for a car
# whose outline is about 6 x 10 px), which the identification study, judging visible targets
# only, never sees.
MAX_BOX_TO_OUTLINE_AREA = 3.0
# A twin whose projected outline, less the share nearer twins' outlines hide (twin data only), is
# smaller than this many pixels gets no box drawn: a car of about 7 x 7 px, ~200 m away with the
# shipped 90-degree 640 px camera. Cause: far cars showing 15-30 px took boxes on the truck or car
# next to them (curved.yaml seed 101: cars13 at 20-24 px on trucks2's box for 1.2 s, cars6 hidden
# behind f0.1 at a hidden share of 0.75-0.88 on f0.1's box), which the detector cannot resolve and
# the driver cannot check. Chosen on the guidance matrix's seeds 100-101 (five scenarios, fusion
# arm): 50 px keeps 86 % of the drawn updates and leaves 1 wrong of 1092; the highlight
# definition's 100 px (vcfusion.metrics.highlights.MIN_VISIBLE_PX) kept 61 % and lost the guided
# driver's gap (docs/components/guidance-loop.md). Where the surface drawing the matched box's outline
# lies at the twin (within HIDDEN_DEPTH_CONFIRM_SIGMAS, JointMatch.depth_on_surface), the part of the
# box within the outline counts instead (accident_heavy.yaml seed 96, changer4 at 33 m: the outlines
# leave 42 px of it, its box shows 108 px on its own surface, 0.01 sigma off; on the development
# records, curved.yaml 94-96 and accident_heavy.yaml 94-96, 3 warned missed and 26 warned unseen
# updates become right and none wrong; taking the samples' depth as well, 3 became wrong).
MIN_DRAWN_VISIBLE_PX = 50.0


# A twin whose outline nearer twins hide whole (MAX_HIDDEN_SHARE_DRAWN) still gets its matched box
# drawn when depth shows the box at the twin's own distance, within this many of the joint matcher's
# depth sigmas (JointMatcherParams: 5 % of the distance + 1 m): the depth of the surface drawing the
# box's outline (box_refine.box_surface_depths; JointMatch.depth_on_surface), against the twin's
# face or the part of it the box's columns show (JointMatch.shown_depth_sigmas). The outlines are the
# twins' reports drawn as cuboids, and a near car's position error of a few decimetres (tens of
# pixels at 10-20 m) hides a car that shows 150-600 px beside it (curved.yaml seed 100 cars14,
# accident_heavy.yaml seeds 95, 97 changer2 and changer5). One sigma: the box's depth must agree with
# the twin as closely as the matcher's own scale allows; a far car's box taken from the truck 20 m
# behind it (3 sigmas at 160 m) stays undrawn. The lower-quarter samples alone do not confirm: they
# read the vehicle in front of a hidden twin at about its depth (development records, curved.yaml
# 94-96 and accident_heavy.yaml 94-96: of the hidden-whole twins' boxes drawn on the samples alone
# 15 of 15 were wrong, on the surface 131 of 131 right).
HIDDEN_DEPTH_CONFIRM_SIGMAS = 1.0


# A twin whose outline nearer twins' outlines hide by at least this share (and not whole) is drawn,
# as a twin hidden whole is, only where depth puts its box at the twin: the surface drawing the box's
# outline within HIDDEN_DEPTH_CONFIRM_SIGMAS of the twin (its face or the part the box's columns show).
# What the outlines leave of such a twin is a strip a few pixels wide, and the box the matcher gives it
# there can be the nearer or farther vehicle beside the strip (curved.yaml seed 125: trucks1, 0.83
# of its outline hidden, took trucks2's box 15 m nearer, depth read by the lower-quarter samples
# only). Share of the outline's 16 x 16 raster cells (matching.visible_boxes). Chosen on the
# development records (fusion arm, curved.yaml 118, 119, 121, 123-125 and accident_heavy.yaml
# 122-125; every AR update re-judged; docs/components/guidance-loop.md): at 0.8 the rule makes 1
# warned and 4 unwarned wrong boxes missed or unseen and no right box undrawn; 0.75 / 0.7 undraw 8 /
# 13 right boxes (unwarned) as well, 0.85 / 0.9 leave the warned wrong box (0.83 hidden) drawn. In
# the oracle arm (curved.yaml 124, 125) 0.8 undraws 5 unwarned right boxes and no warned one.
MOSTLY_HIDDEN_SHARE = 0.8


def drawable_box(box, expected_box, hidden_share: float = 0.0, max_ratio: float | None = None,
                 max_hidden: float | None = None, depth_sigmas: float = np.inf, depth_on_surface: bool = False,
                 shown_depth_sigmas: float = np.inf):
    """`box` unless :func:`undrawn_reason` gives a reason not to draw it (then None: nothing is
    drawn for the twin). Boxes (x1, y1, x2, y2) px."""
    return box if undrawn_reason(box, expected_box, hidden_share, max_ratio, max_hidden, depth_sigmas,
                                 depth_on_surface, shown_depth_sigmas) == "" else None


def _area_within(box, outline) -> float:
    """Pixels of `box` within `outline` (both (x1, y1, x2, y2) px)."""
    b, e = box, outline
    return max(min(b[2], e[2]) - max(b[0], e[0]), 0.0) * max(min(b[3], e[3]) - max(b[1], e[1]), 0.0)


# A matched box of which less than this share lies within the twin's own projected outline (twin
# data only: GNSS-smoothed position, heading and size) shows mostly something else: the overlay draws
# the part of it within the outline (under MIN_DRAWN_VISIBLE_PX of it: nothing, "small"). Causes: the
# depth step joined a car and the truck behind it into one surface and the car's twin took the
# truck-high box (curved.yaml seed 95 cars12 at 15 m: 26 % of the box within its outline; the part
# within it is right, IoU 0.62-0.73), and a box over a far changer and the stopped truck above it
# (accident_heavy.yaml seed 94 changer4 at 48 m: 52 %, IoU 0.43 -> 0.59). Chosen on the development
# seeds (curved.yaml 94-96, accident_heavy.yaml 94-95; per AR update, the boxes the overlay drew): at
# 0.4 / 0.5 / 0.6 / 0.7 / 0.8 the rule makes 4 / 4 / 6 / 6 / 6 warned wrong boxes right or undrawn
# and no right box wrong at any of them; from 0.7 more right boxes become too small to draw (3 at
# 0.7, 11 at 0.8, 1 at 0.6, all unwarned). An outline the image's side cuts (a car alongside the
# camera) is not the vehicle's extent, and its boxes are drawn whole.
MIN_BOX_INSIDE_OUTLINE = 0.6


def box_within_outline(box, expected_box, width: int, height: int):
    """The box the overlay draws for a twin matched to `box`: `box`, or where less than
    MIN_BOX_INSIDE_OUTLINE of it lies within the twin's outline `expected_box`, the outline keeps
    a pixel from every side of the `width` x `height` image and the box is not over
    MAX_BOX_TO_OUTLINE_AREA times the outline (then "too_large" stands), the part of `box` within the outline
    (None: under MIN_DRAWN_VISIBLE_PX of it lies there). Boxes (x1, y1, x2, y2) px, the image spanning
    [-0.5, width - 0.5]."""
    if box is None or expected_box is None:
        return box
    b, e = np.asarray(box, dtype=float), np.asarray(expected_box, dtype=float)
    if e[0] <= 0.5 or e[1] <= 0.5 or e[2] >= width - 1.5 or e[3] >= height - 1.5:
        return box
    area = float((b[2] - b[0]) * (b[3] - b[1]))
    inside = _area_within(b, e)
    outline = float((e[2] - e[0]) * (e[3] - e[1]))
    if area <= 0 or inside >= MIN_BOX_INSIDE_OUTLINE * area or area > MAX_BOX_TO_OUTLINE_AREA * outline:
        return box  # mostly within the outline, or no box of the twin at all ("too_large")
    if inside < MIN_DRAWN_VISIBLE_PX:
        return None
    return np.array([max(b[0], e[0]), max(b[1], e[1]), min(b[2], e[2]), min(b[3], e[3])])  # the part within


UNDRAWN_REASONS = ("", "no_match", "hidden", "small", "too_large")


def undrawn_reason(box, expected_box, hidden_share: float = 0.0, max_ratio: float | None = None,
                   max_hidden: float | None = None, depth_sigmas: float = np.inf,
                   depth_on_surface: bool = False, shown_depth_sigmas: float = np.inf) -> str:
    """Why nothing is drawn for a twin matched to `box`: "" (drawn), "no_match" (no box matched),
    "hidden" (nearer twins hide at least `max_hidden`, default MAX_HIDDEN_SHARE_DRAWN, or
    MOSTLY_HIDDEN_SHARE of its outline `expected_box`, and the box's depth does not confirm the twin: its disagreement
    `depth_sigmas`, and its disagreement with the part of the twin the box's columns show,
    `shown_depth_sigmas` (JointMatch.shown_depth_sigmas), are both over
    HIDDEN_DEPTH_CONFIRM_SIGMAS, or it is not the depth of the surface drawing the box's outline,
    `depth_on_surface`: the lower-quarter samples alone do not confirm), "small" (the
    part of its outline nearer twins leave visible is under MIN_DRAWN_VISIBLE_PX, and so is, for a
    depth-confirmed twin hidden whole or a twin whose box's outline surface lies at it
    (`depth_on_surface`, within HIDDEN_DEPTH_CONFIRM_SIGMAS), the part of the box within its
    outline), "too_large" (the box is more than `max_ratio`, default
    MAX_BOX_TO_OUTLINE_AREA, times the outline's area)."""
    max_ratio = MAX_BOX_TO_OUTLINE_AREA if max_ratio is None else max_ratio
    max_hidden = MAX_HIDDEN_SHARE_DRAWN if max_hidden is None else max_hidden
    if box is None:
        return "no_match"
    if expected_box is None:
        return ""
    e = np.asarray(expected_box, dtype=float)
    outline = max(float((e[2] - e[0]) * (e[3] - e[1])), 1.0)
    confirmed = min(depth_sigmas, shown_depth_sigmas) <= HIDDEN_DEPTH_CONFIRM_SIGMAS
    within = _area_within(np.asarray(box, dtype=float), e)
    if hidden_share >= max_hidden:
        if not confirmed or not depth_on_surface:
            return "hidden"
        # depth puts the box's surface at the twin: what shows of it is the box, within its outline
        shown = within
    else:
        shown = outline * (1.0 - hidden_share)
        if shown < MIN_DRAWN_VISIBLE_PX and confirmed and depth_on_surface:
            # the outlines leave little of it, but the surface drawing the box's outline lies at the
            # twin: what shows of it is the box, within its outline, as for a twin hidden whole
            shown = max(shown, within)
    if shown < MIN_DRAWN_VISIBLE_PX:
        return "small"
    area = float((box[2] - box[0]) * (box[3] - box[1]))
    if area > max_ratio * outline:
        return "too_large"
    if hidden_share >= MOSTLY_HIDDEN_SHARE and not (confirmed and depth_on_surface):
        return "hidden"  # mostly hidden, and depth does not put the box's surface at the twin
    return ""


class VisionFusionHook:
    """Tick hook: fuse the camera frame with the ego's neighbour twins, set ``tick.detections`` and
    ``tick.guidance`` (source ``fusion``, levels from `policy`), draw the AR overlay (into
    ``recorder`` when given) and log one row per neighbour in view to the run folder's ``fusion``
    table. Without a `frame_source` it reads the camera stage's ``tick.frame``."""

    table = "fusion"
    columns = ("time", "vehicle_id", "method", "lc_prob", "level", "matched", "box_vehicle_id", "x1", "y1", "x2", "y2",
               "outcome", "gt_iou", "visible_px", "visible_share", "frame", "undrawn", "hidden_share")
    provides = ("detections", "guidance")

    def __init__(self, frame_source: FrameSource | None, detector: Detector, seed: int, policy: GuidancePolicy,
                 method: str = "joint", depth_params: DepthEvalParams = DepthEvalParams(),
                 joint: JointMatcher | None = None, recorder: OverlayRecorder | None = None,
                 period_s: float | None = None, only_when_warning: bool = False,
                 refine: BoxRefineParams | None = None):
        if method not in METHODS:
            raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
        if frame_source is None:
            from vcfusion.fusion.stage import tick_frame_source  # the camera stage's frames (imports fuse.py)

            frame_source = tick_frame_source
            self.needs = ("neighbours", "frame")
        elif getattr(frame_source, "reads_tick_frame", False):  # the camera stage's frames, through the sensors
            self.needs = ("neighbours", "frame")
        else:
            self.needs = ("neighbours",)
        self.frame_source = frame_source
        self.policy = policy
        self.detector = detector
        self.rng = np.random.default_rng(seed)
        self.method = method
        self.depth_params = depth_params
        self.refine = refine
        self.joint = joint or JointMatcher()
        self.recorder = recorder
        self.timings: list[dict] = []
        self.depth_counts: dict = {}  # the depth step's counts over the run (depth_step's `stats`)
        # run every period_s (the AR update period, ar.period_s); None = every tick
        self.period_s = period_s
        self._next_time = -np.inf
        self._shown: GuidanceSet | None = None  # the overlay on the screen
        # fuse only where a neighbour carries a warning (the camera stage renders only there too)
        self.only_when_warning = only_when_warning

    def __call__(self, tick) -> list[dict] | None:
        if tick.neighbours is None:
            return None
        if self.period_s is not None:
            if tick.time < self._next_time - 1e-9:
                # between AR updates the overlay drawn last stays on the screen
                tick.guidance = self._shown
                return None
            self._next_time = tick.time + self.period_s
        if self.only_when_warning and not self.policy.any_warning(tick.neighbours):
            # nothing to warn about: the overlay draws no warning (no frame was rendered for it)
            tick.guidance = self._shown = GuidanceSet((), "fusion")
            return None
        t0 = wallclock.perf_counter()
        frame = self.frame_source(tick)
        if frame is None:
            # no camera frame at an update: nothing is drawn, and nothing stands in for it (the
            # guidance log counts the tick as "no_frame")
            self._shown = None
            return None
        t_render = wallclock.perf_counter() - t0
        twins = tick.neighbours
        result = fuse_frame(frame, twins, self.detector, self.rng, self.depth_params, self.joint, (self.method,),
                            refine=self.refine)
        for key, v in result.depth_counts.items():
            count_depth_step(self.depth_counts, key, v)
        lc = np.asarray(twins.outputs.get("lc_prob", np.full(len(twins), np.nan)), dtype=float)
        view = np.flatnonzero(result.in_view)
        sigmas = result.depth_sigmas if result.depth_sigmas is not None else np.full(len(twins), np.inf)
        surface = result.depth_on_surface if result.depth_on_surface is not None else np.zeros(len(twins), bool)
        shown = (result.shown_depth_sigmas if result.shown_depth_sigmas is not None
                 else np.full(len(twins), np.inf))
        cam = frame.camera
        given = [result.box_of(self.method, i) for i in view]
        matched = [box_within_outline(g, result.expected_boxes[i], cam.width, cam.height) for g, i in zip(given, view)]
        # a matched box of which too little lies within the outline leaves nothing to draw: "small"
        reasons = ["small" if b is None and g is not None else
                   undrawn_reason(b, result.expected_boxes[i], result.hidden_share[i],
                                  depth_sigmas=float(sigmas[i]), depth_on_surface=bool(surface[i]),
                                  shown_depth_sigmas=float(shown[i]))
                   for b, g, i in zip(matched, given, view)]
        boxes = [b if r == "" else None for b, r in zip(matched, reasons)]
        chosen = [int(result.choice[self.method][i]) for i in view]
        decision = twins.outputs.get("lc_decision")
        in_view = make_guidance(tick.time, [twins.ids[i] for i in view], lc[view], boxes, self.policy,
                                None if decision is None else np.asarray(decision)[view])
        # What is drawn is what the driver is shown: a twin without a matched box gives no item.
        # Each twin is judged against the frame's ground truth (vcfusion.metrics.highlights, the
        # one definition of a right highlight), and each item names the vehicle its box shows (the
        # one whose visible box it overlaps most: whom a person looking at the overlay would see
        # highlighted); ground truth serves that model of the driver's eye and the scoring only.
        # Each drawn item carries its box's depth as the fusion measured it.
        judged = [judge_highlight(g.vehicle_id, g.box, frame.visible_boxes, frame.gt_ids,
                                  frame.gt_visible_share) for g in in_view]
        in_view = [replace(g, box_vehicle_id=jd.box_vehicle_id or None, box_depth_m=_finite_or_none(result.box_depths[j]))
                   if g.box is not None else g for g, jd, j in zip(in_view, judged, chosen)]
        guidance = [g for g in in_view if g.box is not None]
        tick.detections = result.detections
        tick.guidance = self._shown = GuidanceSet(tuple(guidance), "fusion")
        t3 = wallclock.perf_counter()
        frame_index = -1  # the overlay frame of this update (frames/NNNNNN.png), -1 when none is recorded
        if self.recorder is not None:
            frame_index = self.recorder.count
            ego_speed = tick.ego.speed if tick.ego is not None else float("nan")
            self.recorder.add(draw_overlay(frame.image, guidance, Hud(tick.time, ego_speed)))
        self.timings.append({"render": t_render, **result.timings_s, "overlay": wallclock.perf_counter() - t3})
        # every twin in view, matched or not, with its judgement: an unmatched warning on a
        # visible vehicle is missed, on a vehicle the frame does not show unseen
        rows = []
        for g, j, why, i in zip(in_view, judged, reasons, view):
            b = g.box if g.box is not None else (np.nan,) * 4
            rows.append({"time": round(tick.time, 6), "vehicle_id": g.vehicle_id, "method": self.method,
                         "lc_prob": g.lc_prob, "level": g.level, "matched": g.box is not None,
                         "box_vehicle_id": g.box_vehicle_id or "",
                         "x1": b[0], "y1": b[1], "x2": b[2], "y2": b[3],
                         "outcome": j.outcome, "gt_iou": j.iou, "visible_px": j.visible_px,
                         "visible_share": j.visible_share, "frame": frame_index,
                         "undrawn": why, "hidden_share": float(result.hidden_share[i])})
        return rows

