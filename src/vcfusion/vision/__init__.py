"""Vision stage: the ego camera (projection, rendering, ground truth) and, beside it, detection,
depth evaluation, matching and the AR overlay.

Importing this package sets ``PYOPENGL_PLATFORM`` (unless the user already did) before any
module of it imports OpenGL: ``egl`` where an NVIDIA GPU is present, ``osmesa`` (headless CPU
rendering) otherwise. Only :mod:`vcfusion.vision.render` and :mod:`vcfusion.vision.scene`
import OpenGL, and only when a camera is used, so traffic-only runs never load it.
"""

from __future__ import annotations

import os


def _default_gl_platform() -> str:
    return "egl" if os.path.exists("/dev/nvidiactl") else "osmesa"


os.environ.setdefault("PYOPENGL_PLATFORM", _default_gl_platform())
