"""Depth evaluation (the paper's Algorithm 1): one distance per detected box from a depth image.

For each box:
1. shrink it about its centre by the resize threshold ``th`` (each side is multiplied by ``th``:
   0.8 gives a box 20% narrower and 20% shorter), so that the samples most likely fall on the
   vehicle and not on the road or sky around it;
2. keep the lower quarter of the shrunk box (the vehicle's rear face, nearest the camera);
3. draw ``n`` pixel positions uniformly in that area (a seeded NumPy Generator) and reduce their
   depths with the mean (the paper) or the median (robust to samples that miss the vehicle).

Box coordinates follow the project's pixel-centre convention (integer coordinates at pixel
centres; pixel c covers [c - 0.5, c + 0.5)). Depth images are metric camera-Z (float32 metres). Samples that fall on sky or on pixels without
a depth (``inf``, ``nan`` or ``<= 0``; renderers write 0 or inf for "nothing hit") are ignored.
A box whose samples are all invalid gets ``nan`` (the matchers treat it as "no depth").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

Reducer = Literal["mean", "median"]


@dataclass(frozen=True)
class DepthEvalParams:
    th: float = 0.8  # box resize threshold (side scale), 0 < th <= 1
    n: int = 30  # sample points per box
    reducer: Reducer = "mean"  # the paper averages; "median" is the robust option

    def __post_init__(self):
        if not 0.0 < self.th <= 1.0:
            raise ValueError(f"th: expected 0 < th <= 1, got {self.th}")
        if self.n < 1:
            raise ValueError(f"n: expected at least one sample point, got {self.n}")
        if self.reducer not in ("mean", "median"):
            raise ValueError(f"reducer: expected 'mean' or 'median', got {self.reducer!r}")


def _shrunk(boxes: np.ndarray, th: float) -> np.ndarray:
    """Each box shrunk by ``th`` about its centre, (N, 4) x1, y1, x2, y2."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    cx, cy = (b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2
    w, h = (b[:, 2] - b[:, 0]) * th, (b[:, 3] - b[:, 1]) * th
    return np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)


def sampling_areas(boxes: np.ndarray, th: float) -> np.ndarray:
    """The lower-quarter area of each box shrunk by ``th`` about its centre, (N, 4) x1, y1, x2, y2."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    a = _shrunk(b, th)
    a[:, 1] = a[:, 3] - (b[:, 3] - b[:, 1]) * th / 4
    return a


def _checked_depth(depth: np.ndarray) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth: expected a 2-D depth image (H, W), got shape {depth.shape}")
    return depth


def _depths_at(depth: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Depth at image positions (any shape), nan for sky / invalid pixels; positions outside the
    image are clamped to its border."""
    height, width = depth.shape
    # pixel-centre convention (OpenCV, the renderer's boxes): pixel c spans [c - 0.5, c + 0.5)
    cols = np.clip(np.floor(xs + 0.5).astype(np.int64), 0, width - 1)
    rows = np.clip(np.floor(ys + 0.5).astype(np.int64), 0, height - 1)
    samples = depth[rows, cols].astype(np.float64)
    samples[~(np.isfinite(samples) & (samples > 0))] = np.nan
    return samples


def sample_box_depths(
    depth: np.ndarray,
    boxes: np.ndarray,
    rng: np.random.Generator,
    params: DepthEvalParams = DepthEvalParams(),
) -> np.ndarray:
    """The sampled depths of Algorithm 1 before averaging, (N, n); nan for sky / invalid pixels."""
    depth = _checked_depth(depth)
    areas = sampling_areas(boxes, params.th)
    n_boxes = len(areas)
    if n_boxes == 0:
        return np.zeros((0, params.n))
    # All boxes at once: uniform positions in each area.
    u = rng.random((n_boxes, params.n))
    v = rng.random((n_boxes, params.n))
    xs = areas[:, [0]] + u * (areas[:, [2]] - areas[:, [0]])
    ys = areas[:, [1]] + v * (areas[:, [3]] - areas[:, [1]])
    return _depths_at(depth, xs, ys)


def reduce_depth_samples(samples: np.ndarray, reducer: Reducer = "mean") -> np.ndarray:
    """One distance per box from its samples (nan where none is valid)."""
    samples = np.asarray(samples, dtype=np.float64)
    out = np.full(len(samples), np.nan)
    valid = np.isfinite(samples).any(axis=1) if samples.size else np.zeros(len(samples), bool)
    if valid.any():
        reduce = np.nanmean if reducer == "mean" else np.nanmedian
        out[valid] = reduce(samples[valid], axis=1)
    return out


def evaluate_box_depths(
    depth: np.ndarray,
    boxes: np.ndarray,
    rng: np.random.Generator,
    params: DepthEvalParams = DepthEvalParams(),
) -> np.ndarray:
    """Algorithm 1: distance (m) of each box from the camera, (N,); nan where no valid depth was sampled."""
    return reduce_depth_samples(sample_box_depths(depth, boxes, rng, params), params.reducer)


def grid_box_depths(depth: np.ndarray, boxes: np.ndarray, th: float, nx: int = 6, ny: int = 5) -> np.ndarray:
    """Depths on a regular nx x ny grid over each whole box shrunk by ``th`` (no randomness), (N, nx*ny);
    nan for sky / invalid pixels. Not part of Algorithm 1 (see :func:`joint_depth_samples`)."""
    depth = _checked_depth(depth)
    a = _shrunk(boxes, th)
    fx = (np.arange(nx) + 0.5) / nx  # cell centres, 0..1 of the shrunk box
    fy = (np.arange(ny) + 0.5) / ny
    xs = a[:, 0, None, None] + (a[:, 2] - a[:, 0])[:, None, None] * fx[None, None, :]  # (N, 1, nx)
    ys = a[:, 1, None, None] + (a[:, 3] - a[:, 1])[:, None, None] * fy[None, :, None]  # (N, ny, 1)
    xs, ys = np.broadcast_arrays(xs, ys)
    return _depths_at(depth, xs, ys).reshape(len(a), nx * ny)


def joint_depth_samples(depth: np.ndarray, boxes: np.ndarray, samples: np.ndarray, th: float) -> np.ndarray:
    """What the joint matcher reads per box: Algorithm 1's lower-quarter `samples` plus the
    :func:`grid_box_depths` over the whole box, because a vehicle whose lower part a nearer one
    hides (a truck behind a car) shows its own depth only higher up in its box."""
    return np.concatenate([samples, grid_box_depths(depth, boxes, th)], axis=1)
