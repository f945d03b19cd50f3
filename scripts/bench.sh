#!/usr/bin/env bash
# Reruns the benchmarks of docs/benchmarks.md and writes their CSV, PNG and tables into docs/:
# installs what is missing (matplotlib for the plots), builds the release `mpm`, then
#   mpm bench accuracy  -> docs/benchmarks_accuracy.csv, docs/img/benchmarks_accuracy.png,
#                          docs/benchmarks_pareto.md   (about 40 min on one core)
#   mpm bench stability -> docs/benchmarks_stability.csv, docs/img/benchmarks_stability.png,
#                          failing scenes in bench_failures/   (about 10 min)
# Usage: scripts/bench.sh [accuracy|stability] [extra mpm bench options, e.g. -j 1]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/deps.sh
ensure_packages python3-matplotlib
[ -f build/build.ninja ] || cmake --preset release >/dev/null
cmake --build build --target mpm -j2
kinds=${1:-"accuracy stability"}
shift || true
status=0
for kind in $kinds; do
  build/bin/mpm bench "$kind" --csv "docs/benchmarks_$kind.csv" "$@" || status=$?
  if [ "$kind" = accuracy ]; then
    /usr/bin/python3 scripts/bench_plot.py accuracy docs/benchmarks_accuracy.csv \
      docs/img/benchmarks_accuracy.png --table docs/benchmarks_pareto.md
  else
    /usr/bin/python3 scripts/bench_plot.py stability docs/benchmarks_stability.csv \
      docs/img/benchmarks_stability.png
  fi
done
exit $status
