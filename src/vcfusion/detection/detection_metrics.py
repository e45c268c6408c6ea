"""COCO-style box mAP (the 'bbox', area 'all', maxDets 100 numbers of the COCO evaluation).

Our own implementation so the runtime does not need pycocotools; the tests check it against
pycocotools on random detections. Per category and image, detections (highest score first, at most
``max_dets``) are greedily matched to the unmatched ground truth of highest IoU >= the threshold;
precision is made monotone and read at 101 recall points; AP is averaged over the categories that
have ground truth, and mAP@0.5:0.95 over the IoU thresholds 0.50, 0.55, ..., 0.95.
Crowd annotations and area ranges are not used (our datasets have neither).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

IOU_THRESHOLDS = np.linspace(0.5, 0.95, 10)
RECALL_POINTS = np.linspace(0.0, 1.0, 101)


@dataclass(frozen=True)
class BoxMap:
    map_50: float
    map_50_95: float
    ap_per_iou: np.ndarray  # (10,) over IOU_THRESHOLDS, averaged over categories
    ap_per_category: dict  # category id -> AP@0.5:0.95


def _iou_xyxy(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ix = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]), 0, None)
    iy = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]), 0, None)
    inter = ix * iy
    aa = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    ab = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = aa[:, None] + ab[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def coco_map(ground_truth: dict, detections: dict, max_dets: int = 100, min_area: float = 0.0) -> BoxMap:
    """mAP over images.

    ground_truth: image id -> (boxes (G, 4) xyxy, classes (G,));
    detections: image id -> (boxes (D, 4) xyxy, scores (D,), classes (D,)).
    ``min_area`` (px^2) is COCOeval's area range [min_area, inf): smaller ground truth is ignored
    (a detection matched to it counts neither way), as are unmatched detections smaller than it.
    """
    categories = sorted({int(c) for _, cls in ground_truth.values() for c in np.asarray(cls).reshape(-1)})
    try:  # images in id order, as COCOeval takes them: detections of equal score rank in that order
        image_ids = sorted(ground_truth)
    except TypeError:  # ids of mixed kinds: as given
        image_ids = list(ground_truth)
    n_t = len(IOU_THRESHOLDS)
    ap = np.full((len(categories), n_t), np.nan)  # NaN: a category with nothing to find (COCOeval's -1)
    for k, cat in enumerate(categories):
        scores_all, tp_all = [], []
        n_pos = 0
        for image_id in image_ids:
            gt_boxes, gt_cls = ground_truth[image_id]
            gt = np.asarray(gt_boxes, float).reshape(-1, 4)[np.asarray(gt_cls).reshape(-1) == cat]
            n_pos += int((((gt[:, 2] - gt[:, 0]) * (gt[:, 3] - gt[:, 1])) >= min_area).sum())
            if image_id not in detections:
                continue
            d_boxes, d_scores, d_cls = detections[image_id]
            sel = np.asarray(d_cls).reshape(-1) == cat
            db = np.asarray(d_boxes, float).reshape(-1, 4)[sel]
            ds = np.asarray(d_scores, float).reshape(-1)[sel]
            order = np.argsort(-ds, kind="mergesort")[:max_dets]
            db, ds = db[order], ds[order]
            gt_area = (gt[:, 2] - gt[:, 0]) * (gt[:, 3] - gt[:, 1])
            gt_ignore = gt_area < min_area
            # COCOeval: non-ignored ground truth first, so a detection prefers it
            gorder = np.argsort(gt_ignore, kind="mergesort")
            gt, gt_ignore = gt[gorder], gt_ignore[gorder]
            det_small = (db[:, 2] - db[:, 0]) * (db[:, 3] - db[:, 1]) < min_area
            tp = np.zeros((n_t, len(db)), bool)
            ignored = np.tile(det_small, (n_t, 1)) if len(gt) == 0 else np.zeros((n_t, len(db)), bool)
            if len(gt) and len(db):
                iou = _iou_xyxy(db, gt)
                for t, thr in enumerate(IOU_THRESHOLDS):
                    taken = np.zeros(len(gt), bool)
                    for d in range(len(db)):
                        best, g_best = min(thr, 1 - 1e-10), -1
                        for g in range(len(gt)):
                            if taken[g]:
                                continue
                            # once a real match is found, ignored ground truth is not considered
                            if g_best > -1 and not gt_ignore[g_best] and gt_ignore[g]:
                                break
                            if iou[d, g] < best:
                                continue
                            best, g_best = iou[d, g], g
                        if g_best == -1:
                            ignored[t, d] = det_small[d]
                            continue
                        taken[g_best] = True
                        if gt_ignore[g_best]:
                            ignored[t, d] = True
                        else:
                            tp[t, d] = True
            elif len(db):
                ignored[:] = det_small[None, :]
            scores_all.append(ds)
            tp_all.append(np.where(ignored, -1, tp.astype(np.int8)))
        if n_pos == 0:
            continue  # all its ground truth is below min_area: no category of the mean, as in COCOeval
        ap[k] = 0.0
        if not scores_all or sum(len(s) for s in scores_all) == 0:
            continue  # nothing detected: AP 0
        scores = np.concatenate(scores_all)
        tps = np.concatenate(tp_all, axis=1)  # 1 true positive, 0 false positive, -1 ignored
        order = np.argsort(-scores, kind="mergesort")
        tps = tps[:, order]
        for t in range(n_t):
            tp_c = np.cumsum(tps[t] == 1).astype(float)
            fp_c = np.cumsum(tps[t] == 0).astype(float)
            recall = tp_c / n_pos
            precision = tp_c / np.maximum(tp_c + fp_c, np.spacing(1))
            precision = np.maximum.accumulate(precision[::-1])[::-1]
            idx = np.searchsorted(recall, RECALL_POINTS, side="left")
            sampled = np.zeros(len(RECALL_POINTS))
            ok = idx < len(precision)
            sampled[ok] = precision[idx[ok]]
            ap[k, t] = sampled.mean()
    if not categories:
        raise ValueError("coco_map: the ground truth has no boxes")
    scored = ~np.isnan(ap[:, 0])
    # no category with ground truth of at least min_area: NaN (COCOeval: -1)
    per_iou = ap[scored].mean(axis=0) if scored.any() else np.full(n_t, np.nan)
    return BoxMap(float(per_iou[0]), float(per_iou.mean()), per_iou,
                  {c: float(ap[k].mean()) for k, c in enumerate(categories) if scored[k]})
