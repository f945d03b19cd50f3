#!/usr/bin/env bash
# Quick start, second command: install what is missing, build everything (Release) and run the
# whole test suite with ctest on both cores. .ci/run calls this.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/deps.sh
cmake --preset release
cmake --build --preset release
ctest --preset release
