#pragma once
// What the dual-grid solvers (the mortar/one-way Schur complement, Enhanced's systems) share:
// the sparsity signature that decides when a fill-reducing ordering (a symbolic factorisation)
// must be recomputed, the reuse of an earlier step's factorisation by refinement, and the sparse
// assembly, products and solves that work in the caller's storage, so that a step that does not
// factorise allocates nothing (issue 9, tests/mpm/test_allocation.cpp).

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <limits>
#include <stdexcept>
#include <type_traits>
#include <vector>

#include <tbb/parallel_invoke.h>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>

#include "mpm/dual_grid.hpp"

namespace mpm {

/// diagonal[c] += sum_i r_ic^2 weight_i for every column c of r: the diagonal of r^T diag(weight)
/// r without forming it (a coupling's Schur complement, whose largest diagonal entry sets its
/// shift).
inline void add_weighted_column_squares(const Eigen::SparseMatrix<double>& r,
                                        const Eigen::VectorXd& weight, Eigen::VectorXd& diagonal) {
  for (Eigen::Index c = 0; c < r.outerSize(); ++c) {
    for (Eigen::SparseMatrix<double>::InnerIterator it(r, c); it; ++it) {
      diagonal[c] += it.value() * it.value() * weight[it.row()];
    }
  }
}

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

/// m.resize(rows, cols), except that a matrix of no columns already of that shape is left as
/// it is: Eigen frees and allocates the column array of every resize to zero columns.
inline void reshape(Eigen::SparseMatrix<double>& m, Eigen::Index rows, Eigen::Index cols) {
  if (cols == 0 && m.cols() == 0 && m.rows() == rows) return;  // no entries to clear
  m.resize(rows, cols);
}

/// dst = src into dst's storage (no allocation once dst has held as many entries and columns).
inline void copy_into(const Eigen::SparseMatrix<double>& src, Eigen::SparseMatrix<double>& dst) {
  reshape(dst, src.rows(), src.cols());
  dst.resizeNonZeros(src.nonZeros());
  std::copy(src.outerIndexPtr(), src.outerIndexPtr() + src.outerSize() + 1, dst.outerIndexPtr());
  std::copy(src.innerIndexPtr(), src.innerIndexPtr() + src.nonZeros(), dst.innerIndexPtr());
  std::copy(src.valuePtr(), src.valuePtr() + src.nonZeros(), dst.valuePtr());
}

/// Sets m to the rows x cols matrix of `entries`, summing the entries of the same (row, column)
/// in their order (as setFromTriplets() does), reusing m's storage and `work` (scratch): unlike
/// setFromTriplets(), no allocation once m has held this many columns and entries. Linear in
/// the entries, rows and columns: the entries are bucketed by row and then dealt to their
/// columns, so each column comes out in increasing row order, as Eigen's algorithms expect.
inline void assign_by_columns(Eigen::SparseMatrix<double>& m, Eigen::Index rows, Eigen::Index cols,
                              const std::vector<Eigen::Triplet<double>>& entries,
                              std::vector<int>& work) {
  const auto nnz = static_cast<Eigen::Index>(entries.size());
  reshape(m, rows, cols);  // keeps the column array when the column count is the same
  m.resizeNonZeros(nnz);   // keeps the capacity
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
  bool merged = false;
  for (Eigen::Index k = 0; k < nnz; ++k) {  // by_row lists the entries by increasing row
    const auto& t = entries[static_cast<std::size_t>(by_row[k])];
    int& slot = next[t.col()];
    // A repeated (row, column) arrives right after the first: its row is the column's last.
    if (slot > outer[t.col()] && inner[slot - 1] == t.row()) {
      value[slot - 1] += t.value();
      merged = true;
      continue;
    }
    inner[slot] = t.row();
    value[slot] = t.value();
    ++slot;
  }
  if (!merged) return;
  int end = 0;  // close the gaps the merged entries left
  for (Eigen::Index c = 0; c < cols; ++c) {
    const int first = outer[c];
    outer[c] = end;
    for (int e = first; e < next[c]; ++e, ++end) {
      inner[end] = inner[e];
      value[end] = value[e];
    }
  }
  outer[cols] = end;
  m.resizeNonZeros(end);
}

/// at = a^T into at's storage (no allocation once at has held as many entries and columns).
inline void transpose_into(const Eigen::SparseMatrix<double>& a, Eigen::SparseMatrix<double>& at) {
  reshape(at, a.cols(), a.rows());
  at.resizeNonZeros(a.nonZeros());
  int* outer = at.outerIndexPtr();  // one column of at per row of a
  std::fill(outer, outer + a.rows() + 1, 0);
  const int* inner = a.innerIndexPtr();
  for (Eigen::Index e = 0; e < a.nonZeros(); ++e) ++outer[inner[e] + 1];
  for (Eigen::Index r = 0; r < a.rows(); ++r) outer[r + 1] += outer[r];
  // a's columns in increasing order, so that each column of at comes out sorted; outer[r] is
  // row r's next free slot meanwhile, shifted back after.
  for (Eigen::Index c = 0; c < a.cols(); ++c) {
    for (Eigen::SparseMatrix<double>::InnerIterator it(a, c); it; ++it) {
      const int slot = outer[it.row()]++;
      at.innerIndexPtr()[slot] = static_cast<int>(c);
      at.valuePtr()[slot] = it.value();
    }
  }
  for (Eigen::Index r = a.rows(); r > 0; --r) outer[r] = outer[r - 1];
  outer[0] = 0;
}

/// C = X - A^T diag(s) B (A^T diag(s) B when X is absent; s = 1 when absent), X given as a
/// sparse matrix or as a diagonal, into C's storage and `w` (no allocation once they have held
/// this much). C's pattern is X's and the product's together; columns sorted. The product is
/// summed column by column (Gustavson), in another order than Eigen's product (round-off).
/// Matrices compressed (as this file's functions make them).
///
/// C's pattern is first assumed to be that of the last call with `w` (the dual-grid couplings'
/// products keep theirs while contact and the set of nodes with mass stay the same, though the
/// patterns of A and B change more often): each column's terms go straight to their entries,
/// found through a row -> entry map of that column; a term outside the pattern, or an entry no
/// term reaches, sends the whole call to the general pass, which finds the pattern (marking the
/// rows each column touches and sorting them: for Enhanced's three products on the floor scene most
/// of their time, docs/performance.md, 2026-12-04, evening). Either way each entry sums its terms
/// in the same order, so C is the same to the bit.
inline void product_into(const Eigen::SparseMatrix<double>* x, const Eigen::VectorXd* x_diagonal,
                         const Eigen::SparseMatrix<double>& a, const Eigen::VectorXd* s,
                         const Eigen::SparseMatrix<double>& b, Eigen::SparseMatrix<double>& c,
                         ProductWork& w) {
  using Sparse = Eigen::SparseMatrix<double>;
  const Eigen::Index rows = a.cols(), cols = b.cols();
  if (!a.isCompressed() || !b.isCompressed() || (x != nullptr && !x->isCompressed())) {
    throw std::logic_error("product_into: a matrix is not compressed");
  }
  transpose_into(a, w.lhs_rows);
  const Sparse& at = w.lhs_rows;
  const int* at_outer = at.outerIndexPtr();
  const int* at_inner = at.innerIndexPtr();
  const double* at_value = at.valuePtr();
  const int* b_outer = b.outerIndexPtr();
  const int* b_inner = b.innerIndexPtr();
  const double* b_value = b.valuePtr();
  const bool subtract = x != nullptr || x_diagonal != nullptr;
  // Column j's terms, each handed to `term(i, a, b)` with its row in C, in the order the sums
  // take them (the term is a b, added to the sum by std::fma: one rounding in both passes,
  // whatever the compiler would contract); then X's entries to `entry(i, value)`.
  auto for_each_term = [&](Eigen::Index j, auto&& term, auto&& entry) {
    for (int eb = b_outer[j]; eb < b_outer[j + 1]; ++eb) {
      const int r = b_inner[eb];
      const double bv = b_value[eb];
      if (s != nullptr) {
        const double scale = (*s)[r];
        for (int ea = at_outer[r]; ea < at_outer[r + 1]; ++ea) {
          term(at_inner[ea], at_value[ea] * scale, bv);
        }
      } else {
        for (int ea = at_outer[r]; ea < at_outer[r + 1]; ++ea) term(at_inner[ea], at_value[ea], bv);
      }
    }
    if (x != nullptr) {
      for (int ex = x->outerIndexPtr()[j]; ex < x->outerIndexPtr()[j + 1]; ++ex) {
        entry(x->innerIndexPtr()[ex], x->valuePtr()[ex]);
      }
    }
    if (x_diagonal != nullptr) entry(static_cast<int>(j), (*x_diagonal)[j]);
  };
  std::vector<int>& place = w.mark;  // row -> its entry in the column at hand (or an earlier one)
  place.assign(static_cast<std::size_t>(rows), -1);

  // The last call's pattern, if it still holds.
  bool same = w.pattern_rows == rows && w.c_outer.size() == static_cast<std::size_t>(cols) + 1;
  if (same) {
    const std::size_t nnz = w.c_inner.size();
    w.product.assign(nnz, 0.0);
    w.base.assign(nnz, 0.0);
    w.reached.assign(nnz, 0);
    for (Eigen::Index j = 0; j < cols && same; ++j) {
      const int first = w.c_outer[static_cast<std::size_t>(j)];
      const int end = w.c_outer[static_cast<std::size_t>(j) + 1];
      for (int e = first; e < end; ++e) place[static_cast<std::size_t>(w.c_inner[e])] = e;
      bool outside = false;
      for_each_term(
          j,
          [&](int i, double u, double v) {
            const int e = place[static_cast<std::size_t>(i)];
            if (e < first) {  // -1, or an earlier column's entry
              outside = true;
              return;
            }
            double& sum = w.product[static_cast<std::size_t>(e)];
            sum = std::fma(u, v, sum);
            w.reached[static_cast<std::size_t>(e)] = 1;
          },
          [&](int i, double v) {
            const int e = place[static_cast<std::size_t>(i)];
            if (e < first) {
              outside = true;
              return;
            }
            w.base[static_cast<std::size_t>(e)] = v;
            w.reached[static_cast<std::size_t>(e)] = 1;
          });
      same = !outside && std::all_of(w.reached.begin() + first, w.reached.begin() + end,
                                     [](char r) { return r != 0; });
    }
    if (!same) place.assign(static_cast<std::size_t>(rows), -1);
  }
  if (!same) {
    // The general pass: column j's rows are those its terms and X's entries touch, sorted.
    w.product.assign(static_cast<std::size_t>(rows), 0.0);
    w.base.assign(static_cast<std::size_t>(rows), 0.0);
    w.c_outer.assign(static_cast<std::size_t>(cols) + 1, 0);
    w.c_inner.clear();
    w.value.clear();
    std::vector<int>& seen = w.touched;
    for (Eigen::Index j = 0; j < cols; ++j) {
      seen.clear();
      auto touch = [&](int i) {
        const auto k = static_cast<std::size_t>(i);
        if (place[k] == j) return k;
        place[k] = static_cast<int>(j);
        w.product[k] = 0.0;
        w.base[k] = 0.0;
        seen.push_back(i);
        return k;
      };
      for_each_term(
          j,
          [&](int i, double u, double v) {
            double& sum = w.product[touch(i)];
            sum = std::fma(u, v, sum);
          },
          [&](int i, double v) { w.base[touch(i)] = v; });
      std::sort(seen.begin(), seen.end());
      for (const int i : seen) {
        const auto k = static_cast<std::size_t>(i);
        w.c_inner.push_back(i);
        w.value.push_back(subtract ? w.base[k] - w.product[k] : w.product[k]);
      }
      w.c_outer[static_cast<std::size_t>(j) + 1] = static_cast<int>(w.c_inner.size());
    }
    w.pattern_rows = rows;
    // The next call's buffers, per entry of this pattern: allocated here, with the pattern.
    w.product.reserve(w.c_inner.size());
    w.base.reserve(w.c_inner.size());
    w.reached.reserve(w.c_inner.size());
  }
  const std::size_t nnz = w.c_inner.size();
  reshape(c, rows, cols);
  c.resizeNonZeros(static_cast<Eigen::Index>(nnz));
  std::copy(w.c_outer.begin(), w.c_outer.end(), c.outerIndexPtr());
  std::copy(w.c_inner.begin(), w.c_inner.end(), c.innerIndexPtr());
  double* value = c.valuePtr();
  if (!same) {
    std::copy(w.value.begin(), w.value.end(), value);
  } else {
    for (std::size_t e = 0; e < nnz; ++e)
      value[e] = subtract ? w.base[e] - w.product[e] : w.product[e];
  }
}

/// x = A^-1 b for every column of b at once with the factorisation in `solver`: the operations
/// of solver.solve(b) on each column (P, L, D^-1, L^T, P^-1), but the columns side by side in
/// `work` (scratch, row-major), so that each entry of L is read once for all of them rather
/// than once per column (the floor scene's Phi coupling 9.5 -> 9.0 ms against a column per
/// core, Enhanced's 19.5 -> 16.6 ms against a column at a time; docs/performance.md). Runs of
/// columns that share their rows below (ColumnRuns) are solved as dense blocks: the rows below
/// read once per run, each column's values as one contiguous stretch, four columns' updates
/// summed before a row is stored (bench/bench_solve.cpp: a flat Phi's factor with 229,409
/// entries 353-373 -> 194-196 us a solve in double, 286-300 -> 201-202 in single). The
/// backward solve sums each row in four partial sums (a run's in eight), and a factor whose
/// elimination tree splits (SubtreeSplit) has its two sides solved on two threads: the sums are
/// grouped differently from Eigen's (round-off apart), the same for any thread count. At most 3
/// columns. No allocation once `work` and x have held this size. With LdltValues::single the
/// solve reads L's single-precision copy (after solver.round_to_single()): a preconditioner's
/// solve, exact to about 1e-7; with LdltValues::dropped, L's dropped copy (SparseLdlt::
/// dropped()) by plain column sweeps on one thread: a cheaper preconditioner's.
template <class Rhs>
void ldlt_solve(const SparseLdlt& solver, const Rhs& b, Rhs& x, std::vector<double>& work,
                LdltValues values = LdltValues::full) {
  const Eigen::Index n = b.rows();
  const Eigen::Index cols = b.cols();
  const auto width = static_cast<std::size_t>(cols);
  const SubtreeSplit& split = solver.split();
  const ColumnRuns& runs = solver.runs();
  // The rows, then (split solves) the second side's updates of the top rows, then a buffer of
  // the rows below a run for each thread.
  const std::size_t rows_size = static_cast<std::size_t>(n) * width;
  const std::size_t spill_size = split.parallel ? split.top.size() * width : 0;
  const std::size_t run_size = static_cast<std::size_t>(runs.most_below) * width;
  work.resize(rows_size + spill_size + 2 * run_size);
  x.resize(n, b.cols());
  const int* perm =
      solver.permutationP().size() > 0 ? solver.permutationP().indices().data() : nullptr;
  for (Eigen::Index i = 0; i < n; ++i) {
    double* row = &work[static_cast<std::size_t>(perm != nullptr ? perm[i] : i) * width];
    for (Eigen::Index c = 0; c < cols; ++c) row[c] = b(i, c);
  }
  // L is unit lower (SimplicialLDLT keeps D apart), by columns; L^T is its transpose, so its
  // row i is L's column i. Entries on or above the diagonal are skipped as Eigen's triangular
  // solves skip them.
  const auto& l = solver.matrixL().nestedExpression();
  const int* outer = l.outerIndexPtr();
  const int* inner = l.innerIndexPtr();
  const Eigen::VectorXd& d = solver.diagonal();
  if (values == LdltValues::dropped &&
      solver.dropped().outer.size() != static_cast<std::size_t>(n) + 1) {
    throw std::logic_error("ldlt_solve: no dropped copy of L for this factorisation");
  }
  if (values == LdltValues::single && !solver.rounded()) {
    throw std::logic_error("ldlt_solve: L not rounded to single precision since it was factorised");
  }
  // rows *= D^-1, C columns to a row (between the forward and the backward solve).
  auto divide_by_diagonal = [&](auto fixed) {
    constexpr int C = decltype(fixed)::value;
    for (Eigen::Index j = 0; j < d.size(); ++j) {
      const double inverse = 1.0 / d[j];
      for (int c = 0; c < C; ++c) work[static_cast<std::size_t>(j) * C + c] *= inverse;
    }
  };
  // Each row's values are held in locals while its column is applied, so that the compiler
  // need not reload them after every store through the aliasing row pointers.
  // `value`: L's values, double or float (the arithmetic is in double either way).
  auto apply_rows = [&](auto fixed, const auto* value) {
    constexpr int C = decltype(fixed)::value;
    double* const rows = work.data();
    // Forward: column j's update of the rows below it; rows beyond `limit` go to `spill`
    // (their place among the top rows) instead.
    auto forward = [&](int j, int limit, double* spill) {
      double xj[C];
      for (int c = 0; c < C; ++c) xj[c] = rows[static_cast<std::size_t>(j) * C + c];
      for (int p = outer[j]; p < outer[j + 1]; ++p) {
        const int i = inner[p];
        if (i <= j) continue;
        double* xi = i <= limit ? &rows[static_cast<std::size_t>(i) * C]
                                : &spill[static_cast<std::size_t>(split.top_slot[i]) * C];
        for (int c = 0; c < C; ++c) xi[c] -= xj[c] * value[p];
      }
    };
    // Backward: row i of L^T against the rows below it (final by then). Its entries are summed
    // into four partial sums, every fourth entry each: with one sum every multiply-add waited
    // for the one before (the floor's Enhanced coupling 46-49 -> 38-41 ms a step;
    // docs/performance.md). A column's rows increase, so those at or above the diagonal (none
    // in Eigen's LDL^T, whose diagonal is D) come first.
    auto backward = [&](int i) {
      double xi[C], yi[C] = {}, zi[C] = {}, wi[C] = {};
      for (int c = 0; c < C; ++c) xi[c] = rows[static_cast<std::size_t>(i) * C + c];
      int p = outer[i];
      const int end = outer[i + 1];
      while (p < end && inner[p] <= i) ++p;
      for (; p + 3 < end; p += 4) {
        const double* xk = &rows[static_cast<std::size_t>(inner[p]) * C];
        const double* xl = &rows[static_cast<std::size_t>(inner[p + 1]) * C];
        const double* xm = &rows[static_cast<std::size_t>(inner[p + 2]) * C];
        const double* xn = &rows[static_cast<std::size_t>(inner[p + 3]) * C];
        for (int c = 0; c < C; ++c) {
          xi[c] -= value[p] * xk[c];
          yi[c] += value[p + 1] * xl[c];
          zi[c] += value[p + 2] * xm[c];
          wi[c] += value[p + 3] * xn[c];
        }
      }
      for (; p < end; ++p) {
        const double* xk = &rows[static_cast<std::size_t>(inner[p]) * C];
        for (int c = 0; c < C; ++c) xi[c] -= value[p] * xk[c];
      }
      for (int c = 0; c < C; ++c)
        rows[static_cast<std::size_t>(i) * C + c] = xi[c] - ((yi[c] + zi[c]) + wi[c]);
    };
    // A run of columns [j0, j1) (ColumnRuns): each row below it is read into `below` (the
    // columns' components apart, `most_below` apart) and written back once; each column
    // updates (forward) or is read against (backward) those rows as a contiguous stretch of
    // its values. The forward solve sums four columns' updates of a row before subtracting
    // them; the backward sums each dot product in eight parts (vectors of them).
    const auto stride = static_cast<std::size_t>(runs.most_below);
    // The place of row i (forward: beyond `limit`, its place among the spilled top rows).
    auto place = [&](int i, int limit, double* spill) {
      return i <= limit ? &rows[static_cast<std::size_t>(i) * C]
                        : &spill[static_cast<std::size_t>(split.top_slot[i]) * C];
    };
    auto forward_run = [&](const std::array<int, 2>& run, int limit, double* spill, double* below) {
      const int j0 = run[0], j1 = run[1], last = j1 - 1;
      if (j1 - j0 == 1) return forward(j0, limit, spill);
      for (int j = j0; j < last; ++j) {  // the run's triangle
        double xj[C];
        for (int c = 0; c < C; ++c) xj[c] = rows[static_cast<std::size_t>(j) * C + c];
        int p = outer[j];
        for (int i = j + 1; i < j1; ++i, ++p) {
          for (int c = 0; c < C; ++c) rows[static_cast<std::size_t>(i) * C + c] -= xj[c] * value[p];
        }
      }
      const int count = outer[j1] - outer[last];
      const int* row = inner + outer[last];
      for (int t = 0; t < count; ++t) {
        const double* from = place(row[t], limit, spill);
        for (int c = 0; c < C; ++c) below[static_cast<std::size_t>(c) * stride + t] = from[c];
      }
      // Four columns at a time: each row's updates from them summed before it is stored.
      int j = j0;
      for (; j + 3 < j1; j += 4) {
        const auto* __restrict v0 = value + outer[j] + (last - j);
        const auto* __restrict v1 = value + outer[j + 1] + (last - j - 1);
        const auto* __restrict v2 = value + outer[j + 2] + (last - j - 2);
        const auto* __restrict v3 = value + outer[j + 3] + (last - j - 3);
        for (int c = 0; c < C; ++c) {
          const double* xs = &rows[static_cast<std::size_t>(j) * C + c];
          const double x0 = xs[0], x1 = xs[C], x2 = xs[2 * C], x3 = xs[3 * C];
          double* __restrict to = below + static_cast<std::size_t>(c) * stride;
          for (int t = 0; t < count; ++t) {
            to[t] -= (x0 * v0[t] + x1 * v1[t]) + (x2 * v2[t] + x3 * v3[t]);
          }
        }
      }
      for (; j < j1; ++j) {
        const auto* __restrict v = value + outer[j] + (last - j);
        for (int c = 0; c < C; ++c) {
          const double xj = rows[static_cast<std::size_t>(j) * C + c];
          double* __restrict to = below + static_cast<std::size_t>(c) * stride;
          for (int t = 0; t < count; ++t) to[t] -= xj * v[t];
        }
      }
      for (int t = 0; t < count; ++t) {
        double* to = place(row[t], limit, spill);
        for (int c = 0; c < C; ++c) to[c] = below[static_cast<std::size_t>(c) * stride + t];
      }
    };
    auto backward_run = [&](const std::array<int, 2>& run, double* below) {
      const int j0 = run[0], j1 = run[1], last = j1 - 1;
      if (j1 - j0 == 1) return backward(j0);
      const int count = outer[j1] - outer[last];
      const int* row = inner + outer[last];
      for (int t = 0; t < count; ++t) {
        const double* from = &rows[static_cast<std::size_t>(row[t]) * C];
        for (int c = 0; c < C; ++c) below[static_cast<std::size_t>(c) * stride + t] = from[c];
      }
      for (int j = j0; j < j1; ++j) {
        const auto* __restrict v = value + outer[j] + (last - j);
        for (int c = 0; c < C; ++c) {
          const double* __restrict rhs = below + static_cast<std::size_t>(c) * stride;
          double sum[8] = {};  // eight partial sums: one vector of them
          int t = 0;
          for (; t + 7 < count; t += 8) {
            for (int k = 0; k < 8; ++k) sum[k] += v[t + k] * rhs[t + k];
          }
          for (; t < count; ++t) sum[0] += v[t] * rhs[t];
          rows[static_cast<std::size_t>(j) * C + c] -=
              ((sum[0] + sum[1]) + (sum[2] + sum[3])) + ((sum[4] + sum[5]) + (sum[6] + sum[7]));
        }
      }
      for (int j = last - 1; j >= j0; --j) {  // the run's triangle, its last column first
        double xj[C];
        for (int c = 0; c < C; ++c) xj[c] = rows[static_cast<std::size_t>(j) * C + c];
        int p = outer[j];
        for (int i = j + 1; i < j1; ++i, ++p) {
          for (int c = 0; c < C; ++c) xj[c] -= value[p] * rows[static_cast<std::size_t>(i) * C + c];
        }
        for (int c = 0; c < C; ++c) rows[static_cast<std::size_t>(j) * C + c] = xj[c];
      }
    };
    constexpr int kAll = std::numeric_limits<int>::max();
    double* const spill = rows + rows_size;
    double* const below0 = spill + spill_size;
    double* const below1 = below0 + run_size;
    if (split.parallel) {
      // The two sides at once, then the top; the second side's updates of top rows added
      // between (SubtreeSplit).
      std::fill(spill, spill + split.top.size() * C, 0.0);
      tbb::parallel_invoke(
          [&] {
            for (const auto& run : runs.side[0]) forward_run(run, kAll, nullptr, below0);
          },
          [&] {
            for (const auto& run : runs.side[1]) {
              forward_run(run, split.root[run[0]], spill, below1);
            }
          });
      for (std::size_t t = 0; t < split.top.size(); ++t) {
        for (int c = 0; c < C; ++c)
          rows[static_cast<std::size_t>(split.top[t]) * C + c] += spill[t * C + c];
      }
      for (const auto& run : runs.top) forward_run(run, kAll, nullptr, below0);
    } else if (l.nonZeros() > 0) {
      for (const auto& run : runs.all) forward_run(run, kAll, nullptr, below0);
    }
    divide_by_diagonal(fixed);
    if (split.parallel) {
      for (auto run = runs.top.rbegin(); run != runs.top.rend(); ++run) backward_run(*run, below0);
      tbb::parallel_invoke(
          [&] {
            for (auto run = runs.side[0].rbegin(); run != runs.side[0].rend(); ++run)
              backward_run(*run, below0);
          },
          [&] {
            for (auto run = runs.side[1].rbegin(); run != runs.side[1].rend(); ++run)
              backward_run(*run, below1);
          });
    } else if (l.nonZeros() > 0) {
      for (auto run = runs.all.rbegin(); run != runs.all.rend(); ++run) backward_run(*run, below0);
    }
  };
  // The dropped copy: plain column sweeps (its columns share few rows: no runs, one thread).
  auto apply_dropped = [&](auto fixed) {
    constexpr int C = decltype(fixed)::value;
    const SparseLdlt::Dropped& dl = solver.dropped();
    double* const rows = work.data();
    const int count = static_cast<int>(n);
    for (int j = 0; j < count; ++j) {
      double xj[C];
      for (int c = 0; c < C; ++c) xj[c] = rows[static_cast<std::size_t>(j) * C + c];
      for (int p = dl.outer[j]; p < dl.outer[j + 1]; ++p) {
        double* xi = &rows[static_cast<std::size_t>(dl.inner[p]) * C];
        const double v = dl.value[p];
        for (int c = 0; c < C; ++c) xi[c] -= xj[c] * v;
      }
    }
    divide_by_diagonal(fixed);
    for (int i = count - 1; i >= 0; --i) {
      double xi[C];
      for (int c = 0; c < C; ++c) xi[c] = rows[static_cast<std::size_t>(i) * C + c];
      for (int p = dl.outer[i]; p < dl.outer[i + 1]; ++p) {
        const double* xk = &rows[static_cast<std::size_t>(dl.inner[p]) * C];
        const double v = dl.value[p];
        for (int c = 0; c < C; ++c) xi[c] -= v * xk[c];
      }
      for (int c = 0; c < C; ++c) rows[static_cast<std::size_t>(i) * C + c] = xi[c];
    }
  };
  auto apply_columns = [&](auto fixed) {
    if (values == LdltValues::dropped) {
      apply_dropped(fixed);
    } else if (values == LdltValues::single) {
      apply_rows(fixed, solver.single_values().data());
    } else {
      apply_rows(fixed, l.valuePtr());
    }
  };
  switch (cols) {
    case 1:
      apply_columns(std::integral_constant<int, 1>{});
      break;
    case 2:
      apply_columns(std::integral_constant<int, 2>{});
      break;
    case 3:
      apply_columns(std::integral_constant<int, 3>{});
      break;
    default:
      throw std::logic_error("ldlt_solve: more than 3 right-hand sides");
  }
  for (Eigen::Index i = 0; i < n; ++i) {  // x = P^-1 work
    const double* row = &work[static_cast<std::size_t>(perm != nullptr ? perm[i] : i) * width];
    for (Eigen::Index c = 0; c < cols; ++c) x(i, c) = row[c];
  }
}

/// refine()'s relative tolerance (below).
constexpr double kRefineTolerance = 1e-10;

/// Decides, once per factorisation, whether solves against it that only precondition (once
/// the matrix has moved) read L's dropped copy (SparseLdlt::dropped()): from an exact solve
/// `exact` of b with the factorisation in hand, the copy's answer for b within kDroppedAnswer
/// of it in `norm`. Where the matrix is near singular (the one-way floor's S, whose shift
/// holds multipliers the active nodes cannot all satisfy) the entries left out can carry its
/// small eigenvalues: that copy failed CG every step, and a failed solve factorises. Does
/// nothing for a solver without the copy or already checked. `scratch` of b's shape.
template <class Rhs, class Norm>
void check_dropped(SparseLdlt& solver, const Rhs& b, const Rhs& exact, Rhs& scratch,
                   std::vector<double>& work, const Norm& norm) {
  constexpr double kDroppedAnswer = 0.1;
  if (!solver.keeps_dropped() || solver.dropped_use() != SparseLdlt::DroppedUse::unchecked) return;
  ldlt_solve(solver, b, scratch, work, LdltValues::dropped);
  scratch -= exact;
  solver.set_dropped_use(norm(scratch) <= kDroppedAnswer * norm(exact)
                             ? SparseLdlt::DroppedUse::usable
                             : SparseLdlt::DroppedUse::unusable);
}

/// The Euclidean norm: refine()'s measure of x and its updates unless the caller gives another
/// (Enhanced's contact system weighs its impulses into velocities: unknowns of other units).
struct EuclideanNorm {
  template <class V>
  double operator()(const V& v) const {
    return v.norm();
  }
};

/// Refinement passes x += solve(b - apply(x)) from the x in hand: `apply(x, y)` sets y to this
/// step's matrix times x and `solve(r, dx)` applies the factorisation in hand (an earlier
/// step's) to r; `residual` and `update` are scratch of b's shape. Each pass
/// shrinks the error by about the relative change of the matrix since the factorised step (the
/// rate q, estimated as the largest ratio of successive updates seen); in a flow whose masses
/// change fast that is slow, and a factorisation costs about as much as 10-20 passes, so
/// refinement stops as soon as the rate says it would need more than kMaxPasses in all (with a
/// fixed 20 passes, the debris scene spent 70% of its run refining and then factorising anyway).
/// True if converged: the error left after a pass, at most q / (1 - q) times its update for a
/// contraction by q, is below `tolerance` of x (x and its updates measured by `norm`).
/// Bounding the error left rather than the update just made saves the pass that only confirms
/// it. The dual-grid walls pass the scene's scheme.coupling_tolerance (default 1e-6); the
/// default here, kRefineTolerance = 1e-10, was theirs until 2026-12-06: the multipliers are
/// impulses, applied equal and opposite to the two grids whatever their error (momentum stays
/// exact), so an error of 1e-10 of them leaves a velocity jump across Phi of that order of the
/// interface's velocities, far below any discretisation error; solving to round-off (1e-13) took
/// one more pass per solve on the floor scene (mortar coupling 7.7-8.6 -> 6.6-6.9 ms at 1e-10;
/// docs/performance.md). The caller factorises when this returns false.
/// A positive `scale` adds a test on the residual itself, before each pass: converged as soon as
/// |b - m x| <= tolerance * scale. The Phi coupling passes the size of the two interface terms
/// b is the difference of (R^A^T v^A and R^alpha^T v^alpha): the constraint then holds to 1e-10
/// of the velocities it joins. Where the two grids nearly agree already (material moving as a
/// whole, or in a linear field both grids carry exactly: the falling block of the floor
/// benchmark had a gap of 1e-15 of the interface terms) the test on x alone chased the
/// multipliers' round-off, three passes per solve; this one accepts the first solve.
template <class Rhs, class Apply, class Solve, class Norm = EuclideanNorm>
bool refine(const Rhs& b, Rhs& x, Apply&& apply, Solve&& solve, std::size_t& passes, Rhs& residual,
            Rhs& update, double scale = 0.0, double tolerance = kRefineTolerance,
            const Norm& norm = {}) {
  constexpr int kMaxPasses = 6;
  double previous = norm(x);
  double q = 0.0;  // the contraction rate: the largest ratio of successive updates seen
  for (int pass = 1;; ++pass) {
    apply(x, residual);
    residual = b - residual;
    if (residual.norm() <= tolerance * scale) return true;
    solve(residual, update);
    x += update;
    ++passes;
    const double step = norm(update), size = norm(x);
    if (step <= tolerance * size) return true;
    const double rate = step / previous;
    previous = step;
    if (!(rate < 0.5)) return false;  // stalled (or not a number)
    q = std::max(q, rate);
    // The first ratio compares the update with x itself, not with an update, and can fall short
    // of the rate: the error bound waits for the second.
    if (pass >= 2 && q / (1.0 - q) * step <= tolerance * size) return true;
    if (pass >= kMaxPasses) return false;
    if (pass + std::log(tolerance * size / step) / std::log(q) > kMaxPasses) return false;
  }
}

/// refine() for a symmetric positive definite m whose factorisation in hand is of an earlier
/// SPD matrix: conjugate gradients preconditioned by that factorisation, each column of b its
/// own system (its own step lengths), the columns side by side so that a pass reads the factor
/// once for all of them. A pass costs what refine()'s does (one product with m, one solve with
/// the factor), but where refinement contracts the error by q = |F^-1 (m - F)| a pass, CG
/// contracts it by about (sqrt(k) - 1) / (sqrt(k) + 1) for k = (1 + q) / (1 - q), q / 2 for a
/// small q and still 0.27 at q = 0.5, where refinement gives up; and a change confined to a few
/// rows (light nodes at a flow's front, whose 1/m weights move fast) is a low-rank change of
/// F^-1 m, which CG removes in as many passes as its rank, whatever its size. Same arguments
/// and tests as refine(), with the relative `tolerance` the caller asks for (the Phi coupling:
/// the scene's scheme.coupling_tolerance): converged when the residual is below tolerance *
/// scale, or when the preconditioned residual z = F^-1 r (the correction refinement would add,
/// the error to within a factor 1 +- q) is below `tolerance` of x, and then z is added (the
/// error left is about q |z|, as after refine()'s last pass). Unconverged after kMaxPasses, when z
/// stops shrinking, or on a breakdown (p^T m p <= 0: m or F not positive definite). Unlike
/// refine(), no forecast of the passes still needed: CG's pass-to-pass ratios are irregular (0.1
/// and then 0.01), and the forecast from them gave up on solves that converged in 4 or 5 passes
/// (the debris scene's first 3 s: 4,483 -> 4,352 factorisations without it; the floor under MLS-MPM
/// 0.104 -> 0.059 a step). `direction` and `product` are scratch of b's shape too.
template <class Rhs, class Apply, class Solve>
bool conjugate_refine(const Rhs& b, Rhs& x, Apply&& apply, Solve&& solve, std::size_t& passes,
                      Rhs& residual, Rhs& update, Rhs& direction, Rhs& product, double scale,
                      double tolerance) {
  constexpr int kMaxPasses = 6;
  constexpr int C = Rhs::ColsAtCompileTime;
  static_assert(C > 0, "conjugate_refine: the columns are fixed at compile time");
  Eigen::Array<double, 1, C> rz, rz_before;  // r_c^T z_c per column
  apply(x, residual);
  residual = b - residual;
  if (residual.norm() <= tolerance * scale) return true;
  double previous = x.norm();
  for (int pass = 1;; ++pass) {
    solve(residual, update);  // z = F^-1 r
    ++passes;
    const double step = update.norm(), size = x.norm();
    if (!std::isfinite(step)) return false;
    if (step <= tolerance * size) {
      x += update;
      return true;
    }
    const double rate = step / previous;  // the first compares z with x itself
    previous = step;
    if (!(rate < 1.0) || pass >= kMaxPasses) return false;  // not shrinking, or out of passes
    // Column sums and updates row by row (the blocks are row-major).
    const Eigen::Index n = b.rows();
    rz.setZero();
    for (Eigen::Index i = 0; i < n; ++i) rz += residual.row(i).array() * update.row(i).array();
    if (pass == 1) {
      direction = update;
    } else {
      Eigen::Array<double, 1, C> beta;
      for (int c = 0; c < C; ++c) beta[c] = rz_before[c] > 0.0 ? rz[c] / rz_before[c] : 0.0;
      for (Eigen::Index i = 0; i < n; ++i) {
        direction.row(i) = update.row(i).array() + beta * direction.row(i).array();
      }
    }
    rz_before = rz;
    apply(direction, product);
    Eigen::Array<double, 1, C> curvature = Eigen::Array<double, 1, C>::Zero();
    for (Eigen::Index i = 0; i < n; ++i) {
      curvature += direction.row(i).array() * product.row(i).array();
    }
    Eigen::Array<double, 1, C> alpha;
    for (int c = 0; c < C; ++c) {
      if (rz[c] == 0.0) {  // this column solved already
        alpha[c] = 0.0;
        continue;
      }
      if (!(curvature[c] > 0.0)) return false;
      alpha[c] = rz[c] / curvature[c];
    }
    for (Eigen::Index i = 0; i < n; ++i) {
      x.row(i).array() += alpha * direction.row(i).array();
      residual.row(i).array() -= alpha * product.row(i).array();
    }
    if (residual.norm() <= tolerance * scale) return true;
  }
}

/// Solves m x = b with `solver`, which holds a factorisation of m itself or, when `refine`, of
/// an earlier matrix of the same size (the previous step's: the masses change a little from
/// step to step), refined then by refine(), with `apply(y, out)` setting out = m y;
/// unconverged (the matrices are too far apart), m is factorised (`form()` returns it: a
/// caller that applies m without forming it forms it only then), its pattern analysed first
/// unless it is `pattern` (the hash of the analysed one's), and `refine` cleared. Returns
/// false if m cannot be factorised. `base` keeps the matrix the solver's factorisation is of
/// (a checkpoint saves it, so a resumed run refines against the same one). `passes` and
/// `factorizations` count the work done (reported by the benchmarks). For a solver that keeps
/// L's dropped copy, the first exact solve with each factorisation checks the copy
/// (check_dropped(), in `norm`), and refinement reads it where it passed: on Enhanced's floor
/// benchmark the same passes and factorisations as with all of L (docs/performance.md,
/// 2026-12-07, night). Refinement starts from the factor's answer, or first from `start` where
/// the caller has a guess (it may be x itself); where it does not converge from the guess, it
/// tries again from the factor's answer before m is factorised. Allocates only to factorise
/// (`w` is the caller's scratch).
template <class Rhs, class Apply, class Form, class Norm = EuclideanNorm>
bool refined_solve(SparseLdlt& solver, Apply&& apply, Form&& form,
                   Eigen::SparseMatrix<double>& base, std::size_t& pattern, bool& refine,
                   const Rhs& b, Rhs& x, std::size_t& passes, std::size_t& factorizations,
                   SolveWork<Rhs>& w, double tolerance = kRefineTolerance, const Norm& norm = {},
                   const Rhs* start = nullptr) {
  if (!refine) {
    ldlt_solve(solver, b, x, w.work);
    check_dropped(solver, b, x, w.update, w.work, norm);
    return true;
  }
  const LdltValues aged = solver.aged_values(LdltValues::full);
  const auto factor = [&](const Rhs& r, Rhs& out) { ldlt_solve(solver, r, out, w.work, aged); };
  if (start != nullptr) {
    if (start != &x) x = *start;
    if (mpm::refine(b, x, apply, factor, passes, w.residual, w.update, 0.0, tolerance, norm)) {
      return true;
    }
  }
  ldlt_solve(solver, b, x, w.work, aged);
  if (mpm::refine(b, x, apply, factor, passes, w.residual, w.update, 0.0, tolerance, norm)) {
    return true;
  }
  // (The unknowns are the factorisation's: its fill-reducing ordering serves while it fits.)
  const Eigen::SparseMatrix<double>& m = form();
  if (const std::size_t hash = pattern_hash(m); hash != pattern) {
    solver.analyzePattern(m, SparseLdlt::Order::kept);
    pattern = hash;
  }
  solver.factorize(m);
  base = m;
  ++factorizations;
  refine = false;
  if (solver.info() != Eigen::Success) return false;
  ldlt_solve(solver, b, x, w.work);
  check_dropped(solver, b, x, w.update, w.work, norm);
  return true;
}

/// refined_solve() of a matrix in hand.
template <class Rhs>
bool refined_solve(SparseLdlt& solver, const Eigen::SparseMatrix<double>& m,
                   Eigen::SparseMatrix<double>& base, std::size_t& pattern, bool& refine,
                   const Rhs& b, Rhs& x, std::size_t& passes, std::size_t& factorizations,
                   SolveWork<Rhs>& w, double tolerance = kRefineTolerance) {
  return refined_solve(
      solver, [&](const Rhs& y, Rhs& out) { out.noalias() = m * y; },
      [&]() -> const Eigen::SparseMatrix<double>& { return m; }, base, pattern, refine, b, x,
      passes, factorizations, w, tolerance);
}

/// Factorises m into `solver` unless `solver` holds a factorisation of an earlier matrix with the
/// same pattern (then refined_solve() refines against it): sets `refine` accordingly. Returns
/// false if m cannot be factorised. `base` as in refined_solve(); `order` as in
/// SparseLdlt::analyzePattern() (Order::kept: m's unknowns are the factorisation's).
inline bool factorise_or_reuse(SparseLdlt& solver, const Eigen::SparseMatrix<double>& m,
                               Eigen::SparseMatrix<double>& base, std::size_t& pattern,
                               bool& factored, bool reusable, bool& refine,
                               std::size_t& factorizations,
                               SparseLdlt::Order order = SparseLdlt::Order::fresh) {
  const std::size_t hash = pattern_hash(m);
  refine = factored && reusable && hash == pattern;
  if (refine) return true;
  if (hash != pattern) {
    solver.analyzePattern(m, order);
    pattern = hash;
  }
  solver.factorize(m);
  copy_into(m, base);
  ++factorizations;
  factored = solver.info() == Eigen::Success;
  return factored;
}

}  // namespace mpm
