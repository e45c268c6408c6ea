"""The GPU path of the vision tick, checked against the CPU path: `vcfusion bench --sections GPU`
(or ``tools/gpu_check.sh``).

1. CPU half (every machine): the ego camera renders frames of one seed of scenarios/accident_ar.yaml
   through OSMesa and the shipped CNN detects on them on the CPU (a fresh process each side, since
   the OpenGL platform is fixed when OpenGL is first imported).
2. GPU half (where an NVIDIA GPU or CUDA is present): the same vehicle states rendered through EGL,
   and the detector run on CUDA, on the CPU renders (the detector alone) and on the EGL renders
   (the whole GPU path). Checked within :data:`TOLERANCES`:
   - ``egl_depth``: the sky (+inf) on the same pixels, and the depth of the pixels both see within
     max(``depth_abs_m``, ``depth_rel`` x depth) on at least ``depth_pixels_ok`` of them;
   - ``egl_instances``: the same vehicle at ``instances_agree`` of the pixels;
   - ``cuda_boxes``: on the same image, every CPU box has a CUDA box of IoU >= ``box_iou_same_image``
     and score within ``score_abs`` (and no extra box);
   - ``egl_cuda_boxes``: on the EGL renders, every CPU-path box has a GPU-path box of IoU >=
     ``box_iou_gpu_path`` (the images differ by the rasteriser's edges and shading rounding);
   then the whole vision tick (render, detect, depth, match, overlay) of one seed on the GPU
   (``vision_tick_ms``, bench P2) and a short real-time drive with the display at 30 frames/s
   (``hitl_frames_per_s``, bench P6).
   Where neither is present the GPU half prints ``no GPU: skipped`` with the number of checks
   skipped (``skipped``), never a pass. A side that cannot run (EGL does not start, CUDA fails)
   fails its checks with the error's last line (``problem``); where EGL fails and CUDA works,
   the CUDA checks and figures still run on OSMesa renders.

A GPU machine without OSMesa takes the CPU half from a file written where OSMesa is
(:func:`write_reference`, `vcfusion bench --sections GPU --write-gpu-reference FILE`; then
`--gpu-reference FILE` there): the file holds the CPU half's arrays and the vehicle states it
rendered, and the GPU half renders those states. In either way the GPU half renders the CPU half's
states (no second simulation, so the two sides see the same scene by construction).

It installs nothing: it runs the package as installed. Sized to finish in under 5 minutes on a
GPU machine (each side's process imports torch and pyrender, simulates one seed, renders and
detects a few frames; then one seed of the vision tick and 10 simulated seconds of driving).
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from vcfusion.accel import DEVICE_ENV, GL_ENV, nvidia_gpu_present
from vcfusion.fusion.matching import box_iou
from vcfusion.records import VehicleStates

SCENARIO = "accident_ar"
SEED = 0
# Agreement of the GPU path with the CPU path (rules; on an NVIDIA H200 with the single-sampled
# framebuffer: depth 100 % of pixels within, median 0.00002 m; instances 100 %; scores within 0.006:
# docs/performance.md "On an NVIDIA H200").
TOLERANCES = {
    "depth_abs_m": 0.05,  # m: depth-buffer precision differences at tens of metres
    "depth_rel": 0.01,  # of the CPU depth
    "depth_pixels_ok": 0.99,  # of the pixels both renderers see a surface at
    "sky_agree": 0.995,  # pixels sky in both or in neither (edges of the far geometry may differ)
    "instances_agree": 0.98,  # pixels with the same vehicle (or none): edges rasterise differently
    "box_iou_same_image": 0.95,  # CUDA vs CPU convolutions: float rounding only
    "score_abs": 0.02,
    "box_iou_gpu_path": 0.8,  # EGL + CUDA vs OSMesa + CPU: different images at the edges
}
GPU_CHECKS = ("egl_depth", "egl_instances", "cuda_boxes", "egl_cuda_boxes", "vision_tick", "hitl_frames")


# -- comparisons (plain arrays: tested without a GPU) -------------------------------------------
def compare_depth(ref: np.ndarray, other: np.ndarray, tol: dict = TOLERANCES) -> dict:
    """Depth images (or stacks of them) of the same views: sky agreement and depth agreement."""
    ref, other = np.asarray(ref, dtype=np.float64), np.asarray(other, dtype=np.float64)
    if ref.shape != other.shape:
        return {"pass": False, "problem": f"shapes differ: {ref.shape} vs {other.shape}"}
    sky_ref, sky_other = ~np.isfinite(ref), ~np.isfinite(other)
    sky_agree = float((sky_ref == sky_other).mean())
    both = ~sky_ref & ~sky_other
    diff = np.abs(ref[both] - other[both])
    ok = diff <= np.maximum(tol["depth_abs_m"], tol["depth_rel"] * ref[both])
    ok_fraction = float(ok.mean()) if ok.size else 1.0
    return {"pass": bool(sky_agree >= tol["sky_agree"] and ok_fraction >= tol["depth_pixels_ok"]),
            "sky_agree": round(sky_agree, 5), "depth_ok_fraction": round(ok_fraction, 5),
            "depth_median_abs_diff_m": round(float(np.median(diff)), 5) if diff.size else 0.0}


def compare_instances(ref: np.ndarray, other: np.ndarray, tol: dict = TOLERANCES) -> dict:
    ref, other = np.asarray(ref), np.asarray(other)
    if ref.shape != other.shape:
        return {"pass": False, "problem": f"shapes differ: {ref.shape} vs {other.shape}"}
    agree = float((ref == other).mean())
    return {"pass": bool(agree >= tol["instances_agree"]), "instances_agree": round(agree, 5)}


def compare_boxes(ref: list[tuple[np.ndarray, np.ndarray]], other: list[tuple[np.ndarray, np.ndarray]],
                  min_iou: float, score_abs: float | None = None) -> dict:
    """Per frame (boxes, scores) of two detector runs: each reference box matched one to one (best
    IoU first) to a box of the other at IoU >= min_iou (and score within score_abs when given);
    passes when every box on both sides is matched."""
    n_ref = n_other = matched = 0
    worst_score = 0.0
    for (rb, rs), (ob, os_) in zip(ref, other, strict=True):
        n_ref, n_other = n_ref + len(rb), n_other + len(ob)
        if not len(rb) or not len(ob):
            continue
        iou = box_iou(rb, ob)
        taken_r, taken_o = set(), set()
        for flat in np.argsort(-iou, axis=None, kind="stable"):
            i, j = divmod(int(flat), iou.shape[1])
            if iou[i, j] < min_iou:
                break
            if i in taken_r or j in taken_o:
                continue
            d = abs(float(rs[i]) - float(os_[j]))
            if score_abs is not None and d > score_abs:
                continue
            taken_r.add(i)
            taken_o.add(j)
            worst_score = max(worst_score, d)
            matched += 1
    return {"pass": bool(matched == n_ref == n_other), "boxes_cpu": n_ref, "boxes_gpu": n_other,
            "matched": matched, "max_score_diff": round(worst_score, 4)}


# -- one side: render and detect in this process ------------------------------------------------
def _states(scenario, seed: int, frames: int) -> list:
    from vcfusion.cosim import CoSimulation
    from vcfusion.driver.idm import IdmController

    states = []

    class Collect:
        table = "gpu_check"

        def __call__(self, tick):
            states.append(tick.truth)

    traffic = scenario.model_copy(update={"vision": scenario.vision.model_copy(update={"enabled": False}),
                                          "fusion": scenario.fusion.model_copy(update={"enabled": False})})
    CoSimulation(traffic, seed, controller=IdmController.for_scenario(traffic), hooks=[Collect()]).run()
    states = [s for s in states if "ego" in s.ids]
    return [states[i] for i in np.linspace(0, len(states) - 1, frames).astype(int)]


def capture(frames: int, device: str, out: Path, rgb_from: Path | None = None) -> None:
    """Render `frames` frames of SEED (the OpenGL platform of PYOPENGL_PLATFORM), detect on them
    with the CNN on `device`, and on the RGB images of `rgb_from` (another side's capture) when
    given, rendering that capture's vehicle states (else simulated here); write arrays, timings and
    the states rendered to `out` (.npz)."""
    from vcfusion.detection.detector_net import TorchDetector, default_weights_path
    from vcfusion.render.renderer import EgoCameraRenderer
    from vcfusion.scenario import load_scenario

    scenario = load_scenario(SCENARIO)
    picks = _load_states(rgb_from) if rgb_from is not None else _states(scenario, SEED, frames)
    renderer = EgoCameraRenderer.for_scenario(scenario)
    detector = TorchDetector(default_weights_path(), device=device)
    renderer.render(picks[0])  # warm-up: shaders, buffers
    detector.detect(renderer.render(picks[0]).rgb)  # warm-up: kernels (cuDNN picks its algorithms)
    rgb, depth, inst, boxes, render_ms, detect_ms = [], [], [], [], [], []
    for truth in picks:
        t0 = time.perf_counter()
        frame = renderer.render(truth)
        render_ms.append(1e3 * (time.perf_counter() - t0))
        t0 = time.perf_counter()
        det = detector.detect(frame.rgb)
        detect_ms.append(1e3 * (time.perf_counter() - t0))
        rgb.append(frame.rgb)
        depth.append(frame.depth)
        inst.append(frame.instances)
        boxes.append((det.boxes, det.scores))
    renderer.close()
    on_ref = []
    if rgb_from is not None:
        with np.load(rgb_from) as ref:
            for image in ref["rgb"]:
                det = detector.detect(image)
                on_ref.append((det.boxes, det.scores))
    arrays = {"rgb": np.stack(rgb), "depth": np.stack(depth), "instances": np.stack(inst),
              "render_ms": np.array(render_ms), "detect_ms": np.array(detect_ms)}
    for name, found in (("boxes", boxes), ("boxes_on_ref", on_ref)):
        for k, (b, s) in enumerate(found):
            arrays[f"{name}_{k}"], arrays[f"{name}_scores_{k}"] = np.asarray(b), np.asarray(s)
    info = {"platform": os.environ.get(GL_ENV), "device": device, "frames": len(picks),
            "on_ref": len(on_ref)}
    for k, truth in enumerate(picks):  # plain arrays (a reference file may come from elsewhere: no pickle)
        arrays |= {f"state_{k}_{f.name}": _field_array(getattr(truth, f.name)) for f in _STATE_FIELDS}
    np.savez_compressed(out, info=np.array(json.dumps(info)), **arrays)


_STATE_FIELDS = [f for f in dataclasses.fields(VehicleStates) if f.init]


def _load_states(path: Path) -> list:
    """The vehicle states a capture rendered (written by capture() above)."""
    with np.load(path) as z:
        frames = json.loads(str(z["info"]))["frames"]
        return [VehicleStates(**{f.name: _state_field(z[f"state_{k}_{f.name}"]) for f in _STATE_FIELDS})
                for k in range(frames)]


def _field_array(value) -> np.ndarray:
    return np.asarray(value, dtype=str) if isinstance(value, tuple) else np.asarray(value)  # names: str, even none


def _state_field(a: np.ndarray):
    """A field as VehicleStates holds it: the time a float, the names (ids, types, classes) a tuple
    of str, the rest arrays."""
    if a.ndim == 0:
        return float(a)
    return tuple(a.tolist()) if a.dtype.kind == "U" else a


def load_capture(path: Path) -> dict:
    with np.load(path) as z:
        info = json.loads(str(z["info"]))
        out = {k: z[k] for k in ("rgb", "depth", "instances", "render_ms", "detect_ms")}
        for name, n in (("boxes", info["frames"]), ("boxes_on_ref", info["on_ref"])):
            out[name] = [(z[f"{name}_{k}"], z[f"{name}_scores_{k}"]) for k in range(n)]
    return out | {"info": info}


def _run_side(platform: str, device: str, frames: int, out: Path, rgb_from: Path | None = None) -> dict:
    """capture() in a fresh interpreter whose OpenGL platform is `platform`."""
    env = dict(os.environ, **{GL_ENV: platform, DEVICE_ENV: device})
    args = [sys.executable, "-c", "import sys; from pathlib import Path; from vcfusion.gpu_check import capture; "
            "capture(int(sys.argv[1]), sys.argv[2], Path(sys.argv[3]), Path(sys.argv[4]) if sys.argv[4] else None)",
            str(frames), device, str(out), str(rgb_from or "")]
    proc = subprocess.run(args, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"GPU check: the {platform}/{device} side failed:\n{proc.stderr[-2000:]}")
    return load_capture(out)


def _section_in_subprocess(name: str, size_arg, platform: str, device: str) -> dict:
    """A bench section (P2 vision tick, P6 drive) in a fresh interpreter on the given platform/device."""
    env = dict(os.environ, **{GL_ENV: platform, DEVICE_ENV: device, "SDL_VIDEODRIVER": "dummy",
                              "SDL_AUDIODRIVER": "dummy"})
    code = (f"import json; from vcfusion.bench import {name}; "
            f"print(json.dumps({name}({size_arg!r})))")
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"GPU check: {name} on {platform}/{device} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _last_line(exc: BaseException) -> str:
    lines = [line for line in str(exc).splitlines() if line.strip()]
    return lines[-1] if lines else type(exc).__name__


def write_reference(frames: int, out: Path) -> dict:
    """The CPU half (OSMesa renders, CPU detections, the states rendered) written to `out` (.npz),
    for `gpu_check(reference=out)` on a GPU machine without OSMesa."""
    out = Path(out)
    if out.suffix != ".npz":
        raise ValueError(f"{out}: expected a .npz file name for the GPU check's reference")
    out.parent.mkdir(parents=True, exist_ok=True)
    cpu = _run_side("osmesa", "cpu", frames, out)
    return {"name": f"GPU check reference ({frames} frames of {SCENARIO} seed {SEED})", "written": str(out),
            **_cpu_figures(cpu)}


def _cpu_figures(cpu: dict) -> dict:
    return {"cpu_render_ms": round(float(np.median(cpu["render_ms"])), 1),
            "cpu_detect_ms": round(float(np.median(cpu["detect_ms"])), 1),
            "cpu_boxes": sum(len(b) for b, _ in cpu["boxes"])}


def _gpu_side(platform: str, device: str, frames: int, tmp: Path, cpu_file: Path) -> tuple[dict | None, str]:
    """The GPU half's capture, and what went wrong (empty when nothing did). Where EGL fails with
    CUDA present, CUDA is captured again on OSMesa renders: its checks still run, EGL's fail."""
    try:
        return _run_side(platform, device, frames, tmp / "gpu.npz", rgb_from=cpu_file), ""
    except RuntimeError as exc:
        problem = f"the {platform}/{device} side failed: {_last_line(exc)}"
    if platform == "egl" and device == "cuda":
        try:
            return _run_side("osmesa", "cuda", frames, tmp / "gpu.npz", rgb_from=cpu_file), problem
        except RuntimeError as exc:
            problem += f"; osmesa/cuda too: {_last_line(exc)}"
    return None, problem


def gpu_check(frames: int, gpu: bool | None = None, cuda: bool | None = None, drive_s: float = 10.0,
              side: tuple[str, str] | None = None, tick_figures: bool = True, reference: Path | None = None) -> dict:
    """The section's figures (see the module docstring). `gpu` / `cuda`: whether EGL on an NVIDIA
    GPU / a CUDA device are there (None: detected). `side`: the (OpenGL platform, torch device)
    of the GPU half (default: egl / cuda where present; tests run the comparisons with the CPU's
    own on a machine without a GPU). `tick_figures`: also the vision tick and the drive.
    `reference`: the CPU half from this file (:func:`write_reference`; its frame count replaces
    `frames`) instead of rendering it here."""
    from vcfusion.accel import cuda_available

    gpu = nvidia_gpu_present() if gpu is None else gpu
    cuda = cuda_available() if cuda is None else cuda
    platform, device = side or (("egl" if gpu else "osmesa"), ("cuda" if cuda else "cpu"))
    with tempfile.TemporaryDirectory(prefix="vcfusion-gpu-check-") as tmp:
        if reference is None:
            cpu_file = Path(tmp) / "cpu.npz"
            cpu = _run_side("osmesa", "cpu", frames, cpu_file)
        else:
            cpu_file = Path(reference)
            cpu = load_capture(cpu_file)  # a missing file: numpy's FileNotFoundError names it
            frames = cpu["info"]["frames"]
        out: dict = {"name": f"GPU check ({frames} frames of {SCENARIO} seed {SEED})"}
        if reference is not None:
            out["cpu_half"] = f"from {Path(reference).name} (rendered on {cpu['info']['platform']}/{cpu['info']['device']})"
        out.update(_cpu_figures(cpu))
        if not gpu and not cuda:
            return out | {"status": "no GPU: skipped", "skipped": len(GPU_CHECKS), "skipped_checks": list(GPU_CHECKS),
                          "failed": 0}
        results, skipped = {}, []
        other, problem = _gpu_side(platform, device, frames, Path(tmp), cpu_file)
        if other is not None:
            platform = other["info"]["platform"]  # OSMesa where EGL failed (the CUDA checks still run)
            out.update({"gpu_platform": platform, "gpu_device": other["info"]["device"],
                        "gpu_render_ms": round(float(np.median(other["render_ms"])), 1),
                        "gpu_detect_ms": round(float(np.median(other["detect_ms"])), 1)})
        failed_side = {"pass": False, "problem": problem}
        egl = other is not None and not problem  # the side asked for ran (EGL where a GPU is)
        if gpu:
            results["egl_depth"] = compare_depth(cpu["depth"], other["depth"]) if egl else failed_side
            results["egl_instances"] = compare_instances(cpu["instances"], other["instances"]) if egl else failed_side
        else:
            skipped += ["egl_depth", "egl_instances"]
        if cuda:
            results["cuda_boxes"] = failed_side if other is None else compare_boxes(
                cpu["boxes"], other["boxes_on_ref"], TOLERANCES["box_iou_same_image"], TOLERANCES["score_abs"])
        else:
            skipped.append("cuda_boxes")
        if gpu and cuda:
            results["egl_cuda_boxes"] = compare_boxes(cpu["boxes"], other["boxes"], TOLERANCES["box_iou_gpu_path"]) \
                if egl else failed_side
        else:
            skipped.append("egl_cuda_boxes")
    if tick_figures:
        try:
            p2 = _section_in_subprocess("p2_vision", 1, platform, device)
            out["vision_tick_ms"] = p2["tick_median_ms"]
            out.update({f"vision_{k}": v for k, v in p2.items() if k.endswith("_ms") and k != "tick_median_ms"})
            results["vision_tick"] = {"pass": True, "platform": platform, "device": device}
        except RuntimeError as exc:
            results["vision_tick"] = {"pass": False, "problem": _last_line(exc)}
        try:
            p6 = _section_in_subprocess("p6_drive", drive_s, platform, device)
            out["hitl_frames_per_s"] = p6.get("display_fps_median")
            out["hitl"] = {k: v for k, v in p6.items() if k not in ("name", "target")}
            results["hitl_frames"] = {"pass": True, "platform": platform, "device": device}
        except RuntimeError as exc:
            results["hitl_frames"] = {"pass": False, "problem": _last_line(exc)}
    else:
        skipped += ["vision_tick", "hitl_frames"]
    failed = [name for name, r in results.items() if not r["pass"]]
    return out | {"checks": results, "failed": len(failed), "failed_checks": failed, "skipped": len(skipped),
                  "skipped_checks": skipped,
                  "status": ("FAIL: " + ", ".join(failed)) if failed else
                            ("pass" if not skipped else f"pass ({len(skipped)} checks skipped: {', '.join(skipped)})"),
                  "tolerances": TOLERANCES}
