// Throughput of the 3D step: an elastic block (Neo-Hookean), quadratic B-spline, MUSL/APIC,
// 8 particles per cell. Reports particle-steps per second (items/s) so it can be set against
// ../shared/tools/yardstick/run.sh measured in the same session.
//
//   BM_StandardStep3D/N  : an N^3-cell block in free flight, no walls (the bare step)
//   BM_StandardStepUSL3D/N : the same with USL, one transfer each way as the yardstick's MLS-MPM
//                          step (MUSL, the default, maps the momenta back to the grid and
//                          gathers again: two transfers each way)
//   BM_StandardStepSparse3D/N : BM_StandardStep3D on the sparse grid layout (grid "storage")
//   BM_FloorStep3D/N/m   : floor_scene(N, m) (bench/perf_scenes.hpp): a block resting on a floor,
//                          10% of its particles within h of it; m the wall method
//   BM_FloorStepMLS3D/N/m : the same under MLS-MPM
//
// BM_StandardStep3D also reports bytes_per_particle: the heap the solver holds after its first
// step (particles and step scratch; glibc's count of bytes in use, from before the solver is
// made) plus the pages the grid's node arrays hold, per particle (issue 9's target: 400 in 3D).
// Every benchmark reports milliseconds per step in each phase (ms_p2g, ms_g2p, ...).

#include <benchmark/benchmark.h>

#include "mpm/solver.hpp"
#include "perf_scenes.hpp"

namespace {

using mpm::perf::block_scene;
using mpm::perf::floor_scene;
using mpm::perf::heap_bytes;

// Milliseconds per step in each phase between `before` and now, over the state's iterations
// (where the time goes: the transfers, the dual-grid overhead).
void phase_counters(benchmark::State& state, const mpm::Solver<3>& solver,
                    const mpm::PhaseTimes& before) {
  const mpm::PhaseTimes ms =
      mpm::perf::ms_per_step(solver.phase_times(), before, static_cast<double>(state.iterations()));
  state.counters["ms_locate"] = ms.locate;
  state.counters["ms_p2g"] = ms.particles_to_grid;
  state.counters["ms_grid"] = ms.grid_update;
  state.counters["ms_walls"] = ms.walls;
  state.counters["ms_coupling"] = ms.coupling;
  state.counters["ms_g2p"] = ms.grid_to_particles;
  state.counters["ms_stress"] = ms.stress;
  state.counters["ms_advect"] = ms.advect;
}

void standard_step(benchmark::State& state, const char* update, const char* storage = "auto") {
  const mpm::Scene scene = block_scene(static_cast<int>(state.range(0)), update, storage);
  const double before = heap_bytes();
  mpm::Solver<3> solver(scene);
  const double dt = solver.stable_dt(0.3);
  solver.step(dt);
  // The grid's node arrays are page-backed mappings outside the heap: add the pages they hold.
  const double grown = heap_bytes() - before + static_cast<double>(solver.grid.committed_bytes());
  const mpm::PhaseTimes before_steps = solver.phase_times();
  for (auto _ : state) solver.step(dt);
  state.SetItemsProcessed(static_cast<int64_t>(state.iterations()) *
                          static_cast<int64_t>(solver.particle_count()));
  phase_counters(state, solver, before_steps);
  state.counters["particles"] = static_cast<double>(solver.particle_count());
  state.counters["bytes_per_particle"] = grown / static_cast<double>(solver.particle_count());
}
void BM_StandardStep3D(benchmark::State& state) { standard_step(state, "musl"); }
BENCHMARK(BM_StandardStep3D)
    ->Arg(16)
    ->Arg(32)
    ->Arg(48)
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();
void BM_StandardStepUSL3D(benchmark::State& state) { standard_step(state, "usl"); }
BENCHMARK(BM_StandardStepUSL3D)->Arg(32)->Unit(benchmark::kMillisecond)->UseRealTime();
// MLS-MPM (Hu et al. 2018): USL's order, with the force and the velocity gradient from the APIC
// moment (the yardstick's algorithm).
void BM_StandardStepMLS3D(benchmark::State& state) { standard_step(state, "mls"); }
BENCHMARK(BM_StandardStepMLS3D)->Arg(32)->Unit(benchmark::kMillisecond)->UseRealTime();
// The same block in the sparse grid layout (a box the block fills is dense by default): what
// the blocked, page-backed storage costs the transfers.
void BM_StandardStepSparse3D(benchmark::State& state) { standard_step(state, "musl", "sparse"); }
BENCHMARK(BM_StandardStepSparse3D)->Arg(32)->Unit(benchmark::kMillisecond)->UseRealTime();

void floor_step(benchmark::State& state, const char* update) {
  const mpm::Scene scene =
      floor_scene(static_cast<int>(state.range(0)), static_cast<int>(state.range(1)), update);
  mpm::Solver<3> solver(scene);
  const double dt = solver.stable_dt(0.3);
  for (int k = 0; k < 5; ++k) solver.step(dt);  // settle onto the floor
  // Factorisations and refinement passes of the timed steps only (the settling steps factorise
  // for every new contact pattern).
  const mpm::perf::SolveCount solves0 = mpm::perf::solve_count(solver);
  const mpm::PhaseTimes before = solver.phase_times();
  for (auto _ : state) solver.step(dt);
  const auto steps = static_cast<double>(state.iterations());
  phase_counters(state, solver, before);
  std::size_t in_layer = 0;
  for (const auto& w : solver.dual_walls()) in_layer += w.layer_particles;
  state.SetItemsProcessed(static_cast<int64_t>(state.iterations()) *
                          static_cast<int64_t>(solver.particle_count()));
  state.counters["particles"] = static_cast<double>(solver.particle_count());
  if (!solver.dual_walls().empty()) {
    const mpm::perf::SolveCount per =
        mpm::perf::per_step(mpm::perf::solve_count(solver), solves0, steps);
    state.counters["factorizations_per_step"] = per.factorizations;
    state.counters["refinements_per_step"] = per.refinements;
    // The coupling's parts, milliseconds per step (wall clock; it runs beside the gather).
    state.counters["ms_assembly"] = per.assembly;
    state.counters["ms_factorizing"] = per.factorizing;
    state.counters["ms_solves"] = per.solves;
  }
  state.counters["in_layer"] =
      static_cast<double>(in_layer) / static_cast<double>(solver.particle_count());
}
void BM_FloorStep3D(benchmark::State& state) { floor_step(state, "musl"); }
BENCHMARK(BM_FloorStep3D)
    ->ArgsProduct({{32}, {0, 1, 2, 3, 4}})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();
void BM_FloorStepMLS3D(benchmark::State& state) { floor_step(state, "mls"); }
BENCHMARK(BM_FloorStepMLS3D)
    ->ArgsProduct({{32}, {0, 1, 2, 3, 4}})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
