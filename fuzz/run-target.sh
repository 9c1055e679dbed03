#!/bin/sh
# Usage: fuzz/run-target.sh TARGET SECONDS [extra libFuzzer flags]
# Runs one target (ASan, debug assertions) on stable via RUSTC_BOOTSTRAP, niced,
# on the working corpus fuzz/corpus-raw/TARGET (seeded from fuzz/corpus/TARGET),
# with a 1 s per-input timeout and a 2048 MB RSS cap; log in fuzz/logs/TARGET.log.
# SANITIZER=none skips AddressSanitizer (the readers are safe Rust; several times faster).
set -eu
cd "$(dirname "$0")"
t=$1; secs=$2; shift 2
mkdir -p corpus-raw/"$t" logs
[ -d corpus/"$t" ] && cp -n corpus/"$t"/* corpus-raw/"$t"/ 2>/dev/null || true
RUSTC_BOOTSTRAP=1 nice -n "${NICE:-10}" cargo fuzz run -a -s "${SANITIZER:-address}" "$t" corpus-raw/"$t" -- \
  -max_total_time="$secs" -timeout=1 -rss_limit_mb=2048 -max_len=16384 \
  -print_final_stats=1 "$@" 2>&1 | tee logs/"$t".log | grep -E "^#[0-9]+ +(DONE|INITED)|ERROR|SUMMARY|stat::|Test unit written" 
