"""Pinhole camera of the ego: intrinsics, extrinsics from the ego pose, projection (paper eq. 1-3).

Frames
- world: SUMO's (x east, y north, z up), metres;
- camera: OpenCV convention, x right, y down, z forward (optical axis); depth = camera Z.
- pixels: OpenCV convention, (u, v) = (column, row) with integer values at pixel *centres*:
  pixel (row r, column c) covers u in [c - 0.5, c + 0.5), v in [r - 0.5, r + 0.5).

Paper eq. 1-3 in this notation: p_c = [R|t] p_w (eq. 1); with M_i of eq. 2 (f/d_x = fx,
f/d_y = fy, principal point (u0, v0) = (cx, cy)), eq. 3 p_i = M_i^-1 p_c is
(u, v, 1) = K p_c / Z_c, which is what :func:`project_points` computes, vectorised.

No OpenGL here: the renderer's (OpenGL) camera pose is derived from these matrices in exactly
one place, :func:`opengl_camera_pose`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vcfusion.scenario import CameraConfig

# OpenCV camera axes (x right, y down, z forward) -> OpenGL camera axes (x right, y up, z back).
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Intrinsics:
    """K of an undistorted pinhole camera and its image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @staticmethod
    def from_fov(hfov_deg: float, width: int, height: int) -> "Intrinsics":
        """Square pixels, horizontal field of view across the full image, centred principal point."""
        f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
        # The image centre in pixel-centre coordinates is ((W-1)/2, (H-1)/2).
        return Intrinsics(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


def mount_pose(ego_x: float, ego_y: float, ego_z: float, ego_yaw: float, cam: CameraConfig) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre C (3,) in world and rotation R_cam_to_world (3, 3) for an ego pose.

    Columns of R_cam_to_world are the camera's x (right), y (down), z (forward) axes in world.
    """
    c, s = math.cos(ego_yaw), math.sin(ego_yaw)
    forward = np.array([c, s, 0.0])
    left = np.array([-s, c, 0.0])
    centre = np.array([ego_x, ego_y, ego_z]) + cam.forward_m * forward + cam.lateral_m * left
    centre[2] += cam.height_m
    pitch = math.radians(cam.pitch_deg)  # > 0: looking down
    z_axis = math.cos(pitch) * forward + np.array([0.0, 0.0, -math.sin(pitch)])
    x_axis = -left  # right; pitch turns about this axis so it stays horizontal
    y_axis = np.cross(z_axis, x_axis)  # right-handed: x cross y = z
    return centre, np.stack([x_axis, y_axis, z_axis], axis=1)


def world_to_camera(ego_x: float, ego_y: float, ego_z: float, ego_yaw: float, cam: CameraConfig) -> np.ndarray:
    """T_world_to_camera (4, 4): [R|t] of eq. 1, OpenCV camera frame."""
    centre, r_cw = mount_pose(ego_x, ego_y, ego_z, ego_yaw, cam)
    rot = r_cw.T
    T = np.eye(4)
    T[:3, :3] = rot
    T[:3, 3] = -rot @ centre
    return T


def opengl_camera_pose(T_world_to_camera: np.ndarray) -> np.ndarray:
    """Camera-to-world pose in OpenGL's camera convention (looks down -z, y up), for the renderer.

    The one place where the OpenCV and OpenGL camera conventions meet.
    """
    return np.linalg.inv(T_world_to_camera) @ _CV_TO_GL


@dataclass(frozen=True)
class Projection:
    """World points projected into the image, one row per point."""

    uv: np.ndarray  # (N, 2) float64 pixel coordinates (nan where behind the camera)
    depth: np.ndarray  # (N,) camera Z in metres (negative behind the camera)
    behind: np.ndarray  # (N,) bool: Z <= min_depth, no valid pixel
    outside: np.ndarray  # (N,) bool: in front but outside the image

    @property
    def in_image(self) -> np.ndarray:
        return ~(self.behind | self.outside)

    def pixel_index(self) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) integer pixel of each point (only meaningful where in_image)."""
        uv = np.nan_to_num(self.uv, nan=-1.0)
        return np.floor(uv[:, 1] + 0.5).astype(np.int64), np.floor(uv[:, 0] + 0.5).astype(np.int64)


def project_points(points_world: np.ndarray, K: np.ndarray, T_world_to_camera: np.ndarray,
                   width: int, height: int, min_depth: float = 1e-6) -> Projection:
    """Project world points (N, 3) to pixels (eq. 1-3), vectorised; flags behind/outside."""
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    pc = pts @ T_world_to_camera[:3, :3].T + T_world_to_camera[:3, 3]  # eq. 1
    z = pc[:, 2]
    behind = z <= min_depth
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = pc @ np.asarray(K, dtype=np.float64).T  # eq. 3: Z_c (u, v, 1) = K p_c
        uv = uvw[:, :2] / z[:, None]
    uv[behind] = np.nan
    u, v = uv[:, 0], uv[:, 1]
    inside = (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
    return Projection(uv=uv, depth=z, behind=behind, outside=~behind & ~inside)


def paper_intrinsic_matrix(K: np.ndarray, z_c: float) -> np.ndarray:
    """M_i of the paper's eq. 2 (for focal length f and pixel sizes d_x, d_y: fx = f/d_x, fy = f/d_y).

    Kept to show the correspondence: M_i^-1 p_c = (u, v, 1) for a point at depth z_c.
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return np.array([[z_c / fx, 0.0, -z_c * cx / fx],
                     [0.0, z_c / fy, -z_c * cy / fy],
                     [0.0, 0.0, z_c]])
