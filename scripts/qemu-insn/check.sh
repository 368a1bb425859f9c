#!/usr/bin/env bash
# Checks the instruction counter of scripts/aarch64-insns (insn.c, a QEMU plugin) against a
# guest loop of known length (loop.c): 1,000,000 more iterations of two instructions must count
# exactly 2,000,000 more instructions (the same digits to parse, the same start-up).
# Needs gcc, gcc-aarch64-linux-gnu with the arm64 libc, and qemu-aarch64.
set -euo pipefail
cd "$(dirname "$0")"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
gcc -shared -fPIC -O2 -Wall -o "$work/insn.so" insn.c
aarch64-linux-gnu-gcc -O1 -static -o "$work/loop" loop.c
count() { qemu-aarch64 -plugin "$work/insn.so" "$work/loop" "$1" 2>&1 >/dev/null | awk '/^insns /{print $2}'; }
a=$(count 1000000)
b=$(count 2000000)
echo "qemu-insn: 1,000,000 iterations: $a instructions; 2,000,000: $b"
if [ "$((b - a))" -ne 2000000 ]; then
  echo "qemu-insn: FAILED: the difference is $((b - a)), not 2000000" >&2
  exit 1
fi
echo "qemu-insn: ok (difference exactly 2,000,000)"
