#!/usr/bin/env bash
# Set up forestmap on a fresh machine: the system libraries open3d and off-screen VTK need
# (installed with apt only when missing), then a virtual environment with forestmap in it.
set -euo pipefail
cd "$(dirname "$0")/.."
need=()
have() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have 'libusb-1.0.so.0' || need+=(libusb-1.0-0)        # open3d
have 'libEGL.so.1' || need+=(libegl1 libgl1-mesa-dri)  # pyvista/VTK off-screen rendering
if [ ${#need[@]} -gt 0 ]; then
  echo "installing ${need[*]} with apt..."
  if [ "$(id -u)" = 0 ]; then SUDO=""; elif command -v sudo >/dev/null; then SUDO="sudo"; else
    echo "setup: ${need[*]} missing and neither root nor sudo is available" >&2; exit 1; fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need[@]}" >/dev/null
fi
[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[dev]"
echo "forestmap installed in $(pwd)/.venv"
