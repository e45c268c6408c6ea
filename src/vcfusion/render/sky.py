"""The sky behind everything: a gradient from a pale, hazy horizon to a deeper blue overhead.

The renderer clears to one colour (the depth +inf, instance code 0 marks sky pixels) and then
paints the sky pixels with this gradient, computed from each pixel's view ray elevation; the
shader uses the same gradient for what paint and glass reflect (``sky()`` in
``shaders/lambert.frag``, constants checked equal by a test). At about 25 degrees up the sky has
the colour :data:`vcfusion.render.meshes.SKY`.
"""

from __future__ import annotations

import numpy as np

from vcfusion.render.meshes import SKY

HORIZON = (0.8, 0.85, 0.9)
ZENITH = (0.38, 0.55, 0.84)


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def sky_colour(sin_elevation: np.ndarray) -> np.ndarray:
    """RGB in 0..1 (..., 3) of the sky seen along directions with the given sine of elevation (>= 0 above the horizon)."""
    s = np.clip(np.asarray(sin_elevation, dtype=np.float32), 0.0, 1.0)[..., None]
    horizon, sky, zenith = (np.asarray(c, np.float32) for c in (HORIZON, SKY, ZENITH))
    c = horizon + (sky - horizon) * _smoothstep(0.0, 0.4, s)
    return c + (zenith - c) * _smoothstep(0.4, 1.0, s)


def sky_image(K: np.ndarray, T_world_to_camera: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8 sky as this camera sees it (world z up)."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    up = np.asarray(T_world_to_camera, np.float32)[:3, 2]  # world z in camera coordinates = R[:, 2]
    s = rays @ up / np.linalg.norm(rays, axis=-1)
    return np.round(255.0 * sky_colour(s)).astype(np.uint8)
