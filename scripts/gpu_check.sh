#!/usr/bin/env bash
# The device check of a GPU machine in one call of at most ten minutes, offline (docs/how-to/gpu.md):
# installs the project and its dependencies from the carried wheels into a fresh virtual environment,
# then runs scripts/gpu_check.py (gsplat's JIT build, the CUDA tests, train + eval on CPU and CUDA,
# NCCL with world size 1, an own scene, the step benchmark's GPU rows); results JSON in $OUT (or --out).
#
#   bash scripts/gpu_check.sh --download     # where there is a network: fill the wheel folder
#   bash scripts/gpu_check.sh --dry-run      # here, no GPU: wheels present? commands parse? CPU parts, tiniest size
#   bash scripts/gpu_check.sh [--out DIR]    # on the GPU machine
#
# WHEELS (default shared/wheels), VENV (default /tmp/controlgs-gpu-venv), PYTHON (default python3.11),
# CUDA_INDEX (default https://download.pytorch.org/whl/cu126) and BUDGET (seconds, default 580) override.
set -euo pipefail
cd "$(dirname "$0")/.."
START=$SECONDS
WHEELS=${WHEELS:-shared/wheels}
VENV=${VENV:-/tmp/controlgs-gpu-venv}
PYTHON=${PYTHON:-python3.11}
CUDA_INDEX=${CUDA_INDEX:-https://download.pytorch.org/whl/cu126}
BUDGET=${BUDGET:-580}
MODE=gpu
ARGS=()
while [ $# -gt 0 ]; do
  case "$1" in
    --download) MODE=download ;;
    --dry-run) MODE=dry ;;
    --out) ARGS+=(--out "$2"); shift ;;
    *) echo "gpu_check.sh: unknown argument $1 (--download, --dry-run, --out DIR)" >&2; exit 2 ;;
  esac
  shift
done

# the pure-Python and binary wheels besides torch, for Linux x86_64, CPython 3.11
PACKAGES=(gsplat jaxtyping rich ninja "numpy>=1.24" "pluggy>=1.3" "safetensors>=0.4" "colour-science>=0.4.4"
          "tqdm>=4.60" "pillow>=9" "flip-evaluator>=1.7" "scikit-image>=0.21" "matplotlib>=3.7" "pytest>=7"
          "hypothesis>=6.80" "setuptools>=68" wheel packaging)
TARGET=(--only-binary=:all: --python-version 3.11 --implementation cp --abi cp311 --abi abi3 --abi none
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform any)

case "$MODE" in
  download)
    mkdir -p "$WHEELS"
    # torch's CUDA build and the nvidia-* runtime wheels it requires, from PyTorch's index
    pip download "${TARGET[@]}" -d "$WHEELS" --index-url "$CUDA_INDEX" torch==2.13.0
    # gsplat's PyPI wheel is pure Python: its CUDA kernels are compiled on first use (nvcc needed on the GPU machine)
    pip download "${TARGET[@]}" -d "$WHEELS" "${PACKAGES[@]}"
    ls "$WHEELS" | wc -l | xargs echo "wheels in $WHEELS:"
    ;;
  dry)
    PY=.venv/bin/python
    [ -x "$PY" ] || PY=python3
    exec "$PY" scripts/gpu_check.py --dry-run --wheels "$WHEELS" "${ARGS[@]}"
    ;;
  gpu)
    command -v "$PYTHON" >/dev/null || { echo "gpu_check.sh: $PYTHON not found (the wheels are for CPython 3.11)" >&2; exit 2; }
    [ -d "$WHEELS" ] || { echo "gpu_check.sh: no wheel folder $WHEELS (bash scripts/gpu_check.sh --download)" >&2; exit 2; }
    "$PYTHON" -m venv "$VENV"
    PIP=("$VENV/bin/python" -m pip install -q --no-index --find-links "$WHEELS")
    "${PIP[@]}" torch==2.13.0
    "${PIP[@]}" --no-deps gsplat                  # never lets a dependency replace the CUDA torch
    "${PIP[@]}" "${PACKAGES[@]:1}"
    "${PIP[@]}" --no-build-isolation --no-deps -e .
    echo "installed in $((SECONDS - START)) s"
    exec "$VENV/bin/python" scripts/gpu_check.py --wheels "$WHEELS" --budget $((BUDGET - (SECONDS - START))) "${ARGS[@]}"
    ;;
esac
