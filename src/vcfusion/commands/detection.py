"""Handlers of the detector subcommands of `vcfusion` (train-detector, eval-detector, export-onnx);
this module parses and checks the arguments. A bad weights file or dataset folder raises DetectorFileError
(InputError: the CLI prints it and exits with 2)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from vcfusion.commands.checks import check_min_area, check_pose_noise_deg, parse_seeds, parse_size
from vcfusion.errors import UsageError


def cmd_train_detector(args: argparse.Namespace) -> int:
    from vcfusion.detection.detector_train import train_detector

    input_wh = parse_size(args.input_size, "--input-size")
    if args.seed < 0:
        raise UsageError(f"--seed: expected 0 or more, got {args.seed}")
    if args.threads < 0:
        raise UsageError(f"--threads: expected 0 (torch's default) or more, got {args.threads}")
    out = Path(args.out)
    if out.is_dir() or not out.parent.is_dir():
        # checked before loading and training, not when the weights are written at the end
        raise UsageError(f"--out {out}: expected a weights file in an existing folder")
    if args.workers < 0:
        raise UsageError(f"--workers: expected 0 or more, got {args.workers}")
    for name in ("epochs", "batch_size", "checkpoint_every", "iterations"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise UsageError(f"--{name.replace('_', '-')}: expected a positive number, got {getattr(args, name)}")
    if not args.lr > 0:
        raise UsageError(f"--lr: expected a positive learning rate, got {args.lr}")
    if args.device not in ("auto", "cpu", "cuda"):
        raise UsageError(f"--device: expected auto, cpu or cuda, got {args.device!r}")
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            raise UsageError("--device cuda: torch sees no CUDA device here (this torch is the CPU build, or "
                             "no GPU); use --device cpu or auto")
    if not 0.0 <= args.val_fraction < 1.0:
        raise UsageError(f"--val-fraction: expected a share in [0, 1) (the rest is trained on), "
                         f"got {args.val_fraction}")
    check_min_area(args.min_area)
    check_min_area(args.min_train_area, "--min-train-area")
    net, report = train_detector(
        args.data, args.out, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, input_wh=input_wh,
        val_fraction=args.val_fraction, val_data=args.val, seed=args.seed, threads=args.threads,
        device=args.device, progress=sys.stderr.isatty(), max_iterations=args.iterations,
        min_train_area=args.min_train_area, eval_min_area=args.min_area, init=args.init,
        checkpoint_every=args.checkpoint_every, workers=args.workers)
    size_mb = out.stat().st_size / 2**20
    print(f"trained {report.iterations} iterations ({report.epochs} epochs) on {report.n_train} images "
          f"in {report.wall_s:.0f} s; loss {report.first_losses[0]:.3f} -> {report.loss_history[-1]:.3f}")
    if report.val is not None:
        print(f"held-out ({report.n_val} images, boxes >= {args.min_area:g} px^2): mAP@0.5 {report.val.map_50:.3f}  mAP@0.5:0.95 {report.val.map_50_95:.3f}")
    print(f"weights: {args.out} ({size_mb:.1f} MB)")
    return 0


def cmd_resize_dataset(args: argparse.Namespace) -> int:
    from vcfusion.detection.detector_train import resize_dataset

    input_wh = parse_size(args.size, "--size")
    if not 1 <= args.quality <= 100:
        raise UsageError(f"--quality: expected 1 to 100, got {args.quality}")
    if Path(args.out).exists():
        raise UsageError(f"--out: {args.out} already exists; choose a new dataset folder")
    n = resize_dataset(args.data, args.out, input_wh, args.quality, progress=sys.stderr.isatty())
    print(f"resized {n} images to {input_wh[0]}x{input_wh[1]} -> {args.out}")
    return 0


def _make_detector(args):
    from vcfusion.detection.detector_net import DetectorFileError, OnnxDetector, TorchDetector, default_weights_path

    if args.onnx and args.layout == "ultralytics":
        keep = tuple(c.strip() for c in args.keep.split(","))
        input_wh = parse_size(args.input_size or "640x640", "--input-size")  # its own message, not --keep's
        try:
            return OnnxDetector.ultralytics(args.onnx, input_wh, keep)
        except ValueError as exc:
            if isinstance(exc, DetectorFileError):
                raise
            raise UsageError(f"--keep: {exc}") from None
    if args.onnx:
        try:
            class_ids = [int(c) for c in (args.classes or "").split(",")]
        except ValueError:
            raise UsageError("--classes: expected the category ids of the ONNX model's score columns, e.g. 1,2, "
                             f"got {args.classes!r}") from None
        return OnnxDetector(args.onnx, parse_size(args.input_size or "320x240", "--input-size"), class_ids,
                            scale=args.scale, objectness=args.objectness, letterbox=args.letterbox)
    return TorchDetector(args.weights or default_weights_path())


def _check_distinct_folders(folders) -> None:
    """Each scene once: a folder listed twice, or a copy of one, counted its targets twice and narrowed
    the intervals over scenes (training may list a folder twice on purpose; scoring may not)."""
    import hashlib

    seen: dict = {}
    for folder in folders:
        path = Path(folder)
        key = path.resolve()
        ann = path / "annotations.json"
        if ann.is_file():
            key = hashlib.sha256(ann.read_bytes()).hexdigest()
        if key in seen:
            raise UsageError(f"data: {folder} holds the same images as {seen[key]} (a folder listed twice, or a "
                             "copy); expected each folder once, so that each scene counts once")
        seen[key] = folder


def cmd_train_box_head(args: argparse.Namespace) -> int:
    """The far-box head (vcfusion.fusion.far_boxes) on COCO folders of rendered training scenes: crops
    around each ground-truth box, jittered copies of it and the shipped detector's boxes matched to it."""
    from vcfusion.detection.detector_net import TorchDetector, default_weights_path
    from vcfusion.detection.detector_train import load_coco_many, read_rgb
    from vcfusion.fusion.far_boxes import CropSpec, save_box_head, train_box_head, training_samples

    if args.epochs < 1 or args.jitters < 0:
        raise UsageError(f"--epochs >= 1 and --jitters >= 0 expected, got {args.epochs}, {args.jitters}")
    ds = load_coco_many(args.data)
    detector = TorchDetector(args.detector or default_weights_path())
    images = [read_rgb(path) for path in ds.images]
    dets = [detector.detect(image).boxes for image in images]
    spec = CropSpec()
    samples = training_samples(images, ds.boxes, dets, spec, np.random.default_rng(args.seed), jitters=args.jitters)
    print(f"{len(images)} images, {len(samples.offsets)} crops")
    meta = {"train_data": [Path(d).name for d in args.data], "images": len(images), "seed": args.seed,
            "jitters": args.jitters}
    head, info = train_box_head(samples, spec, epochs=args.epochs, seed=args.seed, threads=args.threads, meta=meta)
    save_box_head(head, args.out)
    print(f"wrote {args.out}: {info['samples']} crops, {info['steps']} steps, loss {info['final_loss']:.4f}, "
          f"{info['train_s']:.0f} s")
    return 0


def cmd_eval_detector(args: argparse.Namespace) -> int:
    from vcfusion.detection.detector_train import load_coco_many
    from vcfusion.detection.family_eval import (evaluate_families, format_depth_counts, format_failure_table,
                                                format_interval_table, format_table, format_visibility_table)

    check_min_area(args.min_area)
    if not np.isfinite(args.gnss_noise) or args.gnss_noise < 0:
        raise UsageError(f"--gnss-noise: expected a standard deviation >= 0 in metres, got {args.gnss_noise}")
    check_pose_noise_deg(args.pose_noise_deg)
    _check_distinct_folders(args.data)
    detector = _make_detector(args)
    ds = load_coco_many(args.data)
    from vcfusion.fusion.box_refine import BoxRefineParams
    from vcfusion.fusion.stage import road_model

    box_head = None if args.box_head == "none" else args.box_head
    if box_head not in (None, "shipped"):
        from vcfusion.fusion.far_boxes import BoxHead

        BoxHead.load(box_head)  # a missing or unreadable file fails here, before any frame
    # eval-detector's pose noise is a mount error with body motion (family_eval), so any > 0 is a pose error
    road = road_model(args.road, args.depth_sensor, args.pose_noise_deg > 0)
    # the detector's column in the identification tables (an ONNX model's was labelled "cnn")
    detector_name = "onnx" if args.onnx else "cnn"
    results, _ = evaluate_families(detector, ds, min_area=args.min_area, identification=not args.no_identification,
                                   detector_name=detector_name, progress=sys.stderr.isatty(),
                                   refine=None if args.no_refine else BoxRefineParams(road=road, box_head=box_head),
                                   gnss_noise_m=args.gnss_noise,
                                   depth_sensor=args.depth_sensor, pose_noise_deg=args.pose_noise_deg)
    if not results:
        raise UsageError(f"{' '.join(args.data)}: annotations: expected at least one ground-truth box")
    overall = results[-1]  # 'all' when there are several families
    print(f"{' '.join(args.data)}: {len(ds)} images (boxes >= {args.min_area:g} px^2, "
          f"{'boxes as detected' if args.no_refine else 'boxes refined by depth'}"
          f"{f'; identification with {args.gnss_noise:g} m GNSS noise' if args.gnss_noise else ''}"
          f"{f'; {args.depth_sensor} depth' if args.depth_sensor != 'exact' else ''}"
          f"{f'; pose noise {args.pose_noise_deg:g} deg' if args.pose_noise_deg else ''})  "
          f"mAP@0.5 {overall.box_map.map_50:.3f}  mAP@0.5:0.95 {overall.box_map.map_50_95:.3f}")
    for cid, name in zip(ds.class_ids, ds.class_names):
        if cid in overall.box_map.ap_per_category:
            print(f"  {name}: AP@0.5:0.95 {overall.box_map.ap_per_category[cid]:.3f}")
    print(format_table(results, detector_name))
    by_visibility = format_visibility_table(results, detector_name)
    if by_visibility:
        print(by_visibility)
    depth_counts = format_depth_counts(results)
    if depth_counts:
        print(depth_counts)
    failures = format_failure_table(results, detector_name)
    if failures:
        print(failures)
    intervals = format_interval_table(results, detector_name)
    if intervals:
        print(intervals)
    if args.report:
        from vcfusion.runio import json_null_for_nan, write_json

        # strict JSON (an empty visibility bin's accuracy is NaN: null here, as JSON readers expect)
        write_json(Path(args.report), json_null_for_nan({"data": [str(d) for d in args.data],
                                                         "min_area": args.min_area,
                                                         "refined_by_depth": not args.no_refine,
                                                         "box_head": None if args.no_refine else box_head,
                                                         "gnss_noise_m": args.gnss_noise,
                                                         "depth_sensor": args.depth_sensor,
                                                         "road": road,
                                                         "pose_noise_deg": args.pose_noise_deg,
                                                         "families": [r.summary() for r in results]}))
        print(f"report: {args.report}")
    return 0


def cmd_export_onnx(args: argparse.Namespace) -> int:
    from vcfusion.detection.detector_net import DetectorModel, default_weights_path, export_onnx

    try:
        import onnx  # noqa: F401 - torch's exporter needs it
    except ImportError:
        raise UsageError("export-onnx: needs the onnx package (pip install onnx, or the project's dev extra)") from None
    net = DetectorModel.load(args.weights or default_weights_path())
    out = export_onnx(net, args.out)
    w, h = net.input_wh
    ids = ",".join(str(c) for c in net.class_ids)
    print(f"wrote {out}: input images (1, 3, {h}, {w}) RGB 0..255, output detections (1, N, 4 + {len(ids.split(','))})")
    print(f"use it with: vcfusion eval-detector DATA --onnx {out} --input-size {w}x{h} --classes {ids}")
    return 0


def cmd_render_scenes(args: argparse.Namespace) -> int:
    from vcfusion.detection.scenes import FAMILIES, render_scenes
    from vcfusion.scenario import load_scenario

    if args.family not in FAMILIES:
        raise UsageError(f"--family: expected one of {', '.join(FAMILIES)}, got {args.family!r}")
    seeds = parse_seeds(args.seeds)
    scenario = load_scenario(args.scenario)
    if Path(args.out).exists():
        raise UsageError(f"--out: {args.out} already exists; choose a new dataset folder")
    if args.workers < 1:
        raise UsageError(f"--workers: expected at least 1, got {args.workers}")
    counts = render_scenes(scenario, args.family, seeds, Path(args.out), progress=sys.stderr.isatty(),
                           workers=args.workers)
    print(f"rendered {counts['images']} {args.family} scenes, {counts['annotations']} boxes -> {args.out}")
    return 0


def cmd_coco_check(args: argparse.Namespace) -> int:
    from vcfusion.detection.coco_check import CheckInputError, GridOnnxDetector, check_folder

    names = None
    if args.names:
        try:
            names = [line.strip() for line in Path(args.names).read_text().splitlines() if line.strip()]
        except OSError as exc:
            raise UsageError(f"--names: cannot read {args.names}: {exc.strerror}") from None
    try:
        detector = GridOnnxDetector(args.coco_onnx)
        results = [check_folder(detector, folder, args.min_width, args.iou, args.score, names) for folder in args.data]
    except CheckInputError as exc:
        raise UsageError(str(exc)) from None
    print(f"clearly visible vehicles (unoccluded, untruncated, >= {args.min_width:g} px wide) found as car/bus/truck "
          f"(IoU >= {args.iou:g}, score >= {args.score:g}) by {Path(args.coco_onnx).name}:")
    for r in results:
        med = float(np.median(r.best_scores)) if r.best_scores else float("nan")
        top = ", ".join(f"{k} {v}" for k, v in sorted(r.labels.items(), key=lambda kv: -kv[1])[:4])
        print(f"  {r.folder}: {r.found}/{r.vehicles} = {100 * r.share:.0f} % ({r.images} images; "
              f"median best score {med:.2f}; labelled as: {top})")
    found, total = sum(r.found for r in results), sum(r.vehicles for r in results)
    print(f"all: {found}/{total} = {100 * found / max(total, 1):.0f} %")
    return 0


def add_parsers(sub) -> None:
    """The vision subcommands, added to the `vcfusion` parser."""
    p = sub.add_parser("train-detector", help="train the CNN detector on a COCO dataset folder")
    p.add_argument("data", nargs="+", help="COCO folder(s): images + annotations.json (e.g. renders of several scenarios)")
    p.add_argument("--out", required=True, help="weights file to write (e.g. src/vcfusion/assets/detector.pt)")
    p.add_argument("--val", nargs="+", help="held-out COCO folder(s) (e.g. other seeds); default: --val-fraction of DATA")
    p.add_argument("--val-fraction", type=float, default=0.1,
                   help="without --val: this share of DATA's scenes (a render seed's frames together) is held out")
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--init", help="weights file to fine-tune from (same categories, input size and widths)")
    p.add_argument("--iterations", type=int, default=None, help="stop after this many iterations")
    p.add_argument("--checkpoint-every", type=int, default=None,
                   help="also write the weights every N iterations next to --out (WEIGHTS.itNNNN.pt)")
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--input-size", default="320x240", help="network input WIDTHxHEIGHT (multiples of 16)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda")
    p.add_argument("--workers", type=int, default=0,
                   help="processes building the batches ahead of the model (for a GPU; same batches for any number)")
    p.add_argument("--min-train-area", type=float, default=16.0, help="train only on boxes of at least this many px^2 at the network input (16 at 320x240: 64 px^2 of a 640x480 image)")
    p.add_argument("--min-area", type=float, default=100.0,
                   help="held-out mAP ignores ground truth below this many px^2 (COCOeval area range)")
    p.set_defaults(func=cmd_train_detector, interrupted="the weights file was not written (checkpoints written so "
                                                        "far are kept: --init one to fine-tune from it; "
                                                        "the learning-rate schedule starts anew)")

    p = sub.add_parser("train-box-head", help="train the far-box head (box sides from the image where depth is gated)")
    p.add_argument("data", nargs="+", help="COCO folder(s) of rendered training scenes (render-scenes --family train)")
    p.add_argument("--out", required=True, help="weights file to write (e.g. src/vcfusion/assets/far_box_head.pt)")
    p.add_argument("--detector", help="detector weights whose boxes are among the training boxes (default: shipped)")
    p.add_argument("--epochs", type=int, default=12)
    p.add_argument("--jitters", type=int, default=6, help="jittered copies of each ground-truth box")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.set_defaults(func=cmd_train_box_head, interrupted="the weights file was not written")

    for name, func, helptext in (("eval-detector", cmd_eval_detector, "COCO mAP of a detector on a dataset folder"),):
        p = sub.add_parser(name, help=helptext)
        p.add_argument("data", nargs="+", help="COCO folder(s)")
        p.add_argument("--weights", help="our weights file (default: the shipped detector)")
        p.add_argument("--onnx", help="an ONNX detector run through OpenCV DNN instead")
        p.add_argument("--layout", choices=("vcfusion", "ultralytics"), default="vcfusion",
                       help="ONNX output layout: ours (export-onnx) or an Ultralytics YOLO export "
                            "(letterboxed RGB/255 input, output (1, 4 + 80, N), COCO classes)")
        p.add_argument("--input-size", default=None,
                       help="ONNX input WIDTHxHEIGHT (default 320x240 for ours, 640x640 for ultralytics)")
        p.add_argument("--keep", default="car,bus,truck", help="ultralytics: COCO classes kept as vehicles")
        p.add_argument("--classes", help="vcfusion layout: category ids of the score columns, e.g. 1,2")
        p.add_argument("--scale", type=float, default=1.0, help="ONNX: input scale (1/255 for most YOLO exports)")
        p.add_argument("--objectness", action="store_true", help="ONNX: output has an objectness column (YOLOv5)")
        p.add_argument("--letterbox", action="store_true", help="ONNX: letterbox instead of stretch")
        p.add_argument("--min-area", type=float, default=100.0,
                       help="ignore ground truth below this many px^2 (COCOeval area range; 0 = all)")
        p.add_argument("--no-identification", action="store_true",
                       help="skip the joint-matcher identification check (oracle vs detector boxes)")
        p.add_argument("--gnss-noise", type=float, default=0.0, metavar="M",
                       help="identification: GNSS error std on each horizontal axis, m (default 0: the twins "
                            "where the renderer placed them)")
        p.add_argument("--depth-sensor", choices=("exact", "stereo", "tof", "lidar"), default="exact",
                       help="the depth the depth step and the matcher see (vcfusion.fusion.sensors; default exact)")
        p.add_argument("--pose-noise-deg", type=float, default=0.0, metavar="DEG",
                       help="camera mount calibration error std (pitch, yaw, roll), deg (default 0)")
        p.add_argument("--road", choices=("auto", "from_depth", "flat"), default="auto",
                       help="the depth step's road: fitted to each depth image, the pose's flat road, or auto "
                            "(flat with exact depth and no pose noise, else fitted)")
        p.add_argument("--box-head", default="shipped", metavar="WEIGHTS",
                       help="the far-box head that places the sides of boxes the depth step keeps as detected "
                            "(gated) from the image: shipped (default), a weights file, or none")
        p.add_argument("--report", help="also write the per-family figures to this JSON file")
        p.add_argument("--no-refine", action="store_true",
                       help="score the detector's boxes as detected (default: refined by the depth image, as the "
                            "fusion stage uses them; needs the folders' depth images)")
        p.set_defaults(func=func)

    p = sub.add_parser("render-scenes", help="render procedural scenes (no SUMO run) into a COCO dataset folder")
    p.add_argument("--family", default="train",
                   help="train (the training sampler) or a held-out family: jam, far_chain, cut_in, truck_occlusion, "
                        "high_mount, low_mount")
    p.add_argument("--seeds", required=True, help="scene seeds, e.g. 0-1999 (each family has its own scenes per seed)")
    p.add_argument("--out", required=True, help="dataset folder to create")
    p.add_argument("--scenario", default="overlap",
                   help="scenario giving the road and the camera (default: the shipped scenarios/overlap.yaml)")
    p.add_argument("--workers", type=int, default=2,
                   help="processes rendering consecutive runs of seeds (default 2; the folder is the same for any number)")
    p.set_defaults(func=cmd_render_scenes, interrupted="no dataset folder was written; run the same command again")

    p = sub.add_parser("resize-dataset", help="shrink a COCO folder's images to the network input (WebP), "
                                              "boxes scaled: a training set small enough to carry to a GPU")
    p.add_argument("data", help="COCO folder")
    p.add_argument("--out", required=True, help="dataset folder to create")
    p.add_argument("--size", default="320x240", help="WIDTHxHEIGHT, the detector's input size (default 320x240)")
    p.add_argument("--quality", type=int, default=95, help="WebP quality (default 95)")
    p.set_defaults(func=cmd_resize_dataset, interrupted="no dataset folder was written; run the same command again")

    p = sub.add_parser("coco-check", help="share of clearly visible rendered vehicles a COCO detector (ONNX) finds")
    p.add_argument("data", nargs="+", help="`vcfusion render` folder(s)")
    p.add_argument("--coco-onnx", required=True, help="COCO-80 detector, grid layout (1, 5 + 80, H, W), e.g. FastestDet")
    p.add_argument("--names", help="class names file, one a line (for the 'labelled as' summary)")
    p.add_argument("--min-width", type=float, default=40.0, help="vehicles at least this many px wide (default 40)")
    p.add_argument("--iou", type=float, default=0.5)
    p.add_argument("--score", type=float, default=0.3)
    p.set_defaults(func=cmd_coco_check)

    p = sub.add_parser("export-onnx", help="export our detector to ONNX (the layout OnnxDetector reads)")
    p.add_argument("--weights", help="weights file (default: the shipped detector)")
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_export_onnx)
