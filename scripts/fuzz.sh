#!/usr/bin/env bash
# Fuzzes every reader of untrusted input with the seeded mutation fuzzer (deocc-fuzz): each
# target for SECONDS (default 300, the reliability issue's acceptance), failing on a panic or an
# allocation over 1 GB. Usage: bash scripts/fuzz.sh [SECONDS] [SEED]
# With the defaults the summary lines are also written to bench/fuzz.txt.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-300}
seed=${2:-0}
cargo build --release --locked --bin deocc-fuzz
summary=$(mktemp)
trap 'rm -f "$summary"' EXIT
{
  echo "# bash scripts/fuzz.sh $seconds $seed ($(git rev-parse --short HEAD 2>/dev/null || echo unknown), $(date -u +%F))"
  for target in ply obj stl png cameras scene_json train_json safetensors pairs; do
    ./target/release/deocc-fuzz "$target" --seconds "$seconds" --seed "$seed" --max-alloc-mb 1024
  done
} | tee "$summary"
if [[ $seconds == 300 && $seed == 0 ]]; then cp "$summary" bench/fuzz.txt; fi
