#!/usr/bin/env bash
# The ctest smoke run of one libFuzzer target: fuzz for SECONDS in fork mode (which keeps going
# after a finding, so one run lists them all), then judge every artifact it wrote. A crash, a
# sanitizer report, a leak or a timeout fails the test. An out-of-memory input fails it too,
# unless ACCEPT_OOM is 1 and the target, rerun on it with MPM_FUZZ_ISOLATE=1 (the production
# path, where load_mesh reads the file in a child process with a memory budget), handles it.
#
# run_fuzzer.sh FUZZER CORPUS ARTIFACTS SECONDS ACCEPT_OOM [SEED_DIR...]
set -uo pipefail
fuzzer=$1 corpus=$2 artifacts=$3 seconds=$4 accept_oom=$5
shift 5
rm -rf "$artifacts"
mkdir -p "$corpus" "$artifacts"
"$fuzzer" "$corpus" "$@" -fork=1 -ignore_crashes=1 -ignore_timeouts=1 -ignore_ooms=1 \
  -max_total_time="$seconds" -rss_limit_mb=4096 -timeout=10 -artifact_prefix="$artifacts/"
fuzzer_status=$?
status=0
# A failure that left nothing to judge (the fuzzer did not start, or died outside an input).
if [ $fuzzer_status -ne 0 ] && [ -z "$(ls -A "$artifacts")" ]; then
  echo "FINDING: $fuzzer exited with $fuzzer_status and wrote no artifact"
  status=1
fi
for f in "$artifacts"/*; do
  [ -e "$f" ] || continue
  if [[ $(basename "$f") == oom-* && $accept_oom == 1 ]] &&
    MPM_FUZZ_ISOLATE=1 "$fuzzer" "$f" >/dev/null 2>&1; then
    echo "handled: $f (the reader runs out of memory in-process; in a child it is a MeshError)"
  else
    echo "FINDING: $f (rerun: $fuzzer $f)"
    status=1
  fi
done
[ $status -eq 0 ] && echo "no findings"
exit $status
