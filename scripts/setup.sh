#!/usr/bin/env bash
# Sets up a fresh machine for deocc and builds it. Safe to run again.
# Needs the Rust toolchain, and Python 3.9+ with venv for the Python package's test (the wheel's
# build tools and numpy are installed into target/py-venv by scripts/test_python.sh). No apt
# package is required to build; the report.html browser test installs Debian's chromium
# (scripts/setup-browser.sh), the optional peer comparisons theirs (scripts/setup-peers.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v cargo >/dev/null 2>&1; then
  echo "error: cargo not found. Install Rust with rustup (https://rustup.rs) and run this again." >&2
  exit 1
fi
if command -v rustup >/dev/null 2>&1; then
  rustup component add rustfmt clippy >/dev/null 2>&1 || echo "warning: could not add rustfmt/clippy with rustup" >&2
fi
if ! python3 -c 'import sys, venv; sys.exit(sys.version_info < (3, 9))' 2>/dev/null; then
  echo "warning: python3 >= 3.9 with venv not found: the Python package's test (scripts/test_python.sh) needs it" >&2
fi
bash scripts/dds-buffers.sh
# Chromium, for the report.html browser test.
bash scripts/setup-browser.sh || echo "warning: could not install chromium: scripts/test_browser.sh will fail" >&2
# deocc and its tests, built once exactly as scripts/test.sh builds them (same profile and
# features, so the test run compiles nothing again).
cargo test --release --locked --workspace --all-features --no-run
echo "deocc built: target/release/deocc (and target/release/deocc-ros2, the ROS 2 bridge)"
