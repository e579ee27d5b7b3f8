#!/usr/bin/env bash
# Installs Debian's Chromium for the report.html browser test (scripts/test_browser.sh), if it is
# not there yet. Safe to run again.
set -euo pipefail
if command -v chromium >/dev/null 2>&1; then
  exit 0
fi
sudo_if() { if [[ $(id -u) -eq 0 ]]; then "$@"; else sudo "$@"; fi; }
export DEBIAN_FRONTEND=noninteractive
if ! sudo_if apt-get install -y --no-install-recommends chromium >/dev/null 2>&1; then
  sudo_if apt-get update >/dev/null
  sudo_if apt-get install -y --no-install-recommends chromium >/dev/null
fi
command -v chromium >/dev/null
