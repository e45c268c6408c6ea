"""Independent check of a rendered dataset (the acceptance figures of the camera stage).

Reads only the exported files (annotations.json, instance and depth PNGs) and OpenCV:
1. every anchor_uv equals cv2.projectPoints of gnss_world with the image's K and T_world_to_camera;
2. for every unoccluded, untruncated vehicle (visible_fraction 1, truncation 0, >= MIN_PIXELS
   pixels), a point inside its body (footprint centre raised by BODY_POINT_HEIGHT x height)
   projects onto a pixel of its own instance mask;
3. where a vehicle's rear centre (at the same height) is its own pixel, the depth image there
   equals the camera Z of that point computed from the exported world pose.

    python -m vcfusion.render.check DATASET_DIR
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import cv2
import numpy as np

BODY_POINT_HEIGHT = 0.35  # inside the body of both the car and the truck models
MIN_PIXELS = 20


def _project(points: np.ndarray, K: np.ndarray, T: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3).astype(np.float64), rvec, T[:3, 3].astype(np.float64), K, None)
    return uv.reshape(-1, 2)


def _pixel(uv, width, height):
    c, r = int(math.floor(uv[0] + 0.5)), int(math.floor(uv[1] + 0.5))
    return (r, c) if 0 <= r < height and 0 <= c < width else None


def check_dataset(folder: Path) -> dict:
    folder = Path(folder)
    data = json.loads((folder / "annotations.json").read_text())
    scale = data["info"]["depth_scale_m"]
    anns: dict[int, dict[str, dict]] = {}
    for a in data["annotations"]:
        anns.setdefault(a["image_id"], {})[a["vehicle_id"]] = a
    anchor_err = []
    body_total = body_hit = 0
    depth_err = []
    for image in data["images"]:
        K = np.array(image["camera"]["K"])
        T = np.array(image["camera"]["T_world_to_camera"])
        W, H = image["width"], image["height"]
        inst = cv2.imread(str(folder / image["instance_file"]), cv2.IMREAD_UNCHANGED).astype(np.int64) - 1
        depth = cv2.imread(str(folder / image["depth_file"]), cv2.IMREAD_UNCHANGED).astype(np.float64) * scale
        ids = image["instance_vehicle_ids"]
        vehicles = image["vehicles"]
        if not vehicles:
            continue
        gnss = np.array([v["gnss_world"] for v in vehicles])
        anchor_err.append(np.abs(_project(gnss, K, T) - np.array([v["anchor_uv"] for v in vehicles])).max())
        for v in vehicles:
            a = anns.get(image["id"], {}).get(v["vehicle_id"])
            if a is None or v["vehicle_id"] not in ids:
                continue
            k = ids.index(v["vehicle_id"])
            x, y, z = v["footprint_world"]
            length, _, height = v["size"]
            c, s = math.cos(v["yaw"]), math.sin(v["yaw"])
            zb = z + BODY_POINT_HEIGHT * height
            body = np.array([x, y, zb])
            rear = np.array([x - c * length / 2, y - s * length / 2, zb])
            if a["visible_fraction"] == 1.0 and a["truncation"] == 0.0 and a["area"] >= MIN_PIXELS:
                body_total += 1
                px = _pixel(_project(body, K, T)[0], W, H)
                body_hit += int(px is not None and inst[px] == k)
            px = _pixel(_project(rear, K, T)[0], W, H)
            if px is not None and inst[px] == k:
                depth_err.append(abs(depth[px] - (T[2, :3] @ rear + T[2, 3])))
    return {
        "images": len(data["images"]),
        "annotations": len(data["annotations"]),
        "anchor_max_abs_diff_px": float(max(anchor_err)) if anchor_err else float("nan"),
        "unoccluded_vehicles": body_total,
        "body_point_in_mask": body_hit,
        "body_point_in_mask_rate": body_hit / body_total if body_total else float("nan"),
        "rear_depth_checks": len(depth_err),
        "rear_depth_max_abs_err_m": float(max(depth_err)) if depth_err else float("nan"),
        "rear_depth_median_abs_err_m": float(np.median(depth_err)) if depth_err else float("nan"),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vcfusion.render.check", description=__doc__.splitlines()[0])
    parser.add_argument("dataset", help="folder written by `vcfusion render`")
    args = parser.parse_args(argv)
    stats = check_dataset(Path(args.dataset))
    for key, value in stats.items():
        print(f"{key}: {value:.6g}" if isinstance(value, float) else f"{key}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
