"""Our CNN behind an output head in the Ultralytics export layout, for the ONNX-YOLO tests.

Input (1, 3, h, w) RGB / 255 (letterboxed by the caller); output (1, 4 + 80, N): box centre x,
centre y, width, height in input pixels, then 80 COCO class scores. Our two classes (category ids
1 passenger and 2 truck) fill the COCO columns car (2) and truck (7); the other columns carry a
small constant score, and the 'train' column (6) copies half the truck score, so candidates whose
best class is a dropped one stay rare but the column is not trivially empty.
"""

from __future__ import annotations

import torch
from torch import nn

from vcfusion.detection.detector_net import CenterNetLite, decode_dense

COCO_CAR, COCO_TRAIN, COCO_TRUCK = 2, 6, 7


class UltralyticsHead(nn.Module):
    def __init__(self, model: CenterNetLite):
        super().__init__()
        self.model = model

    def forward(self, x):
        dense = decode_dense(*self.model(x * 255.0))  # (1, N, 4 + 2): cx, cy, w, h, car, truck
        n = dense.shape[1]
        scores = torch.full((1, n, 80), 0.001, dtype=dense.dtype)
        scores[:, :, COCO_CAR] = dense[:, :, 4]
        scores[:, :, COCO_TRUCK] = dense[:, :, 5]
        scores[:, :, COCO_TRAIN] = 0.5 * dense[:, :, 5]
        return torch.cat([dense[:, :, :4], scores], dim=2).transpose(1, 2)  # (1, 84, N)


def export_ultralytics_layout(model: CenterNetLite, input_wh: tuple[int, int], path) -> None:
    import warnings

    w, h = input_wh
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(UltralyticsHead(model.cpu().eval()).eval(), torch.zeros(1, 3, h, w), str(path),
                          dynamo=False, opset_version=17, input_names=["images"], output_names=["output0"])
