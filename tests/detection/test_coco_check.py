"""`vcfusion coco-check` with our own tiny grid-layout ONNX model (the FastestDet layout), so the
code path is tested without the photograph-trained detector used to measure the renders."""

import json

import cv2
import numpy as np
import pytest

from vcfusion.detection.coco_check import CheckInputError, GridOnnxDetector, check_folder, decode_grid

GRID, SIZE, CLASSES = 4, 64, 8


def _logit(p):
    return float(np.log(p / (1 - p)))


def _grid_with_one_box(cell, cls, obj, prob, wh):
    """(5 + C, G, G) output: one cell with a box of relative size wh centred on the cell's centre."""
    g = np.zeros((5 + CLASSES, GRID, GRID), np.float32)
    g[5:] = 1.0 / CLASSES
    r, c = cell
    g[0, r, c] = obj
    g[3, r, c], g[4, r, c] = _logit(wh[0]), _logit(wh[1])
    g[5:, r, c] = (1 - prob) / (CLASSES - 1)
    g[5 + cls, r, c] = prob
    return g


def test_decode_grid_by_hand():
    g = _grid_with_one_box((1, 2), cls=2, obj=0.81, prob=0.9, wh=(0.25, 0.5))
    g[1, 1, 2] = np.arctanh(0.5)  # centre half a cell right of the cell's corner
    det = decode_grid(g, (200, 400), min_score=0.3, nms_iou=0.45)
    assert len(det) == 1 and det.classes[0] == 2
    assert det.scores[0] == pytest.approx(0.81 ** 0.6 * 0.9 ** 0.4, rel=1e-6)
    cx, cy = (2 + 0.5) / GRID * 400, (1 + 0.0) / GRID * 200
    np.testing.assert_allclose(det.boxes[0], [cx - 50 - 0.5, cy - 50 - 0.5, cx + 50 - 0.5, cy + 50 - 0.5], atol=1e-4)


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """A constant-output ONNX model: whatever the image, a 'car' (class 2) in cell (1, 1), score 0.9."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    out = torch.from_numpy(_grid_with_one_box((1, 1), cls=2, obj=0.9, prob=0.9, wh=(0.25, 0.25)))

    class Constant(torch.nn.Module):
        def forward(self, x):
            return out[None] + 0.0 * x.mean()

    path = tmp_path_factory.mktemp("onnx") / "grid.onnx"
    torch.onnx.export(Constant(), torch.zeros(1, 3, SIZE, SIZE), str(path), input_names=["images"],
                      output_names=["grid"], opset_version=17, dynamo=False)
    return path


def _folder(tmp_path, anns):
    (tmp_path / "rgb").mkdir(parents=True)
    cv2.imwrite(str(tmp_path / "rgb" / "a.png"), np.full((160, 160, 3), 90, np.uint8))
    coco = {"images": [{"id": 1, "file_name": "rgb/a.png", "width": 160, "height": 160}],
            "annotations": [dict(id=k + 1, image_id=1, category_id=1, **a) for k, a in enumerate(anns)],
            "categories": [{"id": 1, "name": "passenger"}]}
    (tmp_path / "annotations.json").write_text(json.dumps(coco))
    return tmp_path


def test_check_counts_found_missed_and_skipped_vehicles(model, tmp_path):
    # The model's box: centre at the corner of cell (1, 1) (offset tanh(0) = 0), (1 / 4) * 160 = 40 px,
    # 40 px wide: COCO x, y = 20.
    folder = _folder(tmp_path, [
        {"bbox": [20.0, 20.0, 40.0, 40.0], "visible_fraction": 1.0, "truncation": 0.0},  # found
        {"bbox": [100.0, 100.0, 50.0, 50.0], "visible_fraction": 1.0, "truncation": 0.0},  # missed
        {"bbox": [20.0, 20.0, 30.0, 30.0], "visible_fraction": 1.0, "truncation": 0.0},  # too narrow: skipped
        {"bbox": [20.0, 20.0, 40.0, 40.0], "visible_fraction": 0.5, "truncation": 0.0},  # occluded: skipped
        {"bbox": [20.0, 20.0, 40.0, 40.0], "visible_fraction": 1.0, "truncation": 0.2},  # truncated: skipped
    ])
    names = [f"class{k}" for k in range(CLASSES)]
    result = check_folder(GridOnnxDetector(model), folder, min_width_px=40, iou=0.5, score=0.3, class_names=names)
    assert (result.vehicles, result.found) == (2, 1)
    assert result.best_scores[0] == pytest.approx(0.9, abs=1e-5) and result.best_scores[1] == 0.0
    assert result.labels == {"class2": 1, "(nothing)": 1}
    # A stricter score threshold than the model's 0.9 finds nothing.
    assert check_folder(GridOnnxDetector(model), folder, score=0.95).found == 0


def test_bad_inputs_name_the_file(model, tmp_path):
    with pytest.raises(CheckInputError, match="ONNX model not found"):
        GridOnnxDetector(tmp_path / "missing.onnx")
    with pytest.raises(CheckInputError, match="annotations.json"):
        check_folder(GridOnnxDetector(model), tmp_path)


def test_command_prints_the_share_and_rejects_a_missing_folder(model, tmp_path, capsys):
    from vcfusion.commands import main

    folder = _folder(tmp_path / "ds", [{"bbox": [20.0, 20.0, 40.0, 40.0], "visible_fraction": 1.0, "truncation": 0.0}])
    assert main(["coco-check", str(folder), "--coco-onnx", str(model)]) == 0
    assert "1/1 = 100 %" in capsys.readouterr().out
    assert main(["coco-check", str(tmp_path / "nowhere"), "--coco-onnx", str(model)]) == 2
    assert "annotations.json" in capsys.readouterr().err


def test_a_model_of_another_layout_is_refused_saying_what_it_gives(tmp_path):
    # a YOLO-style (1, N, 4 + C) output: the error said what was expected, not what the model gave
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")

    class Flat(torch.nn.Module):
        def forward(self, x):
            return torch.zeros(1, 100, 6) + 0.0 * x.mean()

    path = tmp_path / "flat.onnx"
    torch.onnx.export(Flat(), torch.zeros(1, 3, SIZE, SIZE), str(path), input_names=["images"],
                      output_names=["out"], opset_version=17, dynamo=False)
    with pytest.raises(CheckInputError, match=r"grid output; inputs of S = 352: output \(1, 100, 6\)"):
        GridOnnxDetector(path).detect_rgb(np.full((96, 128, 3), 90, np.uint8))
