#!/usr/bin/env bash
# The ctest smoke run of one libFuzzer target, then the judging of every artifact it wrote: a
# crash, a sanitizer report, a leak or a timeout fails the test. An out-of-memory input (libFuzzer's
# or the sanitizer allocator's) fails it too, unless ACCEPT_OOM is 1 and the target, rerun on it
# with MPM_FUZZ_ISOLATE=1 (the production path, where load_mesh reads the file in a child process
# with a memory budget), handles it.
#
# run_fuzzer.sh FUZZER CORPUS ARTIFACTS RUNS SECONDS ACCEPT_OOM [SEED_DIR...]
#
# Two modes:
# - reproducible (the default, what ctest and CI run): RUNS inputs from a fixed random seed,
#   starting from the seed directories alone (a fresh CORPUS), so the same commit explores the
#   same inputs on every machine and a CI verdict can be reproduced. A run stopped early by an
#   out-of-memory input that the production path handles goes on with the next seed (at most 4).
# - exploring (MPM_FUZZ_EXPLORE=1): fork mode for SECONDS from a random seed on the kept CORPUS,
#   going on after findings; for longer runs by hand (docs/reliability.md). What it finds becomes
#   a regression input under tests/fuzz/regressions.
set -uo pipefail
fuzzer=$1 corpus=$2 artifacts=$3 runs=$4 seconds=$5 accept_oom=$6
shift 6
rm -rf "$artifacts"
mkdir -p "$artifacts"
common=(-rss_limit_mb=4096 -timeout=10 -artifact_prefix="$artifacts/")
# What a seeded run needs to be reproducible (checked: two runs of 2,500 inputs gave the same
# coverage at every step; without any one of these they parted within 400 inputs): no rereading
# of the corpus directory on a clock (-reload=0); ASLR off (setarch -R, where allowed), or the
# libraries' address-dependent orders change the coverage; and the same input file name in every
# run (MPM_FUZZ_FIXED_NAME, in a directory of this build tree), not one made of the pid.
norandom=()
if setarch "$(uname -m)" -R true 2>/dev/null; then norandom=(setarch "$(uname -m)" -R); fi

# An input the production path survives though the in-process target ran out of memory on it.
handled_oom() {
  [[ $accept_oom == 1 ]] || return 1
  local report
  report=$("$fuzzer" -rss_limit_mb=4096 "$1" 2>&1)
  grep -q -E 'out-of-memory|allocator is out of memory' <<<"$report" || return 1
  MPM_FUZZ_ISOLATE=1 "$fuzzer" "$1" >/dev/null 2>&1
}

status=0
if [[ ${MPM_FUZZ_EXPLORE:-0} == 1 ]]; then
  mkdir -p "$corpus"
  "$fuzzer" "$corpus" "$@" -fork=1 -ignore_crashes=1 -ignore_timeouts=1 -ignore_ooms=1 \
    -max_total_time="$seconds" "${common[@]}"
  fuzzer_status=$?
  if [ $fuzzer_status -ne 0 ] && [ -z "$(ls -A "$artifacts")" ]; then
    echo "FINDING: $fuzzer exited with $fuzzer_status and wrote no artifact"
    status=1
  fi
else
  export MPM_FUZZ_FIXED_NAME=1 TMPDIR="$artifacts.tmp"
  rm -rf "$TMPDIR"
  mkdir -p "$TMPDIR"
  for seed in 1 2 3 4; do
    rm -rf "$corpus"
    mkdir -p "$corpus"
    before=$(ls "$artifacts" | wc -l)
    "${norandom[@]}" "$fuzzer" "$corpus" "$@" -seed=$seed -runs="$runs" -reload=0 "${common[@]}"
    fuzzer_status=$?
    new=$(ls -t "$artifacts" | head -n $(($(ls "$artifacts" | wc -l) - before)))
    if [ $fuzzer_status -eq 0 ]; then
      echo "seed $seed: $runs inputs, no findings"
      break
    fi
    if [ -z "$new" ]; then
      echo "FINDING: $fuzzer exited with $fuzzer_status and wrote no artifact (seed $seed)"
      status=1
      break
    fi
    # Only a handled out-of-memory input lets the run go on (with the next seed).
    if ! handled_oom "$artifacts/$new"; then break; fi
    echo "seed $seed stopped at a handled out-of-memory input; next seed"
  done
fi
for f in "$artifacts"/*; do
  [ -e "$f" ] || continue
  if handled_oom "$f"; then
    echo "handled: $f (the reader runs out of memory in-process; in a child it is a MeshError)"
  else
    echo "FINDING: $f (rerun: $fuzzer $f)"
    status=1
  fi
done
[ $status -eq 0 ] && echo "no findings"
exit $status
