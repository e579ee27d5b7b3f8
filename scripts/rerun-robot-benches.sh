#!/usr/bin/env bash
# Reruns the robot-task benchmarks (pickup-v1, pickup-v2, place-v1) clean and under every sensor
# model, full test splits, into bench/: what a change to the front half or the shipped weights
# moves. About 45 minutes on 2 cores. `scripts/figures.py --write README.md` afterwards.
set -euo pipefail
cd "$(dirname "$0")/.."
deocc=${DEOCC:-target/release/deocc}  # DEOCC=path: a copy, so that a rebuild cannot change it mid-run
run() { echo "== $*" >&2; "$deocc" "$@" > /dev/null; }
for s in structured-light clean active-stereo time-of-flight; do
  suffix=$([ "$s" = clean ] && echo "" || echo "-$s")
  run eval place --sensor "$s" --json "bench/place$suffix.json"
  run eval grasp --preset pickup-v2 --sensor "$s" --json "bench/pickup-v2$suffix.json"
done
run eval grasp --json bench/grasp.json
run eval grasp --sensor structured-light --json bench/grasp-structured-light.json
