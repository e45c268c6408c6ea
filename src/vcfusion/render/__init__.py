"""Camera stage: the ego camera's projection (eq. 1-3), the highway scene and its meshes, the
offscreen renderer (RGB, depth, instances), ground-truth boxes and the COCO export.

Detection (``vcfusion.detection``) and the vision-cloud fusion with its AR overlay
(``vcfusion.fusion``) work on the frames this stage produces.

Importing this package sets ``PYOPENGL_PLATFORM`` (unless the user already did) before any
module of it imports OpenGL: ``egl`` where an NVIDIA GPU is present, ``osmesa`` (headless CPU
rendering) otherwise. Only :mod:`vcfusion.render.renderer` and :mod:`vcfusion.render.scene`
import OpenGL, and only when a camera is used, so traffic-only runs never load it.
"""

from __future__ import annotations

from vcfusion.accel import select_gl_platform

select_gl_platform()  # egl on an NVIDIA GPU, osmesa otherwise; `vcfusion --device` chooses (vcfusion.accel)
