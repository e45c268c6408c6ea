"""A small synthetic COCO dataset for unit tests of the detector training code (not the shipped
model's data): coloured rectangles ("cars" wide, "trucks" tall) on a road-like background."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np


def make_synthetic_coco(folder: Path, n_images: int = 40, size=(128, 96), seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    w, h = size
    images, anns = [], []
    for i in range(n_images):
        img = np.zeros((h, w, 3), np.uint8)
        img[: h // 2] = (150, 180, 220)  # sky
        img[h // 2:] = (80, 80, 85)  # road
        img = np.clip(img.astype(int) + rng.integers(-8, 9, img.shape), 0, 255).astype(np.uint8)
        placed = []
        for _ in range(rng.integers(1, 4)):
            cat = int(rng.integers(1, 3))
            bw, bh = (int(rng.integers(18, 34)), int(rng.integers(12, 20))) if cat == 1 else (int(rng.integers(14, 22)), int(rng.integers(22, 34)))
            for _try in range(20):
                x, y = int(rng.integers(0, w - bw)), int(rng.integers(h // 3, h - bh))
                if all(x + bw <= px or px + pw <= x or y + bh <= py or py + ph <= y for px, py, pw, ph in placed):
                    break
            else:
                continue
            placed.append((x, y, bw, bh))
            colour = (220, 40, 40) if cat == 1 else (40, 60, 220)
            cv2.rectangle(img, (x, y), (x + bw - 1, y + bh - 1), colour, -1)
            cv2.rectangle(img, (x + 3, y + 3), (x + bw - 4, y + bh // 2), (30, 30, 30), -1)  # a window
            anns.append({"id": len(anns) + 1, "image_id": i + 1, "category_id": cat, "bbox": [x, y, bw, bh],
                         "area": bw * bh, "iscrowd": 0, "vehicle_id": f"v{len(anns)}"})
        name = f"frame_{i:04d}.png"
        cv2.imwrite(str(folder / name), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        images.append({"id": i + 1, "file_name": name, "width": w, "height": h})
    coco = {"images": images, "annotations": anns, "categories": [{"id": 1, "name": "car"}, {"id": 2, "name": "truck"}]}
    (folder / "annotations.json").write_text(json.dumps(coco))
    return folder
