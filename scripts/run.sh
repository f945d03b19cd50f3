#!/usr/bin/env bash
# Quick start, first command: install what is missing, build the release `mpm`, run the debris
# flow against the barrier (data/scenes/debris_wall.json, or the scene given) into
# out/<scene name>, and plot the wall forces and a picture of the flow.
# Usage: scripts/run.sh [SCENE.json] [OUTDIR]
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/deps.sh
ensure_packages python3-matplotlib python3-h5py python3-numpy
scene=${1:-data/scenes/debris_wall.json}
out=${2:-out/$(basename "$scene" .json)}
[ -f build/build.ninja ] || cmake --preset release >/dev/null
cmake --build build --target mpm -j2
build/bin/mpm run "$scene" -o "$out" --overwrite
/usr/bin/python3 scripts/plot_run.py "$out"
echo "Results in $out: particles.xmf and wall_*.xmf (open in ParaView), history.csv,"
echo "summary.json (peak force per wall, run-out: furthest particle and where the deposit is"
echo "0.5 and 1 m deep, retained volume), forces.png, render.png"
