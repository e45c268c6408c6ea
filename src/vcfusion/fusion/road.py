"""The road plane under the ego, fitted to the depth image every frame, and the depth step's noise model.

The depth step (vcfusion.fusion.box_refine) measures how high each pixel's point stands above the
road. With the renderer's exact pose the road is world z = 0; a real camera's pose is off by its
mount calibration and the body's pitch and roll (0.2 deg of pitch moves a point 30 m ahead by about
10 cm), and roads are not flat. :func:`fit_road_plane` finds the road in the depth image itself:

1. candidates: pixels with a depth within ``max_range_m`` whose height above the road the camera's
   nominal pose predicts lies within ``prior_tol_m`` (+ 3 sigma of the height's noise); at most
   ``max_points`` of them, taken on a regular stride (deterministic);
2. RANSAC (``iterations`` 3-point planes, each within ``max_tilt_deg`` of the nominal road's
   normal): the plane with the most inliers, a point being an inlier within ``inlier_m`` + 2 sigma
   of its height's noise;
3. a least-squares plane through those inliers, refitted ``refits`` times to the points within 3
   robust sigma (1.4826 MAD) of the last plane, plus 2 sigma of their height's noise.
The fit is used when at least ``min_inliers`` points and ``min_share`` of the candidates support it;
otherwise the nominal road stands (the frame is counted as ``road_fit_failed``, never silently).
The result is a world-to-camera pose (:attr:`RoadFit.T`) whose z = 0 plane is the fitted road: the
depth step's heights are then heights above that plane.

The sensor's noise: :class:`DepthNoise`, sigma_z(z) = a + b z + c z^2 (m), the sensor's spec as a car
knows it (vcfusion.fusion.sensors.SensorModel.noise gives it for each model); the height of a road
point at depth z errs by about sigma_z(z) h / z (h: the camera's height above the road).
"""

from __future__ import annotations

import time as wallclock
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class DepthNoise:
    """sigma_z(z) = a + b z + c z^2, m (0: exact depth)."""

    a: float = 0.0
    b: float = 0.0
    c: float = 0.0
    mixed_edges: bool = False  # pixels straddling a depth edge read a mix of both surfaces (ToF)
    # a stereo pair's disparity model, for :meth:`reading` (0: not a stereo pair): f B (px m), the
    # per-pixel disparity noise (px) and the smallest disparity it matches (px; below it a hole)
    focal_baseline_px_m: float = 0.0
    disparity_noise_px: float = 0.0
    min_disparity_px: float = 0.0

    @property
    def exact(self) -> bool:
        return self.a == 0 and self.b == 0 and self.c == 0

    def sigma(self, z):
        # one depth (the gate's per-box test) as a float32 scalar: the same single-precision
        # operations as an array's at a fraction of its overhead
        z = np.float32(z) if isinstance(z, (float, int, np.floating, np.integer)) else np.asarray(z, np.float32)
        return np.float32(self.a) + np.float32(self.b) * z + np.float32(self.c) * z * z

    def reading(self, z) -> np.ndarray:
        """The median depth the sensor reads from a surface at depth `z` (m), float64: `z` itself
        but for a stereo pair near its smallest disparity, whose draws below it are holes (filled
        from the neighbours that were matched): the median of the disparities that remain,
        mu + s Phi^-1((1 + Phi(a)) / 2) with mu = f B / z, s the disparity noise and
        a = (min_disparity - mu) / s, read as depth f B / d. Nearer than the truth: at 0.62 px
        (88 m with f B = 55 px m), 0.25 px noise and a 0.5 px floor, 76 m. Beyond the pair's range
        (mu below the floor: sensors.stereo_depth gives no depth there) nothing is read: nan."""
        z = np.asarray(z, np.float64)
        if self.focal_baseline_px_m <= 0 or self.disparity_noise_px <= 0 or self.min_disparity_px <= 0:
            return z
        from scipy.special import ndtr, ndtri

        fb, s = self.focal_baseline_px_m, self.disparity_noise_px
        with np.errstate(divide="ignore", invalid="ignore"):
            mu = fb / z
            d = mu + s * ndtri((1.0 + ndtr((self.min_disparity_px - mu) / s)) / 2.0)
            return np.where(np.isfinite(z) & (z > 0), np.where(mu >= self.min_disparity_px, fb / d, np.nan), z)

    def scaled(self, k: float) -> "DepthNoise":
        """The error of a filtered image: the sigma scaled by `k`; the per-pixel disparity model
        (what is matched at all) stays."""
        return replace(self, a=self.a * k, b=self.b * k, c=self.c * k)


@dataclass(frozen=True)
class RoadFitParams:
    max_range_m: float = 35.0  # candidates nearer than this (far road points carry the most noise)
    # within this of the nominal road (+ 3 sigma): a 1 deg pose error moves a road point 35 m ahead by 0.6 m
    prior_tol_m: float = 0.7
    max_points: int = 2000
    grid_step: int = 2
    iterations: int = 60
    max_tilt_deg: float = 4.0  # a plane tilted more than this from the nominal road is not the road
    inlier_m: float = 0.04  # RANSAC's inlier distance (+ 2 sigma of the height's noise)
    refits: int = 3  # least-squares refits, each on the points within 3 robust sigma of the last plane
    min_inlier_m: float = 0.005  # ... but no tighter than this (the depth images' 1 cm steps)
    min_inliers: int = 200
    min_share: float = 0.3


@dataclass(frozen=True)
class RoadFit:
    T: np.ndarray  # (4, 4) world-to-camera pose whose z = 0 plane is the road (the nominal pose when not ok)
    ok: bool
    inliers: int
    candidates: int
    tilt_deg: float  # angle between the fitted and the nominal road normal
    height_m: float  # the camera's height above the fitted road
    ms: float


def _plane_pose(T_prior: np.ndarray, n: np.ndarray, c0: float) -> np.ndarray:
    """A world-to-camera pose whose world z axis (in camera coordinates) is `n` and whose z = 0
    plane is n . X + c0 = 0 (camera coordinates): the nominal pose turned by the least rotation."""
    up = T_prior[:3, 2] / np.linalg.norm(T_prior[:3, 2])
    axis = np.cross(up, n)
    s, c = np.linalg.norm(axis), float(up @ n)
    if s < 1e-12:
        R_turn = np.eye(3)
    else:
        k = axis / s
        Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R_turn = np.eye(3) + s * Kx + (1 - c) * Kx @ Kx
    T = np.eye(4)
    T[:3, :3] = R_turn @ T_prior[:3, :3]
    T[:3, 3] = -c0 * n
    return T


def fit_road_plane(depth: np.ndarray, K: np.ndarray, T_prior: np.ndarray, noise: DepthNoise = DepthNoise(),
                   params: RoadFitParams = RoadFitParams()) -> RoadFit:
    """The road plane of one depth image (module doc); deterministic."""
    started = wallclock.perf_counter()
    T_prior = np.asarray(T_prior, float)
    K = np.asarray(K, float)
    z = np.asarray(depth, np.float32)
    H, W = z.shape
    up = T_prior[:3, 2]
    Kinv = np.linalg.inv(K)
    cam_h = float(-(up @ T_prior[:3, 3]))  # camera height above the nominal road
    # candidate pixels: those with a depth in range, at most 4 max_points of them on a regular stride
    # (a sparse scan's returns are all taken)
    # (a dense image is read on every other row and column: a quarter of the work, as good a fit)
    step = params.grid_step if np.isfinite(z[::8, ::8]).mean() > 0.5 else 1
    zg = z[::step, ::step]
    flat = np.flatnonzero((zg > 0) & (zg < params.max_range_m))  # nan and inf compare false
    if len(flat) > 4 * params.max_points:
        flat = flat[np.linspace(0, len(flat) - 1, 4 * params.max_points).astype(np.int64)]
    vs, us = np.divmod(flat, zg.shape[1])
    zs = zg.ravel()[flat].astype(np.float64)
    vs, us = vs.astype(np.float64) * step, us.astype(np.float64) * step
    rays = np.stack([us, vs, np.ones_like(us)], axis=1) @ Kinv.T
    X = rays * zs[:, None]
    sigma_h = noise.sigma(zs).astype(np.float64) * max(cam_h, 0.5) / np.maximum(zs, 1.0)
    prior_h = X @ up + cam_h
    near = np.abs(prior_h) < params.prior_tol_m + 3 * sigma_h
    X, sigma_h = X[near], sigma_h[near]
    if len(X) > params.max_points:
        keep = np.linspace(0, len(X) - 1, params.max_points).astype(int)
        X, sigma_h = X[keep], sigma_h[keep]
    n_cand = len(X)

    def failed():
        return RoadFit(T_prior, False, 0, n_cand, 0.0, cam_h, 1000 * (wallclock.perf_counter() - started))

    if n_cand < max(params.min_inliers, 3):
        return failed()
    thr = params.inlier_m + 2 * sigma_h
    rng = np.random.default_rng(0)
    triples = rng.integers(0, n_cand, size=(params.iterations, 3))
    p0, p1, p2 = X[triples[:, 0]], X[triples[:, 1]], X[triples[:, 2]]
    normals = np.cross(p1 - p0, p2 - p0)
    norms = np.linalg.norm(normals, axis=1)
    good = norms > 1e-9
    normals[good] /= norms[good, None]
    normals *= np.sign(normals @ up)[:, None]  # pointing up, as the nominal normal
    cos_max = np.cos(np.radians(params.max_tilt_deg))
    good &= normals @ up > cos_max
    if not good.any():
        return failed()
    normals, p0 = normals[good], p0[good]
    offsets = -np.einsum("ij,ij->i", normals, p0)
    residual = np.abs(X @ normals.T + offsets[None, :])  # (n, planes)
    counts = (residual < thr[:, None]).sum(axis=0)
    best = int(np.argmax(counts))
    inliers = residual[:, best] < thr
    if inliers.sum() < params.min_inliers or inliers.mean() < params.min_share:
        return failed()
    n, c0 = normals[best], float(offsets[best])
    for _ in range(params.refits):
        P = X[inliers]
        centre = P.mean(axis=0)
        _, _, vt = np.linalg.svd(P - centre, full_matrices=False)
        n = vt[-1] * np.sign(vt[-1] @ up)
        c0 = float(-n @ centre)
        # tighter: the points within 3 robust sigma of this plane (lane markings, kerbs and the
        # lowest parts of vehicles stand a few cm above the road: they tilted the first plane)
        r = X @ n + c0
        spread = 3 * 1.4826 * float(np.median(np.abs(r[inliers] - np.median(r[inliers]))))
        tighter = np.abs(r) < 2 * sigma_h + max(spread, params.min_inlier_m)
        if tighter.sum() < params.min_inliers:
            break
        inliers = tighter
    if n @ up < cos_max:
        return failed()
    tilt = float(np.degrees(np.arccos(np.clip(n @ up, -1.0, 1.0))))
    return RoadFit(_plane_pose(T_prior, n, c0), True, int(inliers.sum()), n_cand, tilt, c0,
                   1000 * (wallclock.perf_counter() - started))
