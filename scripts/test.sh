#!/usr/bin/env bash
# The test command of the README and of CI: formatting, lints, the layering rule, and every test.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo fmt --all -- --check
# The README's headline figures are generated from bench/*.json, never copied by hand.
python3 scripts/figures.py --check README.md
cargo clippy --locked --workspace --all-targets --all-features --release -- -D warnings
# Layering (ARCHITECTURE.md): the light crates never pull the ML stack, and the product path
# never depends on the benchmark renderer.
deny() { # crate, forbidden dependency, why
  if cargo tree --locked -p "$1" -e normal --prefix none | grep -q "^$2 "; then
    echo "error: $1 depends on $2; $3" >&2
    exit 1
  fi
}
for crate in deocc-geometry deocc-io deocc-completion deocc-synth; do
  deny "$crate" candle-core "the geometry, I/O and completion-seam layers must stay free of the ML stack"
done
deny deocc-robot candle-core "robot tasks work on plain clouds, without the ML stack"
deny deocc-ros2 candle-core "the ROS 2 messages and synchroniser build without the ML stack (the node brings it, with --features ros2)"
for crate in deocc-completion deocc-pipeline deocc-model deocc-robot deocc-service deocc-python deocc-ros2; do
  deny "$crate" deocc-synth "the product path must not depend on the benchmark renderer"
done
deny deocc-pipeline candle-core "the pipeline talks to completers through deocc-completion, not candle"
deny deocc-model deocc-pipeline "the model implements the seams (deocc-completion, deocc-io's depth source); the pipeline calls it, never the reverse"
for crate in deocc-geometry deocc-io deocc-completion deocc-pipeline deocc-model deocc-robot deocc-service deocc-python deocc-ros2; do
  deny "$crate" deocc-eval "the product path must not depend on the evaluation crate"
done
# The product binary (deocc-cli without its `lab` feature: run, batch, serve, grasp, place,
# options) links neither the benchmark renderer nor the evaluation crate, and builds and lints
# clean on its own.
for lab in deocc-synth deocc-eval; do
  if cargo tree --locked -p deocc-cli --no-default-features -e normal --prefix none | grep -q "^$lab "; then
    echo "error: the product binary (deocc-cli --no-default-features) depends on $lab" >&2
    exit 1
  fi
done
cargo clippy --locked -p deocc-cli --no-default-features --all-targets --release -- -D warnings
# Two test threads on two cores: candle's and rayon's pools collapse when oversubscribed.
# --all-features: the ROS 2 bridge (deocc-ros2's `ros2` feature) and its loopback test, which
# needs a large UDP receive buffer.
bash scripts/dds-buffers.sh
RUST_TEST_THREADS=2 cargo test --locked --workspace --all-features --release --no-fail-fast
# The Python package: wheel built, installed in a venv, tested against the CLI.
bash scripts/test_python.sh
# report.html in headless Chromium: loads without error, the canvas draws generated points.
bash scripts/test_browser.sh
