#pragma once
// The scenes of issue 9's step targets, shared by bench/bench_step.cpp (Google Benchmark) and
// `mpm bench perf` (tools/perf.cpp), so that both time the same steps.
//
//   block_scene(N)     : an N^3-cell elastic block (Neo-Hookean, quadratic B-spline, APIC, 8
//                        particles per cell) in free flight, no walls: the bare step
//   floor_scene(N, m)  : an N x N x 10-cell block resting on a floor under gravity, so 10% of the
//                        particles are within h of it; m = 0: standard wall on the box face (grid
//                        line), 1: Blending mortar dual-grid floor, 2: one-way, 3: Enhanced
//                        velocity field, 4: mortar with Phi's multipliers merged within h
//                        ("multiplier_radius": 1). The dual-grid floor is a plane 0.3 h off the
//                        grid lines. The block's particles lie on its own lattice, so that the
//                        lowest touch the floor from the first step (on the grid's lattice the
//                        block began 0.2 h above that floor and fell freely through the whole
//                        benchmark: until 2026-12-03 the dual-grid ratios were those of a block
//                        in free fall, docs/performance.md).

#include <malloc.h>

#include <nlohmann/json.hpp>

#include "mpm/scene.hpp"
#include "mpm/solver.hpp"
#include "support/shapes.hpp"

namespace mpm::perf {

inline nlohmann::json material() {
  return {{"name", "m"},
          {"model", "neo_hookean"},
          {"density", 1000.0},
          {"youngs_modulus", 1.0e6},
          {"poisson_ratio", 0.3}};
}

inline mpm::Scene block_scene(int cells, const char* update = "musl",
                              const char* storage = "auto") {
  // Grid box with a one-cell margin around a cube of `cells`^3 filled cells.
  const double h = 1.0 / cells;
  const nlohmann::json doc = {
      {"dimension", 3},
      {"grid",
       {{"min", {-h, -h, -h}},
        {"max", {1.0 + h, 1.0 + h, 1.0 + h}},
        {"spacing", h},
        {"storage", storage}}},
      {"shape_function", "bspline2"},
      {"scheme", {{"update", update}, {"transfer", "apic"}}},
      {"materials", nlohmann::json::array({material()})},
      {"bodies",
       {{{"material", "m"},
         {"shape", {{"type", "box"}, {"min", {0.0, 0.0, 0.0}}, {"max", {1.0, 1.0, 1.0}}}},
         {"particles_per_cell", 2},
         {"velocity", {0.1, -0.2, 0.05}}}}},
      {"time", {{"end", 1.0}}},
  };
  return mpm::parse_scene(doc, "<bench>");
}

inline mpm::Scene floor_scene(int cells, int method, const char* update = "musl") {
  const double h = 1.0 / cells;
  const double base = method == 0 ? 0.0 : 0.3 * h;  // dual-grid floor off the grid lines
  nlohmann::json wall;
  if (method == 0) {
    wall = {{"face", "zmin"}, {"condition", "slip"}, {"separable", true}};
  } else {
    wall = {{"name", "floor"},
            {"surface",
             {{"type", "mesh"},
              {"file", mpm::test::floor_plane_file("mpm_bench", base, -h, 1.0 + h).string()},
              {"remesh", true}}},
            {"method", method == 1 || method == 4 ? "mortar"
                       : method == 2              ? "one-way"
                                                  : "enhanced"},
            {"condition", "slip"},
            {"separable", true}};
    if (method == 4) wall["multiplier_radius"] = 1.0;
  }
  const nlohmann::json doc = {
      {"dimension", 3},
      {"grid", {{"min", {-h, -h, 0.0}}, {"max", {1.0 + h, 1.0 + h, 12.0 * h}}, {"spacing", h}}},
      {"shape_function", "bspline2"},
      {"scheme", {{"update", update}, {"transfer", "apic"}}},
      {"gravity", {0.0, 0.0, -9.81}},
      {"materials", nlohmann::json::array({material()})},
      {"bodies",
       {{{"material", "m"},
         {"shape",
          {{"type", "box"},
           {"min", {0.0, 0.0, base}},
           {"max", {1.0, 1.0, base + 10.0 * h}},
           {"lattice", "body"}}},
         {"particles_per_cell", 2}}}},
      {"walls", nlohmann::json::array({wall})},
      {"time", {{"end", 1.0}}},
  };
  return mpm::parse_scene(doc, "<bench>");
}

/// Heap bytes in use (glibc: small blocks and mmapped ones).
inline double heap_bytes() {
  const struct mallinfo2 info = ::mallinfo2();
  return static_cast<double>(info.uordblks + info.hblkhd);
}

/// The dual-grid walls' factorisations, refinement passes and time by part so far, summed over
/// the walls (Simulation::coupling_work()); per_step() makes it per step.
struct SolveCount {
  double factorizations = 0.0, refinements = 0.0;
  /// Seconds (CouplingWork): assembly, analysis and numeric factorisation, solves (per_step():
  /// milliseconds per step).
  double assembly = 0.0, factorizing = 0.0, solves = 0.0;
};
inline SolveCount solve_count(const Simulation& sim) {
  SolveCount count;
  for (const CouplingWork& c : sim.coupling_work()) {
    count.factorizations += static_cast<double>(c.factorizations);
    count.refinements += static_cast<double>(c.refinement_passes);
    count.assembly += c.assembly_seconds;
    count.factorizing += c.analysis_seconds + c.factorization_seconds;
    count.solves += c.solve_seconds;
  }
  return count;
}

/// The couplings' work per step between two counts `steps` steps apart: factorisations and
/// refinement passes per step, and (as ms_per_step()) milliseconds per step in each part.
inline SolveCount per_step(const SolveCount& after, const SolveCount& before, double steps) {
  SolveCount per;
  per.factorizations = (after.factorizations - before.factorizations) / steps;
  per.refinements = (after.refinements - before.refinements) / steps;
  for (auto member : {&SolveCount::assembly, &SolveCount::factorizing, &SolveCount::solves}) {
    per.*member = (after.*member - before.*member) * 1e3 / steps;
  }
  return per;
}

/// Milliseconds per step in each phase between two readings of the phase timers `steps` steps
/// apart.
inline PhaseTimes ms_per_step(const PhaseTimes& after, const PhaseTimes& before, double steps) {
  PhaseTimes ms;
  for (auto member : {&PhaseTimes::locate, &PhaseTimes::particles_to_grid, &PhaseTimes::grid_update,
                      &PhaseTimes::walls, &PhaseTimes::coupling, &PhaseTimes::grid_to_particles,
                      &PhaseTimes::stress, &PhaseTimes::advect}) {
    ms.*member = (after.*member - before.*member) * 1e3 / steps;
  }
  return ms;
}

}  // namespace mpm::perf
