#!/usr/bin/env bash
# report.html in a real headless browser (Debian's Chromium): the page of `deocc run --example`
# loads without a script error (the page sets <body data-status="ok"> only after drawing; any
# error sets it to "error: ...") and its canvas shows generated points. Called by scripts/test.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-browser.sh
out=target/browser-test
cargo build --release --locked --workspace --all-features --bin deocc >/dev/null 2>&1 || true
./target/release/deocc run --example --completer rules --out "$out" >/dev/null
body=$(timeout 120 chromium --headless=new --no-sandbox --disable-gpu --virtual-time-budget=20000 \
  --dump-dom "file://$PWD/$out/report.html" 2>/dev/null | grep -o '<body[^>]*>' || true)
echo "report.html in Chromium: $body"
if [[ $body != *'data-status="ok"'* ]]; then
  echo "error: report.html did not load and draw cleanly: ${body:-no <body> in the DOM}" >&2
  exit 1
fi
generated=$(sed -E 's/.*data-generated-pixels="([0-9]+)".*/\1/' <<<"$body")
if (( generated < 100 )); then
  echo "error: the canvas shows only $generated pixels of generated points" >&2
  exit 1
fi
echo "browser test passed: $generated canvas pixels show generated points"
