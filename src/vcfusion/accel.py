"""Where the vision tick runs: the OpenGL platform of the camera renderer and the torch device
of the detector.

- The renderer draws through EGL on an NVIDIA GPU and through OSMesa (llvmpipe, CPU) elsewhere.
  ``PYOPENGL_PLATFORM`` must be set before anything imports OpenGL: :mod:`vcfusion.render` sets
  it from :func:`gl_platform` when it is first imported (a value the user set is kept).
- The CNN detector runs on CUDA when torch finds a CUDA device, else on the CPU
  (:func:`torch_device`).

Both follow one setting, the device: ``auto`` (the default: the GPU when present), ``cpu`` or
``cuda``. The command line's ``vcfusion --device`` sets it for the whole command, worker
processes included (through the ``VCFUSION_DEVICE`` environment variable); a scenario's
``fusion.device`` sets the detector's for its runs when the command line does not. ``cuda``
where there is no GPU is refused with a message, never run on the CPU instead.

Nothing here imports torch or OpenGL at import time: traffic-only runs load neither.
"""

from __future__ import annotations

import os

from vcfusion.errors import InputError

DEVICES = ("auto", "cpu", "cuda")
DEVICE_ENV = "VCFUSION_DEVICE"  # set by `vcfusion --device`; read in every process of the command
GL_ENV = "PYOPENGL_PLATFORM"
# The NVIDIA driver's control node: present where an NVIDIA GPU and its kernel driver are.
NVIDIA_DEVICE_NODE = "/dev/nvidiactl"


class DeviceError(InputError):
    """A device asked for that this machine does not have (or an unknown device name)."""


def nvidia_gpu_present() -> bool:
    return os.path.exists(NVIDIA_DEVICE_NODE)


def check_device(name: str, where: str) -> str:
    if name not in DEVICES:
        raise DeviceError(f"{where}: expected one of {', '.join(DEVICES)}, got {name!r}")
    return name


def command_device() -> str | None:
    """The device the command line asked for (``vcfusion --device``), or None."""
    value = os.environ.get(DEVICE_ENV)
    return check_device(value, f"environment variable {DEVICE_ENV}") if value else None


def gl_platform() -> str:
    """The OpenGL platform for this process: ``egl`` on an NVIDIA GPU, ``osmesa`` otherwise;
    ``--device cpu`` forces OSMesa and ``--device cuda`` EGL."""
    device = command_device() or "auto"
    if device == "cpu":
        return "osmesa"
    if device == "cuda":
        return "egl"
    return "egl" if nvidia_gpu_present() else "osmesa"


def select_gl_platform() -> str:
    """Set ``PYOPENGL_PLATFORM`` (unless already set) before OpenGL is imported; returns it."""
    return os.environ.setdefault(GL_ENV, gl_platform())


def cuda_available() -> bool:
    import torch

    return bool(torch.cuda.is_available())


def torch_device(setting: str = "auto", where: str = "fusion.device") -> str:
    """The detector's torch device: the command line's ``--device`` when given, else `setting`
    (a scenario's ``fusion.device``); ``auto`` is ``cuda`` when torch finds a CUDA device."""
    requested = command_device() or check_device(setting, where)
    if requested == "cpu":
        return "cpu"
    available = cuda_available()
    if requested == "cuda" and not available:
        import torch

        source = f"vcfusion --device ({DEVICE_ENV})" if command_device() else where
        raise DeviceError(f"{source}: cuda asked for, but torch {torch.__version__} finds no CUDA device "
                          f"(built for CUDA {torch.version.cuda or 'none: a CPU-only build'}); use cpu or auto")
    return "cuda" if available else "cpu"
