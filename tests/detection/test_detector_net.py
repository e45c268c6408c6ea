"""The learned detector's training loop, weights files and ONNX round trip, on a synthetic COCO set
(coloured rectangles): a unit test of the training code, not of the shipped model."""

import json

import numpy as np
import pytest
import torch

from support.synthetic_coco import make_synthetic_coco
from vcfusion.detection.detector_net import (DetectorFileError, DetectorModel, OnnxDetector, PostParams,
                                          TorchDetector, decode_dense, export_onnx, inference_copy)
from vcfusion.detection.detector_train import (checkpoint_path, evaluate_detector, load_coco, read_rgb,
                                               train_detector)
from vcfusion.fusion.matching import box_iou


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("det")
    data = make_synthetic_coco(root / "data", n_images=32, size=(96, 64), seed=0)
    net, report = train_detector(data, root / "w.pt", epochs=100, max_iterations=60, batch_size=8,
                                 input_wh=(96, 64), widths=(8, 16, 16, 32, 16), val_fraction=0.0, lr=1e-2,
                                 threads=2, progress=False, seed=0, checkpoint_every=25)
    return root, data, net, report


def test_training_decreases_the_loss_and_finds_the_objects(trained):
    root, data, net, report = trained
    assert report.iterations == 60
    assert report.loss_history[-1] < 0.25 * np.mean(report.first_losses[:3])
    ds = load_coco(data)
    result = evaluate_detector(TorchDetector(net), ds)
    assert result.map_50 > 0.8
    # one image: every ground-truth box found with IoU > 0.5 and the right class
    det = TorchDetector(net).detect(read_rgb(ds.images[0]))
    iou = box_iou(ds.boxes[0], det.boxes)
    best = iou.argmax(axis=1)
    assert (iou.max(axis=1) > 0.5).all()
    np.testing.assert_array_equal(det.classes[best], ds.classes[0])


def test_weights_file_round_trip_and_size(trained):
    root, data, net, _ = trained
    loaded = DetectorModel.load(root / "w.pt")
    assert loaded.class_ids == [1, 2] and loaded.class_names == ["car", "truck"]
    assert loaded.meta["iterations"] == 60
    # shipped weights name their data folders, not this machine's paths
    assert loaded.meta["train_data"] == [data.name]
    image = read_rgb(load_coco(data).images[3])
    np.testing.assert_array_equal(TorchDetector(loaded).dense(image), TorchDetector(net).dense(image))
    assert (root / "w.pt").stat().st_size < 10 * 2**20
    assert not list(root.glob("*.tmp"))


def test_inference_copy_folds_batch_norm_and_leaves_the_model_alone(trained):
    import torch

    root, data, net, _ = trained
    before = {k: v.clone() for k, v in net.model.state_dict().items()}
    folded = inference_copy(net.model)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    assert sum(isinstance(m, torch.nn.BatchNorm2d) for m in net.model.modules()) > 0
    x = torch.from_numpy(np.stack([read_rgb(p).transpose(2, 0, 1) for p in load_coco(data).images[:4]])
                         .astype(np.float32))
    with torch.inference_mode():
        ref = decode_dense(*net.model.eval()(x))
        got = decode_dense(*folded(x.contiguous(memory_format=torch.channels_last)))
    np.testing.assert_allclose(got.numpy(), ref.numpy(), rtol=1e-4, atol=1e-4)
    # the trained model keeps its own layers and weights (training can go on with it)
    for k, v in net.model.state_dict().items():
        assert torch.equal(v, before[k]), k


def test_the_forward_pass_gets_back_its_threads_after_sumo_took_them(trained):
    # SUMO's steps set the main thread's OpenMP thread count to 1 (through torch's runtime when
    # torch was loaded first); the detector restores the count it was built with before each pass
    import torch

    root, data, net, _ = trained
    before = torch.get_num_threads()
    try:
        det = TorchDetector(net, threads=2)
        torch.set_num_threads(1)  # what a SUMO step does
        det.dense(read_rgb(load_coco(data).images[0]))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_checkpoints_are_written_along_the_way(trained):
    root, data, net, _ = trained
    assert checkpoint_path(root / "w.pt", 25) == root / "w.it0025.pt"
    # every 25 of 60 iterations; the last iteration is the --out file itself
    assert sorted(p.name for p in root.glob("w.it*.pt")) == ["w.it0025.pt", "w.it0050.pt"]
    image = read_rgb(load_coco(data).images[3])
    final = TorchDetector(net).dense(image)
    for step in (25, 50):
        saved = DetectorModel.load(checkpoint_path(root / "w.pt", step))
        assert saved.meta["iterations"] == step
        assert not np.allclose(TorchDetector(saved).dense(image), final)  # an earlier state, not a copy
    with pytest.raises(ValueError, match="checkpoint_every"):
        train_detector(data, None, checkpoint_every=10, epochs=1, input_wh=(96, 64), progress=False)


def test_fine_tuning_starts_from_the_given_weights(trained):
    root, data, net, report = trained
    common = dict(epochs=1, max_iterations=3, batch_size=8, input_wh=(96, 64), widths=(8, 16, 16, 32, 16),
                  val_fraction=0.0, lr=1e-4, threads=2, progress=False, seed=1)
    _, tuned = train_detector(data, root / "tuned.pt", init=root / "w.pt", **common)
    _, fresh = train_detector(data, None, **common)
    # the first iterations already have the trained model's low loss; from scratch they do not
    assert np.mean(tuned.first_losses) < 0.5 * np.mean(fresh.first_losses)
    assert DetectorModel.load(root / "tuned.pt").meta["init"] == "w.pt"
    with pytest.raises(DetectorFileError, match="input_wh"):
        train_detector(data, None, init=root / "w.pt", **{**common, "input_wh": (128, 64)})


def test_onnx_through_opencv_equals_torch(trained):
    pytest.importorskip("onnx")
    root, data, net, _ = trained
    path = export_onnx(net, root / "det.onnx")
    onnx_det = OnnxDetector(path, net.input_wh, net.class_ids)
    torch_det = TorchDetector(net)
    for image_path in load_coco(data).images[:4]:
        image = read_rgb(image_path)
        ref = torch_det.dense(image)
        got, _ = onnx_det.dense(image)
        got = got[0]
        assert got.shape == ref.shape == ((64 // 4) * (96 // 4), 4 + 2)
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4)
        a, b = torch_det.detect(image), onnx_det.detect(image)
        assert len(a) > 0
        np.testing.assert_allclose(a.boxes, b.boxes, atol=1e-2)
        np.testing.assert_array_equal(a.classes, b.classes)


class FixedOutputNet:
    """Stands in for cv2.dnn.Net to feed the loader other exporters' output layouts."""

    def __init__(self, output):
        self.output = output

    def setInput(self, blob):  # noqa: N802 - OpenCV's name
        assert blob.shape[:2] == (1, 3)

    def forward(self):
        return self.output


def test_onnx_loader_accepts_transposed_and_objectness_layouts(trained):
    pytest.importorskip("onnx")
    root, data, net, _ = trained
    path = root / "det.onnx"
    if not path.exists():
        export_onnx(net, path)
    det = OnnxDetector(path, net.input_wh, net.class_ids, PostParams(score_threshold=0.2))
    image = read_rgb(load_coco(data).images[0])
    dense, _ = det.dense(image)
    dense = dense[0]
    ref = det.detect(image)
    # a YOLOv8-style (1, 4 + C, N) output gives the same detections
    det.net = FixedOutputNet(dense.T[None].copy())
    got = det.detect(image)
    np.testing.assert_allclose(got.boxes, ref.boxes)
    # YOLOv5-style (1, N, 5 + C): objectness times class score
    with_obj = np.concatenate([dense[:, :4], np.full((len(dense), 1), 0.5, np.float32), dense[:, 4:]], axis=1)
    det_obj = OnnxDetector(path, net.input_wh, net.class_ids, PostParams(score_threshold=0.1), objectness=True)
    det_obj.net = FixedOutputNet(with_obj[None])
    got_obj = det_obj.detect(image)
    np.testing.assert_allclose(np.sort(got_obj.scores), np.sort(ref.scores * 0.5)[-len(got_obj):], rtol=1e-5)
    # a wrong number of classes is refused with the layout in the message
    bad = OnnxDetector(path, net.input_wh, [1, 2, 3])
    with pytest.raises(DetectorFileError, match="class values per candidate"):
        bad.detect(image)


def test_bad_files_get_one_clear_error(tmp_path):
    (tmp_path / "x.pt").write_bytes(b"not a model")
    with pytest.raises(DetectorFileError, match="x.pt"):
        DetectorModel.load(tmp_path / "x.pt")
    with pytest.raises(DetectorFileError, match="ONNX model not found"):
        OnnxDetector(tmp_path / "none.onnx", (96, 64), [1])
    data = tmp_path / "d"
    data.mkdir()
    (data / "annotations.json").write_text(json.dumps({"images": [{"id": 1, "file_name": "a.png"}],
                                                       "annotations": [], "categories": [{"id": 1}]}))
    with pytest.raises(DetectorFileError, match=r"images\[0\].file_name: image not found"):
        load_coco(data)
    (data / "annotations.json").write_text(json.dumps({"images": [], "annotations": [{"bbox": [1, 2]}],
                                                       "categories": [{"id": 1}]}))
    with pytest.raises(DetectorFileError, match=r"annotations\[0\]"):
        load_coco(data)
    (data / "annotations.json").write_text(json.dumps({"images": [], "categories": [{"id": 1}], "annotations": [
        {"image_id": 1, "bbox": [1, 2, 30, 20], "category_id": 1, "iscrowd": 1}]}))
    with pytest.raises(DetectorFileError, match=r"annotations\[0\]: iscrowd: crowd regions are not supported"):
        load_coco(data)


def test_ultralytics_layout_through_opencv_equals_the_torch_model(trained, tmp_path):
    """Our network behind an Ultralytics-layout head (1, 84, N), exported to ONNX and read by
    OnnxDetector.ultralytics through OpenCV DNN, gives the boxes the torch model gives on the
    same letterboxed frames (decoded here independently of the package's decoder)."""
    pytest.importorskip("onnx")
    import torch

    from support.ultralytics_head import COCO_CAR, COCO_TRUCK, UltralyticsHead, export_ultralytics_layout
    from vcfusion.detection.detector_net import letterbox
    from vcfusion.detection.detectors import nms

    root, data, net, _ = trained
    input_wh = (128, 128)  # 96x64 frames: scale 4/3, 21 rows of padding above, 22 below
    path = tmp_path / "yolo.onnx"
    export_ultralytics_layout(net.model, input_wh, path)
    params = PostParams(score_threshold=0.3, nms_iou=0.7)
    det = OnnxDetector.ultralytics(path, input_wh, keep=("car", "truck"), params=params)
    head = UltralyticsHead(net.model).eval()
    n_boxes = 0
    for image_path in load_coco(data).images[:4]:
        image = read_rgb(image_path)
        canvas, box = letterbox(image, input_wh)
        assert (box.pad_x, box.pad_y) == (0, 21)
        with torch.inference_mode():
            ref = head(torch.from_numpy(canvas.transpose(2, 0, 1)[None].astype(np.float32) / 255.0))[0].numpy().T
        raw, _ = det.dense(image)
        assert raw.shape == (1, 84, (128 // 4) ** 2)
        np.testing.assert_allclose(raw[0].T, ref, rtol=1e-4, atol=1e-4)
        # the torch model's boxes: best class car or truck, score threshold, NMS per class,
        # then back through the letterbox into the frame (pixel-centre convention: - 0.5)
        cls = ref[:, 4:].argmax(axis=1)
        score = ref[np.arange(len(ref)), 4 + cls]
        sel = np.flatnonzero(np.isin(cls, [COCO_CAR, COCO_TRUCK]) & (score >= 0.3))
        cx = (ref[sel, 0] - box.pad_x) / box.sx
        cy = (ref[sel, 1] - box.pad_y) / box.sy
        w, h = ref[sel, 2] / box.sx, ref[sel, 3] / box.sy
        boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1) - 0.5
        boxes[:, [0, 2]] = boxes[:, [0, 2]].clip(-0.5, image.shape[1] - 0.5)
        boxes[:, [1, 3]] = boxes[:, [1, 3]].clip(-0.5, image.shape[0] - 0.5)
        expected = []
        for c, ours in ((COCO_CAR, 1), (COCO_TRUCK, 2)):
            k = np.flatnonzero(cls[sel] == c)
            expected += [(ours, *boxes[k[i]]) for i in nms(boxes[k], score[sel][k], 0.7)]
        got = det.detect(image)
        assert len(got) == len(expected)
        n_boxes += len(got)
        order = np.lexsort((got.boxes[:, 1], got.boxes[:, 0], got.classes))
        exp = np.array(sorted(expected, key=lambda r: (r[0], r[1], r[2]))).reshape(-1, 5)
        np.testing.assert_array_equal(got.classes[order], exp[:, 0])
        np.testing.assert_allclose(got.boxes[order], exp[:, 1:], atol=1e-2)
    assert n_boxes >= 4  # the trained model finds the rectangles in the letterboxed frames too


def test_shipped_weights_name_no_machine_paths():
    from vcfusion.detection.detector_net import default_weights_path
    shipped = DetectorModel.load(default_weights_path())
    assert default_weights_path().stat().st_size < 10 * 2**20
    assert shipped.meta["train_data"], "the shipped weights say what they were trained on"
    for name in shipped.meta["train_data"]:
        assert "/" not in name and "\\" not in name, name


def test_worker_processes_build_the_same_batches_as_the_main_thread(trained):
    import torch

    root, data, _, _ = trained
    common = dict(epochs=2, max_iterations=6, batch_size=8, input_wh=(96, 64), widths=(8, 16, 16, 32, 16),
                  val_fraction=0.0, lr=1e-2, threads=1, progress=False, seed=3)
    alone, report = train_detector(data, None, **common)
    helped, report_helped = train_detector(data, None, workers=2, **common)
    assert report.iterations == report_helped.iterations == 6 and report.epochs == 2  # 32 images, 4 per epoch
    assert report.first_losses == report_helped.first_losses
    for (name, a), b in zip(alone.model.state_dict().items(), helped.model.state_dict().values()):
        assert torch.equal(a, b), name


def test_a_resized_folder_feeds_training_the_same_boxes_and_nearly_the_same_pixels(tmp_path):
    from vcfusion.detection.detector_train import _cache, resize_dataset

    data = make_synthetic_coco(tmp_path / "data", n_images=6, size=(192, 128), seed=4)
    assert resize_dataset(data, tmp_path / "small", (96, 64), quality=95, progress=False) == 6
    full, small = load_coco(data), load_coco(tmp_path / "small")
    assert [im.name for im in small.images] == [f"{i:07d}.webp" for i in full.image_ids]
    images_full, boxes_full = _cache(full, (96, 64), "", False)
    images_small, boxes_small = _cache(small, (96, 64), "", False)
    for a, b in zip(boxes_full, boxes_small):  # the boxes the network is trained on
        np.testing.assert_allclose(b, a, atol=1e-9)
    diff = np.abs(images_full.astype(int) - images_small.astype(int))
    assert diff.mean() < 4 and np.percentile(diff, 99) < 30  # lossy WebP at 95 on noisy rectangles (renders: 1.2)
    assert small.records[0]["width"] == 96 and not list(tmp_path.glob("small.tmp-writing*"))


def test_the_validation_split_takes_whole_scenes_and_never_an_image_trained_on():
    """`vcfusion render` writes several frames per seed: split by image, consecutive frames of one
    seed were in training and validation both; a folder listed twice (as the shipped weights'
    recipe lists the accident frames) put the same images in both."""
    from pathlib import Path

    from vcfusion.detection.detector_train import CocoDataset, split_by_scene

    def folder(name, seeds, frames):
        images = [Path(f"/data/{name}/frame_{s}_{f}.png") for s in seeds for f in range(frames)]
        records = [{"seed": s} for s in seeds for f in range(frames)]
        return images, records

    a, b = folder("acc", range(6), 5), folder("plat", range(4), 3)
    images = a[0] + b[0] + a[0]  # acc listed twice
    records = a[1] + b[1] + a[1]
    n = len(images)
    ds = CocoDataset(Path("/data"), images, list(range(n)), [np.zeros((0, 4))] * n, [np.zeros(0, np.int64)] * n,
                     [1, 2], ["car", "truck"], records)
    for seed in range(5):
        train, val = split_by_scene(ds, 0.2, np.random.default_rng(seed))
        assert len(train) + len(val) == n and len(val) >= round(0.2 * n)
        assert not set(train.scenes()) & set(val.scenes())
        assert not {str(p) for p in train.images} & {str(p) for p in val.images}
    one = ds.subset(range(5))  # five frames of one seed: nothing to split
    with pytest.raises(DetectorFileError, match="holds one scene"):
        split_by_scene(one, 0.2, np.random.default_rng(0))
    # images without a seed (a COCO folder from elsewhere) are each a scene of their own
    loose = CocoDataset(Path("/x"), [Path(f"/x/{k}.png") for k in range(10)], list(range(10)),
                        [np.zeros((0, 4))] * 10, [np.zeros(0, np.int64)] * 10, [1], ["car"])
    train, val = split_by_scene(loose, 0.3, np.random.default_rng(0))
    assert (len(train), len(val)) == (7, 3)


def test_ids_written_as_floats_or_text_read_as_the_integers_they_are(tmp_path):
    """The id check accepts 5.0 and "5.0" as image 5; the rest of the loader and resize-dataset then
    read the raw ids again with int(), which refused "5.0" in a traceback."""
    from vcfusion.detection.detector_train import resize_dataset

    folder = make_synthetic_coco(tmp_path / "c", n_images=3, size=(64, 48))
    coco = json.loads((folder / "annotations.json").read_text())
    boxes_before = [len(b) for b in load_coco(folder).boxes]
    for image in coco["images"]:
        image["id"] = f"{image['id']}.0"
    for ann in coco["annotations"]:
        ann["image_id"] = float(ann["image_id"])
    (folder / "annotations.json").write_text(json.dumps(coco))
    ds = load_coco(folder)
    assert ds.image_ids == [1, 2, 3] and [len(b) for b in ds.boxes] == boxes_before
    resize_dataset(folder, tmp_path / "small", (32, 32), 90, progress=False)
    assert [len(b) for b in load_coco(tmp_path / "small").boxes] == boxes_before


def test_a_folder_and_its_resized_copy_train_on_the_same_boxes(tmp_path):
    """--min-train-area was in the folder's pixels: a 192x128 folder kept boxes 4x smaller than its
    96x64 copy made for the same network input."""
    from vcfusion.detection.detector_train import resize_dataset

    data = make_synthetic_coco(tmp_path / "data", n_images=8, size=(192, 128), seed=5)
    resize_dataset(data, tmp_path / "small", (96, 64), progress=False)
    areas = np.concatenate([(b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) / 4 for b in load_coco(data).boxes])
    threshold = float(np.median(areas))  # at the input: half the boxes go
    common = dict(epochs=1, max_iterations=1, batch_size=4, input_wh=(96, 64), widths=(8, 16, 16, 32, 16),
                  val_fraction=0.0, threads=1, progress=False, min_train_area=threshold)
    kept = [train_detector(folder, None, **common)[0].meta["n_train_boxes"] for folder in (data, tmp_path / "small")]
    assert kept[0] == kept[1] == int(np.sum(areas >= threshold - 1e-6)) and 0 < kept[0] < len(areas)


def test_decoding_builds_its_grid_on_the_networks_device():
    """The output of the network on another device (CUDA in use; `meta` here, which any CPU tensor
    added to it fails like a CUDA one does) decodes there: the grid follows the heatmap's device."""
    h, w, c = 6, 8, 2
    hm, size, offset = (torch.zeros(1, k, h, w, device="meta") for k in (c, 2, 2))
    dense = decode_dense(hm, size, offset)
    assert dense.device.type == "meta" and tuple(dense.shape) == (1, h * w, 4 + c)
