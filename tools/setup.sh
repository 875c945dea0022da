#!/usr/bin/env bash
# One-shot setup of a fresh Debian machine for favormap (system packages + Python packages).
# Usage: bash tools/setup.sh        (as root, or with sudo available)
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
# open3d needs libusb; libgomp for torch/open3d threading
if ! ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0"; then
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq libusb-1.0-0 libgomp1 >/dev/null
fi
PY=${PYTHON:-python3}
# torch 2.13.0 first: on this platform it resolves to the CPU wheel (an unpinned torch pulls a CUDA build)
$PY -m pip install -q "torch==2.13.0"
$PY -m pip install -q -e ".[test]"
$PY -c "import favormap, open3d, pycolmap, torch, h5py, cv2, rerun, trimesh; print('favormap', favormap.__version__, 'ready')"
