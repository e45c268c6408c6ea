"""COCO-format detection dataset of rendered frames, with each image's camera and vehicle anchors.

Conventions of the JSON (also written to its ``info``):
- ``bbox`` is COCO's [x, y, w, h] with pixel c spanning [c, c + 1) (so a mask's leftmost column
  c_min gives x = c_min); ``segmentation`` is the COCO RLE of the visible mask; ``area`` its pixels;
- ``camera.K`` / ``camera.T_world_to_camera`` follow OpenCV: world (SUMO x east, y north, z up,
  metres) -> camera (x right, y down, z forward); (u, v, 1) ~ K (R p + t) with integer (u, v) at
  pixel centres. ``vehicles[].anchor_uv`` uses this convention: the anchor lies in a box iff
  x <= u + 0.5 < x + w and y <= v + 0.5 < y + h;
- ``vehicles`` lists every vehicle whose GNSS point (body centre) lies in front of the camera,
  seen or hidden (``visible`` says which), its point in the image or not (``in_image``: a vehicle
  beside the camera, cut by the image border, has its centre outside: it is still a vehicle the
  cloud knows, a twin to match);
- depth PNGs are uint16 camera Z / ``depth_scale_m`` (0 = sky, beyond the far plane or beyond the
  format's range, 655.35 m: a far plane set further would otherwise read as 655.35 m);
  instance PNGs are uint16, value k + 1 for ``instance_vehicle_ids[k]`` of the image, 0 = none.
"""

from __future__ import annotations

import numpy as np

from vcfusion.records import CATEGORY_OF_VCLASS, VEHICLE_CATEGORIES, gnss_antenna_points
from vcfusion.render.camera import project_points

DEPTH_SCALE_M = 0.01

CONVENTIONS = {
    "bbox": "COCO [x, y, w, h]; pixel column c spans [c, c+1)",
    "camera": "OpenCV: world (x east, y north, z up, m) -> camera (x right, y down, z forward); "
              "(u, v, 1) ~ K (R p + t); integer (u, v) at pixel centres",
    "anchor_in_bbox": "x <= u + 0.5 < x + w and y <= v + 0.5 < y + h",
    "gnss_world": "body centre: footprint centre raised by half the vehicle height",
    "depth_png": f"uint16 camera Z / {DEPTH_SCALE_M} m; 0 = sky, beyond the far plane or beyond "
                 f"{65535 * DEPTH_SCALE_M:g} m",
    "instance_png": "uint16 k + 1 for instance_vehicle_ids[k]; 0 = no vehicle",
}


def category_id(vclass: str) -> int:
    try:
        return VEHICLE_CATEGORIES.index(CATEGORY_OF_VCLASS[vclass]) + 1
    except KeyError:  # load_scenario and require_camera_world refuse such a scenario before a run
        raise ValueError(f"vehicle class {vclass!r} has no COCO category (known: "
                         f"{', '.join(CATEGORY_OF_VCLASS)})") from None


def depth_to_png16(depth: np.ndarray) -> np.ndarray:
    finite = np.isfinite(depth)
    scaled = np.where(finite, np.round(np.where(finite, depth, 0.0) / DEPTH_SCALE_M), 0.0)
    return np.where(scaled > 65535, 0, np.clip(scaled, 0, None)).astype(np.uint16)  # out of range: no depth


FRAME_KINDS = ("rgb", "depth", "instances")  # a dataset folder's image subfolders


def write_frame_files(folder, stem: str, frame) -> dict[str, str]:
    """A frame's RGB, depth and instance PNGs as FOLDER/KIND/STEM.png; their paths relative to the
    folder, as the COCO records name them."""
    import cv2

    files = {kind: f"{kind}/{stem}.png" for kind in FRAME_KINDS}
    cv2.imwrite(str(folder / files["rgb"]), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(folder / files["depth"]), depth_to_png16(frame.depth))
    cv2.imwrite(str(folder / files["instances"]), (frame.instances + 1).astype("uint16"))
    return files


def vehicle_anchors(frame, truth, ego_id: str) -> list[dict]:
    """GNSS anchors of every vehicle (not the ego) whose GNSS point lies in front of the camera."""
    keep = np.array([vid != ego_id for vid in truth.ids])
    ids = [vid for vid, k in zip(truth.ids, keep) if k]
    rows = np.flatnonzero(keep)
    pts = gnss_antenna_points(truth.x[keep], truth.y[keep], truth.z[keep], truth.height[keep])
    proj = project_points(pts, frame.K, frame.T_world_to_camera, frame.width, frame.height)
    seen = set(frame.vehicle_ids[k] for k in np.unique(frame.instances) if k >= 0)
    out = []
    for j in np.flatnonzero(~proj.behind):
        out.append({
            "vehicle_id": ids[j],
            "gnss_world": [float(v) for v in pts[j]],
            "anchor_uv": [float(proj.uv[j, 0]), float(proj.uv[j, 1])],
            "anchor_depth": float(proj.depth[j]),
            "in_image": bool(proj.in_image[j]),
            "visible": ids[j] in seen,
            # The full pose, so the vehicle's 3D box can be rebuilt: footprint centre, yaw, size.
            "footprint_world": [float(truth.x[rows[j]]), float(truth.y[rows[j]]), float(truth.z[rows[j]])],
            "yaw": float(truth.heading[rows[j]]),
            "size": [float(truth.length[rows[j]]), float(truth.width[rows[j]]), float(truth.height[rows[j]])],
        })
    return out


class CocoBuilder:
    """Accumulates images and annotations; :meth:`to_dict` gives the COCO JSON object."""

    def __init__(self, description: str):
        self.images: list[dict] = []
        self.annotations: list[dict] = []
        self.info = {"description": description, "conventions": CONVENTIONS, "depth_scale_m": DEPTH_SCALE_M}

    def add(self, frame, boxes, anchors: list[dict], files: dict[str, str], extra: dict | None = None) -> int:
        # here, not at the top: the fusion stage imports this module (category_id) in every run
        from pycocotools import mask as mask_utils

        image_id = len(self.images) + 1
        self.images.append({
            "id": image_id,
            "file_name": files["rgb"],
            "depth_file": files["depth"],
            "instance_file": files["instances"],
            "width": frame.width,
            "height": frame.height,
            "camera": {"K": frame.K.tolist(), "T_world_to_camera": frame.T_world_to_camera.tolist(),
                       "time": float(frame.time)},
            "instance_vehicle_ids": list(frame.vehicle_ids),
            "vehicles": anchors,
            **(extra or {}),
        })
        for j, vid in enumerate(boxes.vehicle_ids):
            x1, y1, x2, y2 = boxes.box[j]
            mask = np.asfortranarray((frame.instances == boxes.instance[j]).astype(np.uint8))
            rle = mask_utils.encode(mask)
            rle["counts"] = rle["counts"].decode("ascii")
            self.annotations.append({
                "id": len(self.annotations) + 1,
                "image_id": image_id,
                "category_id": category_id(boxes.vclass[j]),
                # Pixel-centre edges (c - 0.5) -> COCO's pixel-corner convention (c).
                "bbox": [float(x1 + 0.5), float(y1 + 0.5), float(x2 - x1), float(y2 - y1)],
                "area": int(boxes.pixels[j]),
                "segmentation": rle,
                "iscrowd": 0,
                "vehicle_id": vid,
                "visible_fraction": None if np.isnan(boxes.visible_fraction[j]) else float(boxes.visible_fraction[j]),
                "truncation": float(boxes.truncation[j]),
                "median_depth": float(boxes.median_depth[j]),
            })
        return image_id

    def extend(self, images: list[dict], annotations: list[dict]) -> None:
        """Append another builder's records (its ids counted from 1), renumbered to follow these: a
        worker's share of a dataset, merged in order, gets the ids one builder would have given."""
        first_image, first_annotation = len(self.images), len(self.annotations)
        for image in images:
            image["id"] += first_image
        for ann in annotations:
            ann["id"] += first_annotation
            ann["image_id"] += first_image
        self.images += images
        self.annotations += annotations

    def to_dict(self) -> dict:
        return {
            "info": self.info,
            "licenses": [],
            "categories": [{"id": i + 1, "name": name, "supercategory": "vehicle"}
                           for i, name in enumerate(VEHICLE_CATEGORIES)],
            "images": self.images,
            "annotations": self.annotations,
        }
