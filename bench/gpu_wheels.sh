#!/usr/bin/env bash
# The wheels bench/gpu_session.sh needs on a GPU machine that has only torch (CUDA), triton,
# lightning, torchmetrics, pytest and hypothesis and no network: bench/gpu_requirements.txt for
# that machine's Python (binary wheels, manylinux x86-64) plus antlr4-python3-runtime 4.9.3 built
# as a pure-Python wheel. About 56 MB. Run here, from the repository root:
#
#   bash bench/gpu_wheels.sh 3.12 gpu-wheels        # the GPU machine's Python version, a folder
#
# then on the GPU machine (docs/results.md, "The A layer as one fused kernel"):
#
#   python3 -m pip install -q --no-deps --no-index --target /tmp/w gpu-wheels/*.whl &&
#       PYTHONPATH=/tmp/w bash bench/gpu_session.sh OUT_DIR
set -euo pipefail
cd "$(dirname "$0")/.."
version=${1:?usage: bash bench/gpu_wheels.sh PYTHON_VERSION DIR}
dir=${2:?usage: bash bench/gpu_wheels.sh PYTHON_VERSION DIR}
PY=${PYTHON:-python3}
mkdir -p "$dir"
"$PY" -m pip download --quiet --no-deps --only-binary=:all: --dest "$dir" \
    --python-version "$version" --platform manylinux_2_31_x86_64 \
    --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 \
    -r bench/gpu_requirements.txt
"$PY" -m pip wheel --quiet --no-deps --wheel-dir "$dir" antlr4-python3-runtime==4.9.3
ls "$dir"
du -sh "$dir"
