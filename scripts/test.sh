#!/usr/bin/env bash
# The test command of the README and of CI: formatting, lints, the layering rule, and every test.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo fmt --all -- --check
cargo clippy --locked --all-targets --release -- -D warnings
# Layering: the geometry and I/O crates must not pull the ML stack.
for crate in deocc-geometry deocc-io deocc-synth; do
  if cargo tree --locked -p "$crate" -e normal | grep -q candle; then
    echo "error: $crate depends on candle; the geometry layers must stay free of the ML stack" >&2
    exit 1
  fi
done
# Two test threads on two cores: candle's and rayon's pools collapse when oversubscribed.
RUST_TEST_THREADS=2 cargo test --locked --workspace --release
