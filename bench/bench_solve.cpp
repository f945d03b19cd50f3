// The dual-grid couplings' triangular solves (ldlt_solve(), libmpm/src/sparse_pattern.hpp): three
// right-hand sides through the LDL^T factor of a Schur complement's pattern, an m x m grid of
// multipliers each coupled to those within `reach` spacings (a flat Phi: the floor benchmark's
// has 1,620 multipliers and 261,001 entries in L; m 40, reach 4 gives one of 229,409).
//
//   BM_LdltSolve/m/reach/single : one solve, L as factorised (single 0) or rounded to single
//                                 precision (single 1, the refinement's preconditioner)
//
// Counters: the factor's entries, its columns in runs of two or more (ColumnRuns), and whether
// its elimination tree splits for two threads.

#include <benchmark/benchmark.h>

#include <random>
#include <vector>

#include "sparse_pattern.hpp"
#include "support/grid_spd.hpp"

namespace {

void BM_LdltSolve(benchmark::State& state) {
  const auto m = static_cast<int>(state.range(0));
  const auto reach = static_cast<int>(state.range(1));
  const bool single = state.range(2) != 0;
  const Eigen::SparseMatrix<double> a = mpm::test::grid_spd(m, reach);
  mpm::SparseLdlt solver(single ? mpm::LdltValues::single : mpm::LdltValues::full);
  solver.compute(a);
  if (solver.info() != Eigen::Success) {
    state.SkipWithError("factorisation failed");
    return;
  }
  if (single) solver.round_to_single();
  const mpm::LdltValues values = single ? mpm::LdltValues::single : mpm::LdltValues::full;
  Eigen::Matrix<double, Eigen::Dynamic, 3> b(a.rows(), 3), x;
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> value(-1.0, 1.0);
  for (Eigen::Index i = 0; i < b.rows(); ++i) {
    for (int c = 0; c < 3; ++c) b(i, c) = value(rng);
  }
  std::vector<double> work;
  for (auto _ : state) {
    mpm::ldlt_solve(solver, b, x, work, values);
    benchmark::DoNotOptimize(x.data());
  }
  state.counters["entries"] = static_cast<double>(solver.matrixL().nestedExpression().nonZeros());
  state.counters["split"] = solver.split().parallel ? 1.0 : 0.0;
  double in_runs = 0.0, runs = 0.0;
  for (const auto& run : solver.runs().all) {
    if (run[1] - run[0] < 2) continue;
    in_runs += run[1] - run[0];
    runs += 1.0;
  }
  state.counters["columns_in_runs"] = in_runs / static_cast<double>(a.cols());
  state.counters["runs"] = runs;
}
BENCHMARK(BM_LdltSolve)
    ->ArgsProduct({{40}, {4}, {0, 1}})
    ->Args({80, 2, 1})
    ->Unit(benchmark::kMicrosecond)
    ->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
