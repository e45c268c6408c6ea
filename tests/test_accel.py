"""vcfusion.accel: the OpenGL platform and the detector's device follow `--device` (the
VCFUSION_DEVICE environment variable), a scenario's fusion.device, and what the machine has;
cuda where there is none is refused with a message, never run on the CPU instead."""

import os

import pytest

from vcfusion import accel
from vcfusion.accel import DeviceError, gl_platform, torch_device


@pytest.fixture
def no_command_device(monkeypatch):
    monkeypatch.delenv(accel.DEVICE_ENV, raising=False)


@pytest.mark.parametrize("gpu, expected", [(True, "egl"), (False, "osmesa")])
def test_auto_picks_egl_on_an_nvidia_gpu_and_osmesa_elsewhere(monkeypatch, no_command_device, gpu, expected):
    monkeypatch.setattr(accel, "nvidia_gpu_present", lambda: gpu)
    assert gl_platform() == expected


@pytest.mark.parametrize("device, expected", [("cpu", "osmesa"), ("cuda", "egl")])
def test_the_command_line_device_chooses_the_platform(monkeypatch, device, expected):
    monkeypatch.setattr(accel, "nvidia_gpu_present", lambda: not (expected == "egl"))  # against the machine
    monkeypatch.setenv(accel.DEVICE_ENV, device)
    assert gl_platform() == expected


def test_detector_device_from_the_setting_and_the_machine(monkeypatch, no_command_device):
    monkeypatch.setattr(accel, "cuda_available", lambda: True)
    assert torch_device("auto") == "cuda" and torch_device("cpu") == "cpu" and torch_device("cuda") == "cuda"
    monkeypatch.setattr(accel, "cuda_available", lambda: False)
    assert torch_device("auto") == "cpu"
    with pytest.raises(DeviceError, match=r"scenario.yaml: fusion.device: cuda asked for, but torch .* no CUDA"):
        torch_device("cuda", "scenario.yaml: fusion.device")


def test_the_command_line_device_overrides_the_scenario(monkeypatch):
    monkeypatch.setattr(accel, "cuda_available", lambda: False)
    monkeypatch.setenv(accel.DEVICE_ENV, "cpu")
    assert torch_device("cuda") == "cpu"
    monkeypatch.setenv(accel.DEVICE_ENV, "cuda")
    with pytest.raises(DeviceError, match=r"vcfusion --device"):
        torch_device("cpu")
    monkeypatch.setenv(accel.DEVICE_ENV, "gpu0")
    with pytest.raises(DeviceError, match=r"VCFUSION_DEVICE: expected one of auto, cpu, cuda, got 'gpu0'"):
        gl_platform()


def test_the_command_line_option_sets_the_device_for_the_command(monkeypatch):
    from vcfusion.commands import build_parser, main

    monkeypatch.setenv(accel.DEVICE_ENV, "auto")  # recorded, so the value main() sets is undone after
    assert build_parser().parse_args(["--device", "cpu", "scenarios"]).command_device == "cpu"
    # a command's own --device (train-detector's torch device) is its own option
    args = build_parser().parse_args(["--device", "cpu", "train-detector", "coco", "--out", "d.pt", "--device", "cuda"])
    assert (args.command_device, args.device) == ("cpu", "cuda")
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--device", "tpu", "scenarios"])
    monkeypatch.setattr("vcfusion.commands.simulation.cmd_scenarios", lambda args: 0)
    assert main(["--device", "cpu", "scenarios"]) == 0
    assert os.environ[accel.DEVICE_ENV] == "cpu"
