"""A camera above a flat road and the exact depth it sees: the synthetic depth images of the depth
step's tests (road fit, scan fill, compiled kernels)."""

from __future__ import annotations

import numpy as np

from vcfusion.fusion.sensors import _rotation


def road_camera_pose(pitch_deg: float, height_m: float) -> np.ndarray:
    """World-to-camera transform of a camera height_m above the road at the origin, looking along
    +x, pitched down by pitch_deg."""
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [0, 0, -1], [1, 0, 0]]
    T[:3, 3] = -T[:3, :3] @ np.array([0.0, 0.0, height_m])
    T[:3, :] = _rotation(pitch_deg, 0.0, 0.0).T @ T[:3, :]  # the camera turned by the pitch
    return T


def flat_road_depth(T: np.ndarray, K: np.ndarray, width: int, height: int, max_range_m: float,
                    blocks=()) -> np.ndarray:
    """(height, width) float32 depth of the road z = 0 seen from T (inf beyond max_range_m and
    above the horizon), with fronto-parallel blocks (x1, y1, x2, y2, depth) in front of it."""
    vs, us = np.mgrid[0:height, 0:width]
    rays = np.stack([us, vs, np.ones_like(us)], axis=-1).reshape(-1, 3) @ np.linalg.inv(K).T  # per unit Z
    R, t = T[:3, :3], T[:3, 3]
    world_dir = rays @ R  # R^T ray
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -(-R.T @ t)[2] / world_dir[:, 2]
    depth = np.where((world_dir[:, 2] < 0) & (s < max_range_m), s, np.inf).reshape(height, width).astype(np.float32)
    for x1, y1, x2, y2, d in blocks:
        depth[y1:y2, x1:x2] = np.minimum(depth[y1:y2, x1:x2], d)
    return depth
