#!/usr/bin/env bash
# Optional: installs the peers the benchmark scripts compare against (never used on the main path).
# Open3D 0.20 from PyPI needs libusb at import time on Debian.
set -euo pipefail
if command -v apt-get >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi
python3 -m pip install --quiet "open3d==0.20.0" "numpy<2.3"
python3 -c "import open3d; print('open3d', open3d.__version__)"
