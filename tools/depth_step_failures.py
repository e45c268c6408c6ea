"""Where the depth step loses identification targets, by range: per target of rendered scene folders
(`vcfusion render-scenes`), what became of it (vcfusion.detection.family_eval.failure_kinds), the
state of the detector's box on it in the refinement (gated, snapped, kept, none) and its range
(camera-Z of its true footprint centre), with the raw boxes' and the oracle's outcome beside it.
The frames, draws and boxes are those of `vcfusion eval-detector FOLDERS --depth-sensor S
--pose-noise-deg P` (the folders in the same order).

    python tools/depth_step_failures.py --depth-sensor stereo --pose-noise-deg 0.3 DEV/jam DEV/cut_in ...
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

from vcfusion.detection.detector_net import TorchDetector, default_weights_path
from vcfusion.detection.detector_train import load_coco_many, read_rgb
from vcfusion.detection.detectors import OracleDetector
from vcfusion.detection.family_eval import (IDENTIFICATION_IOU, _camera_frame, _Fixed, _identification, _sensed,
                                            _twins, failure_kinds)
from vcfusion.fusion.box_refine import BoxRefineParams, refine_boxes
from vcfusion.fusion.fuse import depth_step, depth_view, frame_segments
from vcfusion.fusion.matching import box_iou
from vcfusion.fusion.stage import road_model

RANGES_M = [0, 15, 30, 45, np.inf]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="+")
    ap.add_argument("--depth-sensor", default="exact", choices=("exact", "stereo", "tof", "lidar"))
    ap.add_argument("--pose-noise-deg", type=float, default=0.0)
    ap.add_argument("--min-area", type=float, default=100.0)
    ap.add_argument("--csv", help="also write the per-target table to this CSV file")
    ap.add_argument("--box-head", default="shipped",
                    help="far-box head for gated boxes: shipped, a weights file or none (as eval-detector)")
    args = ap.parse_args()
    ds = load_coco_many(args.data)
    detector = TorchDetector(default_weights_path())  # at its operating threshold: eval-detector's working boxes
    refine = BoxRefineParams(road=road_model("auto", args.depth_sensor, args.pose_noise_deg > 0),
                             box_head=None if args.box_head == "none" else args.box_head)
    rows = []
    for k, path in enumerate(ds.images):
        exact = _camera_frame(ds, k, read_rgb(path))
        frame = exact
        if args.depth_sensor != "exact" or args.pose_noise_deg > 0:
            frame = _sensed(exact, args.depth_sensor, args.pose_noise_deg, k)
        working = detector.detect(frame.image)
        segments = frame_segments(frame, refine)
        view = depth_view(frame, refine)
        refined = refine_boxes(working.boxes, view.depth, frame.camera.K, view.T, refine, view.noise, view.returns)
        stepped = depth_step(frame, working, refine, segments, {})
        twins = _twins(ds.records[k], frame.time, 0.0, np.random.default_rng([k, 1]))
        if twins is None:
            continue
        outcome = {}
        for name, det in (("oracle", OracleDetector()), ("step", _Fixed(stepped)), ("raw", _Fixed(working))):
            iou_t, vids = _identification(frame, twins, det, k, args.min_area, segments)
            outcome[name] = dict(zip(vids, iou_t))
        vids = list(outcome["step"])
        gt_index = {v: j for j, v in enumerate(frame.gt_ids)}
        gt = frame.gt_boxes[[gt_index[v] for v in vids]].reshape(-1, 4)
        kinds = failure_kinds(np.array([outcome["step"][v] for v in vids]), gt, stepped.boxes, working.boxes)
        records = ds.records[k].get("twins") or ds.records[k].get("vehicles")
        footprint = {r["vehicle_id"]: r["footprint_world"] for r in records}
        T = exact.camera.T_world_to_camera  # the true pose, for the range only
        for v, g, kind in zip(vids, gt, kinds):
            iou = box_iou(g[None], working.boxes)[0] if len(working) else np.zeros(0)
            j = int(iou.argmax()) if len(iou) else -1
            state = ("none" if j < 0 or iou[j] < 0.3 else
                     "gated" if refined.gated[j] else "snapped" if refined.refined[j] else "kept")
            rows.append({"image": k, "vehicle_id": v, "range_m": float((T @ np.r_[footprint[v][:2], 0.75, 1.0])[2]),
                         "kind": kind, "detector_box": state, "detector_iou": float(iou[j]) if j >= 0 else 0.0,
                         **{name: bool(outcome[name][v] >= IDENTIFICATION_IOU - 1e-12) for name in outcome}})
    df = pd.DataFrame(rows)
    if args.csv:
        df.to_csv(args.csv, index=False)
    print(f"{len(df)} targets: depth step {df.step.mean():.1%}, raw boxes {df.raw.mean():.1%}, "
          f"oracle {df.oracle.mean():.1%}")
    df["range"] = pd.cut(df.range_m, RANGES_M, right=False)
    print(pd.crosstab(df.range, df.kind, margins=True).to_string())
    lost = df[~df.step]
    print("lost targets by the detector's box in the refinement:")
    print(pd.crosstab(lost.kind, lost.detector_box, margins=True).to_string())
    print(f"right with the step, not raw: {int((df.step & ~df.raw).sum())}; right raw, not with the step: "
          f"{int((df.raw & ~df.step).sum())}")
    print(lost.sort_values("range_m").to_string(index=False))


if __name__ == "__main__":
    main()
