#!/usr/bin/env bash
# Set up forestmap on a fresh machine: the system libraries open3d and off-screen VTK need
# (installed with apt, as root or through sudo, only when missing), then a virtual environment
# .venv with forestmap and its dev extra (tests, ruff, Jupyter Lab for notebooks/) in it.
#
#   bash scripts/setup.sh           install what is missing; one line per thing it installs
#   bash scripts/setup.sh --check   one line per system library (found / missing); installs
#                                   nothing and exits 0
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck source=scripts/system_libs.sh
source scripts/system_libs.sh

case "${1:-}" in
  "") ;;
  --check) check_system_libs; exit 0 ;;
  -h | --help) echo "usage: bash scripts/setup.sh [--check]"; exit 0 ;;
  *) echo "setup: unknown option '$1' (usage: bash scripts/setup.sh [--check])" >&2; exit 2 ;;
esac

check_system_libs >/dev/null  # sets MISSING_PACKAGES
if [ ${#MISSING_PACKAGES[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ]; then SUDO=(); elif command -v sudo >/dev/null; then SUDO=(sudo); else
    echo "setup: system packages ${MISSING_PACKAGES[*]} are missing and neither root nor sudo is" \
         "available; ask an administrator to install them (bash scripts/setup.sh --check lists" \
         "the libraries)" >&2
    exit 1
  fi
  for package in "${MISSING_PACKAGES[@]}"; do echo "setup: installing $package (apt)"; done
  "${SUDO[@]}" apt-get update -qq
  # env: sudo drops the caller's environment, so DEBIAN_FRONTEND goes in through env
  "${SUDO[@]}" env DEBIAN_FRONTEND=noninteractive \
    apt-get install -y -qq "${MISSING_PACKAGES[@]}" >/dev/null
fi
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating the virtual environment $(pwd)/.venv"
  python3 -m venv .venv
fi
echo "setup: installing the latest pip into .venv"
.venv/bin/python -m pip install -q --upgrade pip
echo "setup: installing forestmap (editable, with its dev extra) into .venv"
.venv/bin/python -m pip install -q -e ".[dev]"
echo "forestmap installed in $(pwd)/.venv"
# the numba kernels, compiled once into their disk cache so that no run pays for it (issue 16);
# skipped while the cache is current; a failure here only means the first run compiles them
if ! .venv/bin/python -m forestmap_assets.warm_kernels --check >/dev/null; then
  echo "setup: compiling forestmap's kernels into their cache (once, about 3 min on 2 cores)"
  .venv/bin/python -m forestmap_assets.warm_kernels || true
fi
