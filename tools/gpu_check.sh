#!/bin/sh
# The GPU path of the vision tick checked against the CPU path, with its figures
# (`vcfusion bench --sections GPU`, vcfusion.gpu_check): EGL depth and instances against OSMesa's,
# CUDA boxes against the CPU's, render / detect / vision tick ms and the display's frames/s.
# Installs nothing: run it where the package is installed (python -m vcfusion works).
# Without a GPU it says "no GPU: skipped". Exit status: 0 pass or skipped, 1 a check failed.
#   tools/gpu_check.sh [OUT_DIR]   (default runs/gpu-check; bench.json + bench.md there)
set -eu
PYTHON="${PYTHON:-python}"
exec timeout 300 "$PYTHON" -m vcfusion bench --sections GPU --out "${1:-runs/gpu-check}"
