"""Hand-made geometry for the vision tests: a tiny pinhole camera and twin records."""

from __future__ import annotations

import numpy as np

from vcfusion.records import TwinStates
from vcfusion.fusion.matching import CameraView

W, H = 640, 480
FX = FY = 500.0
CX, CY = 320.0, 240.0


def pinhole_camera(position=(0.0, 0.0, 1.5), time: float = 0.0) -> CameraView:
    """A camera at `position` looking along world +x (the road), OpenCV frame: x right, y down, z fwd."""
    pos = np.asarray(position, dtype=float)

    def project(points):
        p = np.asarray(points, dtype=float).reshape(-1, 3) - pos
        xc, yc, zc = -p[:, 1], -p[:, 2], p[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([FX * xc / zc + CX, FY * yc / zc + CY], axis=1)
        return uv, zc

    return CameraView(project=project, position=pos, width=W, height=H, time=time)


def make_twins(ids, x, y, *, measured_time=0.0, heading=0.0, speed=0.0, length=4.5, width=1.8,
               height=1.5, z_ground=0.0, lc_prob=None) -> TwinStates:
    n = len(ids)
    arr = lambda v: np.broadcast_to(np.asarray(v, dtype=float), (n,)).copy()  # noqa: E731
    h = arr(height)
    outputs = {} if lc_prob is None else {"lc_prob": arr(lc_prob)}
    return TwinStates(
        time=0.0, ids=tuple(ids), measured_time=arr(measured_time), x=arr(x), y=arr(y), z=arr(z_ground) + h,
        heading=arr(heading), speed=arr(speed), accel=arr(0.0), lane=np.zeros(n, np.int16),
        length=arr(length), width=arr(width), height=h, outputs=outputs)


def vehicle_box(camera: CameraView, x, y, length=4.5, width=1.8, height=1.5) -> np.ndarray:
    """Image box of a vehicle driving along +x whose footprint centre is (x, y): its visible faces
    span the rear (nearest) to the front; written independently of the package's cuboid code."""
    pts = []
    for dx in (-length / 2, length / 2):
        for dy in (-width / 2, width / 2):
            for z in (0.0, height):
                pts.append((x + dx, y + dy, z))
    uv, _ = camera.project(np.array(pts))
    return np.array([uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max(), uv[:, 1].max()])
