"""A test-only frame source: every vehicle drawn as the image rectangle of its 3-D box, painted far
to near (so nearer vehicles occlude), with the camera-Z of its nearest face as depth. It stands in
for the renderer to test the study and fusion code end to end on real SUMO traffic; it is not the
renderer (no meshes, no lighting)."""

from __future__ import annotations

import numpy as np

from vcfusion.detection.detectors import Detections
from vcfusion.records import EGO_ID
from vcfusion.fusion.fuse import CameraFrame
from vcfusion.fusion.matching import CameraView


class CuboidFrameSource:
    def __init__(self, width=640, height=480, focal_px=500.0, camera_height_m=1.3):
        self.w, self.h, self.f, self.cam_h = width, height, focal_px, camera_height_m

    def camera(self, truth, time) -> CameraView:
        i = truth.index_of(EGO_ID)
        psi = float(truth.heading[i])
        fwd = np.array([np.cos(psi), np.sin(psi), 0.0])
        right = np.array([np.sin(psi), -np.cos(psi), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        pos = np.array([truth.x[i], truth.y[i], truth.z[i] + self.cam_h]) + 0.5 * truth.length[i] * fwd
        rot = np.stack([right, down, fwd])
        f, cx, cy = self.f, self.w / 2, self.h / 2

        def project(points):
            pc = (np.asarray(points, float).reshape(-1, 3) - pos) @ rot.T
            with np.errstate(divide="ignore", invalid="ignore"):
                uv = np.stack([f * pc[:, 0] / pc[:, 2] + cx, f * pc[:, 1] / pc[:, 2] + cy], axis=1)
            return uv, pc[:, 2]

        return CameraView(project, pos, self.w, self.h, time)

    def __call__(self, tick) -> CameraFrame:
        truth = tick.truth
        cam = self.camera(truth, tick.time)
        entries = []
        for k, vid in enumerate(truth.ids):
            if vid == EGO_ID:
                continue
            c, s = np.cos(truth.heading[k]), np.sin(truth.heading[k])
            pts = []
            for dl in (-0.5, 0.5):
                for dw in (-0.5, 0.5):
                    for dz in (0.0, 1.0):
                        pts.append((truth.x[k] + dl * truth.length[k] * c - dw * truth.width[k] * s,
                                    truth.y[k] + dl * truth.length[k] * s + dw * truth.width[k] * c,
                                    truth.z[k] + dz * truth.height[k]))
            uv, z = cam.project(np.array(pts))
            if (z <= 0.5).any():
                continue
            x1, y1 = np.clip(np.floor(uv.min(axis=0)), 0, [self.w, self.h]).astype(int)
            x2, y2 = np.clip(np.ceil(uv.max(axis=0)), 0, [self.w, self.h]).astype(int)
            if x2 > x1 and y2 > y1:
                entries.append((float(z.min()), vid, (x1, y1, x2, y2)))
        image = np.zeros((self.h, self.w, 3), np.uint8)
        image[self.h // 2:] = 90
        depth = np.full((self.h, self.w), np.inf, np.float32)
        inst = np.full((self.h, self.w), -1, np.int32)
        for n, (zmin, vid, (x1, y1, x2, y2)) in enumerate(sorted(entries, key=lambda e: -e[0])):
            depth[y1:y2, x1:x2] = zmin
            inst[y1:y2, x1:x2] = n
            image[y1:y2, x1:x2] = (60 + 37 * n % 190, 200 - 23 * n % 150, 120)
        order = sorted(entries, key=lambda e: -e[0])
        boxes, ids = [], []
        for n, (_, vid, _) in enumerate(order):
            ys, xs = np.nonzero(inst == n)
            if len(xs) >= 20:
                boxes.append((xs.min(), ys.min(), xs.max() + 1, ys.max() + 1))
                ids.append(vid)
        return CameraFrame(tick.time, image, depth, cam, np.array(boxes, float).reshape(-1, 4), tuple(ids),
                           instances=inst, instance_ids=tuple(vid for _, vid, _ in order))


class ShiftedOntoNeighbour:
    """A detector whose box for the cutter spreads onto the neighbouring vehicle: one box over
    both (the nearer neighbour owns most of its pixels; it still holds the cutter's anchor, so the
    matcher gives it to the cutter's twin). `frame` is set per tick by the test."""

    frame = None

    def detect(self, image):
        ids = list(self.frame.gt_ids)
        cut, nb = self.frame.gt_boxes[ids.index("cutter")], self.frame.gt_boxes[ids.index("neighbour")]
        box = [min(nb[0], cut[0]), min(nb[1], cut[1]), max(nb[2], cut[2]), max(nb[3], cut[3])]
        return Detections.of(np.array([box]), np.array([0.9]), np.array([3]))
