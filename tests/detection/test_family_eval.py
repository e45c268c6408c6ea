"""`vcfusion eval-detector` per scene family: mAP equal to pycocotools' on the same files, the
best-IoU distribution and the identification check (joint matcher, oracle vs detector boxes)."""

import contextlib
import hashlib
import io
import json

import numpy as np
import pytest

from vcfusion.detection.detectors import Detections


@pytest.fixture(scope="module")
def families(tmp_path_factory):
    from scenario_files import SCENARIOS
    from vcfusion.detection.scenes import render_scenes
    from vcfusion.scenario import load_scenario

    root = tmp_path_factory.mktemp("families")
    sc = load_scenario(SCENARIOS / "overlap.yaml")
    folders = []
    for family, seeds in (("train", [0, 1, 2]), ("jam", [0, 1]), ("cut_in", [0, 1])):
        render_scenes(sc, family, seeds, root / family, progress=False)
        folders.append(root / family)
    return folders


def _pycocotools_family_map(folder, dets, image_ids, min_area):
    """COCOeval on the folder's annotations.json and our detections written as COCO results."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO(str(folder / "annotations.json"))
        # COCOeval's area range reads the annotation's 'area' (mask pixels in our files);
        # eval-detector's min_area is on the box area (COCO's bbox area): use that here too
        for ann in gt.dataset["annotations"]:
            ann["area"] = ann["bbox"][2] * ann["bbox"][3]
        gt.createIndex()
        results = [{"image_id": int(iid), "category_id": int(c), "score": float(s),
                    # our pixel-centre boxes -> COCO's pixel-corner bbox
                    "bbox": [float(b[0] + 0.5), float(b[1] + 0.5), float(b[2] - b[0]), float(b[3] - b[1])]}
                   for iid in image_ids for b, s, c in zip(*dets[iid])]
        ev = COCOeval(gt, gt.loadRes(results), "bbox")
        ev.params.imgIds = sorted(int(i) for i in image_ids)
        ev.params.areaRng = [[min_area, 1e10]] * 4
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return ev.stats[1], ev.stats[0]


@pytest.mark.slow
@pytest.mark.parametrize("min_area", [0.0, 100.0])
def test_per_family_map_equals_pycocotools(families, min_area):
    pytest.importorskip("pycocotools")
    from vcfusion.detection.detector_net import TorchDetector, default_weights_path
    from vcfusion.detection.detector_train import load_coco
    from vcfusion.detection.family_eval import evaluate_families

    detector = TorchDetector(default_weights_path())
    n_checked = 0
    for folder in families:  # one family per folder: image ids are the file's own
        ds = load_coco(folder)
        results, dets = evaluate_families(detector, ds, min_area=min_area, identification=False)
        assert [r.family for r in results] == [folder.name]
        ref50, ref = _pycocotools_family_map(folder, dets, ds.image_ids, min_area)
        assert results[0].box_map.map_50 == pytest.approx(ref50, abs=1e-9)
        assert results[0].box_map.map_50_95 == pytest.approx(ref, abs=1e-9)
        n_checked += 0 < ref < 1
    assert n_checked >= 1  # at least one non-trivial family


class TruthLookup:
    """A detector that returns each image's ground-truth boxes (found by the image's bytes)."""

    def __init__(self, ds):
        from vcfusion.detection.detector_train import read_rgb

        self.truth = {hashlib.sha1(read_rgb(p).tobytes()).hexdigest(): (b, c)
                      for p, b, c in zip(ds.images, ds.boxes, ds.classes)}

    def detect(self, image):
        boxes, classes = self.truth[hashlib.sha1(image.tobytes()).hexdigest()]
        return Detections.of(boxes, np.ones(len(boxes)), classes)


@pytest.mark.slow
def test_family_groups_best_iou_and_identification(families, tmp_path):
    from vcfusion.detection.detector_train import load_coco_many
    from vcfusion.detection.family_eval import evaluate_families

    ds = load_coco_many(families)
    perfect = TruthLookup(ds)
    results, _ = evaluate_families(perfect, ds, min_area=100.0, detector_name="truth")
    by = {r.family: r for r in results}
    assert list(by) == ["train", "jam", "cut_in", "all"]
    assert by["all"].n_images == 7 and by["jam"].n_images == 2
    for r in results:
        assert r.box_map.map_50 == pytest.approx(1.0) and r.box_map.map_50_95 == pytest.approx(1.0)
        np.testing.assert_allclose(r.best_iou, 1.0)
        # ground-truth boxes as the detector: the same identification as the oracle
        assert r.identification["truth"] == pytest.approx(r.identification["oracle"])
        assert r.n_identified_targets > 0
    # targets: ground-truth boxes of at least 100 px^2
    n_big = sum(int((((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])) >= 100).sum()) for b in ds.boxes)
    assert by["all"].n_targets == n_big
    # on these synthetic scenes the joint matcher with true boxes identifies most targets
    assert by["all"].identification["oracle"] >= 0.8
    # per visible fraction: the bins hold every identification target (the renders carry the
    # fraction of each box) and their accuracies average back to the family's
    for r in results:
        bins = r.identification_by_visibility["truth"]
        assert sum(n for n, _ in bins.values()) == r.n_identified_targets
        pooled = sum(n * acc for n, acc in bins.values() if n) / r.n_identified_targets
        assert pooled == pytest.approx(r.identification["truth"])
    # the intervals hold their accuracy; ground-truth boxes trail the oracle by exactly nothing
    for r in results:
        lo, hi = r.identification_interval["truth"]
        assert lo <= r.identification["truth"] <= hi
        assert r.identification_interval["gap_truth"] == (0.0, 0.0)
    # the jam hides cars behind cars: some of its targets are less than half visible
    assert sum(n for label, (n, _) in by["jam"].identification_by_visibility["oracle"].items() if label != ">=0.5") > 0
    # a detector that finds nothing: mAP 0, best IoU 0, identification 0
    class Blind:
        def detect(self, image):
            return Detections.empty()

    blind, _ = evaluate_families(Blind(), ds, min_area=100.0, detector_name="blind")
    for r in blind:
        assert r.box_map.map_50 == 0 and (r.best_iou == 0).all() and r.identification["blind"] == 0


@pytest.mark.slow
def test_eval_detector_cli_reports_families(families, tmp_path):
    import subprocess
    import sys

    report = tmp_path / "r.json"
    proc = subprocess.run([sys.executable, "-m", "vcfusion", "eval-detector", *map(str, families[1:]),
                           "--report", str(report)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "jam" in proc.stdout and "cut_in" in proc.stdout and "ident@0.7 oracle" in proc.stdout
    # strict JSON: an empty bin's NaN is null (NaN is no JSON; strict readers refuse the file)
    strict = json.loads(report.read_text(), parse_constant=lambda name: pytest.fail(f"{name} in the report"))
    rows = {r["family"]: r for r in strict["families"]}
    assert set(rows) == {"jam", "cut_in", "all"}
    assert 0 <= rows["jam"]["map_50"] <= 1 and "ident_0.7_oracle" in rows["jam"]
    assert "by the share of the target left visible" in proc.stdout
    assert rows["jam"]["ident_0.7_oracle_visible_>=0.5"]["targets"] > 0
    assert "95 % intervals over scenes" in proc.stdout
    lo, hi = rows["jam"]["ident_0.7_cnn_interval95"]
    assert lo <= rows["jam"]["ident_0.7_cnn"] <= hi and "ident_0.7_gap_cnn_interval95" in rows["jam"]
    bad = subprocess.run([sys.executable, "-m", "vcfusion", "eval-detector", str(families[0]), "--onnx",
                          str(tmp_path / "none.onnx"), "--layout", "ultralytics"], capture_output=True, text=True)
    assert bad.returncode == 2 and "none.onnx: ONNX model not found" in bad.stderr
    # an ONNX detector's identification columns carry its name (they were labelled "cnn")
    pytest.importorskip("onnx")
    export = subprocess.run([sys.executable, "-m", "vcfusion", "export-onnx", "--out", str(tmp_path / "d.onnx")],
                            capture_output=True, text=True)
    assert export.returncode == 0, export.stderr
    use = export.stdout.strip().splitlines()[-1].split("eval-detector DATA ")[1].split()
    onnx = subprocess.run([sys.executable, "-m", "vcfusion", "eval-detector", str(families[2]), *use,
                           "--report", str(tmp_path / "o.json")], capture_output=True, text=True)
    assert onnx.returncode == 0, onnx.stderr
    assert "ident_0.7_onnx" in json.loads((tmp_path / "o.json").read_text())["families"][0]
    assert "oracle - onnx" in onnx.stdout and "cnn" not in onnx.stdout


def test_identification_by_visible_fraction_against_hand_values():
    from vcfusion.detection.family_eval import _by_visibility

    right = np.array([True, False, True, True, False, True])
    visible = np.array([0.1, 0.2, 0.25, 0.49, 0.5, np.nan])  # a target without a fraction is left out
    bins = _by_visibility(right, visible)
    assert bins["<0.25"] == (2, 0.5) and bins["0.25-0.5"] == (2, 1.0)
    assert bins[">=0.5"] == (1, 0.0)


def test_scene_bootstrap_against_the_binomial_interval_and_pairing():
    """One target per image: resampling images is the ordinary bootstrap of a proportion, whose
    95 % interval is the normal one, p +- 1.96 sqrt(p (1 - p) / n), to within the resampling noise;
    the gap to the oracle is paired (same draws), so a detector right wherever the oracle is has
    an interval of exactly zero gap."""
    from vcfusion.detection.family_eval import scene_bootstrap

    n, p = 400, 0.9
    right = np.zeros(n, bool)
    right[: int(p * n)] = True
    iv = scene_bootstrap({"oracle": [np.array([True])] * n, "cnn": [np.array([r]) for r in right]})
    half = 1.96 * np.sqrt(p * (1 - p) / n)
    assert iv["cnn"][0] == pytest.approx(p - half, abs=0.006) and iv["cnn"][1] == pytest.approx(p + half, abs=0.006)
    assert iv["oracle"] == (1.0, 1.0)
    assert iv["gap_cnn"][0] == pytest.approx(1 - iv["cnn"][1]) and iv["gap_cnn"][1] == pytest.approx(1 - iv["cnn"][0])
    # seeded: the same figures again; another seed moves them only within the resampling noise
    assert scene_bootstrap({"cnn": [np.array([r]) for r in right]}) == {"cnn": iv["cnn"]}
    same = scene_bootstrap({"oracle": [np.array([r]) for r in right], "cnn": [np.array([r]) for r in right]}, seed=3)
    assert same["gap_cnn"] == (0.0, 0.0)
    # scenes, not targets, are the unit: ten targets per scene that fail together give a wider
    # interval than the same 4,000 targets drawn independently
    clustered = scene_bootstrap({"cnn": [np.full(10, r) for r in right]})["cnn"]
    independent = scene_bootstrap({"cnn": [np.array([r]) for r in np.repeat(right, 10)]})["cnn"]
    assert clustered[1] - clustered[0] > 2.5 * (independent[1] - independent[0])
    assert scene_bootstrap({}) == {} and scene_bootstrap({"cnn": []}) == {}
    assert scene_bootstrap({"cnn": [np.zeros(0, bool)] * 3}) == {}  # images without a target


def test_the_frames_of_one_seed_are_resampled_as_one_scene():
    # 4 SUMO seeds of 56 frames, 3 targets each, the CNN missing one target in every frame of one
    # seed: resampled by frame the interval was (0.90, 0.94); the seeds are the scenes, 4 of them
    from vcfusion.detection.family_eval import scene_bootstrap

    right = [np.array([True, True, s != 2]) for s in range(4) for _ in range(56)]
    scenes = [("acc_val", s) for s in range(4) for _ in range(56)]
    by_scene = scene_bootstrap({"cnn": right}, scenes)["cnn"]
    per_seed = [np.concatenate(right[56 * s:56 * (s + 1)]) for s in range(4)]
    assert by_scene == scene_bootstrap({"cnn": per_seed})["cnn"]  # a scene's frames pooled: the same draws
    assert by_scene[0] <= 0.76 and by_scene[1] == 1.0
    low, high = scene_bootstrap({"cnn": right})["cnn"]
    assert high - low < 0.05  # resampled as if 224 scenes


@pytest.mark.slow
@pytest.mark.parametrize("noise", [0.0, 0.5])
def test_identification_scores_the_boxes_the_fusion_stage_gets(families, noise):
    """With the depth step, eval-detector identifies with exactly the run-time fusion path (the
    detector at its operating threshold, then refinement and proposals), whatever that threshold:
    at 0.5 a selection of the evaluation-threshold boxes had dropped every depth proposal (0.3).
    With GNSS noise, the twins are moved by the draw the documentation names."""
    from vcfusion.detection.detector_net import PostParams, TorchDetector, default_weights_path
    from vcfusion.detection.detector_train import load_coco
    from vcfusion.detection.family_eval import _camera_frame, _twins, evaluate_families, read_rgb
    from vcfusion.fusion.box_refine import BoxRefineParams
    from vcfusion.fusion.depth_eval import DepthEvalParams
    from vcfusion.fusion.fuse import fuse_frame
    from vcfusion.fusion.matching import JointMatcher, JointMatcherParams
    from vcfusion.studies.identification import identification_rows

    ds = load_coco(families[1])  # the jam: hidden cars, which the depth step proposes
    detector = TorchDetector(default_weights_path())
    detector.params = PostParams(score_threshold=0.5)
    refine = BoxRefineParams()
    results, _ = evaluate_families(detector, ds, min_area=100.0, refine=refine, gnss_noise_m=noise)
    assert detector.params == PostParams(score_threshold=0.5)  # left as it was
    right = []
    for k in range(len(ds)):
        frame = _camera_frame(ds, k, read_rgb(ds.images[k]))
        twins = _twins(ds.records[k], frame.time, noise, np.random.default_rng([k, 1]))
        if noise:
            clean = _twins(ds.records[k], frame.time)
            moved = np.hypot(twins.x - clean.x, twins.y - clean.y)
            assert (moved > 0).all() and (moved < 6 * noise).all() and np.array_equal(twins.z, clean.z)
        fused = fuse_frame(frame, twins, detector, np.random.default_rng(k),
                           DepthEvalParams(), JointMatcher(JointMatcherParams(smoothing_alpha=None)), ("joint",),
                           refine=refine)
        right += [r["iou"] >= 0.7 - 1e-12 for r in identification_rows(frame, fused, 100.0)]
    assert results[0].n_identified_targets == len(right) > 0
    assert results[0].identification["cnn"] == pytest.approx(np.mean(right))


@pytest.mark.parametrize("damage", ["missing", "smaller"])
def test_a_frame_whose_depth_image_is_missing_or_misfits_is_refused(families, tmp_path, capsys, damage):
    # scoring boxes as detected (--no-refine) still identifies targets with the depth: a missing depth
    # image left its frame's targets out of the identification without a word (15 of 18 counted), and
    # a depth image of another size was used as if it fitted
    import shutil

    import cv2

    from vcfusion.commands import main

    folder = tmp_path / "cut_in"
    shutil.copytree(families[2], folder)
    depth = sorted((folder / "depth").iterdir())[1]
    if damage == "missing":
        depth.unlink()
    else:
        png = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(depth), png[::2, ::2])
    assert main(["eval-detector", str(folder), "--no-refine"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    if damage == "missing":
        assert "its depth image depth/" in err and "is missing or unreadable" in err
    else:
        assert str(depth) in err and "expected a single-channel image of the RGB image's size" in err


def test_a_lidar_scan_is_filled_and_snapped_or_left_as_detected_and_says_so(families, tmp_path):
    # a 64-beam scan with its gaps left open cannot snap a box: every box is kept as detected
    # (counted), none is proposed, and the identification is that of the raw boxes under the same
    # depth; with the gaps filled between returns (the default) boxes crossed by enough scan rows snap
    import subprocess
    import sys

    from vcfusion.detection.detector_net import TorchDetector, default_weights_path
    from vcfusion.detection.detector_train import load_coco_many
    from vcfusion.detection.family_eval import evaluate_families
    from vcfusion.fusion.box_refine import BoxRefineParams

    ds = load_coco_many([families[1]])
    det = TorchDetector(default_weights_path())
    sparse = BoxRefineParams(scan_fill_px=None)
    refined, _ = evaluate_families(det, ds, refine=sparse, depth_sensor="lidar")
    raw, _ = evaluate_families(det, ds, refine=None, depth_sensor="lidar")
    c = refined[0].depth_counts
    assert c["frames"] == len(ds) and c["frames_without_proposals"] == len(ds)
    assert c["boxes_refined"] == 0 and c["boxes_gated"] > 0
    assert refined[0].summary()["depth_step_boxes_gated"] == c["boxes_gated"]
    filled, _ = evaluate_families(det, ds, refine=BoxRefineParams(), depth_sensor="lidar")
    f = filled[0].depth_counts
    assert f["frames"] == len(ds) and f.get("frames_without_proposals", 0) == 0
    assert f["boxes_refined"] > 0 and f["boxes_refined"] + f["boxes_gated"] <= c["boxes_gated"]
    bad = subprocess.run([sys.executable, "-m", "vcfusion", "eval-detector", str(families[1]), "--pose-noise-deg",
                          "-1"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--pose-noise-deg: expected a standard deviation" in bad.stderr


def test_each_target_is_told_what_became_of_it():
    from vcfusion.detection.family_eval import failure_kinds, format_failure_table, FamilyResult

    gt = np.array([[0, 0, 10, 10], [20, 0, 30, 10], [40, 0, 50, 10], [60, 0, 70, 10], [80, 0, 90, 10]], float)
    detected = np.array([[0, 0, 10, 10], [20, 0, 26, 10], [40, 0, 50, 10], [80, 0, 85, 10]], float)
    # the depth step kept boxes 0-2 as detected, snapped the last one off and proposed nothing for gt 3
    boxes = np.array([[0, 0, 10, 10], [20, 0, 26, 10], [40, 0, 50, 10], [80, 0, 84, 10]], float)
    matched = np.array([1.0, 0.6, 0.0, 0.0, 0.4])  # gt 2's right box was there, the matcher took another
    kinds = failure_kinds(matched, gt, boxes, detected)
    assert kinds == ["right", "detector_box_off", "matcher", "missed", "depth_box_off"]
    r = FamilyResult("f", 1, 5, None, np.zeros(5), failures={"cnn": {k: kinds.count(k) for k in
                                                                      ("right", "missed", "detector_box_off",
                                                                       "depth_box_off", "matcher")}})
    table = format_failure_table([r])
    assert table.splitlines()[1].split() == ["f", "1", "1", "1", "1", "1"]
