"""Per-family evaluation of a detector on rendered COCO folders (`vcfusion eval-detector`).

Images are grouped by their ``family`` (procedural scenes, :mod:`vcfusion.detection.scenes`;
frames of `vcfusion render` have none and form the group ``frames``; with several groups, ``all``
pools them). Per group:
- COCO mAP@0.5 and mAP@0.5:0.95 (:func:`coco_map`, ground truth below ``min_area`` px^2 ignored);
- the IoU of the best-matching detected box per target (class-agnostic; the boxes the fusion
  stage gets: the detector at its operating score threshold, then the depth step when refining):
  quantiles and the shares >= 0.5 and >= 0.7;
- identification accuracy at IoU 0.7 of the joint matcher (share of targets whose matched box has
  IoU >= 0.7 with the target's box), with the detector's boxes and with ground-truth boxes
  (oracle). The twins are the image's vehicles as the renderer placed them (the recipe's
  ``twins`` for procedural scenes, else the ``vehicles`` anchors): GNSS point = body centre
  (:func:`vcfusion.records.gnss_antenna_points`), no latency, no noise unless asked for
  (``gnss_noise_m``); the depth image is the rendered one. A target is a vehicle with a ground-truth box of at least ``min_area`` px^2;
- the same identification per share of the target that nearer objects leave visible
  (:data:`VISIBILITY_BINS` of the renderer's ``visible_fraction``), where the folder has it;
- 95 % intervals of the identification accuracies and of each detector's gap to the oracle, by
  resampling the family's scenes (:func:`scene_bootstrap`): a seed of a folder is one scene, the
  one image of a procedural scene, the many frames of a `vcfusion render` seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from vcfusion.detection.detection_metrics import BoxMap, coco_map
from vcfusion.detection.detector_net import DetectorFileError
from vcfusion.detection.detector_train import CocoDataset, read_rgb
from vcfusion.detection.detectors import Detections, OracleDetector
from vcfusion.metrics.cluster_bootstrap import cluster_weights, percentile_interval, ratio_draws

IDENTIFICATION_IOU = 0.7
IOU_QUANTILES = (0.1, 0.25, 0.5)
# identification per how much of the target nearer objects leave visible (the renderer's
# visible_fraction): the bins' lower edges and labels
VISIBILITY_BINS = ((0.0, "<0.25"), (0.25, "0.25-0.5"), (0.5, ">=0.5"))
BOOTSTRAP_RESAMPLES = 2000


@dataclass
class FamilyResult:
    family: str
    n_images: int
    n_targets: int
    box_map: BoxMap
    best_iou: np.ndarray  # (targets,) best IoU of a detected box per target (0 where none)
    identification: dict = field(default_factory=dict)  # detector name -> accuracy at IoU 0.7 (joint matcher)
    n_identified_targets: int = 0
    # detector name -> {visibility bin label: (targets, accuracy at IoU 0.7)}; empty without visible_fraction
    identification_by_visibility: dict = field(default_factory=dict)
    # detector name -> (low, high) 95 % interval of its accuracy; "gap_NAME": of oracle minus NAME
    identification_interval: dict = field(default_factory=dict)
    # the depth step's counts over the family's images (vcfusion.fusion.fuse.depth_step): boxes kept
    # as detected because depth could not decide (boxes_gated), road fits that failed, ...
    depth_counts: dict = field(default_factory=dict)
    # detector name -> {failure kind (FAILURE_KINDS): targets}: where each identification target's
    # box came from (failure_kinds)
    failures: dict = field(default_factory=dict)

    def summary(self) -> dict:
        q = np.quantile(self.best_iou, IOU_QUANTILES) if len(self.best_iou) else [np.nan] * len(IOU_QUANTILES)
        return {"family": self.family, "images": self.n_images, "targets": self.n_targets,
                "map_50": self.box_map.map_50, "map_50_95": self.box_map.map_50_95,
                **{f"best_iou_p{int(100 * p)}": float(v) for p, v in zip(IOU_QUANTILES, q)},
                "best_iou_ge_0.5": float((self.best_iou >= 0.5).mean()) if len(self.best_iou) else np.nan,
                "best_iou_ge_0.7": float((self.best_iou >= 0.7).mean()) if len(self.best_iou) else np.nan,
                "identification_targets": self.n_identified_targets,
                **{f"ident_0.7_{k}": v for k, v in self.identification.items()},
                **{f"ident_0.7_{k}_visible_{label}": {"targets": n, "accuracy": acc}
                   for k, bins in self.identification_by_visibility.items() for label, (n, acc) in bins.items()},
                **{f"ident_0.7_{k}_interval95": list(bounds) for k, bounds in self.identification_interval.items()},
                **{f"depth_step_{k}": v for k, v in self.depth_counts.items()},
                **{f"targets_{k}_{kind}": n for k, kinds in self.failures.items() for kind, n in kinds.items()}}


class _Fixed:
    """A detector that returns the detections given (to reuse one detector pass)."""

    def __init__(self, detections: Detections):
        self.detections = detections

    def detect(self, image) -> Detections:
        return self.detections


def family_of(record: dict) -> str:
    return str(record.get("family", "frames"))


def _dataset_file(image: Path, record: dict, name: str) -> Path | None:
    """A file named relative to the dataset folder of an image (the folder holding its rgb file's
    path, or that folder's parent where images sit under images/)."""
    parent = image
    for _ in Path(record["file_name"]).parts:
        parent = parent.parent
    for folder in (parent, parent.parent):
        if (folder / name).is_file():
            return folder / name
    return None


def _twins(record: dict, time: float, gnss_noise_m: float = 0.0, rng: np.random.Generator | None = None):
    from vcfusion.records import TwinStates, add_gnss_error, gnss_antenna_points

    rows = record.get("twins") or record.get("vehicles") or []
    if not rows:
        return None
    fp = np.array([r["footprint_world"] for r in rows], float).reshape(-1, 3)
    size = np.array([r["size"] for r in rows], float).reshape(-1, 3)
    gnss = add_gnss_error(gnss_antenna_points(fp[:, 0], fp[:, 1], fp[:, 2], size[:, 2]), gnss_noise_m, rng)
    n = len(rows)
    return TwinStates(time=time, ids=tuple(r["vehicle_id"] for r in rows), measured_time=np.full(n, time),
                      x=gnss[:, 0], y=gnss[:, 1], z=gnss[:, 2], heading=np.array([r["yaw"] for r in rows], float),
                      speed=np.array([r.get("speed", 0.0) for r in rows], float), accel=np.zeros(n),
                      lane=np.full(n, -1, np.int16), length=size[:, 0], width=size[:, 1], height=size[:, 2], outputs={})


def _camera_frame(ds: CocoDataset, k: int, image: np.ndarray):
    from vcfusion.fusion.fuse import CameraFrame
    from vcfusion.fusion.stage import camera_view

    rec = ds.records[k]
    cam = rec.get("camera")
    depth_file = rec.get("depth_file")
    if not cam or not depth_file:
        return None  # not a frame of ours (a COCO folder from elsewhere): no depth to fuse with
    path = _dataset_file(ds.images[k], rec, depth_file)
    png = None if path is None else cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    # a frame that names its depth image must have it: its targets were silently left out of the
    # identification (and a wrong-sized depth image scored as if it fitted)
    if png is None:
        raise DetectorFileError(f"{ds.images[k]}: its depth image {depth_file} is missing or unreadable; expected "
                                "the 16-bit depth PNG that vcfusion render / render-scenes wrote beside it")
    if png.shape != image.shape[:2]:
        raise DetectorFileError(f"{path}: depth image of shape {png.shape}; expected a single-channel image of the "
                                f"RGB image's size {image.shape[:2]} (the 16-bit depth PNG vcfusion render wrote)")
    depth = np.where(png > 0, png.astype(np.float32) * np.float32(0.01), np.float32(np.inf))
    time = float(cam.get("time", 0.0))
    view = camera_view(np.array(cam["K"]), np.array(cam["T_world_to_camera"]), image.shape[1], image.shape[0], time)
    return CameraFrame(time=time, image=image, depth=depth, camera=view, gt_boxes=ds.boxes[k],
                       gt_ids=tuple(ds.box_vehicle_ids[k]), gt_classes=ds.classes[k])


def _sensed(frame, depth_sensor: str, pose_noise_deg: float, k: int):
    """The dataset frame as the sensors deliver it (vcfusion.fusion.sensors; image k's own draws)."""
    from dataclasses import replace

    from vcfusion.fusion.sensors import PoseNoiseParams, SensorModel
    from vcfusion.fusion.stage import SENSOR_STREAM, camera_view

    cam = frame.camera
    sensors = SensorModel(depth_sensor, pose=PoseNoiseParams(mount_std_deg=pose_noise_deg),
                          rng=np.random.default_rng([k, SENSOR_STREAM]))
    depth = sensors.depth(frame.depth, cam.K, cam.T_world_to_camera, frame.image)
    T = sensors.believed_pose(cam.T_world_to_camera)
    return replace(frame, depth=depth, camera=camera_view(cam.K, T, cam.width, cam.height, cam.time),
                   depth_noise=sensors.noise(cam.K))


# what became of each identification target (failure_kinds), in table order
FAILURE_KINDS = ("right", "missed", "detector_box_off", "depth_box_off", "matcher")
MISSED_IOU = 0.3  # no box overlaps the target this much: it was missed


def failure_kinds(iou_matched: np.ndarray, gt: np.ndarray, boxes: np.ndarray, detected: np.ndarray) -> list[str]:
    """Per target, what became of it (FAILURE_KINDS): ``right`` (its matched box at IoU >= 0.7);
    ``missed`` (no box overlaps it by MISSED_IOU); ``matcher`` (a box at IoU >= 0.7 was there, the
    matcher took another); else the best box overlapping it was off: ``detector_box_off`` when that box
    is one of the detector's as detected (gated, not snapped, or no depth step), ``depth_box_off`` when
    the depth step snapped or proposed it. `iou_matched`: (T,) the matched box's IoU per target, `gt`
    (T, 4) the targets' boxes, `boxes` the boxes the matcher chose from, `detected` the detector's."""
    from vcfusion.fusion.matching import box_iou

    iou = box_iou(gt, boxes) if len(boxes) and len(gt) else np.zeros((len(gt), 0))
    out = []
    for t in range(len(gt)):
        best = int(iou[t].argmax()) if iou.shape[1] else -1
        best_iou = iou[t, best] if best >= 0 else 0.0
        if iou_matched[t] >= IDENTIFICATION_IOU - 1e-12:
            out.append("right")
        elif best_iou >= IDENTIFICATION_IOU - 1e-12:
            out.append("matcher")
        elif best_iou < MISSED_IOU:
            out.append("missed")
        else:
            as_detected = len(detected) and bool(np.any(np.all(np.abs(detected - boxes[best]) < 1e-6, axis=1)))
            out.append("detector_box_off" if as_detected else "depth_box_off")
    return out


def _identification(frame, twins, detector, seed: int, min_area: float, segments=None) -> tuple[np.ndarray, list]:
    """IoU of the joint matcher's box per target (0 where unmatched) and the targets' vehicle ids
    (`segments`: the frame's depth segments, when already computed)."""
    from vcfusion.fusion.depth_eval import DepthEvalParams
    from vcfusion.fusion.fuse import fuse_frame
    from vcfusion.fusion.matching import JointMatcher, JointMatcherParams
    from vcfusion.studies.identification import identification_rows

    # each image is its own scene: no position smoothing across images
    joint = JointMatcher(JointMatcherParams(smoothing_alpha=None))
    result = fuse_frame(frame, twins, detector, np.random.default_rng(seed), DepthEvalParams(), joint, ("joint",),
                        segments=segments)
    rows = identification_rows(frame, result, min_area)
    return np.array([r["iou"] for r in rows], float), [r["vehicle_id"] for r in rows]


def evaluate_families(detector, ds: CocoDataset, min_area: float = 100.0, identification: bool = True,
                      detector_name: str = "cnn", progress: bool = False,
                      refine=None, gnss_noise_m: float = 0.0, depth_sensor: str = "exact",
                      pose_noise_deg: float = 0.0) -> tuple[list[FamilyResult], dict]:
    """Per-family results (in order of first appearance; plus 'all' over every image when there is
    more than one family) and the detections at COCO-evaluation threshold per image id. ``refine``
    (BoxRefineParams): score the boxes as the fusion stage uses them, snapped to each image's depth
    (every image then needs its depth image and camera record). ``gnss_noise_m``: the twins' GNSS
    points for the identification moved by a Gaussian of this std on each horizontal axis (one draw
    per image, seeded by its index, the same for the oracle and the detector). ``depth_sensor`` and
    ``pose_noise_deg`` (a mount calibration error std, deg; frames of a dataset have no motion, so no
    body pitch): what the fusion and the depth step see instead of the rendered depth and the exact
    pose (vcfusion.fusion.sensors; seeded per image)."""
    from vcfusion.fusion.fuse import depth_step, frame_segments
    from vcfusion.detection.detector_net import PostParams
    from vcfusion.fusion.matching import box_iou

    operating = getattr(detector, "params", PostParams()).score_threshold
    if hasattr(detector, "params"):
        saved = detector.params
        detector.params = PostParams(score_threshold=0.01, nms_iou=saved.nms_iou, max_detections=100)
    records = ds.records or [{} for _ in ds.images]
    dets, best, ident, counts, kinds = {}, {}, {}, {}, {}
    try:
        for k, (iid, path) in enumerate(tqdm(list(zip(ds.image_ids, ds.images)), desc="evaluate", unit="img",
                                             disable=not progress, leave=False)):
            image = read_rgb(path)
            frame = _camera_frame(ds, k, image) if ds.records and (refine is not None or identification) else None
            if frame is not None and (depth_sensor != "exact" or pose_noise_deg > 0):
                frame = _sensed(frame, depth_sensor, pose_noise_deg, k)
            if refine is not None and frame is None:
                raise DetectorFileError(f"{path}: box refinement needs the image's depth image and camera record "
                                        "(a folder written by vcfusion render / render-scenes); "
                                        "score the boxes as detected instead (--no-refine)")
            raw = detector.detect(image)  # at the evaluation threshold
            # the boxes the fusion stage works with: the detector's above its operating threshold (the
            # same boxes as a detection at that threshold: suppression only removes a box for a more
            # confident one), then the depth step, whose refinements and proposals depend on which
            # boxes it gets (a proposal scores 0.3, which a higher threshold would cut after it)
            working = raw.select(raw.scores >= operating)
            detected = working.boxes
            # the frame's depth segments, once for both depth steps and the matcher
            segments = frame_segments(frame, refine) if frame is not None else None
            if refine is not None:
                counts[iid] = {}
                raw = depth_step(frame, raw, refine, segments)
                working = depth_step(frame, working, refine, segments, counts[iid])
            dets[iid] = (raw.boxes, raw.scores, raw.classes)
            gt = ds.boxes[k]
            big = (gt[:, 2] - gt[:, 0]) * (gt[:, 3] - gt[:, 1]) >= min_area
            iou = box_iou(gt[big], working.boxes) if len(working) and big.any() else np.zeros((int(big.sum()), 0))
            best[iid] = iou.max(axis=1) if iou.shape[1] else np.zeros(int(big.sum()))
            if identification and ds.records and ds.box_vehicle_ids:
                twins = (_twins(records[k], frame.time, gnss_noise_m, np.random.default_rng([k, 1]))
                         if frame is not None else None)
                if frame is not None and twins is not None:
                    visible = dict(zip(ds.box_vehicle_ids[k], ds.box_visible[k])) if ds.box_visible else {}
                    ident[iid], kinds[iid] = {}, {}
                    gt_index = {v: j for j, v in enumerate(frame.gt_ids)}
                    for name, det in (("oracle", OracleDetector()), (detector_name, _Fixed(working))):
                        iou_t, vids = _identification(frame, twins, det, k, min_area, segments)
                        ident[iid][name] = (iou_t, np.array([visible.get(v, np.nan) for v in vids], float))
                        if name == detector_name:
                            gt_t = frame.gt_boxes[[gt_index[v] for v in vids]].reshape(-1, 4)
                            kinds[iid][name] = failure_kinds(iou_t, gt_t, working.boxes, detected)
    finally:
        if hasattr(detector, "params"):
            detector.params = saved
    families = list(dict.fromkeys(family_of(r) for r in records))
    groups = [(f, [k for k, r in enumerate(records) if family_of(r) == f]) for f in families]
    if len(families) > 1:
        groups.append(("all", list(range(len(ds)))))
    results = []
    gt_all = ds.ground_truth()
    scene_of = ds.scenes() if ident else []  # the bootstrap's clusters, once for every family
    for fam, index in groups:
        ids = [ds.image_ids[k] for k in index]
        if not any(len(gt_all[i][0]) for i in ids):
            continue  # no ground truth: mAP undefined
        bm = coco_map({i: gt_all[i] for i in ids}, {i: dets[i] for i in ids}, min_area=min_area)
        best_iou = np.concatenate([best[i] for i in ids]) if ids else np.zeros(0)
        res = FamilyResult(fam, len(ids), len(best_iou), bm, best_iou)
        for i in ids:
            for key, v in counts.get(i, {}).items():
                res.depth_counts[key] = res.depth_counts.get(key, 0) + v
        with_k = [k for k in index if ds.image_ids[k] in ident]
        with_ident = [ds.image_ids[k] for k in with_k]
        if with_ident:
            # per detector, per image: whether each target was identified (pooled, binned and resampled)
            right_per_image = {name: [ident[i][name][0] >= IDENTIFICATION_IOU - 1e-12 for i in with_ident]
                               for name in ident[with_ident[0]]}
            for name, per_image in right_per_image.items():
                right = np.concatenate(per_image)
                vis = np.concatenate([ident[i][name][1] for i in with_ident])
                res.identification[name] = float(right.mean()) if len(right) else np.nan
                if np.isfinite(vis).any():
                    res.identification_by_visibility[name] = _by_visibility(right, vis)
            res.n_identified_targets = int(sum(len(ident[i]["oracle"][0]) for i in with_ident))
            for i in with_ident:
                for name, per_target in kinds.get(i, {}).items():
                    tally = res.failures.setdefault(name, dict.fromkeys(FAILURE_KINDS, 0))
                    for kind in per_target:
                        tally[kind] += 1
            res.identification_interval = scene_bootstrap(right_per_image, [scene_of[k] for k in with_k])
        results.append(res)
    return results, dets


def scene_bootstrap(right: dict[str, list[np.ndarray]], scenes: list | None = None,
                    resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> dict[str, tuple[float, float]]:
    """95 % percentile intervals of identification accuracy, resampling scenes with replacement.

    ``right``: detector name -> per image, whether each target was identified (the same targets,
    in the same order, for every detector). ``scenes``: per image, the scene it shows (default:
    each image its own); the images of one scene are resampled together. Scenes, not targets or
    frames, are resampled: one scene's targets are not independent (one occluded cluster fails
    together; the frames of one SUMO seed show the same vehicles), and a scene is what a seed draws.
    Returns {name: (low, high)} and, for every detector but the oracle (when it is given),
    {"gap_" + name: (low, high)} of the oracle's accuracy minus the detector's on the same draws
    (paired: the oracle and the detector saw the same scenes). Seeded: the same inputs give the
    same intervals.
    """
    names = list(right)
    if not names or not sum(len(r) for r in right[names[0]]):
        return {}  # no target: no accuracy to bound
    scenes = list(range(len(right[names[0]]))) if scenes is None else list(scenes)
    cluster = {key: c for c, key in enumerate(dict.fromkeys(scenes))}
    of = np.array([cluster[key] for key in scenes])
    n_scenes = len(cluster)
    targets = np.bincount(of, [len(r) for r in right[names[0]]], n_scenes)
    counts = {name: np.bincount(of, [np.count_nonzero(r) for r in right[name]], n_scenes) for name in names}
    weights = cluster_weights(n_scenes, resamples, seed)
    acc = {name: ratio_draws(weights, c, targets) for name, c in counts.items()}  # nan where a draw has no target
    out = {name: percentile_interval(a) for name, a in acc.items()}
    if "oracle" in acc:
        out.update({f"gap_{name}": percentile_interval(acc["oracle"] - a)
                    for name, a in acc.items() if name != "oracle"})
    return out


def format_interval_table(results: list[FamilyResult], detector_name: str = "cnn") -> str:
    """Identification at IoU 0.7 per family with 95 % intervals over scenes (:func:`scene_bootstrap`):
    oracle, detector, and the oracle's lead over the detector in points."""
    rows = [r for r in results if detector_name in r.identification_interval]
    if not rows:
        return ""
    lines = [f"identification at IoU 0.7 with 95 % intervals over scenes ({BOOTSTRAP_RESAMPLES} resamples of "
             "the scenes: a folder's seeds)",
             f"{'family':<16} {'oracle':>22} {detector_name:>22} {'oracle - ' + detector_name + ' (points)':>26}"]
    for r in rows:
        lead = r.identification["oracle"] - r.identification[detector_name]
        lo, hi = r.identification_interval[f"gap_{detector_name}"]
        lines.append(f"{r.family:<16} {_interval_cell(r, 'oracle'):>22} {_interval_cell(r, detector_name):>22} "
                     f"{100 * lead:>10.1f} [{100 * lo:>5.1f}, {100 * hi:>5.1f}]")
    return "\n".join(lines)


def _interval_cell(r: FamilyResult, name: str) -> str:
    lo, hi = r.identification_interval[name]
    return f"{r.identification[name]:>7.1%} [{lo:>5.1%}, {hi:>5.1%}]"


def _by_visibility(right: np.ndarray, visible: np.ndarray) -> dict:
    """{bin label: (targets, share right)} over VISIBILITY_BINS (targets without a visible fraction
    are left out)."""
    edges = [lo for lo, _ in VISIBILITY_BINS] + [np.inf]
    out = {}
    for (lo, label), hi in zip(VISIBILITY_BINS, edges[1:]):
        m = (visible >= lo) & (visible < hi)
        out[label] = (int(m.sum()), float(right[m].mean()) if m.any() else np.nan)
    return out


def format_visibility_table(results: list[FamilyResult], detector_name: str = "cnn") -> str:
    """Identification at IoU 0.7 per family and visible fraction of the target (oracle / detector);
    empty when the folders carry no visible fractions."""
    rows = [r for r in results if detector_name in r.identification_by_visibility]
    if not rows:
        return ""
    labels = [label for _, label in VISIBILITY_BINS]
    lines = ["identification at IoU 0.7 by the share of the target left visible by nearer objects",
             f"{'':<16} " + " ".join(f"{'visible ' + label:^25}" for label in labels),
             f"{'family':<16} " + " ".join(f"{'targets':>7} {'oracle':>8} {detector_name:>8}" for _ in labels)]
    def cell(n: int, oracle: float, acc: float) -> str:
        return f"{n:>7} " + (f"{oracle:>8.1%} {acc:>8.1%}" if n else f"{'-':>8} {'-':>8}")  # an empty bin: no accuracy

    for r in rows:
        oracle = r.identification_by_visibility.get("oracle", {})
        cells = [cell(n, oracle.get(label, (n, np.nan))[1], acc)
                 for label, (n, acc) in r.identification_by_visibility[detector_name].items()]
        lines.append(f"{r.family:<16} " + " ".join(cells))
    return "\n".join(lines)


def format_table(results: list[FamilyResult], detector_name: str = "cnn") -> str:
    head = (f"{'family':<16} {'images':>6} {'targets':>7} {'mAP@.5':>7} {'mAP@.5:.95':>10} "
            f"{'IoU p10':>7} {'p25':>5} {'median':>6} {'>=0.7':>6} {'ident@0.7 oracle':>16} {detector_name:>6}")
    lines = [head]
    for r in results:
        s = r.summary()
        lines.append(
            f"{r.family:<16} {r.n_images:>6} {r.n_targets:>7} {s['map_50']:>7.3f} {s['map_50_95']:>10.3f} "
            f"{s['best_iou_p10']:>7.3f} {s['best_iou_p25']:>5.3f} {s['best_iou_p50']:>6.3f} "
            f"{s['best_iou_ge_0.7']:>6.1%} "
            f"{_share(s.get('ident_0.7_oracle')):>16} {_share(s.get(f'ident_0.7_{detector_name}')):>6}")
    return "\n".join(lines)


def format_depth_counts(results: list[FamilyResult]) -> str:
    """What the depth step could not decide, per family (depth_counts_table)."""
    return depth_counts_table({r.family: r.depth_counts for r in results})


def depth_counts_table(counts: dict[str, dict]) -> str:
    """What the depth step could not decide, per name (a family, a detector): boxes kept as
    detected (gated; of them, those behind the noise gate placed from the image: from image), road
    fits that failed, images without depth proposals; and the road fit's mean time. Names without
    counts are left out; "" when none has any."""
    rows = {name: c for name, c in counts.items() if c and c.get("frames")}
    if not rows:
        return ""
    lines = [f"{'depth step':<16} {'boxes refined':>13} {'gated':>6} {'from image':>10} {'road fit failed':>15} "
             f"{'no proposals':>12} {'road fit ms':>11}"]
    for name, c in rows.items():
        lines.append(f"{name:<16} {c.get('boxes_refined', 0):>13} {c.get('boxes_gated', 0):>6} "
                     f"{c.get('boxes_from_image', 0):>10} "
                     f"{c.get('frames_road_fit_failed', 0):>15} {c.get('frames_without_proposals', 0):>12} "
                     f"{c.get('road_fit_ms', 0.0) / c['frames']:>11.2f}")
    return "\n".join(lines)


def format_failure_table(results: list[FamilyResult], detector_name: str = "cnn") -> str:
    """What became of each identification target, per family (failure_kinds): right, missed, the
    detector's box off (kept as detected), the depth step's box off, the matcher's choice; "" when no
    family has identification targets."""
    rows = [r for r in results if detector_name in r.failures]
    if not rows:
        return ""
    lines = [f"{'targets':<16} " + " ".join(f"{k:>16}" for k in FAILURE_KINDS)]
    for r in rows:
        lines.append(f"{r.family:<16} " + " ".join(f"{r.failures[detector_name][k]:>16}" for k in FAILURE_KINDS))
    return "\n".join(lines)


def _share(value: float | None) -> str:
    """A percentage, or '-' where there is none (--no-identification, or no target)."""
    return "-" if value is None or np.isnan(value) else f"{value:.1%}"
