import contextlib
import io

import numpy as np
import pytest

from vcfusion.detection.detection_metrics import coco_map
from vcfusion.detection.detectors import Detections, OracleDetector, batched_nms, nms


def random_dataset(rng, n_images=12, n_cats=2):
    gt, det = {}, {}
    for img in range(n_images):
        g = rng.integers(0, 6)
        xy = rng.uniform(0, 300, (g, 2))
        wh = rng.uniform(8, 120, (g, 2))
        boxes = np.concatenate([xy, xy + wh], 1)
        cls = rng.integers(1, n_cats + 1, g)
        gt[img] = (boxes, cls)
        # detections: noisy copies of some ground truth, plus false positives
        keep = rng.random(g) < 0.8
        noisy = boxes[keep] + rng.normal(0, 6, (keep.sum(), 4))
        fp_xy = rng.uniform(0, 300, (rng.integers(0, 4), 2))
        fps = np.concatenate([fp_xy, fp_xy + rng.uniform(8, 80, (len(fp_xy), 2))], 1)
        d_boxes = np.concatenate([noisy, fps])
        d_boxes = np.concatenate([np.minimum(d_boxes[:, :2], d_boxes[:, 2:]), np.maximum(d_boxes[:, :2], d_boxes[:, 2:])], 1)
        d_cls = np.concatenate([cls[keep], rng.integers(1, n_cats + 1, len(fps))])
        det[img] = (d_boxes, rng.random(len(d_boxes)), d_cls)
    return gt, det


def pycocotools_map(gt, det, n_cats=2, min_area=0.0):
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    images = [{"id": i + 1, "width": 640, "height": 480} for i in gt]
    anns, k = [], 1
    for i, (boxes, cls) in gt.items():
        for b, c in zip(boxes, cls):
            w, h = b[2] - b[0], b[3] - b[1]
            anns.append({"id": k, "image_id": i + 1, "category_id": int(c), "bbox": [b[0], b[1], w, h],
                         "area": w * h, "iscrowd": 0})
            k += 1
    results = [{"image_id": i + 1, "category_id": int(c), "bbox": [b[0], b[1], b[2] - b[0], b[3] - b[1]],
                "score": float(s)} for i, (boxes, scores, cls) in det.items() for b, s, c in zip(boxes, scores, cls)]
    with contextlib.redirect_stdout(io.StringIO()):
        coco = COCO()
        coco.dataset = {"images": images, "annotations": anns,
                        "categories": [{"id": c} for c in range(1, n_cats + 1)]}
        coco.createIndex()
        ev = COCOeval(coco, coco.loadRes(results), "bbox")
        if min_area > 0:
            ev.params.areaRng = [[min_area, 1e10]] * 4  # every summary row uses this range
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return ev.stats[1], ev.stats[0]


@pytest.mark.parametrize("seed,min_area", [(0, 0.0), (1, 0.0), (2, 0.0), (3, 1500.0), (4, 3000.0)])
def test_coco_map_equals_pycocotools(seed, min_area):
    """Including COCOeval's area range (ignored small ground truth and small unmatched detections)."""
    pytest.importorskip("pycocotools")
    gt, det = random_dataset(np.random.default_rng(seed))
    ours = coco_map(gt, det, min_area=min_area)
    ref50, ref = pycocotools_map(gt, det, min_area=min_area)
    assert 0.05 < ours.map_50_95 < 0.95  # a non-trivial case
    assert ours.map_50 == pytest.approx(ref50, abs=1e-9)
    assert ours.map_50_95 == pytest.approx(ref, abs=1e-9)


def test_a_class_whose_ground_truth_is_all_below_min_area_is_left_out_as_pycocotools_does():
    # a far truck in every frame (8 x 11 px, below 100 px^2) and detections of it labelled truck:
    # the class has nothing to find, so it is no class of the mean (it was counted as AP 0,
    # halving the mAP of a render of scenarios/overlap.yaml)
    pytest.importorskip("pycocotools")
    gt, det = random_dataset(np.random.default_rng(5), n_cats=1)
    far = np.array([[316.0, 209.0, 324.0, 220.0]])
    for img, (boxes, cls) in gt.items():
        gt[img] = (np.concatenate([boxes, far]), np.concatenate([cls, [2]]))
        d_boxes, d_scores, d_cls = det[img]
        det[img] = (np.concatenate([d_boxes, far + 0.5]), np.concatenate([d_scores, [0.6]]), np.concatenate([d_cls, [2]]))
    ours = coco_map(gt, det, min_area=100.0)
    ref50, ref = pycocotools_map(gt, det, min_area=100.0)
    assert ours.map_50 == pytest.approx(ref50, abs=1e-9) and ours.map_50_95 == pytest.approx(ref, abs=1e-9)
    assert 2 not in ours.ap_per_category and ours.map_50_95 == pytest.approx(coco_map(
        {i: (b[c == 1], c[c == 1]) for i, (b, c) in gt.items()}, det, min_area=100.0).map_50_95)


def test_equal_scores_rank_in_image_id_order_as_pycocotools_does_whatever_order_images_come_in():
    # a hit in image 1 and a miss in image 2 with the same score, the ground truth listed 2, 1:
    # COCOeval ranks image 1's first (AP@0.5 0.505); taken in the dict's order it was 0.2525
    pytest.importorskip("pycocotools")
    box = np.array([[10.0, 10.0, 50.0, 40.0]])
    gt = {1: (box, np.array([1])), 0: (box, np.array([1]))}
    det = {0: (box, np.array([1.0]), np.array([1])), 1: (box + 100, np.array([1.0]), np.array([1]))}
    ref50, ref = pycocotools_map(gt, det, n_cats=1)
    ours = coco_map(gt, det)
    assert ours.map_50 == pytest.approx(ref50, abs=1e-9) == pytest.approx(0.505, abs=1e-3)


def test_perfect_detections_score_one():
    gt = {0: (np.array([[0, 0, 10, 10], [20, 20, 40, 40]], float), np.array([1, 1]))}
    det = {0: (gt[0][0], np.array([0.9, 0.8]), np.array([1, 1]))}
    r = coco_map(gt, det)
    assert r.map_50 == 1.0 and r.map_50_95 == 1.0


def test_nms_keeps_the_best_of_overlapping_boxes():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [20, 20, 30, 30], [0, 0, 10, 10]], float)
    scores = np.array([0.5, 0.9, 0.7, 0.1])
    np.testing.assert_array_equal(nms(boxes, scores, 0.5), [1, 2])
    # a different class is not suppressed
    np.testing.assert_array_equal(batched_nms(boxes, scores, [0, 0, 0, 1], 0.5), [1, 2, 3])


def test_oracle_detector_returns_truth_and_degrades_when_asked():
    truth = np.array([[10, 10, 50, 40], [100, 100, 200, 180]], float)
    image = np.zeros((480, 640, 3), np.uint8)
    oracle = OracleDetector()
    oracle.set_truth(truth, [3, 8])
    det = oracle.detect(image)
    np.testing.assert_array_equal(det.boxes, truth.astype(np.float32))
    np.testing.assert_array_equal(det.classes, [3, 8])
    noisy = OracleDetector(jitter_px=2.0, miss_probability=0.5, rng=np.random.default_rng(0))
    noisy.set_truth(np.tile(truth, (50, 1)))
    got = noisy.detect(image)
    assert 20 < len(got) < 80
    assert (got.boxes[:, 2] >= got.boxes[:, 0]).all()
    with pytest.raises(ValueError):
        Detections(np.zeros((2, 4)), np.zeros(1), np.zeros(2))
