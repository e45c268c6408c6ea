#!/bin/sh
# The GPU path of the vision tick checked against the CPU path, with its figures
# (`vcfusion bench --sections GPU`, vcfusion.gpu_check): EGL depth and instances against OSMesa's,
# CUDA boxes against the CPU's, render / detect / vision tick ms and the display's frames/s.
# Installs nothing: run it where the package is installed (python -m vcfusion works).
# Without a GPU it says "no GPU: skipped". Exit status: 0 pass or skipped, 1 a check failed.
#   tools/gpu_check.sh [OUT_DIR [BENCH_OPTIONS...]]   (default runs/gpu-check; bench.json + bench.md there)
# A GPU machine without OSMesa: write the CPU half where OSMesa is
#   (vcfusion bench --sections GPU --write-gpu-reference ref.npz), then there
#   tools/gpu_check.sh OUT_DIR --gpu-reference ref.npz
set -eu
PYTHON="${PYTHON:-python}"
# what the check will find (it decides by itself; this is for the log)
if [ -e /dev/nvidiactl ]; then echo "NVIDIA device node: present"; else echo "NVIDIA device node: absent"; fi
if command -v nvidia-smi >/dev/null 2>&1; then nvidia-smi -L || true; fi
"$PYTHON" -c "import torch; print('torch', torch.__version__, 'CUDA available:', torch.cuda.is_available())" || true
OUT_DIR="${1:-runs/gpu-check}"
[ $# -gt 0 ] && shift
exec timeout 300 "$PYTHON" -m vcfusion bench --sections GPU --out "$OUT_DIR" "$@"
