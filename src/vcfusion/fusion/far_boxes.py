"""Box sides from the image where depth cannot place them: a small CNN that reads an RGB crop
around a detector's box and regresses where the vehicle's four sides are.

The depth step (vcfusion.fusion.fuse.depth_step) keeps the detector's box where the depth cannot
support a decision (the noise gate: a stereo pair's depth 35-100 m away is metres off; too little
measured depth in the box). Those boxes are far and small (8-40 px) and the detector's sides are 1-3
px off, enough to miss IoU 0.7. :class:`BoxHead` moves each side of such a box by what it reads in
the image around it, never by more than ``max_shift`` of the box's size.

Crop: the box grown by ``context`` of its width / height per side plus ``pad_px``, warped
(bilinear, edges replicated) to ``crop_px`` x ``crop_px``; the net sees that window's RGB / 255.
Output: the four sides' offsets (x1, y1, x2, y2) in units of the box's width (x) and height (y).
Boxes in the detector's pixel-centre convention (x1, y1, x2, y2 px). The weights file holds the
state dict and these settings; trained by :func:`train_box_head` on rendered training scenes only
(docs/model-cards.md, ``far_box_head.pt``).
"""

from __future__ import annotations

import functools
import time as wallclock
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import nn

from vcfusion.errors import InputError
from vcfusion.resources import default_box_head_path  # noqa: F401  (the shipped head; callers import it here)


class BoxHeadFileError(InputError):
    """A box-head weights file that cannot be read as one; the message names the file."""


@dataclass(frozen=True)
class CropSpec:
    crop_px: int = 48  # side of the warped crop (px); a 10-40 px far box is up-sampled
    context: float = 0.5  # the window: the box grown by this share of its width / height per side
    pad_px: float = 3.0  # ... plus this (px): a 6 px box still shows the road and the car beside it


class BoxHeadNet(nn.Module):
    """Four stride-2 3 x 3 convolutions (16-32-64-64 channels) and two linear layers: 48 x 48 x 3 -> 4."""

    def __init__(self, crop_px: int = 48):
        super().__init__()
        chans = [3, 16, 32, 64, 64]
        layers = []
        for a, b in zip(chans[:-1], chans[1:]):
            layers += [nn.Conv2d(a, b, 3, stride=2, padding=1), nn.BatchNorm2d(b), nn.ReLU(inplace=True)]
        self.features = nn.Sequential(*layers)
        side = crop_px // 16
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(64 * side * side, 128), nn.ReLU(inplace=True),
                                  nn.Linear(128, 4))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x))


def crop_windows(boxes: np.ndarray, spec: CropSpec) -> np.ndarray:
    """(N, 4) the crop window of each box, pixel-edge coordinates x0, y0, x1, y1."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    w, h = np.maximum(b[:, 2] - b[:, 0], 1.0), np.maximum(b[:, 3] - b[:, 1], 1.0)
    gx, gy = spec.context * w + spec.pad_px, spec.context * h + spec.pad_px
    return np.stack([b[:, 0] + 0.5 - gx, b[:, 1] + 0.5 - gy, b[:, 2] + 0.5 + gx, b[:, 3] + 0.5 + gy], axis=1)


def box_crops(image: np.ndarray, boxes: np.ndarray, spec: CropSpec, raw: bool = False) -> np.ndarray:
    """(N, 3, crop_px, crop_px) float32 in [0, 1] (uint8 0-255 with `raw`): each box's window of the
    RGB image."""
    n, s = len(boxes), spec.crop_px
    out = np.zeros((n, 3, s, s), np.uint8 if raw else np.float32)
    for i, (x0, y0, x1, y1) in enumerate(crop_windows(boxes, spec)):
        sx, sy = s / (x1 - x0), s / (y1 - y0)
        # output pixel centre (i + 0.5) / s x (x1 - x0) + x0 = input coordinate u + 0.5
        M = np.array([[sx, 0.0, -x0 * sx + 0.5 * sx - 0.5], [0.0, sy, -y0 * sy + 0.5 * sy - 0.5]])
        crop = cv2.warpAffine(image, M, (s, s), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out[i] = crop.transpose(2, 0, 1) if raw else crop.transpose(2, 0, 1) / 255.0
    return out


def _sizes(b: np.ndarray) -> np.ndarray:
    w, h = np.maximum(b[:, 2] - b[:, 0], 1.0), np.maximum(b[:, 3] - b[:, 1], 1.0)
    return np.stack([w, h, w, h], axis=1)


def side_offsets(boxes: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """(N, 4) the targets' sides minus the boxes', in units of the boxes' width / height."""
    b, t = np.asarray(boxes, np.float64).reshape(-1, 4), np.asarray(targets, np.float64).reshape(-1, 4)
    size = _sizes(b)
    return (t - b) / size


def apply_offsets(boxes: np.ndarray, offsets: np.ndarray, max_shift: float) -> np.ndarray:
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    size = _sizes(b)
    out = b + np.clip(offsets, -max_shift, max_shift) * size
    # a side never crosses the opposite one: at least 1 px wide / high
    out[:, 2] = np.maximum(out[:, 2], out[:, 0] + 1.0)
    out[:, 3] = np.maximum(out[:, 3], out[:, 1] + 1.0)
    return out


class BoxHead:
    """The trained head: :meth:`refine` moves the sides of the given boxes to the vehicle the image
    shows in each box's window."""

    def __init__(self, net: BoxHeadNet, spec: CropSpec, max_shift: float, max_height_px: float,
                 meta: dict | None = None):
        # max_shift: a side moves by at most this share of the box's width / height; max_height_px:
        # the tallest box it was trained on (taller boxes are not given to it)
        self.net, self.spec, self.meta = net.eval(), spec, meta or {}
        self.max_shift, self.max_height_px = max_shift, max_height_px

    @staticmethod
    def load(path) -> "BoxHead":
        return _load(str(Path(path).resolve()))

    def offsets(self, image: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """(N, 4) the sides' offsets, the mean of the crop's and its mirror image's (one batch)."""
        boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
        if len(boxes) == 0:
            return np.zeros((0, 4))
        x = box_crops(image, boxes, self.spec)
        x = torch.from_numpy(np.concatenate([x, x[..., ::-1]]))  # the mirror's window is the box's, flipped
        # one thread: a batch of a few 48 px crops costs about a millisecond; a thread pool's hand-offs
        # cost more than that on a loaded CPU (development stereo frames: p90 155 ms of CPU time with 2)
        threads = torch.get_num_threads()
        try:
            torch.set_num_threads(1)
            with torch.inference_mode():
                out = self.net(x).double().numpy()
        finally:
            torch.set_num_threads(threads)
        n = len(boxes)
        mirrored = out[n:][:, [2, 1, 0, 3]] * [-1.0, 1.0, -1.0, 1.0]  # its left side is the box's right
        return (out[:n] + mirrored) / 2.0

    def refine(self, image: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """(N, 4) the boxes with their sides moved (by at most max_shift of the box's size each)."""
        boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
        if len(boxes) == 0:
            return boxes.copy()
        return apply_offsets(boxes, self.offsets(image, boxes), self.max_shift)


@functools.lru_cache(maxsize=4)
def _load(path: str) -> BoxHead:
    if not Path(path).is_file():
        raise BoxHeadFileError(f"{path}: box-head weights not found")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the same error for the caller
        raise BoxHeadFileError(f"{path}: not a box-head weights file ({exc})") from None
    if not isinstance(blob, dict) or not {"state_dict", "spec", "max_shift", "max_height_px"} <= set(blob):
        raise BoxHeadFileError(f"{path}: expected a dict with state_dict, spec, max_shift and max_height_px")
    spec = CropSpec(**blob["spec"])
    net = BoxHeadNet(spec.crop_px)
    try:
        net.load_state_dict(blob["state_dict"])
    except RuntimeError as exc:
        raise BoxHeadFileError(f"{path}: state_dict does not fit BoxHeadNet({spec.crop_px}): {exc}") from None
    return BoxHead(net, spec, float(blob["max_shift"]), float(blob["max_height_px"]), blob.get("meta"))


# ---------------------------------------------------------------------------------------------
# training


def jittered(gt: np.ndarray, rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """(n, 4) boxes around one ground-truth box: each side moved by N(0, sigma) of its size, plus a
    common shift and scale (the detector's far boxes: sides 1-3 px off on 8-40 px)."""
    g = np.asarray(gt, np.float64)
    w, h = max(g[2] - g[0], 1.0), max(g[3] - g[1], 1.0)
    side = rng.normal(0.0, sigma, (n, 4)) * [w, h, w, h]
    shift = rng.normal(0.0, sigma, (n, 2)) * [w, h]
    out = g + side + np.c_[shift, shift]
    out[:, 2] = np.maximum(out[:, 2], out[:, 0] + 1.0)
    out[:, 3] = np.maximum(out[:, 3], out[:, 1] + 1.0)
    return out


@dataclass
class BoxSamples:
    crops: np.ndarray  # (N, 3, s, s) uint8
    offsets: np.ndarray  # (N, 4) float32: ground truth's sides minus the box's, in box widths / heights


def training_samples(images, gt_boxes, detector_boxes, spec: CropSpec, rng: np.random.Generator,
                     jitters: int = 6, sigma: float = 0.12, min_side_px: float = 4.0,
                     max_height_px: float = 120.0, match_iou: float = 0.4) -> BoxSamples:
    """Crops and their side offsets from images with ground-truth boxes: each ground-truth box (at
    least min_side_px wide and high, at most max_height_px high) with `jitters` jittered boxes and
    the detector's boxes matched to it (IoU >= match_iou, the detector's own errors)."""
    from vcfusion.fusion.matching import box_iou

    crops, offsets = [], []
    for image, gts, dets in zip(images, gt_boxes, detector_boxes):
        gts = np.asarray(gts, np.float64).reshape(-1, 4)
        keep = ((gts[:, 2] - gts[:, 0] >= min_side_px) & (gts[:, 3] - gts[:, 1] >= min_side_px)
                & (gts[:, 3] - gts[:, 1] <= max_height_px))
        boxes, targets = [], []
        dets = np.asarray(dets, np.float64).reshape(-1, 4)
        if len(dets) and len(gts):
            iou = box_iou(dets, gts)
            best = iou.argmax(axis=1)
            for j, g in enumerate(best):
                if iou[j, g] >= match_iou and keep[g]:
                    boxes.append(dets[j])
                    targets.append(gts[g])
        for g in gts[keep]:
            boxes.extend(jittered(g, rng, jitters, sigma))
            targets.extend([g] * jitters)
            boxes.append(g)
            targets.append(g)
        if boxes:
            boxes, targets = np.array(boxes), np.array(targets)
            crops.append(box_crops(image, boxes, spec, raw=True))
            offsets.append(side_offsets(boxes, targets))
    c, o = np.concatenate(crops), np.concatenate(offsets).astype(np.float32)
    return BoxSamples(c, o)


def train_box_head(samples: BoxSamples, spec: CropSpec, epochs: int = 12, batch_size: int = 128,
                   lr: float = 2e-3, seed: int = 0, max_shift: float = 0.35, max_height_px: float = 120.0,
                   threads: int = 2,
                   progress: bool = True, meta: dict | None = None) -> tuple[BoxHead, dict]:
    """Smooth-L1 on the side offsets (AdamW, one-cycle), random horizontal flips (x1 and x2 swap)."""
    torch.manual_seed(seed)
    torch.set_num_threads(threads)
    rng = np.random.default_rng(seed)
    net = BoxHeadNet(spec.crop_px)
    n = len(samples.offsets)
    steps = epochs * max(1, n // batch_size)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps)
    X, Y = torch.from_numpy(samples.crops), torch.from_numpy(samples.offsets)
    t0, step, losses = wallclock.perf_counter(), 0, []
    net.train()
    for epoch in range(epochs):
        order = rng.permutation(n)
        for k in range(n // batch_size):
            idx = torch.from_numpy(order[k * batch_size:(k + 1) * batch_size])
            x, y = X[idx].float() / 255.0, Y[idx].clone()
            flip = torch.from_numpy(rng.random(len(idx)) < 0.5)
            if flip.any():
                x[flip] = x[flip].flip(-1)
                y[flip] = y[flip][:, [2, 1, 0, 3]] * torch.tensor([-1.0, 1.0, -1.0, 1.0])
            loss = nn.functional.smooth_l1_loss(net(x), y, beta=0.02)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            step += 1
            losses.append(float(loss.detach()))
        if progress:
            print(f"epoch {epoch + 1}/{epochs}: loss {np.mean(losses[-max(1, n // batch_size):]):.4f} "
                  f"({wallclock.perf_counter() - t0:.0f} s)", flush=True)
    info = {"samples": n, "epochs": epochs, "steps": step, "final_loss": float(np.mean(losses[-50:])),
            "train_s": wallclock.perf_counter() - t0, **(meta or {})}
    return BoxHead(net.eval(), spec, max_shift, max_height_px, info), info


def save_box_head(head: BoxHead, path) -> Path:
    from vcfusion.runio import atomic_write

    path = Path(path)
    blob = {"state_dict": head.net.state_dict(), "spec": asdict(head.spec), "max_shift": head.max_shift,
            "max_height_px": head.max_height_px, "meta": head.meta}
    atomic_write(path, lambda tmp: torch.save(blob, tmp))
    return path
