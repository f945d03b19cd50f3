#pragma once
// What the dual-grid solvers (the mortar/one-way Schur complement, Enhanced's systems) share:
// the sparsity signature that decides when a fill-reducing ordering (a symbolic factorisation)
// must be recomputed, and the reuse of an earlier step's factorisation by refinement.

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>

#include "mpm/dual_grid.hpp"

namespace mpm {

/// Hash of the non-zero pattern of `m` (not its values).
inline std::size_t pattern_hash(const Eigen::SparseMatrix<double>& m) {
  std::size_t hash = static_cast<std::size_t>(m.nonZeros()) * 1000003U + m.rows();
  for (Eigen::Index c = 0; c < m.outerSize(); ++c) {
    for (Eigen::SparseMatrix<double>::InnerIterator it(m, c); it; ++it) {
      hash = hash * 31U + static_cast<std::size_t>(it.row() * 7919 + c);
    }
  }
  return hash;
}

/// Sets m to the rows x cols matrix of `entries` (no (row, column) twice), reusing m's storage
/// and `work` (scratch): unlike setFromTriplets(), no allocation once m has held this many
/// columns and entries. Linear in the entries, rows and columns: the entries are bucketed by
/// row and then dealt to their columns, so each column comes out in increasing row order, as
/// Eigen's algorithms expect.
inline void assign_by_columns(Eigen::SparseMatrix<double>& m, Eigen::Index rows, Eigen::Index cols,
                              const std::vector<Eigen::Triplet<double>>& entries,
                              std::vector<int>& work) {
  const auto nnz = static_cast<Eigen::Index>(entries.size());
  m.resize(rows, cols);   // keeps the column array when the column count is the same
  m.resizeNonZeros(nnz);  // keeps the capacity
  work.assign(static_cast<std::size_t>(rows + 1 + nnz + cols), 0);
  int* row_start = work.data();        // rows + 1
  int* by_row = row_start + rows + 1;  // nnz entry numbers, grouped by row
  int* next = by_row + nnz;            // cols: each column's next free slot
  int* outer = m.outerIndexPtr();
  int* inner = m.innerIndexPtr();
  double* value = m.valuePtr();
  std::fill(outer, outer + cols + 1, 0);
  for (const auto& t : entries) {
    ++row_start[t.row() + 1];
    ++outer[t.col() + 1];
  }
  for (Eigen::Index r = 0; r < rows; ++r) row_start[r + 1] += row_start[r];
  for (Eigen::Index c = 0; c < cols; ++c) {
    outer[c + 1] += outer[c];
    next[c] = outer[c];
  }
  for (Eigen::Index e = 0; e < nnz; ++e) {
    by_row[row_start[entries[static_cast<std::size_t>(e)].row()]++] = static_cast<int>(e);
  }
  for (Eigen::Index k = 0; k < nnz; ++k) {  // by_row lists the entries by increasing row
    const auto& t = entries[static_cast<std::size_t>(by_row[k])];
    const int slot = next[t.col()]++;
    inner[slot] = t.row();
    value[slot] = t.value();
  }
}

/// x = A^-1 b with the factorisation in `solver`, as solver.solve(b) computes it (the same
/// operations in the same order), without its temporaries: `work` is scratch of b's size.
inline void ldlt_solve(const SparseLdlt& solver, Eigen::Ref<const Eigen::VectorXd> b,
                       Eigen::Ref<Eigen::VectorXd> x, Eigen::Ref<Eigen::VectorXd> work) {
  if (solver.permutationP().size() > 0) {
    work.noalias() = solver.permutationP() * b;
  } else {
    work = b;
  }
  if (solver.matrixL().nestedExpression().nonZeros() > 0) solver.matrixL().solveInPlace(work);
  if (solver.diagonal().size() > 0) work.array() *= solver.diagonal().array().inverse();
  if (solver.matrixL().nestedExpression().nonZeros() > 0) solver.matrixU().solveInPlace(work);
  if (solver.permutationPinv().size() > 0) {
    x.noalias() = solver.permutationPinv() * work;
  } else {
    x = work;
  }
}

/// Refinement passes x += solve(b - apply(x)) from the x in hand: `apply(x, y)` sets y to this
/// step's matrix times x and `solve(r, dx)` applies the factorisation in hand (an earlier
/// step's) to r; `residual` and `update` are scratch of b's shape. Each pass
/// shrinks the error by about the relative change of the matrix since the factorised step (the
/// rate q, estimated as the largest ratio of successive updates seen); in a flow whose masses
/// change fast that is slow, and a factorisation costs about as much as 10-20 passes, so
/// refinement stops as soon as the rate says it would need more than kMaxPasses in all (with a
/// fixed 20 passes, the debris scene spent 70% of its run refining and then factorising anyway).
/// True if converged: the error left after a pass, at most q / (1 - q) times its update for a
/// contraction by q, is below kTolerance of x (round-off). Bounding the error left rather than
/// the update just made saves the pass that only confirms it (at the rates of a resting layer,
/// 1e-5, the update of the second pass is ~1e-10 of x and the error it leaves ~1e-15). The caller
/// factorises when this returns false.
template <class Rhs, class Apply, class Solve>
bool refine(const Rhs& b, Rhs& x, Apply&& apply, Solve&& solve, std::size_t& passes, Rhs& residual,
            Rhs& update) {
  constexpr int kMaxPasses = 6;
  constexpr double kTolerance = 1e-13;
  double previous = x.norm();
  double q = 0.0;  // the contraction rate: the largest ratio of successive updates seen
  for (int pass = 1;; ++pass) {
    apply(x, residual);
    residual = b - residual;
    solve(residual, update);
    x += update;
    ++passes;
    const double step = update.norm(), size = x.norm();
    if (step <= kTolerance * size) return true;
    const double rate = step / previous;
    previous = step;
    if (!(rate < 0.5)) return false;  // stalled (or not a number)
    q = std::max(q, rate);
    // The first ratio compares the update with x itself, not with an update, and can fall short
    // of the rate: the error bound waits for the second.
    if (pass >= 2 && q / (1.0 - q) * step <= kTolerance * size) return true;
    if (pass >= kMaxPasses) return false;
    if (pass + std::log(kTolerance * size / step) / std::log(q) > kMaxPasses) return false;
  }
}

/// Solves m x = b with `solver`, which holds a factorisation of m itself or, when `refine`, of
/// an earlier matrix with the same pattern (the previous step's: the masses change a little
/// from step to step), refined then by refine(); unconverged (the matrices are too far apart),
/// m is factorised and `refine` cleared. Returns false if m cannot be factorised. `base` keeps
/// the matrix the solver's factorisation is of (a checkpoint saves it, so a resumed run refines
/// against the same one). `passes` and `factorizations` count the work done (reported by the
/// benchmarks).
template <class Rhs>
bool refined_solve(SparseLdlt& solver, const Eigen::SparseMatrix<double>& m,
                   Eigen::SparseMatrix<double>& base, bool& refine, const Rhs& b, Rhs& x,
                   std::size_t& passes, std::size_t& factorizations) {
  x = solver.solve(b);
  if (!refine) return true;
  const auto product = [&](const Rhs& y, Rhs& out) { out = m * y; };
  const auto factor = [&](const Rhs& r, Rhs& out) { out = solver.solve(r); };
  Rhs residual, update;
  if (mpm::refine(b, x, product, factor, passes, residual, update)) return true;
  solver.factorize(m);
  base = m;
  ++factorizations;
  refine = false;
  if (solver.info() != Eigen::Success) return false;
  x = solver.solve(b);
  return true;
}

/// Factorises m into `solver` unless `solver` holds a factorisation of an earlier matrix with the
/// same pattern (then refined_solve() refines against it): sets `refine` accordingly. Returns
/// false if m cannot be factorised. `base` as in refined_solve().
inline bool factorise_or_reuse(SparseLdlt& solver, const Eigen::SparseMatrix<double>& m,
                               Eigen::SparseMatrix<double>& base, std::size_t& pattern,
                               bool& factored, bool reusable, bool& refine,
                               std::size_t& factorizations) {
  const std::size_t hash = pattern_hash(m);
  refine = factored && reusable && hash == pattern;
  if (refine) return true;
  if (hash != pattern) {
    solver.analyzePattern(m);
    pattern = hash;
  }
  solver.factorize(m);
  base = m;
  ++factorizations;
  factored = solver.info() == Eigen::Success;
  return factored;
}

}  // namespace mpm
