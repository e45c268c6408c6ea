"""What the ego's depth sensor and camera mount deliver, from the renderer's exact depth and pose.

The renderer gives an exact depth image and the camera's nominal pose (the ego's pose and the
scenario's mount). A real car has neither: :class:`SensorModel` turns them into what the fusion
and the detector see, in ONE place (:func:`vcfusion.fusion.stage.frame_from_render` for rendered
runs and studies, :func:`vcfusion.detection.family_eval` for dataset frames). Ground truth used for
scoring (the instance map, the ground-truth boxes) is never touched.

Depth (``camera.depth``; parameters in ``camera.depth_params``), camera-Z in metres; ``nan``
where the sensor gives no measurement (``inf`` stays "nothing within range", the sky of exact depth):

- ``exact``: the renderer's depth.
- ``stereo``: a rectified pair of baseline ``B`` and the camera's focal length ``f`` (px, from the
  intrinsics). Disparity ``d = f B / z`` gets a Gaussian error of ``disparity_noise_px``; the depth
  is ``f B / d_measured``, so to first order its error grows as ``sigma_z = z^2 sigma_d / (f B)``.
  Holes (``nan``): disparities below ``min_disparity_px`` (beyond the matcher's range, sky
  included), the occlusion band (pixels the right camera cannot see: hidden behind a nearer
  surface to their right), and low-texture pixels (grey-level standard deviation in a 5 x 5
  window below ``texture_min``, where block matching has nothing to match).
- ``tof``: range-dependent Gaussian noise ``sigma = tof_sigma0_m + tof_sigma_rel * z``; no return
  beyond ``tof_max_range_m``; flying pixels: where the 3 x 3 neighbourhood spans a depth step of
  more than ``flying_edge_m``, the pixel reads a random mix of the near and far depth.
- ``lidar``: a 64-beam-like scan (``lidar_beams`` beams evenly spaced in elevation from
  ``lidar_elevation_deg``, one return every ``lidar_azimuth_step_deg``) from a sensor at the
  camera's centre, level with the body, projected into the image: each return's pixel reads the
  range along its ray (Gaussian range noise ``lidar_range_noise_m``); every other pixel has no
  depth (``nan``).

Pose (``camera.pose_noise``): the fusion believes the nominal pose while the camera looks along a
rotated axis: a mount calibration error (pitch, yaw, roll each drawn once per run, Gaussian of
``mount_std_deg``) plus the body's pitch and roll on its suspension (first-order lag of time
constant ``suspension_tau_s`` towards ``pitch_gain_deg_per_mps2`` times the longitudinal and
``roll_gain_deg_per_mps2`` times the lateral acceleration of the ego, its own measurements, when
``body_motion``). The
image is rendered at the nominal pose and the fusion is handed the pose rotated by the inverse of
that rotation: the same relative error as a rotated camera believed nominal.

All random draws come from the run's Generator (:class:`SensorModel` ``rng``): the same seed gives
the same depth image and pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np

DEPTH_MODELS = ("exact", "stereo", "tof", "lidar")


@dataclass(frozen=True)
class DepthSensorParams:
    # stereo: 0.12 m baseline and 0.25 px disparity noise (issue 48's target setting; automotive
    # stereo cameras have 0.12-0.3 m baselines and sub-pixel matchers of about 0.1-0.3 px)
    baseline_m: float = 0.12
    disparity_noise_px: float = 0.25
    # smallest disparity matched, px: beyond f B / 0.5 (about 110 m at B = 0.12 m, f = 457 px) no depth
    min_disparity_px: float = 0.5
    # grey-level std (0-255) in a 5 x 5 window below which block matching fails (a flat patch)
    texture_min: float = 1.0
    # ToF: sigma = 0.01 m + 1 % of the range (continuous-wave ToF error grows with range);
    # no return beyond 60 m; a 3 x 3 depth step above 0.5 m makes a flying pixel
    tof_sigma0_m: float = 0.01
    tof_sigma_rel: float = 0.01
    tof_max_range_m: float = 60.0
    flying_edge_m: float = 0.5
    # LiDAR: 64 beams from +2 to -24.8 deg elevation, a return every 0.17 deg of azimuth and 0.02 m
    # range noise (the layout of a 64-beam rotating LiDAR of the HDL-64E kind at 10 Hz)
    lidar_beams: int = 64
    lidar_elevation_deg: tuple[float, float] = (2.0, -24.8)
    lidar_azimuth_step_deg: float = 0.17
    lidar_range_noise_m: float = 0.02


@dataclass(frozen=True)
class PoseNoiseParams:
    # mount calibration error, deg (std of each of pitch, yaw, roll; drawn once per run)
    mount_std_deg: float = 0.0
    # the body's pitch and roll on its suspension (the gains below); off: a rigid body
    body_motion: bool = False
    # body pitch per longitudinal acceleration, deg per m/s^2 (nose down when braking): 0.15
    # (about 1.5 deg per g, a passenger car's pitch gradient); roll per lateral acceleration 0.4 deg
    # per m/s^2 (about 4 deg per g, inside the 3-7 deg/g roll gradients of passenger cars,
    # Gillespie, Fundamentals of Vehicle Dynamics, 1992, ch. 9)
    pitch_gain_deg_per_mps2: float = 0.15
    roll_gain_deg_per_mps2: float = 0.4
    # the body's response to a step in acceleration: first-order lag of 0.15 s (a damped body
    # mode of about 1-1.5 Hz settles in about this time)
    suspension_tau_s: float = 0.15

    @property
    def active(self) -> bool:
        return self.mount_std_deg > 0 or self.body_motion


def stereo_sigma_z(z: np.ndarray, focal_px: float, baseline_m: float, disparity_noise_px: float) -> np.ndarray:
    """First-order depth error of a stereo pair: sigma_z = z^2 sigma_d / (f B), m."""
    return np.asarray(z, float) ** 2 * disparity_noise_px / (focal_px * baseline_m)


def _grey_blurs(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 5 x 5 box means of the grey level and of its square (float32, OpenCV's box filter)."""
    import cv2

    grey = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float32)
    return cv2.blur(grey, (5, 5)), cv2.blur(grey * grey, (5, 5))


# error_model numpy: a float division by zero gives inf / nan as the array expressions do
@numba.njit(cache=True, error_model="numpy")
def _stereo_kernel(z, fb, noise, min_disparity, mean, sq, texture_min, out):
    """stereo_depth's per-pixel work in one pass a row, from its right end (the occlusion band's
    suffix maximum), in float32 throughout: the same operations in the same order as the array
    expressions they stand for (tests/fusion/test_sensor_kernels.py pins them against those)."""
    H, W = z.shape
    zero, half, nan, ninf = np.float32(0.0), np.float32(0.5), np.float32(np.nan), np.float32(-np.inf)
    textured = texture_min > 0
    for y in range(H):
        right_of = ninf  # the largest d(u') - u' over u' > u
        for x in range(W - 1, -1, -1):
            zz = z[y, x]
            d = fb / zz if np.isfinite(zz) and zz > 0 else zero
            e = d - np.float32(x)
            hole = right_of > e + half  # occluded: hidden from the right camera
            if e > right_of:
                right_of = e
            measured = d + np.float32(noise[y, x])  # the draw rounded to float32, as astype does
            hole = hole or measured < min_disparity or d < min_disparity
            if textured and not hole:
                m = mean[y, x]
                v = sq[y, x] - m * m
                if v < zero:
                    v = zero
                hole = np.sqrt(v) < texture_min
            out[y, x] = nan if hole else fb / measured


def stereo_depth(depth: np.ndarray, focal_px: float, p: DepthSensorParams, rng: np.random.Generator,
                 image: np.ndarray | None = None) -> np.ndarray:
    """The stereo model of the module doc (left camera = the rendered one)."""
    z = np.ascontiguousarray(depth, np.float32)
    if z.ndim != 2:
        raise ValueError(f"depth: expected a 2-D depth image (H, W), got shape {z.shape}")
    fb = np.float32(focal_px * p.baseline_m)
    # disparity d = f B / z (0 where no depth); pixel u of the left image is hidden from the right
    # camera (the occlusion band) when a pixel u' > u lands on or left of it there: d(u') - u' > d(u) - u
    # + 0.5; the measured disparity d + N(0, disparity_noise_px) (one draw a pixel, row-major, the
    # run's Generator); holes where the measured or the true disparity is below min_disparity_px or
    # the grey level's 5 x 5 std is below texture_min; elsewhere f B / measured
    noise = rng.normal(0.0, p.disparity_noise_px, size=z.shape)  # float64, rounded to float32 in the pass
    textured = image is not None and p.texture_min > 0
    mean, sq = _grey_blurs(image) if textured else (z, z)  # (not read without texture)
    if mean.shape != z.shape:
        raise ValueError(f"image: expected the depth image's size {z.shape}, got shape {np.shape(image)}")
    out = np.empty(z.shape, np.float32)
    _stereo_kernel(z, fb, noise, np.float32(p.min_disparity_px), mean, sq,
                   np.float32(p.texture_min if textured else 0.0), out)
    return out


def tof_depth(depth: np.ndarray, p: DepthSensorParams, rng: np.random.Generator) -> np.ndarray:
    import cv2

    z = np.asarray(depth, np.float32)
    finite = np.isfinite(z) & (z > 0)
    zf = np.where(finite, z, np.float32(p.tof_max_range_m * 2))
    near = cv2.erode(zf, np.ones((3, 3), np.uint8))
    far = cv2.dilate(zf, np.ones((3, 3), np.uint8))
    flying = (far - near > p.flying_edge_m) & finite
    mixed = near + rng.random(z.shape, dtype=np.float32) * (far - near)
    z2 = np.where(flying, mixed, zf)
    noisy = z2 + rng.normal(0.0, 1.0, size=z.shape).astype(np.float32) * (p.tof_sigma0_m + p.tof_sigma_rel * z2)
    return np.where(z2 <= p.tof_max_range_m, noisy, np.float32(np.nan)).astype(np.float32)


@lru_cache(maxsize=8)
def _scan_pixels(K_key: tuple, size: tuple[int, int], R_key: tuple, beams: int, elevation: tuple[float, float],
                 az_step_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, columns and ray-Z-per-range (the camera-Z of a unit-length ray) of every LiDAR return
    that lands in the image; one return per pixel (the first in scan order)."""
    K = np.array(K_key, float).reshape(3, 3)
    R = np.array(R_key, float).reshape(3, 3)  # body (x forward, y left, z up) -> camera
    w, h = size
    half_fov = np.degrees(np.arctan2(w / 2, K[0, 0])) + 2.0
    az = np.radians(np.arange(-half_fov, half_fov, az_step_deg))
    el = np.radians(np.linspace(elevation[0], elevation[1], beams))
    A, E = np.meshgrid(az, el)
    rays = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1).reshape(-1, 3)
    cam = rays @ R.T
    front = cam[:, 2] > 1e-3
    cam = cam[front]
    uv = cam @ K.T
    u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
    cols, rows = np.floor(u + 0.5).astype(int), np.floor(v + 0.5).astype(int)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    idx = rows[inside] * w + cols[inside]
    idx, first = np.unique(idx, return_index=True)
    return idx // w, idx % w, cam[inside][first, 2]


def lidar_scan_mask(K: np.ndarray, T_world_to_camera: np.ndarray, size: tuple[int, int],
                    p: DepthSensorParams) -> np.ndarray:
    """(H, W) bool: the pixels the LiDAR's returns land on."""
    rows, cols, _ = _scan(K, T_world_to_camera, size, p)
    mask = np.zeros((size[1], size[0]), bool)
    mask[rows, cols] = True
    return mask


def _scan(K, T, size, p):
    # the body axes in camera coordinates: level with the road (the camera's own pitch and roll are
    # the mount's), heading along the camera's forward axis projected on the ground
    R_wc = np.asarray(T, float)[:3, :3]
    fwd_w = R_wc[2].copy()
    fwd_w[2] = 0.0
    fwd_w /= np.linalg.norm(fwd_w)
    up_w = np.array([0.0, 0.0, 1.0])
    left_w = np.cross(up_w, fwd_w)
    R = R_wc @ np.stack([fwd_w, left_w, up_w], axis=1)  # body -> camera
    key = tuple(np.round(R, 9).ravel())
    return _scan_pixels(tuple(np.asarray(K, float).ravel()), tuple(size), key, p.lidar_beams,
                        tuple(p.lidar_elevation_deg), p.lidar_azimuth_step_deg)


def lidar_depth(depth: np.ndarray, K: np.ndarray, T: np.ndarray, p: DepthSensorParams,
                rng: np.random.Generator) -> np.ndarray:
    z = np.asarray(depth, np.float32)
    h, w = z.shape
    rows, cols, ray_z = _scan(K, T, (w, h), p)
    out = np.full((h, w), np.nan, np.float32)
    zs = z[rows, cols]
    # range along the ray = camera-Z / (camera-Z per unit range); noise on the range
    noise = rng.normal(0.0, p.lidar_range_noise_m, size=len(zs)) * ray_z
    out[rows, cols] = np.where(np.isfinite(zs), zs + noise, zs).astype(np.float32)
    return out


def _rotation(pitch_deg: float, yaw_deg: float, roll_deg: float) -> np.ndarray:
    """Q (3, 3): the camera's axes after pitching down, yawing right and rolling clockwise by the
    angles, in the nominal camera's coordinates (OpenCV: x right, y down, z forward)."""
    p, y, r = np.radians([pitch_deg, yaw_deg, roll_deg])
    Rx = np.array([[1, 0, 0], [0, np.cos(p), np.sin(p)], [0, -np.sin(p), np.cos(p)]])  # z -> (0, sin, cos): down
    Ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])  # z -> (sin, 0, cos): right
    Rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])  # x -> (cos, sin, 0)
    return Rx @ Ry @ Rz


class SensorModel:
    """One run's depth sensor and camera pose error (module doc); `rng`: the run's Generator."""

    def __init__(self, depth: str = "exact", params: DepthSensorParams = DepthSensorParams(),
                 pose: PoseNoiseParams = PoseNoiseParams(), rng: np.random.Generator | None = None):
        if depth not in DEPTH_MODELS:
            raise ValueError(f"depth sensor: expected one of {DEPTH_MODELS}, got {depth!r}")
        self.depth_model, self.params, self.pose = depth, params, pose
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.mount = self.rng.normal(0.0, pose.mount_std_deg, size=3) if pose.mount_std_deg > 0 else np.zeros(3)
        self._body = np.zeros(2)  # pitch, roll (deg)
        self._last: tuple[float, float] | None = None  # time, heading of the last frame

    @classmethod
    def for_camera(cls, camera, rng: np.random.Generator) -> "SensorModel | None":
        """The model of a scenario's ``camera`` block (vcfusion.scenario.CameraConfig); None when
        its depth and pose are exact."""
        pose = PoseNoiseParams(**camera.pose_noise.model_dump())
        if camera.depth == "exact" and not pose.active:
            return None
        params = camera.depth_params.model_dump()
        params["lidar_elevation_deg"] = tuple(params["lidar_elevation_deg"])
        return cls(camera.depth, DepthSensorParams(**params), pose, rng)

    def describe(self) -> str:
        pose = (f", mount error {self.pose.mount_std_deg:g} deg" if self.pose.mount_std_deg else "") + \
            (", body pitch/roll" if self.pose.body_motion else "")
        return f"{self.depth_model} depth{pose}"

    @property
    def exact(self) -> bool:
        return self.depth_model == "exact" and not self.pose.active

    def noise(self, K: np.ndarray):
        """The depth's error as the sensor's spec gives it (vcfusion.fusion.road.DepthNoise):
        stereo z^2 sigma_d / (f B), ToF sigma0 + rel z, LiDAR its range noise, exact none."""
        from vcfusion.fusion.road import DepthNoise

        p = self.params
        if self.depth_model == "stereo":
            fb = float(np.asarray(K)[0, 0]) * p.baseline_m
            return DepthNoise(c=p.disparity_noise_px / fb, focal_baseline_px_m=fb,
                              disparity_noise_px=p.disparity_noise_px, min_disparity_px=p.min_disparity_px)
        if self.depth_model == "tof":
            return DepthNoise(a=p.tof_sigma0_m, b=p.tof_sigma_rel, mixed_edges=True)
        if self.depth_model == "lidar":
            return DepthNoise(a=p.lidar_range_noise_m)
        return DepthNoise()

    def depth(self, depth: np.ndarray, K: np.ndarray, T: np.ndarray, image: np.ndarray | None = None) -> np.ndarray:
        p = self.params
        if self.depth_model == "stereo":
            return stereo_depth(depth, float(K[0, 0]), p, self.rng, image)
        if self.depth_model == "tof":
            return tof_depth(depth, p, self.rng)
        if self.depth_model == "lidar":
            return lidar_depth(depth, K, T, p, self.rng)
        return depth

    def believed_pose(self, T: np.ndarray, time: float | None = None, accel: float = 0.0, speed: float = 0.0,
                      heading: float | None = None) -> np.ndarray:
        """The extrinsics the fusion believes for an image taken at nominal pose `T`; the ego's own
        acceleration (m/s^2), speed (m/s) and heading (rad) at `time` drive the suspension."""
        if not self.pose.active:
            return T
        pp = self.pose
        if time is not None and pp.body_motion:
            if self._last is not None and time > self._last[0]:
                dt = time - self._last[0]
                yaw_rate = float(np.angle(np.exp(1j * ((heading or 0.0) - self._last[1])))) / dt
                lateral = speed * yaw_rate
                target = np.array([-pp.pitch_gain_deg_per_mps2 * accel, pp.roll_gain_deg_per_mps2 * lateral])
                self._body += (target - self._body) * (1.0 - np.exp(-dt / pp.suspension_tau_s))
            self._last = (time, heading or 0.0)
        pitch = self.mount[0] + self._body[0]
        roll = self.mount[2] + self._body[1]
        Q = _rotation(pitch, self.mount[1], roll)
        out = np.array(T, float, copy=True)
        out[:3, :] = Q @ out[:3, :]
        return out
