#!/usr/bin/env bash
# Install byoc-cli and everything it needs (CPU build of PyTorch first, so pip never pulls
# a multi-GB CUDA build). Idempotent: safe to run again. Use it inside a virtual
# environment (python3 -m venv .venv && . .venv/bin/activate).
#
#   PYTHON=python3.12 bash scripts/setup.sh           another interpreter
#   BYOC_TORCH_INDEX=URL bash scripts/setup.sh        another wheel index for torch
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
TORCH="torch==2.13.0"
CPU_INDEX=${BYOC_TORCH_INDEX:-https://download.pytorch.org/whl/cpu}

# open3d needs the system library libusb-1.0 on Linux
if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "setup: libusb-1.0 is missing; install it (apt-get install libusb-1.0-0) for open3d" >&2
  fi
fi

index_reachable() {
  "$PY" - "$1" <<'PYEOF' >/dev/null 2>&1
import sys
import urllib.request

urllib.request.urlopen(sys.argv[1].rstrip("/") + "/torch/", timeout=15)
PYEOF
}

# the CPU wheel of torch before anything else asks for torch: from PyTorch's CPU index when
# it can be reached, else (offline mirror, proxy, no network) from pip's default index
if ! "$PY" -c "import torch" 2>/dev/null; then
  if index_reachable "$CPU_INDEX" &&
    "$PY" -m pip install -q --index-url "$CPU_INDEX" "$TORCH"; then
    echo "setup: installed $TORCH from the CPU wheel index $CPU_INDEX" >&2
  else
    echo "setup: the CPU wheel index $CPU_INDEX cannot be used; installing $TORCH from" \
      "pip's default index (on Linux x86-64 that may be a CUDA build of several GB)" >&2
    "$PY" -m pip install -q "$TORCH"
  fi
fi
"$PY" -m pip install -q -e ".[test]"
"$PY" - <<'PYEOF' >&2
import byoc_cli
import open3d
import torch

build = f"CUDA {torch.version.cuda} build" if torch.version.cuda else "CPU build"
print(f"setup: torch {torch.__version__} ({build}); byoc-cli {byoc_cli.__version__}; "
      f"open3d {open3d.__version__}")
PYEOF
