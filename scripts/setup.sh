#!/usr/bin/env bash
# Create .venv and install the project with its pinned dependencies.
# torch is installed first, pinned to the CPU build (2.13.0+cpu): on these machines the wheel lies
# in /opt/wheels (TORCH_WHEEL_DIR overrides); the "+cpu" pin means no CUDA build is ever pulled.
set -euo pipefail
cd "$(dirname "$0")/.."
# System packages, installed only when missing, only as root with apt-get;
# BRDF_SKIP_SYSTEM_PACKAGES=1 skips this (image builds):
# - chromium, chromium-driver: headless browser tests of the dashboard;
# - libllvm19: Mitsuba's vectorised llvm_ad_rgb variant (paper-BRDF ground truth, core/synth/mitsuba_paper.py);
#   Debian's default LLVM 14/15 cannot compile its kernels ("Cannot select: fminimum").
if [ "${BRDF_SKIP_SYSTEM_PACKAGES:-0}" != "1" ] && [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
  pkgs=""
  { command -v chromium >/dev/null 2>&1 && command -v chromedriver >/dev/null 2>&1; } || pkgs="chromium chromium-driver"
  ls /usr/lib/x86_64-linux-gnu/libLLVM.so.19* /usr/lib/*/libLLVM-19.so >/dev/null 2>&1 || pkgs="$pkgs libllvm19"
  if [ -n "$pkgs" ]; then
    echo "installing system packages:$pkgs"
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $pkgs >/dev/null \
      || echo "warning: could not install$pkgs (the tests that need them will be skipped or fail)"
  fi
fi
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
