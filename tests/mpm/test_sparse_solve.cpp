// The dual-grid couplings' sparse kernels (libmpm/src/sparse_pattern.hpp): the LDL^T solve of
// several right-hand sides side by side gives what Eigen's own solve gives column by column, and
// the allocation-free assembly gives what setFromTriplets gives.

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <numeric>
#include <random>
#include <stdexcept>
#include <vector>

#include <tbb/global_control.h>

#include "sparse_pattern.hpp"
#include "support/grid_spd.hpp"

namespace mpm {
namespace {

/// A symmetric, strictly diagonally dominant (so positive definite, condition number below
/// (1 + r) / (1 - r) for a row sum r of the off-diagonal magnitudes relative to the diagonal:
/// here r <= 0.5, cond <= 3) random sparse matrix of n rows, about `per_row` off-diagonal
/// entries in each, scattered so that the fill-reducing ordering is not the identity.
Eigen::SparseMatrix<double> random_spd(int n, int per_row, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_int_distribution<int> column(0, n - 1);
  std::uniform_real_distribution<double> value(-1.0, 1.0);
  std::vector<Eigen::Triplet<double>> entries;
  std::vector<double> row_sum(static_cast<std::size_t>(n), 0.0);
  for (int i = 0; i < n; ++i) {
    for (int k = 0; k < per_row / 2; ++k) {
      const int j = column(rng);
      if (j == i) continue;
      const double v = value(rng);
      entries.emplace_back(i, j, v);
      entries.emplace_back(j, i, v);
      row_sum[static_cast<std::size_t>(i)] += std::abs(v);
      row_sum[static_cast<std::size_t>(j)] += std::abs(v);
    }
  }
  for (int i = 0; i < n; ++i) entries.emplace_back(i, i, 1.0 + 2.0 * row_sum[i]);
  Eigen::SparseMatrix<double> a(n, n);
  a.setFromTriplets(entries.begin(), entries.end());
  return a;
}

template <class Rhs>
void check_block_solve(const SparseLdlt& solver, const Eigen::SparseMatrix<double>& a, int cols,
                       unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> value(-1.0, 1.0);
  Rhs b(a.rows(), cols);
  for (Eigen::Index i = 0; i < b.rows(); ++i) {
    for (Eigen::Index c = 0; c < b.cols(); ++c) b(i, c) = value(rng);
  }
  Rhs x;
  std::vector<double> work;
  ldlt_solve(solver, b, x, work);
  ldlt_solve(solver, b, x, work);  // the scratch reused
  ASSERT_EQ(x.rows(), b.rows());
  ASSERT_EQ(x.cols(), b.cols());
  for (Eigen::Index c = 0; c < b.cols(); ++c) {
    const Eigen::VectorXd reference = solver.solve(Eigen::VectorXd(b.col(c)));
    // The same operations on each entry as Eigen's solve; only the compiler's contraction of
    // a multiply and a subtraction into one rounding may differ: a few ulps through a solve of
    // condition number <= 3.
    EXPECT_LE((x.col(c) - reference).norm(), 1e-14 * reference.norm()) << "column " << c;
    EXPECT_LE((a * x.col(c) - b.col(c)).norm(), 1e-13 * b.col(c).norm()) << "column " << c;
  }
}

TEST(SparseSolve, BlockSolveGivesEigensSolveForEachColumn) {
  const Eigen::SparseMatrix<double> a = random_spd(400, 10, 7);
  SparseLdlt solver;
  solver.compute(a);
  ASSERT_EQ(solver.info(), Eigen::Success);
  ASSERT_GT(solver.permutationP().size(), 0);  // a fill-reducing ordering is applied
  check_block_solve<Eigen::VectorXd>(solver, a, 1, 1);
  check_block_solve<Eigen::Matrix<double, Eigen::Dynamic, 2>>(solver, a, 2, 2);
  check_block_solve<Eigen::Matrix<double, Eigen::Dynamic, 3>>(solver, a, 3, 3);
  check_block_solve<Eigen::MatrixXd>(solver, a, 3, 4);
  check_block_solve<Eigen::MatrixXd>(solver, a, 2, 5);
}

using test::grid_spd;  // a flat Phi's Schur complement pattern, 5 x 5 neighbours

TEST(SparseSolve, SubtreeSplitCoversTheTreeAndKeepsItsOrder) {
  SparseLdlt solver;
  solver.compute(grid_spd(40));
  ASSERT_EQ(solver.info(), Eigen::Success);
  const SubtreeSplit& split = solver.split();
  ASSERT_TRUE(split.parallel);
  const auto& l = solver.matrixL().nestedExpression();
  const auto n = static_cast<int>(l.cols());
  // The elimination tree, from L's structure.
  std::vector<int> parent(static_cast<std::size_t>(n), -1);
  for (int j = 0; j < n; ++j) {
    for (Eigen::SparseMatrix<double>::InnerIterator it(l, j); it; ++it) {
      if (it.row() > j) {
        parent[j] = static_cast<int>(it.row());
        break;
      }
    }
  }
  std::vector<int> part(static_cast<std::size_t>(n), -1);  // 0, 1: sides; 2: top
  auto claim = [&](const std::vector<int>& columns, int which) {
    for (std::size_t k = 0; k < columns.size(); ++k) {
      if (k > 0) {
        EXPECT_LT(columns[k - 1], columns[k]) << "part " << which << " not increasing";
      }
      EXPECT_EQ(part[columns[k]], -1) << "column " << columns[k] << " in two parts";
      part[columns[k]] = which;
    }
  };
  claim(split.side[0], 0);
  claim(split.side[1], 1);
  claim(split.top, 2);
  for (int j = 0; j < n; ++j) {
    ASSERT_NE(part[j], -1) << "column " << j << " in no part";
    if (part[j] == 2) {
      // The top is closed towards the root.
      if (parent[j] >= 0) {
        EXPECT_EQ(part[parent[j]], 2) << "column " << j;
      }
      EXPECT_EQ(split.top[split.top_slot[j]], j);
      continue;
    }
    // A side holds whole subtrees: a column's parent is on its side or in the top, and every
    // row of its column up to its subtree's root is on its side, every row beyond in the top.
    const int r = split.root[j];
    ASSERT_GE(r, j);
    EXPECT_EQ(part[r], part[j]) << "column " << j;
    EXPECT_TRUE(parent[r] < 0 || part[parent[r]] == 2) << "column " << j;
    for (Eigen::SparseMatrix<double>::InnerIterator it(l, j); it; ++it) {
      if (it.row() <= j) continue;
      EXPECT_EQ(part[it.row()], it.row() <= r ? part[j] : 2) << "column " << j;
    }
  }
  // Both sides carry work: the split halves the part of the solve below the top.
  EXPECT_GT(split.side[0].size(), static_cast<std::size_t>(n) / 8);
  EXPECT_GT(split.side[1].size(), static_cast<std::size_t>(n) / 8);
}

TEST(SparseSolve, SplitSolveMatchesEigenAndIsTheSameOnOneThread) {
  const Eigen::SparseMatrix<double> a = grid_spd(40);
  SparseLdlt solver;
  solver.compute(a);
  ASSERT_TRUE(solver.split().parallel);
  Eigen::Matrix<double, Eigen::Dynamic, 3> b(a.rows(), 3), x, x_one;
  std::mt19937 rng(13);
  std::uniform_real_distribution<double> value(-1.0, 1.0);
  for (Eigen::Index i = 0; i < b.rows(); ++i) {
    for (int c = 0; c < 3; ++c) b(i, c) = value(rng);
  }
  std::vector<double> work;
  ldlt_solve(solver, b, x, work);
  for (int c = 0; c < 3; ++c) {
    const Eigen::VectorXd reference = solver.solve(Eigen::VectorXd(b.col(c)));
    // Only the order in which a top row's updates are summed differs from Eigen's solve (the
    // second side's as one partial sum): a few ulps of each entry, through a solve of
    // condition number <= 3.
    EXPECT_LE((x.col(c) - reference).norm(), 1e-13 * reference.norm()) << "column " << c;
  }
  {
    tbb::global_control one(tbb::global_control::max_allowed_parallelism, 1);
    ldlt_solve(solver, b, x_one, work);
  }
  EXPECT_TRUE(x == x_one) << "the split solve depends on the thread count";
}

TEST(SparseSolve, ColumnRunsCoverEveryColumnAndShareTheirRowsBelow) {
  // The runs ldlt_solve() takes as one (ColumnRuns): on the pattern of a flat Phi's Schur
  // complement (most columns in runs) and a random one (few). In each list the runs are in
  // order, consecutive and within one part of the split; every column is in exactly one run of
  // `all` and one of its part's; inside a run, column j's rows are j + 1 and then exactly column
  // j + 1's, so all columns share the rows below the run.
  for (const auto& a : {grid_spd(40), random_spd(400, 10, 7)}) {
    SparseLdlt solver;
    solver.compute(a);
    ASSERT_EQ(solver.info(), Eigen::Success);
    const auto& l = solver.matrixL().nestedExpression();
    const int* outer = l.outerIndexPtr();
    const int* inner = l.innerIndexPtr();
    const auto n = static_cast<int>(l.cols());
    const ColumnRuns& runs = solver.runs();
    const SubtreeSplit& split = solver.split();
    int longest = 0, most_below = 0;
    auto check = [&](const std::vector<std::array<int, 2>>& list, const std::vector<int>& columns,
                     const char* what) {
      std::vector<int> covered;
      for (const auto& run : list) {
        ASSERT_LT(run[0], run[1]) << what;
        for (int j = run[0]; j < run[1]; ++j) covered.push_back(j);
        longest = std::max(longest, run[1] - run[0]);
        if (run[1] - run[0] > 1) {
          most_below = std::max(most_below, outer[run[1]] - outer[run[1] - 1]);
        }
        for (int j = run[0]; j + 1 < run[1]; ++j) {
          ASSERT_EQ(outer[j + 1] - outer[j], outer[j + 2] - outer[j + 1] + 1) << what << " " << j;
          EXPECT_EQ(inner[outer[j]], j + 1) << what << ", column " << j;
          for (int p = outer[j] + 1; p < outer[j + 1]; ++p) {
            EXPECT_EQ(inner[p], inner[p - outer[j] - 1 + outer[j + 1]]) << what << ", column " << j;
          }
        }
      }
      EXPECT_EQ(covered, columns) << what;
    };
    std::vector<int> every(static_cast<std::size_t>(n));
    for (int j = 0; j < n; ++j) every[static_cast<std::size_t>(j)] = j;
    check(runs.all, every, "all");
    if (split.parallel) {
      check(runs.side[0], split.side[0], "side 0");
      check(runs.side[1], split.side[1], "side 1");
      check(runs.top, split.top, "top");
    }
    EXPECT_EQ(runs.most_below, most_below);
    if (a.rows() == 1600) {
      EXPECT_GE(longest, 16);  // a flat Phi's separators: long runs
    }
  }
}

TEST(SparseSolve, RunSolveMatchesEigenOnDenseBlocksAndTheirSeparator) {
  // Sixteen dense blocks (29 and 30 columns), each coupled densely to a separator of 43: each
  // block factorises into a run with the separator's rows below it, the separator into a run of
  // its own, and the tree splits for two threads with the separator on top. The solve is then
  // all run arithmetic: the four-column updates and eight-part dot products with their
  // remainders, the second side's updates of the separator through the spill. Against Eigen's
  // solve (diagonal dominance: condition number below 3): a few ulps; on one thread the same.
  std::mt19937 rng(21);
  std::uniform_real_distribution<double> value(-1.0, 1.0);
  constexpr int kBlocks = 16, kSeparator = 43;
  std::vector<int> first{0};
  for (int k = 0; k < kBlocks; ++k) first.push_back(first.back() + 29 + k % 2);
  const int n = first.back() + kSeparator;
  std::vector<Eigen::Triplet<double>> entries;
  std::vector<double> row_sum(static_cast<std::size_t>(n), 0.0);
  auto couple = [&](int i, int j) {
    const double v = 0.5 * value(rng);
    entries.emplace_back(i, j, v);
    entries.emplace_back(j, i, v);
    row_sum[static_cast<std::size_t>(i)] += std::abs(v);
    row_sum[static_cast<std::size_t>(j)] += std::abs(v);
  };
  for (int k = 0; k < kBlocks; ++k) {
    for (int i = first[k]; i < first[k + 1]; ++i) {
      for (int j = first[k]; j < i; ++j) couple(i, j);
      for (int j = first.back(); j < n; ++j) couple(i, j);
    }
  }
  for (int i = first.back(); i < n; ++i) {
    for (int j = first.back(); j < i; ++j) couple(i, j);
  }
  for (int i = 0; i < n; ++i) entries.emplace_back(i, i, 1.0 + 2.0 * row_sum[i]);
  Eigen::SparseMatrix<double> a(n, n);
  a.setFromTriplets(entries.begin(), entries.end());
  for (const LdltValues values : {LdltValues::full, LdltValues::single}) {
    SparseLdlt solver(values);
    solver.compute(a);
    ASSERT_EQ(solver.info(), Eigen::Success);
    if (values == LdltValues::single) solver.round_to_single();
    ASSERT_TRUE(solver.split().parallel);
    ASSERT_FALSE(solver.runs().side[0].empty());
    ASSERT_FALSE(solver.runs().side[1].empty());
    EXPECT_GE(solver.runs().most_below, kSeparator);
    Eigen::Matrix<double, Eigen::Dynamic, 3> b(n, 3), x, x_one;
    for (int i = 0; i < n; ++i) {
      for (int c = 0; c < 3; ++c) b(i, c) = value(rng);
    }
    std::vector<double> work;
    ldlt_solve(solver, b, x, work, values);
    for (int c = 0; c < 3; ++c) {
      const Eigen::VectorXd reference = solver.solve(Eigen::VectorXd(b.col(c)));
      // Single precision: L's entries rounded by 6e-8, through a condition number below 3.
      const double tolerance = values == LdltValues::full ? 1e-14 : 1e-6;
      EXPECT_LE((x.col(c) - reference).norm(), tolerance * reference.norm()) << "column " << c;
    }
    {
      tbb::global_control one(tbb::global_control::max_allowed_parallelism, 1);
      ldlt_solve(solver, b, x_one, work, values);
    }
    EXPECT_TRUE(x == x_one) << "the solve depends on the thread count";
  }
}

/// The matrix of a later step: `a` with its diagonal scaled by 1 + `change` (the masses of the
/// Schur complement moved). A factorisation of `a` solves it by refinement at the rate
/// q = |a^-1 (m - a)| = change |a^-1 diag(a)|, between `change` and 3 `change` (a's condition
/// number is at most 3).
Eigen::SparseMatrix<double> moved(const Eigen::SparseMatrix<double>& a, double change) {
  Eigen::SparseMatrix<double> m = a;
  for (Eigen::Index i = 0; i < m.rows(); ++i) m.coeffRef(i, i) *= 1.0 + change;
  return m;
}

using Block3 = Eigen::Matrix<double, Eigen::Dynamic, 3>;

/// refine() (or, when `conjugate`, conjugate_refine()) of m x = b against a factorisation of
/// `a`, from x = F^-1 b (as the couplings start); `passes` counts the passes. `values`: the
/// factor's solves read L as factorised or rounded to single precision. `tolerance`: CG's (refine()
/// has its own, kRefineTolerance).
bool refine_against(const Eigen::SparseMatrix<double>& a, const Eigen::SparseMatrix<double>& m,
                    const Block3& b, Block3& x, std::size_t& passes, double scale,
                    bool conjugate = false, LdltValues values = LdltValues::full,
                    double tolerance = kRefineTolerance) {
  // (A solver made to keep single-precision copies keeps the dropped one too.)
  SparseLdlt solver(values == LdltValues::full ? LdltValues::full : LdltValues::single);
  solver.compute(a);
  if (values == LdltValues::single) solver.round_to_single();
  std::vector<double> work;
  const auto factor = [&](const Block3& r, Block3& out) {
    ldlt_solve(solver, r, out, work, values);
  };
  const auto product = [&](const Block3& y, Block3& out) { out.noalias() = m * y; };
  factor(b, x);
  Block3 residual, update, direction, image;
  if (conjugate) {
    return conjugate_refine(b, x, product, factor, passes, residual, update, direction, image,
                            scale, tolerance);
  }
  return refine(b, x, product, factor, passes, residual, update, scale);
}

/// refine_against() by conjugate gradients.
bool conjugate_refine_against(const Eigen::SparseMatrix<double>& a,
                              const Eigen::SparseMatrix<double>& m, const Block3& b, Block3& x,
                              std::size_t& passes, double scale) {
  return refine_against(a, m, b, x, passes, scale, true);
}

Block3 random_block(Eigen::Index rows, unsigned seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> value(-1.0, 1.0);
  Block3 b(rows, 3);
  for (Eigen::Index i = 0; i < rows; ++i) {
    for (int c = 0; c < 3; ++c) b(i, c) = value(rng);
  }
  return b;
}

TEST(SparseSolve, RefinementAgainstAnEarlierFactorisationSolvesTheNewMatrix) {
  const Eigen::SparseMatrix<double> a = grid_spd(30);
  const Eigen::SparseMatrix<double> m = moved(a, 0.002);
  const Block3 b = random_block(a.rows(), 17);
  Block3 x;
  std::size_t passes = 0;
  ASSERT_TRUE(refine_against(a, m, b, x, passes, 0.0));
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> exact(m);
  const Block3 reference = exact.solve(b);
  // refine() stops when its estimate of the error left (q / (1 - q) times the last update, q
  // the largest ratio of successive updates seen) is below 1e-10 of x: the estimate is exact
  // for a contraction by q; 2e-10 leaves room for the estimate only.
  EXPECT_LE((x - reference).norm(), 2e-10 * reference.norm());
  // q in [0.002, 0.006] reaches 1e-10 in log(1e-10) / log(q) = 3.0 to 4.4 contractions: the
  // first solve and 2 to 4 passes.
  EXPECT_GE(passes, 2U);
  EXPECT_LE(passes, 4U);
}

TEST(SparseSolve, RefinementStopsAtAResidualSmallAgainstItsScale) {
  const Eigen::SparseMatrix<double> a = grid_spd(30);
  const Eigen::SparseMatrix<double> m = moved(a, 0.002);
  // The right-hand side is the difference of two terms of size 1 that agree to 1e-12 (two grids
  // that already carry the same interface velocities): the first solve leaves a residual of
  // at most 0.006 of b, far below 1e-10 of the terms, and no pass is needed.
  const Block3 b = 1e-12 * random_block(a.rows(), 19);
  const double scale = std::sqrt(static_cast<double>(b.size()));  // entries of size ~1
  Block3 x;
  std::size_t passes = 0;
  ASSERT_TRUE(refine_against(a, m, b, x, passes, scale));
  EXPECT_EQ(passes, 0U);
  EXPECT_LE((b - m * x).norm(), 1e-10 * scale);
  // Without the scale the same system is refined to 1e-10 of x itself.
  passes = 0;
  ASSERT_TRUE(refine_against(a, m, b, x, passes, 0.0));
  EXPECT_GE(passes, 2U);
  // Terms of the size of b itself: the residual test is no looser than the test on x.
  passes = 0;
  ASSERT_TRUE(refine_against(a, m, b, x, passes, b.norm()));
  EXPECT_GE(passes, 2U);
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> exact(m);
  EXPECT_LE((x - exact.solve(b)).norm(), 2e-10 * x.norm());
}

TEST(SparseSolve, RefinementGivesUpAgainstAFactorisationTooFarAway) {
  const Eigen::SparseMatrix<double> a = grid_spd(30);
  // The diagonal tripled: q = 2 |a^-1 diag(a)| >= 2, refinement diverges; refine() reports the
  // failure at its second rate estimate at the latest (the caller then factorises) instead of
  // passing on and on.
  const Eigen::SparseMatrix<double> m = moved(a, 2.0);
  const Block3 b = random_block(a.rows(), 23);
  Block3 x;
  std::size_t passes = 0;
  EXPECT_FALSE(refine_against(a, m, b, x, passes, 0.0));
  EXPECT_LE(passes, 2U);
}

/// m x = b against a factorisation of `a`: refine() gives up, conjugate_refine() converges within
/// `max_passes` to 1e-10 of the exact solution (it stops when the preconditioned residual z, the
/// error to within 1 +- q, falls below 1e-10 of x, and adds z: the error left is about q of
/// that).
void expect_conjugate_solves_alone(const Eigen::SparseMatrix<double>& a,
                                   const Eigen::SparseMatrix<double>& m, const Block3& b,
                                   std::size_t max_passes) {
  Block3 x;
  std::size_t passes = 0;
  EXPECT_FALSE(refine_against(a, m, b, x, passes, 0.0));
  passes = 0;
  ASSERT_TRUE(conjugate_refine_against(a, m, b, x, passes, 0.0));
  EXPECT_LE(passes, max_passes);
  const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> exact(m);
  const Block3 reference = exact.solve(b);
  EXPECT_LE((x - reference).norm(), 1e-10 * reference.norm());
}

TEST(SparseSolve, ConjugateRefinementSolvesWhereRefinementGivesUp) {
  const Eigen::SparseMatrix<double> a = grid_spd(30);
  // The diagonal up by 3%: refinement contracts by q in [0.03, 0.09] a pass and would need up
  // to log(1e-10) / log(0.09) = 9.6 passes, more than it allows (6); it gives up. F^-1 m =
  // I + 0.03 F^-1 diag(a) has its spectrum in [1, 1.09], so CG contracts by at most
  // (sqrt(1.09) - 1) / (sqrt(1.09) + 1) = 0.022 a pass: 1e-10 within 6 (5 passes here).
  const Block3 b = random_block(a.rows(), 29);
  expect_conjugate_solves_alone(a, moved(a, 0.03), b, 6U);
  // The change 0.002, which refinement handles in 3 passes: at most one more (refine() stops
  // one pass early on its estimate of the error left from its contraction rate; CG's passes do
  // not contract at a steady rate, and it stops when F^-1 r itself is small).
  const Eigen::SparseMatrix<double> near = moved(a, 0.002);
  std::size_t refined = 0, conjugate = 0;
  Block3 x;
  ASSERT_TRUE(refine_against(a, near, b, x, refined, 0.0));
  ASSERT_TRUE(conjugate_refine_against(a, near, b, x, conjugate, 0.0));
  EXPECT_LE(conjugate, refined + 1);
  const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> exact(near);
  EXPECT_LE((x - Block3(exact.solve(b))).norm(), 1e-10 * x.norm());
}

TEST(SparseSolve, ConjugateRefinementRemovesALowRankChangeInAsManyPasses) {
  // Three rows' diagonals ten times larger (three light nodes' 1/m weights at a flow's front):
  // refinement diverges (q >= 9 along those rows), but F^-1 m is the identity plus a rank-3
  // term. The first residual, (F - m) F^-1 b, lies in the range of that term, and so does the
  // error: three eigenvalues, which CG removes in three steps in exact arithmetic; the fourth
  // pass's solve with F finds the error gone (4 passes here; 5 allowed for round-off).
  const Eigen::SparseMatrix<double> a = grid_spd(30);
  Eigen::SparseMatrix<double> m = a;
  for (const int row : {17, 400, 811}) m.coeffRef(row, row) *= 10.0;
  expect_conjugate_solves_alone(a, m, random_block(a.rows(), 31), 5U);
}

TEST(SparseSolve, ConjugateRefinementGivesUpAndStopsAtASmallResidual) {
  const Eigen::SparseMatrix<double> a = grid_spd(30);
  // The diagonal tripled: the first correction F^-1 r = F^-1 (F - m) x is 2 to 6 times x
  // itself (F^-1 m spans [3, 7]), an error larger than the solution: CG gives up at once (the
  // caller then factorises), within its 6 passes in any case.
  {
    const Block3 b = random_block(a.rows(), 37);
    Block3 x;
    std::size_t passes = 0;
    EXPECT_FALSE(conjugate_refine_against(a, moved(a, 2.0), b, x, passes, 0.0));
    EXPECT_LE(passes, 6U);
  }
  // Two grids that already agree to 1e-12 of their terms (as for refine()): the first solve is
  // accepted, no pass made.
  const Block3 b = 1e-12 * random_block(a.rows(), 41);
  const double scale = std::sqrt(static_cast<double>(b.size()));
  Block3 x;
  std::size_t passes = 0;
  ASSERT_TRUE(conjugate_refine_against(a, moved(a, 0.002), b, x, passes, scale));
  EXPECT_EQ(passes, 0U);
}

// The Phi coupling solves to the scene's scheme.coupling_tolerance (default 1e-6), not to
// refine()'s 1e-10: CG stops at the error it is asked for, and a looser one costs fewer passes.
TEST(SparseSolve, ConjugateRefinementStopsAtTheToleranceItIsGiven) {
  const Eigen::SparseMatrix<double> a = grid_spd(30);
  // The diagonal up by 3% (as above): a CG pass leaves at most 0.022 of the error (here about
  // 0.01), from a first error of at most q = 0.09.
  const Eigen::SparseMatrix<double> m = moved(a, 0.03);
  const Block3 b = random_block(a.rows(), 43);
  const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> exact(m);
  const Block3 reference = exact.solve(b);
  std::vector<std::size_t> passes;
  for (const double tolerance : {1e-10, 1e-8, 1e-6, 1e-4}) {
    Block3 x;
    std::size_t count = 0;
    ASSERT_TRUE(refine_against(a, m, b, x, count, 0.0, true, LdltValues::full, tolerance));
    // It stops when z = F^-1 r, the error to within 1 +- q, is below `tolerance` of x, and adds
    // z: what is left is about q of that.
    EXPECT_LE((x - reference).norm(), tolerance * reference.norm()) << tolerance;
    if (!passes.empty()) {
      EXPECT_LE(count, passes.back()) << tolerance;
    }
    passes.push_back(count);
  }
  // About two decades a pass: 5 passes to 1e-10, 3 to 1e-4.
  EXPECT_LE(passes.back() + 2, passes.front());
}

// The Phi coupling's CG passes read L in single precision (SparseLdlt::round_to_single()):
// the solve is then exact only to the rounding of L, but as a preconditioner it changes
// nothing CG's answer depends on.
TEST(SparseSolve, SinglePrecisionFactorPreconditionsAsWellAsTheFullOne) {
  const Eigen::SparseMatrix<double> a = grid_spd(30);
  const Block3 b = random_block(a.rows(), 43);
  SparseLdlt plain;  // keeps no single-precision copy
  plain.compute(a);
  EXPECT_THROW(plain.round_to_single(), std::logic_error);
  SparseLdlt solver(LdltValues::single);
  solver.compute(a);
  std::vector<double> work;
  Block3 full, single;
  // Not rounded since the factorisation: refused rather than read stale values.
  EXPECT_THROW(ldlt_solve(solver, b, single, work, LdltValues::single), std::logic_error);
  solver.round_to_single();
  ldlt_solve(solver, b, full, work);
  ldlt_solve(solver, b, single, work, LdltValues::single);
  // Rounding L's entries by at most 2^-24 of themselves perturbs L D L^T by about 1e-7 of a;
  // through a's condition number (at most 3) the solution moves by at most a few 1e-7.
  EXPECT_GT((single - full).norm(), 0.0);  // the float copy is what was read
  EXPECT_LE((single - full).norm(), 1e-6 * full.norm());
  // As CG's preconditioner for a later matrix (the diagonal moved 0.2%, q ~ 2e-3 >> 1e-7): the
  // same passes, and the answer to 1e-10, since CG's residual is formed in double.
  const Eigen::SparseMatrix<double> near = moved(a, 0.002);
  std::size_t passes_full = 0, passes_single = 0;
  Block3 x;
  ASSERT_TRUE(refine_against(a, near, b, x, passes_full, 0.0, true));
  ASSERT_TRUE(refine_against(a, near, b, x, passes_single, 0.0, true, LdltValues::single));
  EXPECT_EQ(passes_single, passes_full);
  const Block3 reference = Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>(near).solve(b);
  EXPECT_LE((x - reference).norm(), 1e-10 * reference.norm());
  // A new factorisation makes the rounded copy stale until it is rounded again.
  solver.factorize(near);
  EXPECT_FALSE(solver.rounded());
  EXPECT_THROW(ldlt_solve(solver, b, single, work, LdltValues::single), std::logic_error);
}

// The Phi coupling's CG passes read L's dropped copy (SparseLdlt::dropped(): the entries of at
// least kDropBelow of their row's scale, in single precision). As a preconditioner of a later
// matrix it costs no more passes than all of L where the matrix has moved more than the
// dropped entries weigh, and CG's answer is as exact.
TEST(SparseSolve, DroppedFactorPreconditionsAsWellAsTheFullOne) {
  // Wide neighbourhoods, as the Phi coupling's S: L fills with entries that decay away from
  // the diagonal, about half of them below 1e-4 of their row here (the floor benchmark's S:
  // four fifths).
  const Eigen::SparseMatrix<double> a = grid_spd(30, 3);
  const Block3 b = random_block(a.rows(), 47);
  SparseLdlt plain;  // keeps no copy
  plain.compute(a);
  std::vector<double> work;
  Block3 full, dropped;
  EXPECT_THROW(ldlt_solve(plain, b, dropped, work, LdltValues::dropped), std::logic_error);
  SparseLdlt solver(LdltValues::single);
  solver.compute(a);
  const auto kept = static_cast<Eigen::Index>(solver.dropped().inner.size());
  const Eigen::Index all = solver.matrixL().nestedExpression().nonZeros();
  EXPECT_LT(3 * kept, 2 * all) << "kept " << kept << " of " << all;
  EXPECT_GT(kept, 0);
  // Every entry kept is at least kDropBelow of its row's scale, and every one left out below it.
  {
    const auto& l = solver.matrixL().nestedExpression();
    const Eigen::VectorXd& d = solver.diagonal();
    Eigen::Index counted = 0;
    for (Eigen::Index j = 0; j < l.outerSize(); ++j) {
      for (Eigen::SparseMatrix<double>::InnerIterator it(l, j); it; ++it) {
        if (it.row() <= j) continue;
        const double size = std::abs(it.value()) * std::sqrt(d[j] / d[it.row()]);
        if (size >= SparseLdlt::kDropBelow) ++counted;
      }
    }
    EXPECT_EQ(counted, kept);
  }
  ldlt_solve(solver, b, full, work);
  ldlt_solve(solver, b, dropped, work, LdltValues::dropped);
  // The left-out entries perturb L D L^T a little: the solve is close to exact, not exact.
  EXPECT_GT((dropped - full).norm(), 0.0);
  EXPECT_LE((dropped - full).norm(), 1e-3 * full.norm());
  // As CG's preconditioner for a later matrix (the diagonal moved 0.2%): at most one pass more
  // than with all of L, and the answer to 1e-10, since CG's residual is formed in double.
  const Eigen::SparseMatrix<double> near = moved(a, 0.002);
  std::size_t passes_full = 0, passes_dropped = 0;
  Block3 x;
  ASSERT_TRUE(refine_against(a, near, b, x, passes_full, 0.0, true));
  ASSERT_TRUE(refine_against(a, near, b, x, passes_dropped, 0.0, true, LdltValues::dropped));
  EXPECT_LE(passes_dropped, passes_full + 1);
  const Block3 reference = Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>(near).solve(b);
  EXPECT_LE((x - reference).norm(), 1e-10 * reference.norm());
  std::printf("dropped copy: %ld of %ld entries; CG passes %zu (all of L: %zu)\n",
              static_cast<long>(kept), static_cast<long>(all), passes_dropped, passes_full);
  // A new factorisation makes its own copy.
  solver.factorize(near);
  ldlt_solve(solver, b, dropped, work, LdltValues::dropped);
  ldlt_solve(solver, b, full, work);
  EXPECT_LE((dropped - full).norm(), 1e-3 * full.norm());
}

/// `m` with entries of size `size` times their row's diagonal added between node pairs 3 and 4
/// rows of the grid apart (outside grid_spd()'s pattern: a new pattern), the diagonals raised by
/// as much (still diagonally dominant, so positive definite).
Eigen::SparseMatrix<double> with_new_entries(const Eigen::SparseMatrix<double>& m, double size) {
  std::vector<Eigen::Triplet<double>> entries;
  for (int c = 0; c < m.outerSize(); ++c) {
    for (Eigen::SparseMatrix<double>::InnerIterator it(m, c); it; ++it) {
      entries.emplace_back(static_cast<int>(it.row()), c, it.value());
    }
  }
  const auto n = static_cast<int>(m.rows());
  for (int i = 0; i + 97 < n; i += 7) {
    const int j = i + 97;
    const double v = size * std::min(m.coeff(i, i), m.coeff(j, j));
    entries.emplace_back(i, j, -v);
    entries.emplace_back(j, i, -v);
    entries.emplace_back(i, i, v);
    entries.emplace_back(j, j, v);
  }
  Eigen::SparseMatrix<double> out(n, n);
  out.setFromTriplets(entries.begin(), entries.end());
  return out;
}

// refined_solve() refines against the factorisation in hand whatever the new matrix's pattern
// (Enhanced tries it while its unknowns hold: its cross mass gains and loses entries from step
// to step); where refinement converges, the solution is the new matrix's and the factorisation
// stays; where it fails, the new matrix is analysed (its pattern is not the factorised one's)
// and factorised, and the solve is exact.
TEST(SparseSolve, RefinedSolveAcrossAPatternChange) {
  const Eigen::SparseMatrix<double> a = grid_spd(30);
  SparseLdlt solver;
  solver.compute(a);
  ASSERT_EQ(solver.info(), Eigen::Success);
  Eigen::SparseMatrix<double> base = a;
  std::size_t pattern = pattern_hash(a);
  const Block3 b = random_block(a.rows(), 29);
  SolveWork<Block3> work;
  std::size_t passes = 0, factorizations = 0;
  Block3 x;

  // Close: new entries of 1e-3 of the diagonal and the diagonals moved by 0.2%.
  const Eigen::SparseMatrix<double> near = with_new_entries(moved(a, 0.002), 1e-3);
  ASSERT_NE(pattern_hash(near), pattern);
  bool refine = true;
  ASSERT_TRUE(
      refined_solve(solver, near, base, pattern, refine, b, x, passes, factorizations, work));
  EXPECT_TRUE(refine);
  EXPECT_EQ(factorizations, 0U);
  EXPECT_GE(passes, 1U);
  EXPECT_EQ(pattern, pattern_hash(a));
  const Block3 near_solution = Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>(near).solve(b);
  EXPECT_LE((x - near_solution).norm(), 2e-10 * near_solution.norm());

  // Far: the diagonals tripled, and new entries of a fifth of them.
  const Eigen::SparseMatrix<double> far = with_new_entries(moved(a, 2.0), 0.2);
  ASSERT_NE(pattern_hash(far), pattern);
  refine = true;
  ASSERT_TRUE(
      refined_solve(solver, far, base, pattern, refine, b, x, passes, factorizations, work));
  EXPECT_FALSE(refine);
  EXPECT_EQ(factorizations, 1U);
  EXPECT_EQ(pattern, pattern_hash(far));  // analysed anew
  EXPECT_EQ(pattern_hash(base), pattern_hash(far));
  const Block3 far_solution = Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>(far).solve(b);
  // The condition number stays below 3 (diagonal dominance): round-off only.
  EXPECT_LE((x - far_solution).norm(), 1e-13 * far_solution.norm());
  EXPECT_LE((far * x - b).norm(), 1e-12 * b.norm());
}

// A solver that keeps L's dropped copy (Enhanced's) checks it on the first exact solve with
// each factorisation (check_dropped(): the copy's answer within 0.1 of the exact one), and
// refined_solve() refines against an aged factorisation through the copy only where it passed:
// as many passes (one more at most) as with all of L, and the same answer, since the residual
// is formed in double. Where it failed, refinement reads all of L: the same operations as a
// solver that keeps no copy, bit for bit.
TEST(SparseSolve, RefinedSolveReadsTheDroppedCopyOnlyWhereItsCheckPassed) {
  const Eigen::SparseMatrix<double> a = grid_spd(30, 3);
  const Eigen::SparseMatrix<double> near = moved(a, 0.002);
  const Block3 b = random_block(a.rows(), 53);
  const Block3 reference = Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>(near).solve(b);
  // Factorises a, solves a x = b exactly (the check), overrides the verdict if `verdict` is
  // given, then refines near x = b against a's factorisation; returns the passes.
  auto refine_near = [&](LdltValues kept, SparseLdlt::DroppedUse& use, Block3& x,
                         const SparseLdlt::DroppedUse* verdict = nullptr) {
    SparseLdlt solver(kept);
    Eigen::SparseMatrix<double> base;
    std::size_t pattern = 0, passes = 0, factorizations = 0;
    bool factored = false, refine = false;
    SolveWork<Block3> work;
    EXPECT_TRUE(
        factorise_or_reuse(solver, a, base, pattern, factored, true, refine, factorizations));
    EXPECT_EQ(solver.dropped_use(), SparseLdlt::DroppedUse::unchecked);
    EXPECT_TRUE(
        refined_solve(solver, a, base, pattern, refine, b, x, passes, factorizations, work));
    use = solver.dropped_use();
    if (verdict != nullptr) solver.set_dropped_use(*verdict);
    EXPECT_TRUE(
        factorise_or_reuse(solver, near, base, pattern, factored, true, refine, factorizations));
    EXPECT_TRUE(refine);  // same pattern: the factorisation in hand
    EXPECT_TRUE(
        refined_solve(solver, near, base, pattern, refine, b, x, passes, factorizations, work));
    EXPECT_EQ(factorizations, 1U);
    EXPECT_LE((x - reference).norm(), 2e-10 * reference.norm());
    return passes;
  };
  SparseLdlt::DroppedUse use{};
  Block3 x_full, x_dropped, x_unusable;
  const std::size_t passes_full = refine_near(LdltValues::full, use, x_full);
  EXPECT_EQ(use, SparseLdlt::DroppedUse::unchecked);  // no copy to check
  const std::size_t passes_dropped = refine_near(LdltValues::dropped, use, x_dropped);
  EXPECT_EQ(use, SparseLdlt::DroppedUse::usable);
  EXPECT_LE(passes_dropped, passes_full + 1);
  EXPECT_NE((x_dropped - x_full).norm(), 0.0);  // another preconditioner, the same answer
  std::printf("refinement passes: %zu through the dropped copy, %zu through all of L\n",
              passes_dropped, passes_full);
  const SparseLdlt::DroppedUse unusable = SparseLdlt::DroppedUse::unusable;
  refine_near(LdltValues::dropped, use, x_unusable, &unusable);
  EXPECT_EQ((x_unusable - x_full).norm(), 0.0);

  // The check's rule: against an answer 20% off the exact one (the copy's within 1e-3 of
  // it), the copy fails; once checked, a factorisation is not checked again.
  SparseLdlt solver(LdltValues::dropped);
  solver.compute(a);
  std::vector<double> work;
  Block3 exact, scratch;
  ldlt_solve(solver, b, exact, work);
  const Block3 off = 1.2 * exact;
  check_dropped(solver, b, off, scratch, work, EuclideanNorm{});
  EXPECT_EQ(solver.dropped_use(), SparseLdlt::DroppedUse::unusable);
  solver.factorize(a);  // each factorisation is checked anew
  EXPECT_EQ(solver.dropped_use(), SparseLdlt::DroppedUse::unchecked);
  check_dropped(solver, b, exact, scratch, work, EuclideanNorm{});
  EXPECT_EQ(solver.dropped_use(), SparseLdlt::DroppedUse::usable);
  check_dropped(solver, b, off, scratch, work, EuclideanNorm{});
  EXPECT_EQ(solver.dropped_use(), SparseLdlt::DroppedUse::usable);
  EXPECT_THROW(solver.round_to_single(), std::logic_error);  // the dropped copy alone
}

/// A contact system as Enhanced's: `velocity` (SPD) for the velocity unknowns, then one row per
/// entry of `held` (ids into 30 possible rows, each coupled to a few velocity unknowns and to
/// its neighbouring rows): [velocity, -W; -W^T, -S], quasi-definite.
Eigen::SparseMatrix<double> contact_system(const Eigen::SparseMatrix<double>& velocity,
                                           const std::vector<int>& held) {
  const Eigen::Index nv = velocity.rows();
  const auto nc = static_cast<Eigen::Index>(held.size());
  std::vector<Eigen::Triplet<double>> t;
  for (Eigen::Index c = 0; c < velocity.outerSize(); ++c) {
    for (Eigen::SparseMatrix<double>::InnerIterator it(velocity, c); it; ++it) {
      t.emplace_back(it.row(), it.col(), it.value());
    }
  }
  for (Eigen::Index c = 0; c < nc; ++c) {
    const int id = held[static_cast<std::size_t>(c)];
    for (int k = 0; k < 4; ++k) {  // W: four velocity unknowns per row
      const auto v = static_cast<Eigen::Index>((id * 37 + k * 11) % nv);
      const double w = 0.3 + 0.1 * k;
      t.emplace_back(v, nv + c, -w);
      t.emplace_back(nv + c, v, -w);
    }
    for (Eigen::Index c2 = 0; c2 < nc; ++c2) {  // S: rows whose ids are neighbours couple
      const int id2 = held[static_cast<std::size_t>(c2)];
      if (id2 == id) t.emplace_back(nv + c, nv + c, -1.0);
      if (std::abs(id2 - id) == 1) t.emplace_back(nv + c, nv + c2, -0.2);
    }
  }
  Eigen::SparseMatrix<double> m(nv + nc, nv + nc);
  m.setFromTriplets(t.begin(), t.end());
  return m;
}

// A matrix with the unknowns of the one analysed last (refinement against an aged factorisation
// that failed) keeps its fill-reducing ordering (SparseLdlt::Order::kept) while the fill it
// gives stays within kReorderFill of the fill it was made with; the unknowns renumbered, it
// would give far more, and a new ordering is made, the one a fresh analysis makes. A saved
// ordering (a checkpoint's) makes the factorisation again bit for bit.
TEST(SparseSolve, KeptOrderingServesWhileItsFillHolds) {
  const Eigen::SparseMatrix<double> a = grid_spd(30);
  const auto n = static_cast<int>(a.rows());
  SparseLdlt solver;
  solver.analyzePattern(a);
  const std::size_t fill = solver.ordered_fill();
  const std::vector<int> ordering(solver.permutationPinv().indices().data(),
                                  solver.permutationPinv().indices().data() + n);
  ASSERT_GT(fill, 0U);
  EXPECT_EQ(solver.kept_orderings(), 0U);

  // Two entries more (nodes three apart now coupled, the diagonals kept dominant) and the
  // diagonals moved: the ordering serves, and its factorisation solves the new matrix exactly.
  std::vector<Eigen::Triplet<double>> entries;
  for (int c = 0; c < n; ++c) {
    for (Eigen::SparseMatrix<double>::InnerIterator it(a, c); it; ++it) {
      entries.emplace_back(static_cast<int>(it.row()), c, it.value() * (it.row() == c ? 1.1 : 1));
    }
  }
  for (const int i : {400, 433}) {
    entries.emplace_back(i, i + 3, -0.1);
    entries.emplace_back(i + 3, i, -0.1);
  }
  Eigen::SparseMatrix<double> near(n, n);
  near.setFromTriplets(entries.begin(), entries.end());
  ASSERT_NE(pattern_hash(near), pattern_hash(a));
  solver.analyzePattern(near, SparseLdlt::Order::kept);
  EXPECT_EQ(solver.kept_orderings(), 1U);
  EXPECT_EQ(solver.ordered_fill(), fill);  // what the ordering gave its own matrix
  EXPECT_TRUE(
      std::equal(ordering.begin(), ordering.end(), solver.permutationPinv().indices().data()));
  solver.factorize(near);
  ASSERT_EQ(solver.info(), Eigen::Success);
  const Block3 b = random_block(n, 41);
  Block3 x;
  std::vector<double> work;
  ldlt_solve(solver, b, x, work);
  EXPECT_LE((near * x - b).norm(), 1e-12 * b.norm());

  // Made again from the saved ordering: the same L and D, bit for bit.
  SparseLdlt again;
  again.analyzePattern(near, ordering, fill);
  again.factorize(near);
  ASSERT_EQ(again.info(), Eigen::Success);
  EXPECT_EQ(again.ordered_fill(), fill);
  const auto& l = solver.matrixL().nestedExpression();
  const auto& l_again = again.matrixL().nestedExpression();
  ASSERT_EQ(l_again.nonZeros(), l.nonZeros());
  EXPECT_TRUE(std::equal(l.valuePtr(), l.valuePtr() + l.nonZeros(), l_again.valuePtr()));
  EXPECT_EQ(again.diagonal(), solver.diagonal());

  // A fresh analysis makes its own ordering whatever the fill.
  solver.analyzePattern(near);
  EXPECT_EQ(solver.kept_orderings(), 1U);

  // The unknowns renumbered at random (the same graph): the ordering in hand would give far
  // more fill, and the one made is a fresh analysis's.
  std::vector<int> order(static_cast<std::size_t>(n));
  std::iota(order.begin(), order.end(), 0);
  std::shuffle(order.begin(), order.end(), std::mt19937(5));
  Eigen::PermutationMatrix<Eigen::Dynamic, Eigen::Dynamic, int> shuffle(n);
  std::copy(order.begin(), order.end(), shuffle.indices().data());
  Eigen::SparseMatrix<double> renumbered;
  renumbered = near.twistedBy(shuffle);
  solver.analyzePattern(renumbered, SparseLdlt::Order::kept);
  EXPECT_EQ(solver.kept_orderings(), 1U);
  SparseLdlt fresh;
  fresh.analyzePattern(renumbered);
  EXPECT_EQ(solver.ordered_fill(), fresh.ordered_fill());
  EXPECT_EQ(solver.permutationPinv().indices(), fresh.permutationPinv().indices());

  // Not a permutation of the unknowns: refused.
  std::vector<int> twice = ordering;
  twice[1] = twice[0];
  EXPECT_THROW(again.analyzePattern(near, twice, fill), std::invalid_argument);
  EXPECT_THROW(
      again.analyzePattern(near, std::vector<int>(ordering.begin(), ordering.end() - 1), fill),
      std::invalid_argument);
}

// BorderedFactor inverts, through the factorisation of an earlier contact system, one with a
// few rows gone and a few new (in another order): exactly where the kept block is the
// factorised one's, and as a preconditioner of refinement as good as the factorisation itself
// where that block has moved (a drift of the masses), since the rest is exact.
TEST(SparseSolve, BorderedFactorSolvesAfterRowsComeAndGo) {
  const Eigen::SparseMatrix<double> velocity = grid_spd(12, 2);
  const Eigen::Index nv = velocity.rows();
  std::vector<int> old_rows(20);
  for (int c = 0; c < 20; ++c) old_rows[static_cast<std::size_t>(c)] = c;
  // Rows 3, 11 and 12 gone, 20, 21 and 25 new (and 25 listed before 14).
  const std::vector<int> new_rows = {0,  1,  2,  4,  5,  6,  7,  8,  9,  10,
                                     13, 25, 14, 15, 16, 17, 18, 19, 20, 21};
  std::vector<int> old_of(static_cast<std::size_t>(nv) + new_rows.size(), -1);
  for (Eigen::Index i = 0; i < nv; ++i) old_of[static_cast<std::size_t>(i)] = static_cast<int>(i);
  for (std::size_t c = 0; c < new_rows.size(); ++c) {
    const auto at = std::find(old_rows.begin(), old_rows.end(), new_rows[c]);
    if (at != old_rows.end()) {
      old_of[static_cast<std::size_t>(nv) + c] = static_cast<int>(nv + (at - old_rows.begin()));
    }
  }
  const Eigen::SparseMatrix<double> old_matrix = contact_system(velocity, old_rows);
  SparseLdlt solver(LdltValues::dropped);
  solver.compute(old_matrix);
  ASSERT_EQ(solver.info(), Eigen::Success);
  std::mt19937 rng(61);
  std::uniform_real_distribution<double> value(-1.0, 1.0);
  Eigen::VectorXd b(static_cast<Eigen::Index>(old_of.size()));
  for (Eigen::Index i = 0; i < b.size(); ++i) b[i] = value(rng);

  // Unmoved: exact.
  const Eigen::SparseMatrix<double> same = contact_system(velocity, new_rows);
  auto column_of = [](const Eigen::SparseMatrix<double>& m) {
    return [&m](int j, Eigen::VectorXd& out) { out = Eigen::VectorXd(m.col(j)); };
  };
  BorderedFactor bordered;
  ASSERT_TRUE(bordered.prepare(solver, LdltValues::full, old_of, column_of(same)));
  EXPECT_EQ(bordered.removed(), 3U);
  EXPECT_EQ(bordered.added(), 3U);
  Eigen::VectorXd x;
  bordered.solve(b, x);
  const Eigen::VectorXd exact = Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>(same).solve(b);
  EXPECT_LE((x - exact).norm(), 1e-12 * exact.norm());

  // Moved (the velocity block's diagonal by 0.2%): refinement against the bordered factor, in
  // no more passes than against a factorisation of the old rows for the old rows' moved matrix.
  const Eigen::SparseMatrix<double> near = contact_system(moved(velocity, 0.002), new_rows);
  ASSERT_TRUE(bordered.prepare(solver, LdltValues::full, old_of, column_of(near)));
  const auto product = [&](const Eigen::VectorXd& y, Eigen::VectorXd& out) {
    out.noalias() = near * y;
  };
  const auto precondition = [&](const Eigen::VectorXd& r, Eigen::VectorXd& out) {
    bordered.solve(r, out);
  };
  Eigen::VectorXd residual, update;
  std::size_t passes = 0;
  bordered.solve(b, x);
  ASSERT_TRUE(refine(b, x, product, precondition, passes, residual, update));
  const Eigen::VectorXd near_exact =
      Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>(near).solve(b);
  EXPECT_LE((x - near_exact).norm(), 1e-9 * near_exact.norm());
  const Eigen::SparseMatrix<double> old_near = contact_system(moved(velocity, 0.002), old_rows);
  const auto old_product = [&](const Eigen::VectorXd& y, Eigen::VectorXd& out) {
    out.noalias() = old_near * y;
  };
  std::vector<double> work;
  const auto old_solve = [&](const Eigen::VectorXd& r, Eigen::VectorXd& out) {
    ldlt_solve(solver, r, out, work);
  };
  const Eigen::VectorXd b_old = b.head(old_matrix.rows());
  Eigen::VectorXd x_old;
  std::size_t passes_old = 0;
  old_solve(b_old, x_old);
  ASSERT_TRUE(refine(b_old, x_old, old_product, old_solve, passes_old, residual, update));
  EXPECT_LE(passes, passes_old + 1);
  std::printf("bordered: %zu passes (the old rows' own: %zu)\n", passes, passes_old);

  // Through the dropped copy too (each solve with F reads it).
  ASSERT_TRUE(bordered.prepare(solver, LdltValues::dropped, old_of, column_of(near)));
  passes = 0;
  bordered.solve(b, x);
  ASSERT_TRUE(refine(b, x, product, precondition, passes, residual, update));
  EXPECT_LE((x - near_exact).norm(), 1e-9 * near_exact.norm());

  // Rows only gone, and rows only new.
  for (const auto& rows :
       {std::vector<int>{0, 1, 2, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19},
        std::vector<int>{0,  1,  2,  3,  4,  5,  6,  7,  8,  9,  10,
                         11, 12, 13, 14, 15, 16, 17, 18, 19, 22, 23}}) {
    std::vector<int> map(static_cast<std::size_t>(nv) + rows.size(), -1);
    for (Eigen::Index i = 0; i < nv; ++i) map[static_cast<std::size_t>(i)] = static_cast<int>(i);
    for (std::size_t c = 0; c < rows.size(); ++c) {
      if (rows[c] < 20) map[static_cast<std::size_t>(nv) + c] = static_cast<int>(nv + rows[c]);
    }
    const Eigen::SparseMatrix<double> m = contact_system(velocity, rows);
    ASSERT_TRUE(bordered.prepare(solver, LdltValues::full, map, column_of(m)));
    const Eigen::VectorXd rhs = Eigen::VectorXd::Ones(m.rows());
    bordered.solve(rhs, x);
    const Eigen::VectorXd answer = Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>(m).solve(rhs);
    EXPECT_LE((x - answer).norm(), 1e-12 * answer.norm());
  }
  // A map that names an unknown F does not have, or one of F's twice, is the caller's bug.
  std::vector<int> twice = old_of;
  twice[1] = 0;
  EXPECT_THROW(bordered.prepare(solver, LdltValues::full, twice, column_of(same)),
               std::logic_error);
  std::vector<int> beyond = old_of;
  beyond[0] = static_cast<int>(old_matrix.rows());
  EXPECT_THROW(bordered.prepare(solver, LdltValues::full, beyond, column_of(same)),
               std::logic_error);
}

TEST(SparseSolve, BlockSolveRefusesMoreThanThreeColumns) {
  const Eigen::SparseMatrix<double> a = random_spd(20, 4, 9);
  SparseLdlt solver;
  solver.compute(a);
  const Eigen::MatrixXd b = Eigen::MatrixXd::Ones(20, 4);
  Eigen::MatrixXd x;
  std::vector<double> work;
  EXPECT_THROW(ldlt_solve(solver, b, x, work), std::logic_error);
}

/// A random rows x cols sparse matrix with about `fill` of its entries set.
Eigen::SparseMatrix<double> random_sparse(int rows, int cols, double fill, std::mt19937& rng) {
  std::uniform_real_distribution<double> unit(0.0, 1.0), value(-1.0, 1.0);
  std::vector<Eigen::Triplet<double>> entries;
  for (int r = 0; r < rows; ++r) {
    for (int c = 0; c < cols; ++c) {
      if (unit(rng) < fill) entries.emplace_back(r, c, value(rng));
    }
  }
  Eigen::SparseMatrix<double> m(rows, cols);
  m.setFromTriplets(entries.begin(), entries.end());
  return m;
}

/// a and b the same matrix: pattern and values, bit for bit.
void expect_identical(const Eigen::SparseMatrix<double>& a, const Eigen::SparseMatrix<double>& b,
                      const char* what) {
  ASSERT_EQ(a.rows(), b.rows()) << what;
  ASSERT_EQ(a.cols(), b.cols()) << what;
  ASSERT_EQ(a.nonZeros(), b.nonZeros()) << what;
  for (Eigen::Index c = 0; c <= a.cols(); ++c) {
    ASSERT_EQ(a.outerIndexPtr()[c], b.outerIndexPtr()[c]) << what << ", column " << c;
  }
  for (Eigen::Index e = 0; e < a.nonZeros(); ++e) {
    EXPECT_EQ(a.innerIndexPtr()[e], b.innerIndexPtr()[e]) << what << ", entry " << e;
    EXPECT_EQ(a.valuePtr()[e], b.valuePtr()[e]) << what << ", entry " << e;
  }
}

TEST(SparseSolve, ProductKeepsItsPatternOnlyWhileItHolds) {
  // product_into() first tries the pattern of its last product. Through a sequence of calls
  // with one scratch (new values on the same patterns; a term outside the pattern; an entry no
  // term reaches any more; X as a matrix, a diagonal, or absent) each product must be the one a
  // fresh scratch makes, pattern and values bit for bit, and that one X - A^T diag(s) B (to
  // round-off: a few terms per entry of size about 1).
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> value(0.5, 2.0);
  const int r = 50, n = 30, m = 20;
  Eigen::SparseMatrix<double> a = random_sparse(r, n, 0.08, rng);
  Eigen::SparseMatrix<double> b = random_sparse(r, m, 0.08, rng);
  const Eigen::SparseMatrix<double> x = random_sparse(n, m, 0.05, rng);
  Eigen::VectorXd s(r), d(m);
  for (Eigen::Index i = 0; i < r; ++i) s[i] = value(rng);
  for (Eigen::Index i = 0; i < m; ++i) d[i] = value(rng);
  ProductWork kept;
  Eigen::SparseMatrix<double> c, fresh;
  auto check = [&](const Eigen::SparseMatrix<double>* with_x, const Eigen::VectorXd* with_d,
                   const char* what) {
    product_into(with_x, with_d, a, &s, b, c, kept);
    ProductWork scratch;
    product_into(with_x, with_d, a, &s, b, fresh, scratch);
    expect_identical(c, fresh, what);
    // X - A^T diag(s) B, or A^T diag(s) B when X is absent.
    const Eigen::MatrixXd product =
        Eigen::MatrixXd(a).transpose() * s.asDiagonal() * Eigen::MatrixXd(b);
    Eigen::MatrixXd reference = with_x == nullptr && with_d == nullptr ? product : -product;
    if (with_x != nullptr) reference += Eigen::MatrixXd(*with_x);
    if (with_d != nullptr) reference.diagonal().head(m) += *with_d;
    EXPECT_LE((Eigen::MatrixXd(c) - reference).norm(), 1e-14 * reference.norm()) << what;
  };
  check(&x, nullptr, "first product");
  for (auto* v : {&a, &b}) {
    for (Eigen::Index e = 0; e < v->nonZeros(); ++e) v->valuePtr()[e] *= value(rng);
  }
  check(&x, nullptr, "new values");
  // A term outside the pattern: a new entry of B whose row meets a column of A^T that does not
  // reach the product's column yet.
  std::vector<Eigen::Triplet<double>> entries;
  for (Eigen::Index col = 0; col < b.outerSize(); ++col) {
    for (Eigen::SparseMatrix<double>::InnerIterator it(b, col); it; ++it) {
      entries.emplace_back(static_cast<int>(it.row()), static_cast<int>(col), it.value());
    }
  }
  const std::size_t before = c.nonZeros();
  entries.emplace_back(r - 1, 0, 1.5);
  entries.emplace_back(0, m - 1, -0.5);
  b.setFromTriplets(entries.begin(), entries.end());
  check(&x, nullptr, "pattern grown");
  EXPECT_GE(static_cast<std::size_t>(c.nonZeros()), before);
  // Entries no term reaches any more: B loses its first column's entries.
  entries.erase(
      std::remove_if(entries.begin(), entries.end(), [](const auto& t) { return t.col() == 0; }),
      entries.end());
  const std::size_t grown = c.nonZeros();
  b.setFromTriplets(entries.begin(), entries.end());
  check(&x, nullptr, "pattern shrunk");
  EXPECT_LT(static_cast<std::size_t>(c.nonZeros()), grown);
  check(nullptr, &d, "X a diagonal");
  check(nullptr, &d, "X a diagonal, again");
  check(nullptr, nullptr, "no X");
  check(nullptr, nullptr, "no X, again");
}

TEST(SparseSolve, AssemblyByColumnsEqualsSetFromTriplets) {
  // Repeated (row, column) pairs are summed in their order, as setFromTriplets sums them: the
  // two matrices are equal entry for entry, bit for bit.
  std::mt19937 rng(11);
  std::uniform_int_distribution<int> row(0, 59), column(0, 39);
  std::uniform_real_distribution<double> value(-1.0, 1.0);
  std::vector<Eigen::Triplet<double>> entries;
  for (int e = 0; e < 900; ++e) entries.emplace_back(row(rng), column(rng), value(rng));
  Eigen::SparseMatrix<double> reference(60, 40), m;
  reference.setFromTriplets(entries.begin(), entries.end());
  std::vector<int> work;
  assign_by_columns(m, 60, 40, entries, work);
  ASSERT_EQ(m.nonZeros(), reference.nonZeros());
  for (Eigen::Index c = 0; c < 40; ++c) {
    Eigen::SparseMatrix<double>::InnerIterator it(m, c), jt(reference, c);
    for (; it && jt; ++it, ++jt) {
      EXPECT_EQ(it.row(), jt.row());
      EXPECT_EQ(it.value(), jt.value());
    }
    EXPECT_FALSE(it || jt) << "column " << c;
  }
}

}  // namespace
}  // namespace mpm
