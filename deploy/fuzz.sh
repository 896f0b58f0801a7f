#!/usr/bin/env bash
# Runs every cargo-fuzz target in fuzz/ for a fixed number of executions and prints a
# Markdown table: target, executions, seconds, crashes. Needs a nightly toolchain and
# cargo-fuzz (installed here when missing); not part of `make test`.
#   deploy/fuzz.sh [RUNS]          (default 1000000 executions per target)
# A crash leaves its input in fuzz/artifacts/<target>/; keep it as a regression test.
set -uo pipefail
cd "$(dirname "$0")/.."
RUNS=${1:-1000000}
TARGETS=(depth color hello export zenoh_message)

rustup toolchain list | grep -q '^nightly' || rustup toolchain install nightly --profile minimal
command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz --locked
cargo +nightly fuzz build -O || exit 1

echo "| target | executions | seconds | edges covered | crashes |"
echo "|---|---|---|---|---|"
failed=0
for t in "${TARGETS[@]}"; do
  mkdir -p "fuzz/corpus/$t"
  log=$(mktemp)
  start=$(date +%s)
  # -rss_limit_mb: an allocation the input declares must never reach it.
  cargo +nightly fuzz run -O "$t" "fuzz/corpus/$t" -- -runs="$RUNS" -rss_limit_mb=2048 -max_len=65536 >"$log" 2>&1
  rc=$?
  secs=$(( $(date +%s) - start ))
  runs=$(grep -o 'Done [0-9]* runs' "$log" | grep -o '[0-9]*' | tail -1)
  edges=$(grep -o 'cov: [0-9]*' "$log" | grep -o '[0-9]*' | tail -1)
  crashes=$(ls "fuzz/artifacts/$t" 2>/dev/null | grep -c -E '^(crash|oom|leak|timeout)-' || true)
  echo "| $t | ${runs:-stopped} | $secs | ${edges:-?} | $crashes |"
  if [ "$rc" -ne 0 ]; then
    failed=1
    tail -30 "$log" >&2
  fi
  rm -f "$log"
done
exit $failed
