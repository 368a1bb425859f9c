#!/usr/bin/env bash
# Runs every fuzz target for RUNS executions (default 1,000,000), one at a time, with a time cap
# per target, and prints libFuzzer's final line per target. Needs cargo-fuzz; works on a stable
# toolchain through RUSTC_BOOTSTRAP=1 (see README.md).
set -uo pipefail
cd "$(dirname "$0")"
RUNS="${RUNS:-1000000}"
MAX_TIME="${MAX_TIME:-900}"
export RUSTC_BOOTSTRAP=1
for t in $(cargo fuzz list); do
  mkdir -p "corpus/$t"
  log="$(mktemp)"
  cargo fuzz run -O "$t" "corpus/$t" -- -runs="$RUNS" -max_total_time="$MAX_TIME" -max_len=70000 -print_final_stats=1 >"$log" 2>&1
  rc=$?
  execs=$(grep -E "^stat::number_of_executed_units" "$log" | awk '{print $2}')
  echo "$t rc=$rc executions=${execs:-?} $(grep -E '^(Done|==[0-9]+==ERROR|SUMMARY)' "$log" | head -2 | tr '\n' ' ')"
  if [ $rc -ne 0 ]; then tail -40 "$log"; fi
  rm -f "$log"
done
