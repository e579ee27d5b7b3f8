#!/usr/bin/env bash
# Fuzzes every reader of untrusted input with the seeded mutation fuzzer (deocc-fuzz): each
# target for SECONDS (default 300, the reliability issue's acceptance), failing on a panic or an
# allocation over 1 GB. Usage: bash scripts/fuzz.sh [SECONDS] [SEED]
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-300}
seed=${2:-0}
cargo build --release --locked --bin deocc-fuzz
for target in ply obj stl png cameras scene_json train_json safetensors pairs; do
  ./target/release/deocc-fuzz "$target" --seconds "$seconds" --seed "$seed" --max-alloc-mb 1024
done
