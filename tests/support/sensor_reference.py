"""Reference (whole-image numpy) versions of the depth sensor models' compiled parts: the kernels in
vcfusion.fusion.sensors must give the same images, bit for bit, from the same draws
(tests/fusion/test_sensor_kernels.py)."""

from __future__ import annotations

import numpy as np

from vcfusion.fusion.sensors import DepthSensorParams, _grey_blurs


def stereo_depth_reference(depth: np.ndarray, focal_px: float, p: DepthSensorParams, rng: np.random.Generator,
                           image: np.ndarray | None = None) -> np.ndarray:
    """vcfusion.fusion.sensors.stereo_depth as whole-image array expressions: the definition its
    kernel is tested against."""
    z = np.asarray(depth, np.float32)
    fb = np.float32(focal_px * p.baseline_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.where(np.isfinite(z) & (z > 0), fb / z, np.float32(0.0)).astype(np.float32)
    e = d - np.arange(z.shape[1], dtype=np.float32)[None, :]
    suffix = np.maximum.accumulate(e[:, ::-1], axis=1)[:, ::-1]
    right_of = np.concatenate([suffix[:, 1:], np.full((z.shape[0], 1), -np.inf, np.float32)], axis=1)
    occluded = right_of > e + 0.5
    measured = d + rng.normal(0.0, p.disparity_noise_px, size=d.shape).astype(np.float32)
    hole = occluded | (measured < p.min_disparity_px) | (d < p.min_disparity_px)
    if image is not None and p.texture_min > 0:
        mean, sq = _grey_blurs(image)  # the grey level's 5 x 5 standard deviation
        hole |= np.sqrt(np.maximum(sq - mean * mean, 0.0)) < p.texture_min
    with np.errstate(divide="ignore", invalid="ignore"):
        out = fb / measured
    return np.where(hole, np.float32(np.nan), out).astype(np.float32)

