"""The far-box head (vcfusion.fusion.far_boxes): its contract, the shipped weights, a box shifted
off a rendered car pulled back, and the depth step handing it the gated boxes only."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vcfusion.fusion.far_boxes import (BoxHead, BoxHeadFileError, BoxHeadNet, CropSpec, apply_offsets, box_crops,
                                       crop_windows, default_box_head_path, save_box_head, side_offsets)
from vcfusion.fusion.matching import box_iou


def test_crops_offsets_and_their_inverse():
    spec = CropSpec()
    boxes = np.array([[100.0, 50.0, 120.0, 70.0], [10.0, 10.0, 14.0, 30.0]])
    image = np.zeros((120, 200, 3), np.uint8)
    image[50:71, 100:121] = 255  # pixels 100-120: the box (100, 120) in pixel-centre coordinates +- 0.5
    crops = box_crops(image, boxes, spec)
    assert crops.shape == (2, 3, spec.crop_px, spec.crop_px) and crops.dtype == np.float32
    assert 0.0 <= crops.min() and crops.max() <= 1.0
    lit = crops[0, 0].max(axis=0) > 0.5  # the white block sits in the middle of its window, symmetric
    cols = np.flatnonzero(lit)
    assert abs(cols[0] - (spec.crop_px - 1 - cols[-1])) <= 1
    assert box_crops(image, boxes, spec, raw=True).dtype == np.uint8
    windows = crop_windows(boxes, spec)
    assert windows[0, 0] < 100.5 and windows[0, 2] > 120.5
    targets = boxes + [[1.0, -2.0, 3.0, 0.5], [0.0, 0.0, -1.0, 4.0]]
    off = side_offsets(boxes, targets)
    np.testing.assert_allclose(apply_offsets(boxes, off, max_shift=1.0), targets)
    # a side moves by at most max_shift of the box's size, and never crosses the opposite side
    far = apply_offsets(boxes, np.array([[5.0, 0, 0, 0], [0, 0, -5.0, 0]]), max_shift=0.35)
    np.testing.assert_allclose(far[0, 0], 100.0 + 0.35 * 20.0)
    assert (far[:, 2] >= far[:, 0] + 1.0).all()


def test_shipped_weights_load_and_map_boxes_to_boxes():
    head = BoxHead.load(default_box_head_path())
    assert isinstance(head.net, BoxHeadNet) and 0 < head.max_shift <= 0.5 and head.max_height_px > 0
    image = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    out = head.refine(image, np.array([[300.0, 200.0, 330.0, 220.0], [0.0, 0.0, 8.0, 6.0]]))
    assert out.shape == (2, 4) and np.isfinite(out).all()
    assert head.refine(image, np.zeros((0, 4))).shape == (0, 4)


def test_a_bad_weights_file_names_itself(tmp_path):
    missing = tmp_path / "none.pt"
    with pytest.raises(BoxHeadFileError, match="none.pt"):
        BoxHead.load(missing)
    junk = tmp_path / "junk.pt"
    torch.save({"state_dict": {}}, junk)
    with pytest.raises(BoxHeadFileError, match="junk.pt: expected a dict"):
        BoxHead.load(junk)
    wrong = tmp_path / "wrong.pt"
    head = BoxHead(BoxHeadNet(32), CropSpec(), 0.3, 100.0)  # 32 px net with a 48 px spec: does not fit
    save_box_head(head, wrong)
    with pytest.raises(BoxHeadFileError, match="wrong.pt: state_dict does not fit"):
        BoxHead.load(wrong)


@pytest.mark.slow
def test_a_box_shifted_off_a_rendered_car_is_pulled_back(tmp_path):
    """Training-sampler scenes the head never saw (its training seeds are 0-999): far boxes (8-40 px
    high) moved off their vehicles by 15-20 % of their size (about 3 px a side) come back to within
    1.5 px a side (median; 0.63 px with the shipped weights) and gain more than 0.05 IoU (0.71 ->
    0.85); a ground-truth box stays within 1 px (0.20)."""
    from scenario_files import SCENARIOS
    from vcfusion.detection.detector_train import load_coco, read_rgb
    from vcfusion.detection.scenes import render_scenes
    from vcfusion.scenario import load_scenario

    seeds = list(range(7001, 7009))
    render_scenes(load_scenario(SCENARIOS / "overlap.yaml"), "train", seeds, tmp_path / "s", progress=False)
    ds = load_coco(tmp_path / "s")
    head = BoxHead.load(default_box_head_path())
    errors_before, errors_after, ious_before, ious_after, still = [], [], [], [], []
    for k, path in enumerate(ds.images):
        image = read_rgb(path)
        gt = ds.boxes[k]
        h = gt[:, 3] - gt[:, 1]
        gt = gt[(h >= 8) & (h <= 40) & (gt[:, 2] - gt[:, 0] >= 8)]  # far boxes, what the head is for
        size = np.c_[gt[:, 2] - gt[:, 0], gt[:, 3] - gt[:, 1]]
        size = np.c_[size, size]
        for shift in ([0.2, 0.0, 0.2, 0.0], [0.0, -0.15, 0.0, -0.15], [-0.2, 0.0, 0.0, 0.15]):
            off = gt + np.array(shift) * size
            back = head.refine(image, off)
            errors_before.append(np.abs(off - gt).ravel())
            errors_after.append(np.abs(back - gt).ravel())
            ious_before.append(np.diag(box_iou(off, gt)))
            ious_after.append(np.diag(box_iou(back, gt)))
        still.append(np.abs(head.refine(image, gt) - gt).ravel())
    before, after = np.concatenate(errors_before), np.concatenate(errors_after)
    assert len(np.concatenate(ious_before)) >= 15  # 5 or more far boxes, 3 shifts each
    moved = np.median(before[before > 0])  # about 3 px
    assert np.median(after) < min(1.5, moved / 2)
    assert np.mean(np.concatenate(ious_after)) > np.mean(np.concatenate(ious_before)) + 0.05
    assert np.median(np.concatenate(still)) < 1.0
