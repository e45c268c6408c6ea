"""Benchmark of the fusion stages of one vision tick at 640x480 (detect, refine and propose by depth,
depth, match, overlay).

    python -m vcfusion.fusion.bench [--frames 200] [--weights W] [--threads 2]

Prints the median and 90th percentile time per stage. The frame is synthetic (noise image, the
depth of the default camera's road with ten box-shaped vehicles on it, eight twins): the stages'
costs depend on the image size, the number and size of boxes and twins, not on the content. Rendering is timed by the renderer's own benchmark; add it
to these figures for the full tick. Without --weights (and no shipped model) the detector is an
untrained network of the default architecture: the same computation as the trained one.
``overlay_handover`` is what a tick pays for the video: the recorder encodes on its own thread.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from vcfusion.fusion.box_refine import (BoxRefineParams, box_surface_depths, depth_proposals, object_segments,
                                       refine_boxes)
from vcfusion.fusion.depth_eval import DepthEvalParams, joint_depth_samples, reduce_depth_samples, sample_box_depths
from vcfusion.detection.detector_net import CenterNetLite, DetectorModel, TorchDetector, default_weights_path
from vcfusion.fusion.matching import JointMatcher, TwinProjection, match_all_baseline, match_all_paper
from vcfusion.fusion.overlay import Hud, OverlayRecorder, draw_overlay, make_guidance
from vcfusion.guidance import GuidancePolicy
from vcfusion.render.camera import Intrinsics, world_to_camera
from vcfusion.scenario import AROverlayConfig, CameraConfig


def default_camera(width=640, height=480) -> tuple[np.ndarray, np.ndarray]:
    """K and T_world_to_camera of the scenario's default camera on an ego at the origin."""
    cam = CameraConfig()
    return Intrinsics.from_fov(cam.hfov_deg, width, height).K, world_to_camera(0.0, 0.0, 0.0, 0.0, cam)


def road_depth(K, T, width, height) -> np.ndarray:
    """Camera-Z of the flat road (z = 0) at each pixel, inf above the horizon."""
    v, u = np.mgrid[0:height, 0:width].astype(float)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T  # camera-Z = 1
    down = rays @ T[:3, 2]  # world-z change per unit camera-Z
    centre_z = (-T[:3, :3].T @ T[:3, 3])[2]
    with np.errstate(divide="ignore"):
        z = np.where(down < -1e-9, centre_z / -down, np.inf)
    return z.astype(np.float32)


def synthetic_scene(rng, width=640, height=480, n_boxes=10, n_twins=8):
    image = rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
    K, T = default_camera(width, height)
    depth = road_depth(K, T, width, height)
    xy = rng.uniform([0, height * 0.4], [width - 120, height - 100], (n_boxes, 2))
    wh = rng.uniform([30, 25], [120, 100], (n_boxes, 2))
    boxes = np.concatenate([xy, xy + wh], axis=1)
    # each vehicle stands on the road: its face is as far as the road under its box's bottom edge
    dist = depth[np.minimum(boxes[:, 3].astype(int), height - 1), ((boxes[:, 0] + boxes[:, 2]) / 2).astype(int)]
    for b, d in sorted(zip(boxes.astype(int), dist), key=lambda e: -e[1]):
        depth[b[1]:b[3], b[0]:b[2]] = d
    k = np.arange(n_twins)
    proj = TwinProjection(anchor=(boxes[k, :2] + boxes[k, 2:]) / 2, anchor_z=dist[k] + 2.0, gnss_range=dist[k] + 2.1,
                          expected_box=boxes[k] + rng.normal(0, 3, (n_twins, 4)), face_z=dist[k],
                          in_view=np.ones(n_twins, bool))
    return image, depth, boxes, proj, K, T


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--weights")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    weights = Path(args.weights) if args.weights else default_weights_path()
    if weights.is_file():
        detector, label = TorchDetector(weights), str(weights)
    else:
        torch.manual_seed(0)
        net = DetectorModel(CenterNetLite(2).eval(), (320, 240), [1, 2], ["car", "truck"], (16, 32, 64, 128, 64))
        detector, label = TorchDetector(net), "untrained default architecture (same compute)"
    image, depth, boxes, proj, K, T = synthetic_scene(rng)
    # the detector's boxes, a few pixels off (what the refinement corrects)
    detected = boxes + rng.normal(0.0, 3.0, boxes.shape)
    matcher = JointMatcher()
    ar = AROverlayConfig()  # the scenario defaults' colours; the lane geometry plays no part in drawing
    policy = GuidancePolicy(ar.medium_threshold, ar.high_threshold, view_range_m=150.0, ego_lane=0, lane_width_m=3.2,
                            ego_lane_centre_d=1.6)
    times = {k: [] for k in ("detect", "refine", "propose", "depth", "match", "overlay_draw", "overlay_handover")}
    params = BoxRefineParams()
    with tempfile.TemporaryDirectory() as tmp, OverlayRecorder(Path(tmp) / "v") as rec:
        for i in range(args.frames + 5):
            t0 = time.perf_counter()
            detector.detect(image)
            t05 = time.perf_counter()
            refine_boxes(detected, depth, K, T, params)
            t06 = time.perf_counter()
            # the whole frame is segmented whatever it holds; two boxes withheld as the detector's misses
            segments = object_segments(depth, K, T, params)  # shared with the matcher, as in fuse_frame
            depth_proposals(depth, K, T, detected[2:], params, segments)
            t1 = time.perf_counter()
            samples = sample_box_depths(depth, boxes, rng, DepthEvalParams())
            depths = reduce_depth_samples(samples)
            t2 = time.perf_counter()
            match_all_baseline(proj, boxes)
            match_all_paper(proj, boxes, depths)
            chosen = matcher.assign(proj, boxes, joint_depth_samples(depth, boxes, samples, DepthEvalParams().th),
                                    box_surface_depths(boxes, segments, params))
            t3 = time.perf_counter()
            guidance = make_guidance(0.1 * i, [f"v{k}" for k in range(len(chosen))], rng.random(len(chosen)),
                                     [boxes[j] if j >= 0 else None for j in chosen], policy)
            frame = draw_overlay(image, guidance, Hud(0.1 * i, 19.0))
            t4 = time.perf_counter()
            rec.add(frame)
            t5 = time.perf_counter()
            if i >= 5:  # warm-up excluded
                for key, dt in zip(times, (t05 - t0, t06 - t05, t1 - t06, t2 - t1, t3 - t2, t4 - t3, t5 - t4)):
                    times[key].append(dt)
    print(f"fusion stages at 640x480, {args.frames} frames, {args.threads} torch threads; detector: {label}")
    print(f"{'stage':<15}{'median ms':>10}{'p90 ms':>10}")
    total = 0.0
    for key, vals in times.items():
        med = 1e3 * float(np.median(vals))
        total += med
        print(f"{key:<15}{med:>10.2f}{1e3 * float(np.percentile(vals, 90)):>10.2f}")
    print(f"{'total':<15}{total:>10.2f}   (+ rendering, from the renderer's benchmark)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
