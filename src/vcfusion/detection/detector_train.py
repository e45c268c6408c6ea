"""Training and evaluation of :class:`CenterNetLite` on a COCO-format dataset folder.

A dataset folder holds RGB images (PNG) and one COCO JSON (``annotations.json``, ``coco.json``, or
the only ``*.json`` in the folder) with ``images`` (id, file_name, width, height),
``annotations`` (image_id, bbox [x, y, w, h] px, category_id; extra keys such as vehicle_id are
ignored) and ``categories`` (id, name). Image paths are relative to the folder (or its
``images/`` subfolder).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from vcfusion.detection.detection_metrics import BoxMap, coco_map
from vcfusion.detection.detector_net import (STRIDE, CenterNetLite, DetectorFileError, DetectorModel, PostParams,
                                          TorchDetector, resize_to_input)


@dataclass
class CocoDataset:
    folder: Path
    images: list[Path]
    image_ids: list  # COCO image ids (tuples (folder index, id) when folders are combined)
    boxes: list[np.ndarray]  # per image (G, 4) xyxy px, pixel-centre convention (COCO x - 0.5)
    classes: list[np.ndarray]  # per image (G,) category ids
    class_ids: list[int]
    class_names: list[str]
    # per image: its COCO image record (camera, vehicles, family, ...) and the vehicle_id of each box
    # (None where the file has none); empty lists where not loaded
    records: list[dict] = field(default_factory=list)
    box_vehicle_ids: list[list] = field(default_factory=list)
    # per image (G,): the share of each box's vehicle that nearer objects leave visible (the
    # renderer's visible_fraction; nan where the file has none); empty where not loaded
    box_visible: list[np.ndarray] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, index) -> "CocoDataset":
        index = list(index)
        pick = lambda items: [items[i] for i in index] if items else []  # noqa: E731
        return CocoDataset(self.folder, pick(self.images), pick(self.image_ids), pick(self.boxes), pick(self.classes),
                           self.class_ids, self.class_names, pick(self.records), pick(self.box_vehicle_ids),
                           pick(self.box_visible))

    def ground_truth(self) -> dict:
        return {iid: (b, c) for iid, b, c in zip(self.image_ids, self.boxes, self.classes)}

    def scenes(self) -> list[tuple[str, object]]:
        """Per image, the scene it shows: a seed of a folder (`vcfusion render` writes several frames
        per seed), else the image file itself (one folder listed twice: the same scenes)."""
        records = self.records or [{} for _ in self.images]
        files = [Path(image).resolve() for image in self.images]
        return [(str(file.parent), record.get("seed", file.name)) for file, record in zip(files, records)]


def _find_json(folder: Path) -> Path:
    for name in ("annotations.json", "coco.json"):
        if (folder / name).is_file():
            return folder / name
    found = sorted(folder.glob("*.json"))
    if len(found) != 1:
        raise DetectorFileError(f"{folder}: expected annotations.json, coco.json or exactly one *.json COCO file, "
                                f"found {len(found)} json files")
    return found[0]


def _coco_int(value, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise DetectorFileError(f"{where}: expected an integer id, got {value!r}")
    try:
        number = float(value)
    except ValueError:
        raise DetectorFileError(f"{where}: expected an integer id, got {value!r}") from None
    if not number.is_integer():
        raise DetectorFileError(f"{where}: expected an integer id, got {value!r}")
    return int(number)


def load_coco(folder) -> CocoDataset:
    return _read_coco(folder)[0]


def _read_coco(folder) -> tuple[CocoDataset, dict]:
    """The dataset and the checked COCO object it was read from, its ids as integers (an image's
    ``id``, an annotation's ``image_id``, a category's ``id``: a 5.0 or "5" is 5)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DetectorFileError(f"{folder}: dataset folder not found")
    path = _find_json(folder)
    try:
        coco = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DetectorFileError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(coco, dict):
        raise DetectorFileError(f"{path}: expected a COCO object with images, annotations and categories")
    for key in ("images", "annotations", "categories"):
        if not isinstance(coco.get(key), list):
            raise DetectorFileError(f"{path}: {key}: expected a list")
        for k, item in enumerate(coco[key]):
            if not isinstance(item, dict):
                raise DetectorFileError(f"{path}: {key}[{k}]: expected an object, got {item!r}")
    for k, cat in enumerate(coco["categories"]):
        cat["id"] = _coco_int(cat.get("id"), f"{path}: categories[{k}].id")
    cats = sorted(coco["categories"], key=lambda c: c["id"])
    if not cats:
        raise DetectorFileError(f"{path}: categories: expected at least one category")
    class_ids = [c["id"] for c in cats]
    image_ids = set()
    for k, img in enumerate(coco["images"]):
        iid = _coco_int(img.get("id"), f"{path}: images[{k}].id")
        if iid in image_ids:  # the second image got the first one's boxes, and its own were lost
            raise DetectorFileError(f"{path}: images[{k}].id: {iid} is the id of an earlier image; expected "
                                    "one id per image")
        image_ids.add(iid)
        img["id"] = iid  # as read from here on (the records keep it)
    per_image: dict[int, list] = {}
    vids: dict[int, list] = {}
    visible: dict[int, list] = {}
    for k, ann in enumerate(coco["annotations"]):
        bbox = ann.get("bbox")
        if not (isinstance(bbox, list) and len(bbox) == 4) or ann.get("category_id") not in class_ids:
            raise DetectorFileError(f"{path}: annotations[{k}]: expected bbox [x, y, w, h] and a category_id "
                                    f"among {class_ids}")
        if ann.get("iscrowd"):
            # COCOeval ignores detections on a crowd region; read as one vehicle it would score them wrong
            raise DetectorFileError(f"{path}: annotations[{k}]: iscrowd: crowd regions are not supported; expected "
                                    "one annotation per vehicle (iscrowd 0 or absent)")
        try:
            x, y, w, h = map(float, bbox)
        except (TypeError, ValueError):
            raise DetectorFileError(f"{path}: annotations[{k}].bbox: expected four numbers, got {bbox!r}") from None
        if not np.isfinite([x, y, w, h]).all() or w < 0 or h < 0:  # dropped silently before
            raise DetectorFileError(f"{path}: annotations[{k}].bbox: expected [x, y, width, height] with finite "
                                    f"values and width, height >= 0, got {bbox!r}")
        image_id = _coco_int(ann.get("image_id"), f"{path}: annotations[{k}].image_id")
        if image_id not in image_ids:  # silently dropped before
            raise DetectorFileError(f"{path}: annotations[{k}].image_id: {image_id} is the id of no image")
        ann["image_id"] = image_id
        if w > 0 and h > 0:
            # COCO's pixel c spans [c, c + 1); our boxes put integer coordinates at pixel centres
            x, y = x - 0.5, y - 0.5
            per_image.setdefault(image_id, []).append((x, y, x + w, y + h, int(ann["category_id"])))
            vids.setdefault(image_id, []).append(ann.get("vehicle_id"))
            vis = ann.get("visible_fraction")
            visible.setdefault(image_id, []).append(np.nan if vis is None else float(vis))
    images, ids, boxes, classes = [], [], [], []
    for k, img in enumerate(coco["images"]):
        name = img.get("file_name")
        if not name:
            raise DetectorFileError(f"{path}: images[{k}]: expected a file_name")
        file = folder / name if (folder / name).is_file() else folder / "images" / name
        if not file.is_file():
            raise DetectorFileError(f"{path}: images[{k}].file_name: image not found: {name}")
        rows = np.array(per_image.get(img["id"], []), dtype=np.float64).reshape(-1, 5)
        images.append(file)
        ids.append(img["id"])
        boxes.append(rows[:, :4])
        classes.append(rows[:, 4].astype(np.int64))
    if not images:
        raise DetectorFileError(f"{path}: images: expected at least one image")
    return CocoDataset(folder, images, ids, boxes, classes, class_ids, [str(c.get("name", c["id"])) for c in cats],
                       list(coco["images"]), [vids.get(img["id"], []) for img in coco["images"]],
                       [np.array(visible.get(img["id"], []), float) for img in coco["images"]]), coco


def load_coco_many(folders) -> CocoDataset:
    """Several COCO folders (e.g. renders of several scenarios) as one dataset; same categories."""
    folders = [folders] if isinstance(folders, (str, Path)) else list(folders)
    parts = [load_coco(f) for f in folders]
    first = parts[0]
    for f, part in zip(folders[1:], parts[1:]):
        if part.class_ids != first.class_ids:
            raise DetectorFileError(f"{f}: categories: expected the same category ids as {folders[0]} "
                                    f"({first.class_ids}), got {part.class_ids}")
    if len(parts) == 1:
        return first
    return CocoDataset(first.folder, [p for d in parts for p in d.images],
                       [(k, i) for k, d in enumerate(parts) for i in d.image_ids],  # ids unique across folders
                       [b for d in parts for b in d.boxes], [c for d in parts for c in d.classes],
                       first.class_ids, first.class_names, [r for d in parts for r in d.records],
                       [v for d in parts for v in d.box_vehicle_ids], [v for d in parts for v in d.box_visible])


def read_rgb(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DetectorFileError(f"{path}: cannot decode image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


# ---------------------------------------------------------------------------------------------
# targets and loss


def build_targets(boxes_list, class_index_list, out_hw, num_classes):
    """Heatmaps (elliptical Gaussians, TTFNet-style sigma = 0.54 * size / 6), log sizes, offsets, mask."""
    b_n = len(boxes_list)
    h, w = out_hw
    heat = np.zeros((b_n, num_classes, h, w), np.float32)
    size = np.zeros((b_n, 2, h, w), np.float32)
    offset = np.zeros((b_n, 2, h, w), np.float32)
    mask = np.zeros((b_n, h, w), np.float32)
    ys, xs = np.mgrid[0:h, 0:w]
    for b, (boxes, cls) in enumerate(zip(boxes_list, class_index_list)):
        if len(boxes) == 0:
            continue
        order = np.argsort(-(boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]))  # small boxes win a cell
        for k in order:
            x1, y1, x2, y2 = boxes[k] / STRIDE
            bw, bh = max(x2 - x1, 1e-2), max(y2 - y1, 1e-2)
            cx, cy = (x1 + x2) / 2, (y1 + y2) / 2
            ix, iy = min(max(int(cx), 0), w - 1), min(max(int(cy), 0), h - 1)
            sx, sy = max(0.54 * bw / 6, 0.4), max(0.54 * bh / 6, 0.4)
            g = np.exp(-((xs - ix) ** 2) / (2 * sx * sx) - ((ys - iy) ** 2) / (2 * sy * sy))
            heat[b, cls[k]] = np.maximum(heat[b, cls[k]], g)
            heat[b, cls[k], iy, ix] = 1.0
            size[b, :, iy, ix] = (math.log(bw), math.log(bh))
            offset[b, :, iy, ix] = (cx - ix, cy - iy)
            mask[b, iy, ix] = 1.0
    return heat, size, offset, mask


def detection_loss(outputs, targets) -> tuple[torch.Tensor, dict]:
    hm_logits, log_size, off = outputs
    heat, size, offset, mask = targets
    pred = torch.sigmoid(hm_logits).clamp(1e-4, 1 - 1e-4)
    pos = heat.eq(1.0).float()
    n_pos = pos.sum().clamp(min=1.0)
    focal = -(torch.log(pred) * (1 - pred) ** 2 * pos
              + torch.log(1 - pred) * pred ** 2 * (1 - heat) ** 4 * (1 - pos)).sum() / n_pos
    m = mask.unsqueeze(1)
    n_obj = mask.sum().clamp(min=1.0)
    size_l1 = (F.l1_loss(log_size, size, reduction="none") * m).sum() / n_obj
    off_l1 = (F.l1_loss(off, offset, reduction="none") * m).sum() / n_obj
    total = focal + size_l1 + off_l1
    return total, {"heatmap": float(focal.detach()), "size": float(size_l1.detach()), "offset": float(off_l1.detach())}


# ---------------------------------------------------------------------------------------------
# training


@dataclass
class TrainReport:
    epochs: int
    iterations: int
    loss_history: list[float]  # mean loss per epoch
    first_losses: list[float]  # the first iterations' losses (to show the decrease)
    val: BoxMap | None
    wall_s: float
    n_train: int
    n_val: int


def _cache(ds: CocoDataset, input_wh, desc: str, progress: bool):
    """Images resized to the network input (uint8) and their boxes in input pixels."""
    images, boxes = [], []
    for path, b in tqdm(list(zip(ds.images, ds.boxes)), desc=desc, unit="img", disable=not progress, leave=False):
        rgb = read_rgb(path)
        sx, sy = input_wh[0] / rgb.shape[1], input_wh[1] / rgb.shape[0]
        images.append(resize_to_input(rgb, input_wh))
        boxes.append((b + 0.5) * np.array([sx, sy, sx, sy]))  # pixel-edge coordinates of the network input
    return np.stack(images), boxes


def _pick_device(device: str) -> str:
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def train_detector(
    data, out=None, *, epochs: int = 20, batch_size: int = 16, lr: float = 2e-3,
    input_wh: tuple[int, int] = (320, 240), widths: tuple[int, ...] = (16, 32, 64, 128, 64),
    val_fraction: float = 0.1, val_data=None, seed: int = 0, threads: int = 2, device: str = "auto",
    progress: bool = True, max_iterations: int | None = None, min_train_area: float = 16.0,
    eval_min_area: float = 100.0, init=None, checkpoint_every: int | None = None, workers: int = 0,
) -> tuple[DetectorModel, TrainReport]:
    """Train on the COCO folder(s) ``data``; write the weights atomically to ``out`` if given.
    ``init``: a weights file to start from (fine-tuning) instead of random weights; its categories,
    input size and layer widths must equal this run's. ``checkpoint_every``: also write the weights
    every that many iterations to :func:`checkpoint_path` (``out`` needed), so that a long run cut
    short still leaves a usable model and the iterations can be compared on a validation set.
    ``workers``: processes that build the batches (augmentation and targets) ahead of the model, for
    a GPU that the main thread alone cannot feed; the batches are the same for any number."""
    if checkpoint_every is not None and (checkpoint_every < 1 or out is None):
        raise ValueError(f"checkpoint_every: expected a positive number and an out path, got {checkpoint_every}")
    if input_wh[0] % 16 or input_wh[1] % 16:
        raise ValueError(f"input size: expected width and height multiples of 16, got {input_wh}")
    started = time.perf_counter()
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    if threads:
        torch.set_num_threads(threads)
    device = _pick_device(device)
    base = DetectorModel.load(init) if init is not None else None  # before the data: a bad file fails fast
    ds = load_coco_many(data)
    if val_data is not None:
        train_ds, val_ds = ds, load_coco_many(val_data)
        if val_ds.class_ids != ds.class_ids:
            raise DetectorFileError(f"{val_data}: categories: expected the training categories {ds.class_ids}")
    elif val_fraction > 0:  # any size: a single scene is refused, never trained on without a word
        train_ds, val_ds = split_by_scene(ds, val_fraction, rng)
    else:
        train_ds, val_ds = ds, None
    if val_ds is not None and not any(len(b) for b in val_ds.boxes):
        # checked before training: COCO mAP is undefined without boxes, and the trained weights were lost
        source = val_data if val_data is not None else data
        source = " ".join(map(str, [source] if isinstance(source, (str, Path)) else source))
        raise DetectorFileError(f"{source}: the validation images hold no boxes; give validation folders with "
                                "vehicles (--val), or --val-fraction 0")
    cls_index = {c: k for k, c in enumerate(ds.class_ids)}
    images, boxes = _cache(train_ds, input_wh, "load train", progress)
    classes = [np.array([cls_index[int(c)] for c in cs], np.int64) for cs in train_ds.classes]
    # boxes of a few pixels (far away or nearly hidden vehicles) are not learnable targets; measured
    # at the network input, so a folder and its resize-dataset copy train on the same boxes (in the
    # folder's pixels a 640x480 render kept 4x smaller boxes than its 320x240 copy)
    keep = [(b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) >= min_train_area for b in boxes]
    boxes = [b[k] for b, k in zip(boxes, keep)]
    classes = [c[k] for c, k in zip(classes, keep)]

    if base is not None:
        for what, theirs, ours in (("class_ids", base.class_ids, ds.class_ids),
                                   ("input_wh", tuple(base.input_wh), tuple(input_wh)),
                                   ("widths", tuple(base.widths), tuple(widths))):
            if theirs != ours:
                raise DetectorFileError(f"{init}: {what}: expected {ours} (this training run's), got {theirs}")
        model = base.model.to(device)
    else:
        model = CenterNetLite(len(ds.class_ids), tuple(widths[:4]), widths[4]).to(device)
    n = len(images)
    steps_per_epoch = max(1, math.ceil(n / batch_size))
    total_steps = epochs * steps_per_epoch if max_iterations is None else min(max_iterations, epochs * steps_per_epoch)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=total_steps, pct_start=0.15)
    out_hw = (input_wh[1] // STRIDE, input_wh[0] // STRIDE)
    history, first, step = [], [], 0
    data_list = [data] if isinstance(data, (str, Path)) else list(data)

    def meta(iterations: int, final_loss) -> dict:
        # folder names only: the weights are shipped, and a machine path means nothing elsewhere
        return {"train_data": [Path(d).name for d in data_list], "iterations": iterations, "seed": seed,
                "init": None if init is None else Path(init).name, "final_loss": final_loss,
                "n_train": len(train_ds), "n_train_boxes": sum(len(b) for b in boxes),
                "min_train_area": min_train_area, "eval_min_area": eval_min_area}

    batches = _Batches(images, boxes, classes, _batch_indices(n, batch_size, epochs, total_steps, rng), seed,
                       out_hw, len(ds.class_ids))
    loader = torch.utils.data.DataLoader(batches, batch_size=None, shuffle=False, num_workers=workers,
                                         pin_memory=device.startswith("cuda"), prefetch_factor=4 if workers else None)
    bar = tqdm(total=total_steps, desc="train detector", unit="it", disable=not progress)
    model.train()
    losses = []
    for image_u8, gain, bias, *target_arrays in loader:
        # the brightness / contrast change runs where the model runs: the batch travels as bytes
        x = image_u8.to(device, non_blocking=True).float()
        x = (x * gain.to(device) + bias.to(device)).clamp_(0, 255)
        targets = [t.to(device, non_blocking=True) for t in target_arrays]
        loss, parts = detection_loss(model(x), targets)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        opt.step()
        sched.step()
        step += 1
        losses.append(loss.item())
        if len(first) < 10:
            first.append(losses[-1])
        bar.update(1)
        bar.set_postfix(loss=f"{losses[-1]:.3f}")
        if checkpoint_every and step % checkpoint_every == 0 and step < total_steps:
            DetectorModel(model, tuple(input_wh), ds.class_ids, ds.class_names, tuple(widths),
                          meta(step, float(np.mean(losses)))).save(checkpoint_path(out, step))
        if step == total_steps or step % steps_per_epoch == 0:  # an epoch ends
            history.append(float(np.mean(losses)))
            losses = []
    bar.close()
    model.eval().cpu()
    net = DetectorModel(model, tuple(input_wh), ds.class_ids, ds.class_names, tuple(widths))
    val = (evaluate_detector(TorchDetector(net), val_ds, progress=progress, min_area=eval_min_area)
           if val_ds is not None else None)
    report = TrainReport(len(history), step, history, first, val, time.perf_counter() - started,
                         len(train_ds), 0 if val_ds is None else len(val_ds))
    net.meta = {**meta(step, history[-1] if history else None), "epochs": report.epochs,
                "n_val": report.n_val, "val_map_50": None if val is None else val.map_50,
                "val_map_50_95": None if val is None else val.map_50_95}
    if out is not None:
        net.save(Path(out))
    return net, report


def split_by_scene(ds: CocoDataset, val_fraction: float, rng) -> tuple[CocoDataset, CocoDataset]:
    """(train, validation): whole scenes drawn for validation until they hold `val_fraction` of the
    images. Split by image, consecutive frames of one seed (and the images of a folder listed
    twice) were in both: the validation figure measured frames trained on."""
    scenes = ds.scenes()
    keys = list(dict.fromkeys(scenes))
    if len(keys) < 2:
        raise DetectorFileError(f"{ds.folder}: the data holds one scene, which cannot be split into training and "
                                "validation; give validation folders (--val), or --val-fraction 0")
    of = {key: k for k, key in enumerate(keys)}
    scene_of = np.array([of[key] for key in scenes])
    size = np.bincount(scene_of, minlength=len(keys))
    want = max(1, int(round(val_fraction * len(ds))))
    chosen, n_val = [], 0
    for k in rng.permutation(len(keys)):
        if n_val >= want or len(chosen) == len(keys) - 1:  # at least one scene stays to train on
            break
        chosen.append(k)
        n_val += int(size[k])
    val = np.isin(scene_of, chosen)
    return ds.subset(np.flatnonzero(~val)), ds.subset(np.flatnonzero(val))


def _batch_indices(n: int, batch_size: int, epochs: int, total_steps: int, rng) -> list[np.ndarray]:
    """The images of each iteration: a fresh permutation per epoch, the last batch of an epoch short."""
    out: list[np.ndarray] = []
    for _ in range(epochs):
        perm = rng.permutation(n)
        out.extend(perm[k:k + batch_size] for k in range(0, n, batch_size))
        if len(out) >= total_steps:
            break
    return out[:total_steps]


class _Batches(torch.utils.data.Dataset):
    """Batch ``step`` of a training run: its images flipped at random (uint8), the brightness gain and
    bias for each, and the CenterNet targets. The random draws come from (seed, step) alone, so the
    batches do not depend on how many worker processes build them or in which order."""

    def __init__(self, images, boxes, classes, indices, seed, out_hw, num_classes):
        self.images, self.boxes, self.classes, self.indices = images, boxes, classes, indices
        self.seed, self.out_hw, self.num_classes = seed, out_hw, num_classes

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, step: int):
        idx = self.indices[step]
        rng = np.random.default_rng((self.seed, step))
        width = self.images.shape[2]
        flip = rng.random(len(idx)) < 0.5
        batch = self.images[idx]
        batch[flip] = batch[flip, :, ::-1]
        b_boxes = [self.boxes[i].copy() for i in idx]
        for j in np.flatnonzero(flip):
            b_boxes[j][:, [0, 2]] = width - b_boxes[j][:, [2, 0]]
        gain = rng.uniform(0.7, 1.3, (len(idx), 1, 1, 1)).astype(np.float32)
        bias = rng.uniform(-25, 25, (len(idx), 1, 1, 1)).astype(np.float32)
        targets = build_targets(b_boxes, [self.classes[i] for i in idx], self.out_hw, self.num_classes)
        image = torch.from_numpy(np.ascontiguousarray(batch.transpose(0, 3, 1, 2)))
        return (image, torch.from_numpy(gain), torch.from_numpy(bias), *(torch.from_numpy(t) for t in targets))


def checkpoint_path(out, step: int) -> Path:
    """Where ``train_detector(..., checkpoint_every=k)`` writes the weights after ``step`` iterations:
    next to ``out``, e.g. det.pt -> det.it0400.pt."""
    out = Path(out)
    return out.with_name(f"{out.stem}.it{step:04d}{out.suffix}")


def evaluate_detector(detector, ds: CocoDataset, progress: bool = False, min_area: float = 0.0) -> BoxMap:
    """COCO mAP of a detector on a dataset (score threshold lowered to 0.01 as for COCO evaluation);
    ground truth smaller than ``min_area`` px^2 is ignored as COCOeval's area range does."""
    if hasattr(detector, "params"):
        saved = detector.params
        detector.params = PostParams(score_threshold=0.01, nms_iou=saved.nms_iou, max_detections=100)
    try:
        dets = {}
        for iid, path in tqdm(list(zip(ds.image_ids, ds.images)), desc="evaluate", unit="img",
                              disable=not progress, leave=False):
            d = detector.detect(read_rgb(path))
            dets[iid] = (d.boxes, d.scores, d.classes)
    finally:
        if hasattr(detector, "params"):
            detector.params = saved
    return coco_map(ds.ground_truth(), dets, min_area=min_area)


def resize_dataset(src, out, input_wh: tuple[int, int], quality: int = 95, progress: bool = True) -> int:
    """``src``'s images shrunk to the network input as the training loop shrinks them (area
    interpolation), stored as lossy WebP at ``quality``, and its boxes scaled with them, into the new COCO
    folder ``out`` (other keys of the file kept): the training batches nearly unchanged in a tenth of
    the bytes, to carry a dataset to a training machine. Written into OUT.tmp-writing-PID and renamed
    when complete. Returns the number of images."""
    from vcfusion.runio import atomic_folder

    src = Path(src)
    ds, coco = _read_coco(src)  # checked, each image found, the ids integers
    scale: dict[int, tuple[float, float]] = {}
    with atomic_folder(Path(out), "dataset folder") as tmp:
        (tmp / "images").mkdir()
        for record, file in tqdm(list(zip(coco["images"], ds.images)), desc=f"resize {src.name}", unit="img",
                                 disable=not progress):
            rgb = read_rgb(file)
            scale[record["id"]] = (input_wh[0] / rgb.shape[1], input_wh[1] / rgb.shape[0])
            small = resize_to_input(rgb, input_wh)
            name = f"{record['id']:07d}.webp"
            if not cv2.imwrite(str(tmp / "images" / name), cv2.cvtColor(small, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_WEBP_QUALITY, int(quality)]):
                raise DetectorFileError(f"{out}: cannot write {name}")
            record.update(file_name=name, width=int(input_wh[0]), height=int(input_wh[1]))
        for ann in coco["annotations"]:
            sx, sy = scale[ann["image_id"]]
            x, y, w, h = map(float, ann["bbox"])
            # COCO pixel edges scale with the image (what _cache does with the pixel-centre boxes)
            ann["bbox"] = [x * sx, y * sy, w * sx, h * sy]
        (tmp / "annotations.json").write_text(json.dumps(coco))
    return len(coco["images"])
