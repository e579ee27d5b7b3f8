#!/usr/bin/env bash
# The Python package's test: builds the abi3 wheel with maturin, installs it into a fresh venv
# (target/py-venv) with numpy, and runs crates/deocc-python/tests/test_deocc.py against the CLI
# built from the same tree. Called by scripts/test.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=target/py-venv
if [[ ! -x $venv/bin/python ]]; then
  python3 -m venv "$venv"
fi
"$venv/bin/pip" install --quiet --disable-pip-version-check "maturin>=1.9,<2" "numpy>=1.21"
rm -rf target/wheels
"$venv/bin/maturin" build --release --locked --compatibility linux \
  -m crates/deocc-python/Cargo.toml -o target/wheels 2>&1 | tee target/maturin.log
# The workspace's dependencies should come from scripts/test.sh's build (see the feature
# alignment in crates/deocc-python/Cargo.toml); more than the bindings compiling means drift.
recompiled=$(grep -E '^ *Compiling ' target/maturin.log | grep -vE ' (deocc-python|pyo3[a-z-]*|numpy|ndarray|rustc-hash|matrixmultiply|num-complex|num-integer|portable-atomic|indoc|unindent|memoffset|once_cell|target-lexicon|heck) ' || true)
if [[ -n $recompiled ]]; then
  echo "warning: maturin recompiled workspace dependencies (feature drift; align them in crates/deocc-python/Cargo.toml):" >&2
  echo "$recompiled" | head -20 >&2
fi
"$venv/bin/pip" install --quiet --disable-pip-version-check --force-reinstall --no-deps target/wheels/deocc-*.whl
# The CLI the test compares against: built exactly as scripts/test.sh's `cargo test` builds it
# (same feature unification, so nothing is compiled twice).
cargo test --release --locked --workspace --all-features --no-run
"$venv/bin/python" crates/deocc-python/tests/test_deocc.py target/release/deocc
