#!/usr/bin/env bash
# Quick start, first command: install what is missing, build the release `mpm`, and run the
# default scene (or the scene given) into out/<scene name>.
# Usage: scripts/run.sh [SCENE.json] [OUTDIR]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/deps.sh
scene=${1:-data/scenes/default.json}
out=${2:-out/$(basename "$scene" .json)}
[ -f build/build.ninja ] || cmake --preset release >/dev/null
cmake --build build --target mpm -j2
build/bin/mpm run "$scene" -o "$out" --overwrite
echo "Results in $out: particles.xmf (open in ParaView), history.csv, summary.json"
