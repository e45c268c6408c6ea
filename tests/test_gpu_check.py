"""The GPU check (`vcfusion bench --sections GPU`): its comparisons pass on agreeing images and
boxes and fail on the differences they are there to catch; without a GPU it says "no GPU:
skipped" and counts the checks it skipped; its CPU half and its comparison plumbing run here, the
GPU half replaced by a second OSMesa/CPU side (no GPU on these machines)."""

import numpy as np
import pytest

from vcfusion import gpu_check
from vcfusion.gpu_check import GPU_CHECKS, compare_boxes, compare_depth, compare_instances


def _depth(rng):
    depth = rng.uniform(5.0, 80.0, (48, 64)).astype(np.float32)
    depth[:12] = np.inf  # sky
    return depth


def test_depth_agrees_within_tolerance_and_fails_beyond_it():
    rng = np.random.default_rng(0)
    ref = _depth(rng)
    near = ref + rng.uniform(-0.02, 0.02, ref.shape).astype(np.float32)  # below depth_abs_m
    assert compare_depth(ref, near)["pass"]
    off = ref.copy()
    off[20:30] += 0.5  # a band of pixels half a metre off
    result = compare_depth(ref, off)
    assert not result["pass"] and result["depth_ok_fraction"] < 0.9
    sky = ref.copy()
    sky[12:16] = np.inf  # the sky where the CPU saw a surface
    assert not compare_depth(ref, sky)["pass"]
    assert not compare_depth(ref, ref[:-1])["pass"]


def test_instances_agree_or_not():
    ref = np.full((40, 40), -1, np.int32)
    ref[10:20, 10:20] = 0
    edge = ref.copy()
    edge[10, 10:20] = -1  # one edge row rasterised differently: 10 of 1600 pixels
    assert compare_instances(ref, edge)["pass"]
    swapped = ref.copy()
    swapped[10:20, 10:20] = 1  # another vehicle
    assert not compare_instances(ref, swapped)["pass"]


def test_boxes_match_one_to_one_within_iou_and_score():
    ref = [(np.array([[10, 10, 50, 40], [60, 10, 90, 30]], float), np.array([0.9, 0.6])), (np.zeros((0, 4)), np.zeros(0))]
    same = [(ref[0][0] + 0.3, ref[0][1] + 0.001), ref[1]]
    assert compare_boxes(ref, same, 0.95, 0.02)["pass"]
    shifted = [(ref[0][0] + np.array([[8, 0, 8, 0], [0, 0, 0, 0]]), ref[0][1]), ref[1]]
    assert not compare_boxes(ref, shifted, 0.95, 0.02)["pass"]
    assert compare_boxes(ref, shifted, 0.6)["pass"]  # the looser whole-path tolerance
    extra = [ref[0], (np.array([[0, 0, 5, 5]], float), np.array([0.5]))]
    result = compare_boxes(ref, extra, 0.95, 0.02)
    assert not result["pass"] and result["boxes_gpu"] == 3 and result["matched"] == 2
    scored = [(ref[0][0], ref[0][1] + np.array([0.0, 0.1])), ref[1]]
    assert not compare_boxes(ref, scored, 0.95, 0.02)["pass"]


def test_without_a_gpu_it_says_skipped_and_counts_the_checks(monkeypatch):
    calls = []

    def fake_side(platform, device, frames, out, rgb_from=None):
        calls.append((platform, device))
        return {"render_ms": np.array([60.0]), "detect_ms": np.array([40.0]), "boxes": [(np.zeros((2, 4)), np.zeros(2))],
                "info": {"platform": platform, "device": device}}

    monkeypatch.setattr(gpu_check, "_run_side", fake_side)
    out = gpu_check.gpu_check(1, gpu=False, cuda=False)
    assert out["status"] == "no GPU: skipped" and out["skipped"] == len(GPU_CHECKS) and out["failed"] == 0
    assert calls == [("osmesa", "cpu")]  # the CPU half ran, nothing else
    assert out["cpu_render_ms"] == 60.0 and out["cpu_detect_ms"] == 40.0 and out["cpu_boxes"] == 2


@pytest.mark.slow
def test_egl_on_the_cpu_draws_the_frames_osmesa_draws(tmp_path):
    """The GPU half's renderer path without a GPU: EGL on Mesa's llvmpipe draws through pyrender's
    own framebuffer (the path EGL takes on an NVIDIA GPU), OSMesa through the context's. Single-
    sampled, the same rasteriser gives the same depth and instances at every pixel and the same
    boxes (the colour differs at 0.06 % of the pixels: scores within 0.03 on 8 frames); with
    pyrender's 4-sample framebuffer depth moved (0.8 % of the pixels outside the tolerance), and
    the boxes (27 of 28 matched, a score 0.11 off). Also the reference route: the CPU half written
    to a file and the GPU half rendering its states."""
    reference = tmp_path / "ref.npz"
    written = gpu_check.write_reference(2, reference)
    assert written["cpu_boxes"] > 0 and reference.is_file()
    out = gpu_check.gpu_check(99, gpu=True, cuda=True, side=("egl", "cpu"), tick_figures=False, reference=reference)
    assert out["status"].startswith("pass"), out
    assert out["name"].startswith("GPU check (2 frames") and out["gpu_platform"] == "egl"
    checks = out["checks"]
    assert checks["egl_depth"]["depth_ok_fraction"] == 1.0 and checks["egl_depth"]["depth_median_abs_diff_m"] == 0.0
    assert checks["egl_instances"]["instances_agree"] == 1.0
    for name in ("cuda_boxes", "egl_cuda_boxes"):
        assert checks[name]["matched"] == checks[name]["boxes_cpu"] == checks[name]["boxes_gpu"] == written["cpu_boxes"]
    assert checks["cuda_boxes"]["max_score_diff"] == 0.0  # the same images, the same device
    assert checks["egl_cuda_boxes"]["max_score_diff"] <= 0.05
    assert out["skipped_checks"] == ["vision_tick", "hitl_frames"] and out["failed"] == 0


def test_a_failing_egl_side_fails_its_checks_and_cuda_is_still_checked(monkeypatch):
    boxes = [(np.array([[10.0, 10.0, 50.0, 40.0]]), np.array([0.9]))]
    depth = np.full((1, 4, 4), 10.0, np.float32)

    def fake_side(platform, device, frames, out, rgb_from=None):
        if platform == "egl":
            raise RuntimeError("GPU check: the egl/cuda side failed:\nTraceback ...\nOpenGL.error.Error: no EGL display")
        return {"render_ms": np.array([5.0]), "detect_ms": np.array([3.0]), "boxes": boxes, "boxes_on_ref": boxes,
                "depth": depth, "instances": np.zeros((1, 4, 4), np.int32), "info": {"platform": platform, "device": device}}

    monkeypatch.setattr(gpu_check, "_run_side", fake_side)
    out = gpu_check.gpu_check(1, gpu=True, cuda=True, tick_figures=False)
    assert out["status"].startswith("FAIL") and out["failed"] == 3
    assert sorted(out["failed_checks"]) == ["egl_cuda_boxes", "egl_depth", "egl_instances"]
    assert "no EGL display" in out["checks"]["egl_depth"]["problem"]
    assert out["checks"]["cuda_boxes"]["pass"] and out["gpu_platform"] == "osmesa" and out["gpu_device"] == "cuda"
