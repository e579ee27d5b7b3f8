#!/usr/bin/env bash
# Sets up a fresh machine for deocc and builds it. Safe to run again.
# Needs only the Rust toolchain (no apt packages are required on the main path; the optional peer
# comparisons install their own with scripts/setup-peers.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
if ! command -v cargo >/dev/null 2>&1; then
  echo "error: cargo not found. Install Rust with rustup (https://rustup.rs) and run this again." >&2
  exit 1
fi
if command -v rustup >/dev/null 2>&1; then
  rustup component add rustfmt clippy >/dev/null 2>&1 || echo "warning: could not add rustfmt/clippy with rustup" >&2
fi
cargo build --release --locked --bin deocc
echo "deocc built: target/release/deocc"
