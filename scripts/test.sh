#!/usr/bin/env bash
# Quick start, second command: install what is missing, build everything (Release) and run the
# whole test suite with ctest on both cores; then the sanitizer and fuzzing stage. .ci/run calls
# this.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/deps.sh
cmake --preset release
cmake --build --preset release
ctest --preset release

# Sanitizers and fuzzing (docs/reliability.md): a clang build with address and undefined-
# behaviour sanitizers of the input paths (scene loader, mesh import and repair, output,
# checkpoints, materials), their tests, and the two libFuzzer targets for MPM_FUZZ_SECONDS each
# (60 here; longer by hand: build-fuzz/tests/fuzz_scene CORPUS -max_total_time=3600).
ensure_packages clang libclang-rt-14-dev
cmake --preset fuzz
cmake --build --preset fuzz --target mpm fuzz_scene fuzz_mesh test_cli test_checkpoint \
  test_materials test_output test_mesh_import test_mesh_repair
ctest --preset fuzz -R \
  '^(fuzz_|CommandLine\.|Walls/Checkpoint\.|KilledRun\.|DruckerPrager\.|Bingham\.|NewtonianFluid\.|ParticleWriter\.|MeshImport\.|MeshRepair\.)'
