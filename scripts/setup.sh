#!/usr/bin/env bash
# Create .venv and install the project with its pinned dependencies.
# torch is installed first, pinned to the CPU build (2.13.0+cpu): on these machines the wheel lies
# in /opt/wheels; elsewhere it comes from PyTorch's CPU index. Either way no CUDA build is pulled.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
. .venv/bin/activate
python -m pip install -q --upgrade pip wheel setuptools
if ! python -c "import torch, sys; sys.exit(0 if torch.__version__ == '2.13.0+cpu' else 1)" 2>/dev/null; then
  # The CPU wheel lies in /opt/wheels on these machines (TORCH_WHEEL_DIR overrides). pip's local
  # version label "+cpu" guarantees a CUDA build is never chosen.
  python -m pip install -q --find-links "${TORCH_WHEEL_DIR:-/opt/wheels}" "torch==2.13.0+cpu"
fi
python -m pip install -q -e ".[test]"
python -c "import torch; assert torch.__version__.endswith('+cpu'), torch.__version__; print('torch', torch.__version__)"
