#!/usr/bin/env bash
# Install byoc-cli and everything it needs (CPU build of PyTorch first, so pip never pulls
# a multi-GB CUDA build). Idempotent: safe to run again.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# open3d needs the system library libusb-1.0 on Linux
if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "setup: libusb-1.0 is missing; install it (apt-get install libusb-1.0-0) for open3d" >&2
  fi
fi

# the CPU wheel of torch before anything else asks for torch
if ! "$PY" -c "import torch" 2>/dev/null; then
  "$PY" -m pip install -q "torch==2.13.0"
fi
"$PY" -m pip install -q -e ".[test]"
"$PY" -c "import byoc_cli, torch, open3d; print('byoc-cli', byoc_cli.__version__, '| torch', torch.__version__, '| open3d', open3d.__version__)" >&2
