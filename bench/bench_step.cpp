// Throughput of the standard 3D step: an elastic block (Neo-Hookean), quadratic B-spline,
// MUSL/APIC, 8 particles per cell, no walls. Reports particle-steps per second (items/s) so it
// can be set against ../shared/tools/yardstick/run.sh measured in the same session.

#include <benchmark/benchmark.h>

#include <nlohmann/json.hpp>

#include "mpm/solver.hpp"

namespace {

mpm::Scene block_scene(int cells) {
  // Grid box with a one-cell margin around a cube of `cells`^3 filled cells.
  const double h = 1.0 / cells;
  const nlohmann::json doc = {
      {"dimension", 3},
      {"grid", {{"min", {-h, -h, -h}}, {"max", {1.0 + h, 1.0 + h, 1.0 + h}}, {"spacing", h}}},
      {"shape_function", "bspline2"},
      {"scheme", {{"update", "musl"}, {"transfer", "apic"}}},
      {"materials",
       {{{"name", "m"},
         {"model", "neo_hookean"},
         {"density", 1000.0},
         {"youngs_modulus", 1.0e6},
         {"poisson_ratio", 0.3}}}},
      {"bodies",
       {{{"material", "m"},
         {"shape", {{"type", "box"}, {"min", {0.0, 0.0, 0.0}}, {"max", {1.0, 1.0, 1.0}}}},
         {"particles_per_cell", 2},
         {"velocity", {0.1, -0.2, 0.05}}}}},
      {"time", {{"end", 1.0}}},
  };
  return mpm::parse_scene(doc, "<bench>");
}

void BM_StandardStep3D(benchmark::State& state) {
  const mpm::Scene scene = block_scene(static_cast<int>(state.range(0)));
  mpm::Solver<3> solver(scene);
  const double dt = solver.stable_dt(0.3);
  for (auto _ : state) solver.step(dt);
  state.SetItemsProcessed(static_cast<int64_t>(state.iterations()) *
                          static_cast<int64_t>(solver.particle_count()));
  state.counters["particles"] = static_cast<double>(solver.particle_count());
}
BENCHMARK(BM_StandardStep3D)
    ->Arg(16)
    ->Arg(32)
    ->Arg(48)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
