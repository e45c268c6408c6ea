"""The ONNX-YOLO path (Ultralytics export layout): letterbox, decoding of a hand-made output,
class filtering and NMS. The network round trip (torch vs OpenCV DNN) is in test_detector_net.py."""

import numpy as np
import pytest

from vcfusion.detection.detector_net import (COCO80_NAMES, DetectorFileError, Letterbox, PostParams,
                                          coco_column_categories, decode_yolo_output, letterbox)
from vcfusion.render.coco import category_id


def test_letterbox_places_the_image_as_ultralytics_does():
    image = np.zeros((720, 1280, 3), np.uint8)
    image[100:110, 200:220] = 255  # a white block
    canvas, box = letterbox(image, (640, 640))
    assert canvas.shape == (640, 640, 3)
    # scale 0.5, 640 x 360 centred: 140 rows of grey 114 above and below
    assert (box.sx, box.sy, box.pad_x, box.pad_y) == (0.5, 0.5, 0, 140)
    assert (canvas[:140] == 114).all() and (canvas[500:] == 114).all()
    assert (canvas[140 + 50:140 + 55, 100:110] == 255).all()
    assert canvas[140 + 45, 100].max() == 0 and canvas[140 + 60, 100].max() == 0
    # an odd padding: Ultralytics rounds the first side's share down (round(dh - 0.1))
    _, odd = letterbox(np.zeros((61, 100, 3), np.uint8), (100, 64))
    assert (odd.pad_x, odd.pad_y) == (0, 1)


def test_hand_made_ultralytics_output_decodes_to_the_expected_boxes():
    # a 1280x720 frame letterboxed into 640x640: scale 0.5, 140 px of padding above
    _, box = letterbox(np.zeros((720, 1280, 3), np.uint8), (640, 640))
    rows = []  # cx, cy, w, h (input px), then 80 class scores

    def cand(cx, cy, w, h, **scores):
        s = np.zeros(80, np.float32)
        for name, v in scores.items():
            s[COCO80_NAMES.index(name.replace("_", " "))] = v
        rows.append(np.concatenate([[cx, cy, w, h], s]))

    cand(320, 230, 100, 50, car=0.9)  # image: centre (640, 180), 200 x 100
    cand(322, 231, 100, 50, car=0.85)  # the same car again (IoU > 0.7): NMS drops it
    cand(100, 300, 40, 60, truck=0.8, car=0.3)  # a truck: image centre (200, 320), 80 x 120
    cand(500, 250, 30, 30, person=0.95)  # not a vehicle class: dropped
    cand(400, 400, 60, 40, train=0.7, truck=0.6)  # best class 'train' (not kept): dropped, as Ultralytics does
    cand(200, 200, 20, 20, bus=0.2)  # below the score threshold
    cand(560, 300, 50, 40, bus=0.6)  # a bus: image centre (1120, 320), 100 x 80
    out = np.stack(rows).T[None].astype(np.float32)  # (1, 84, N): the Ultralytics orientation
    assert out.shape == (1, 84, 7)
    columns = coco_column_categories()
    det = decode_yolo_output(out, columns, (720, 1280), (640, 640), PostParams(score_threshold=0.3, nms_iou=0.7),
                             box=box)
    # edges in pixel-edge coordinates, minus half a pixel for the project's pixel-centre convention
    expected = {
        category_id("passenger"): [540 - 0.5, 130 - 0.5, 740 - 0.5, 230 - 0.5],
        category_id("truck"): [160 - 0.5, 260 - 0.5, 240 - 0.5, 380 - 0.5],
        category_id("bus"): [1070 - 0.5, 280 - 0.5, 1170 - 0.5, 360 - 0.5],
    }
    assert sorted(det.classes.tolist()) == sorted(expected)
    for cls, ref in expected.items():
        np.testing.assert_allclose(det.boxes[det.classes == cls][0], ref, atol=1e-3)
    np.testing.assert_allclose(np.sort(det.scores), [0.6, 0.8, 0.9], atol=1e-6)
    # the (1, N, 84) orientation gives the same
    again = decode_yolo_output(out.transpose(0, 2, 1), columns, (720, 1280), (640, 640),
                               PostParams(score_threshold=0.3), box=box)
    np.testing.assert_allclose(again.boxes, det.boxes)


def test_class_selection_is_configurable_and_checked():
    only_trucks = coco_column_categories(("truck",))
    assert only_trucks[COCO80_NAMES.index("truck")] == category_id("truck")
    assert sum(c >= 0 for c in only_trucks) == 1
    assert coco_column_categories()[COCO80_NAMES.index("car")] == category_id("passenger")
    with pytest.raises(ValueError, match="COCO class names"):
        coco_column_categories(("lorry",))
    with pytest.raises(ValueError, match="no vcfusion category"):
        coco_column_categories(("person",))
    # the shape as the model gave it, batch axis included (it read "got shape (85, 10)")
    with pytest.raises(DetectorFileError, match=r"\(1, 84, N\).*got shape \(1, 85, 10\)$"):
        decode_yolo_output(np.zeros((1, 85, 10), np.float32), coco_column_categories(), (480, 640), (640, 640))


def test_scenario_onnx_yolo_builds_the_ultralytics_detector(tmp_path):
    pytest.importorskip("onnx")
    from scenario_files import write_scenario
    from support.ultralytics_head import export_ultralytics_layout
    from vcfusion.detection.detector_net import CenterNetLite, OnnxDetector
    from vcfusion.fusion.stage import build_detector
    from vcfusion.scenario import ScenarioError, load_scenario

    export_ultralytics_layout(CenterNetLite(2, (8, 16, 16, 32), 16), (320, 320), tmp_path / "model.onnx")
    base = ("name: t\nnetwork: NET_DIR/highway.net.xml\nvehicle_types: NET_DIR/vtypes.add.xml\n"
            "ego: {lane: 2, depart_pos_m: 50, speed_mps: 19}\nvision: {enabled: true}\n")
    path = write_scenario(tmp_path, base + "fusion: {enabled: true, detector: onnx-yolo, weights: model.onnx, "
                                           "yolo_input_px: [320, 320], yolo_classes: [car, truck]}\n")
    det = build_detector(load_scenario(path), 0)
    assert isinstance(det, OnnxDetector) and det.letterbox and det.input_wh == (320, 320)
    assert det.scale == pytest.approx(1 / 255)
    assert sorted(c for c in det.class_ids if c >= 0) == [category_id("passenger"), category_id("truck")]
    frame = np.full((240, 320, 3), 90, np.uint8)
    assert len(det.detect(frame).boxes.shape) == 2  # runs end to end through OpenCV DNN
    # a wrong input size is named
    det_bad = OnnxDetector.ultralytics(tmp_path / "model.onnx", (640, 480))
    with pytest.raises(DetectorFileError, match="input size"):
        det_bad.detect(frame)
    bad = write_scenario(tmp_path, base + "fusion: {enabled: true, detector: onnx-yolo}\n", "b.yaml")
    with pytest.raises(ScenarioError, match="fusion.*weights: expected the ONNX file"):
        load_scenario(bad)
    # settings the chosen detector never reads are refused, not ignored
    bad = write_scenario(tmp_path, base + "fusion: {enabled: true, detector: cnn, yolo_input_px: [320, 320]}\n",
                         "f.yaml")
    with pytest.raises(ScenarioError, match=r"f.yaml: fusion.*yolo_input_px: read only with detector: onnx-yolo"):
        load_scenario(bad)
    # the defaults written out (as a run's manifest holds them) are no such setting
    full = load_scenario(write_scenario(tmp_path, base + "fusion: {enabled: true}\n", "h.yaml"))
    from vcfusion.scenario import Scenario
    assert Scenario.model_validate(full.model_dump(mode="json")).fusion.yolo_input_px == (640, 640)
    bad = write_scenario(tmp_path, base + "fusion: {enabled: true, detector: oracle, weights: model.onnx}\n",
                         "g.yaml")
    with pytest.raises(ScenarioError, match=r"g.yaml: fusion.*weights: the oracle detector reads no weights file"):
        load_scenario(bad)
    bad = write_scenario(tmp_path, base + "fusion: {enabled: true, detector: onnx-yolo, weights: model.onnx, "
                                          "yolo_classes: [lorry]}\n", "c.yaml")
    with pytest.raises(ScenarioError, match="lorry"):
        load_scenario(bad)
    # the file is checked when the scenario loads, as the CNN's weights are (a batch started every seed
    # and failed each with a traceback): another input size, and a file that is no ONNX model
    bad = write_scenario(tmp_path, base + "fusion: {enabled: true, detector: onnx-yolo, weights: model.onnx}\n",
                         "d.yaml")
    with pytest.raises(ScenarioError, match=r"d.yaml: fusion.weights: .*model.onnx: OpenCV DNN failed on a "
                                            r"\(1, 3, 640, 640\) input \(is that the model's input size\?\)"):
        load_scenario(bad)
    (tmp_path / "junk.onnx").write_text("not a model")
    bad = write_scenario(tmp_path, base + "fusion: {enabled: true, detector: onnx-yolo, weights: junk.onnx, "
                                          "yolo_input_px: [320, 320]}\n", "e.yaml")
    with pytest.raises(ScenarioError, match=r"e.yaml: fusion.weights: .*junk.onnx: OpenCV DNN cannot read"):
        load_scenario(bad)


def test_every_object_of_a_raw_yolo_output_survives_its_many_duplicates():
    """30 cars, each seen by 40 candidates (neighbouring cells, three strides), as a raw Ultralytics
    head gives them: all 30 reach NMS (a cap of 4 x max_detections = 400 candidates kept 11 cars'
    duplicates only and lost 19 cars)."""
    rng = np.random.default_rng(0)
    out = np.zeros((1, 84, 8400), np.float32)
    centres = np.array([(40 + (k % 6) * 110, 60 + (k // 6) * 120) for k in range(30)], float)
    for k, (cx, cy) in enumerate(centres):
        for j in range(40):
            col = 40 * k + j
            out[0, :4, col] = np.array([cx, cy, 60.0, 40.0]) + rng.normal(0, 2, 4)
            out[0, 4 + 2, col] = (0.9 - 0.4 * k / 30) * (1 - 0.3 * j / 40)  # COCO 'car'
    params = PostParams(score_threshold=0.01, nms_iou=0.7, max_detections=100)
    det = decode_yolo_output(out, coco_column_categories(), (640, 640), (640, 640), params,
                             box=Letterbox(1.0, 1.0, 0, 0))
    found = {int(np.argmin(np.hypot(*(centres - ((b[:2] + b[2:]) / 2 + 0.5)).T))) for b in det.boxes}
    assert found == set(range(30))
