// The split of an LDL^T factor's elimination tree that lets ldlt_solve() (sparse_pattern.hpp)
// run its triangular solves on two threads (SubtreeSplit, mpm/dual_grid.hpp), and the bordered
// inverse of a factorisation whose unknowns changed a little (BorderedFactor).

#include <algorithm>
#include <array>
#include <chrono>
#include <cstdint>
#include <queue>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "mpm/dual_grid.hpp"
#include "sparse_pattern.hpp"

namespace mpm {

namespace {

// Below this many entries in L a solve takes a few tens of microseconds, about what handing
// half of it to the other thread costs.
constexpr Eigen::Index kMinEntries = 20000;
// The split is kept only if the solve's predicted time (the top's work plus the larger side's)
// is at most this fraction of the serial solve's.
constexpr double kWorthwhile = 0.75;
// Sides within 2% of the ideal halves end the search.
constexpr double kBalanced = 1.02;

}  // namespace

std::size_t SparseLdlt::symbolic(const Eigen::SparseMatrix<double>& a) {
  CholMatrixType permuted(a.rows(), a.cols());
  permuted.selfadjointView<Eigen::Upper>() = a.selfadjointView<Eigen::Lower>().twistedBy(m_P);
  analyzePattern_preordered(permuted, true);
  return static_cast<std::size_t>(m_nonZerosPerCol.sum());
}

void SparseLdlt::analyzePattern(const Eigen::SparseMatrix<double>& a, Order order) {
  const auto start = std::chrono::steady_clock::now();
  split_stale_ = true;
  // (A kept ordering whose fill grew too far leaves the symbolic step to be taken again below:
  // the matrices are small beside the numeric step's work, about a tenth of the ordering's.)
  if (order == Order::kept && ordered_fill_ > 0 && m_P.size() == a.rows() &&
      static_cast<double>(symbolic(a)) <= kReorderFill * static_cast<double>(ordered_fill_)) {
    ++kept_orderings_;
    analysis_seconds_ += since(start);
    return;
  }
  Base::analyzePattern(a);
  ordered_fill_ = static_cast<std::size_t>(m_nonZerosPerCol.sum());
  analysis_seconds_ += since(start);
}

void SparseLdlt::analyzePattern(const Eigen::SparseMatrix<double>& a,
                                const std::vector<int>& inverse, std::size_t ordered_fill) {
  const auto start = std::chrono::steady_clock::now();
  const auto n = static_cast<std::size_t>(a.rows());
  std::vector<char> seen(n, 0);
  for (const int k : inverse) {
    if (k < 0 || static_cast<std::size_t>(k) >= n || seen[static_cast<std::size_t>(k)] != 0) {
      throw std::invalid_argument("SparseLdlt: the ordering is not a permutation of the unknowns");
    }
    seen[static_cast<std::size_t>(k)] = 1;
  }
  if (inverse.size() != n) {
    throw std::invalid_argument("SparseLdlt: the ordering is not a permutation of the unknowns");
  }
  m_Pinv.resize(a.rows());
  std::copy(inverse.begin(), inverse.end(), m_Pinv.indices().data());
  m_P = m_Pinv.inverse();
  split_stale_ = true;
  symbolic(a);
  ordered_fill_ = ordered_fill;
  analysis_seconds_ += since(start);
}

SubtreeSplit split_subtrees(const Eigen::SparseMatrix<double>& l) {
  SubtreeSplit split;
  const auto n = static_cast<int>(l.cols());
  if (l.nonZeros() < kMinEntries) return split;
  const int* outer = l.outerIndexPtr();
  const int* inner = l.innerIndexPtr();
  // The elimination tree: column j's parent is the first row below the diagonal in column j
  // of L. Parents follow their children, so one pass in increasing order sums each subtree's
  // work (the entries a solve reads, and one for the column itself).
  std::vector<int> parent(static_cast<std::size_t>(n), -1);
  std::vector<double> own(static_cast<std::size_t>(n)), work(static_cast<std::size_t>(n));
  for (int j = 0; j < n; ++j) {
    int below = 0;
    for (int p = outer[j]; p < outer[j + 1]; ++p) {
      if (inner[p] <= j) continue;
      if (below++ == 0) parent[j] = inner[p];
    }
    own[j] = 1.0 + below;
  }
  std::vector<int> child_first(static_cast<std::size_t>(n) + 1, 0), children;
  double total = 0.0;
  for (int j = 0; j < n; ++j) {
    work[j] += own[j];
    if (parent[j] >= 0) {
      work[parent[j]] += work[j];
      ++child_first[parent[j] + 1];
    } else {
      total += work[j];
    }
  }
  for (int j = 0; j < n; ++j) child_first[j + 1] += child_first[j];
  children.resize(static_cast<std::size_t>(child_first[n]));
  {
    std::vector<int> fill(child_first.begin(), child_first.end() - 1);
    for (int j = 0; j < n; ++j) {
      if (parent[j] >= 0) children[fill[parent[j]]++] = j;
    }
  }

  // Move subtrees' roots into the top, heaviest first, starting from the tree's roots; after
  // each move pack the remaining subtrees (the frontier) onto two sides, heaviest first onto
  // the lighter side, and remember the number of moves with the least predicted time.
  const auto heavier = [&](int a, int b) {
    return work[a] < work[b] || (work[a] == work[b] && a > b);
  };
  auto expand = [&](int moves, std::vector<int>& top, auto&& visit) {
    std::priority_queue<int, std::vector<int>, decltype(heavier)> frontier(heavier);
    for (int j = 0; j < n; ++j) {
      if (parent[j] < 0) frontier.push(j);
    }
    double top_work = 0.0;
    for (int move = 0;; ++move) {
      if (!visit(move, top_work, frontier)) return;
      if (move == moves || frontier.empty()) return;
      const int t = frontier.top();
      frontier.pop();
      top.push_back(t);
      top_work += own[t];
      for (int c = child_first[t]; c < child_first[t + 1]; ++c) frontier.push(children[c]);
    }
  };
  // Packs a copy of the frontier (heaviest first); returns the larger side's work.
  std::vector<std::uint8_t> side_of(static_cast<std::size_t>(n), 2);
  auto pack = [&](auto frontier, bool assign) {
    double sides[2] = {0.0, 0.0};
    while (!frontier.empty()) {
      const int t = frontier.top();
      frontier.pop();
      const int s = sides[1] < sides[0] ? 1 : 0;
      sides[s] += work[t];
      if (assign) side_of[t] = static_cast<std::uint8_t>(s);
    }
    return std::max(sides[0], sides[1]);
  };
  double best = total;
  int best_moves = -1;
  std::vector<int> top;
  expand(n, top, [&](int move, double top_work, const auto& frontier) {
    // No later move can beat the top's work plus half the rest.
    const double bound = top_work + 0.5 * (total - top_work);
    if (bound >= best) return false;
    const double predicted = top_work + pack(frontier, false);
    if (predicted < best) {
      best = predicted;
      best_moves = move;
    }
    return predicted > kBalanced * bound;  // balanced: more moves only add to the top
  });
  if (best_moves < 0 || best > kWorthwhile * total) return split;

  top.clear();
  expand(best_moves, top, [&](int move, double, const auto& frontier) {
    if (move == best_moves) pack(frontier, true);
    return true;
  });
  split.root.assign(static_cast<std::size_t>(n), -1);
  split.top_slot.assign(static_cast<std::size_t>(n), -1);
  for (const int t : top) side_of[t] = 3;
  // Parents first (decreasing order): a column below a frontier root takes its root's side.
  for (int j = n - 1; j >= 0; --j) {
    if (side_of[j] == 3) continue;
    if (side_of[j] < 2) {
      split.root[j] = j;
    } else {
      side_of[j] = side_of[parent[j]];
      split.root[j] = split.root[parent[j]];
    }
  }
  for (int j = 0; j < n; ++j) {
    if (side_of[j] == 3) {
      split.top_slot[j] = static_cast<int>(split.top.size());
      split.top.push_back(j);
    } else {
      split.side[side_of[j]].push_back(j);
    }
  }
  split.parallel = true;
  return split;
}

ColumnRuns column_runs(const Eigen::SparseMatrix<double>& l, const SubtreeSplit& split) {
  ColumnRuns runs;
  const auto n = static_cast<int>(l.cols());
  const int* outer = l.outerIndexPtr();
  const int* inner = l.innerIndexPtr();
  // continues[j]: column j + 1 continues column j's run. Column j's rows are j + 1 and then
  // exactly column j + 1's (rows increase in a column, so all lie below both diagonals).
  std::vector<std::uint8_t> continues(static_cast<std::size_t>(n), 0);
  for (int j = 0; j + 1 < n; ++j) {
    const int a = outer[j], b = outer[j + 1], e = outer[j + 2];
    continues[j] = static_cast<std::uint8_t>(b - a == e - b + 1 && inner[a] == j + 1 &&
                                             std::equal(inner + a + 1, inner + b, inner + b));
  }
  auto group = [&](const std::vector<int>& columns, std::vector<std::array<int, 2>>& out) {
    for (std::size_t k = 0; k < columns.size();) {
      std::size_t e = k + 1;
      while (e < columns.size() && columns[e] == columns[e - 1] + 1 && continues[columns[e - 1]])
        ++e;
      const int first = columns[k], end = columns[e - 1] + 1;
      out.push_back({first, end});
      if (end - first > 1) runs.most_below = std::max(runs.most_below, outer[end] - outer[end - 1]);
      k = e;
    }
  };
  std::vector<int> every(static_cast<std::size_t>(n));
  for (int j = 0; j < n; ++j) every[static_cast<std::size_t>(j)] = j;
  group(every, runs.all);
  if (split.parallel) {
    group(split.side[0], runs.side[0]);
    group(split.side[1], runs.side[1]);
    group(split.top, runs.top);
  }
  return runs;
}

bool BorderedFactor::prepare(const SparseLdlt& solver, LdltValues values,
                             const std::vector<int>& old_of,
                             const std::function<void(int, Eigen::VectorXd&)>& column) {
  solver_ = &solver;
  values_ = values;
  old_of_ = old_of;
  const Eigen::Index old_size = solver.rows();
  const auto size = static_cast<Eigen::Index>(old_of.size());
  std::vector<char> kept(static_cast<std::size_t>(old_size), 0);
  added_.clear();
  for (Eigen::Index i = 0; i < size; ++i) {
    const int o = old_of[static_cast<std::size_t>(i)];
    if (o < 0) {
      added_.push_back(static_cast<int>(i));
    } else if (o >= old_size || kept[static_cast<std::size_t>(o)] != 0) {
      throw std::logic_error("BorderedFactor: unknown " + std::to_string(o) +
                             " is not one of the factorisation's, or mapped twice");
    } else {
      kept[static_cast<std::size_t>(o)] = 1;
    }
  }
  removed_.clear();
  for (Eigen::Index o = 0; o < old_size; ++o) {
    if (kept[static_cast<std::size_t>(o)] == 0) removed_.push_back(static_cast<int>(o));
  }
  const auto r = static_cast<Eigen::Index>(removed_.size());
  const auto q = static_cast<Eigen::Index>(added_.size());
  // 1 / rcond below this: A~ (or F_KK) singular to working precision.
  constexpr double kSingular = 1e12;
  g_.resize(old_size, r);
  s_.resize(old_size);
  for (Eigen::Index c = 0; c < r; ++c) {
    s_.setZero();
    s_[removed_[static_cast<std::size_t>(c)]] = 1.0;
    ldlt_solve(*solver_, s_, t_, work_, values_);
    g_.col(c) = t_;
  }
  if (r > 0) {
    Eigen::MatrixXd h(r, r);
    for (Eigen::Index c = 0; c < r; ++c) h.row(c) = g_.row(removed_[static_cast<std::size_t>(c)]);
    h_.compute(h);
    if (!(h_.rcond() * kSingular > 1.0)) return false;
  }
  tau_.resize(r);
  solved_tau_.resize(r);
  xq_.resize(q);
  solved_xq_.resize(q);
  b_.resize(old_size, q);
  Eigen::MatrixXd c_block(q, q);
  y_.resize(old_size, q);
  Eigen::VectorXd col(size);
  for (Eigen::Index a = 0; a < q; ++a) {
    column(added_[static_cast<std::size_t>(a)], col);
    b_.col(a).setZero();
    for (Eigen::Index i = 0; i < size; ++i) {
      const int o = old_of[static_cast<std::size_t>(i)];
      if (o >= 0) b_(o, a) = col[i];
    }
    for (Eigen::Index a2 = 0; a2 < q; ++a2)
      c_block(a2, a) = col[added_[static_cast<std::size_t>(a2)]];
    s_ = b_.col(a);
    reduced_solve();
    y_.col(a) = t_;
  }
  if (q > 0) {
    z_.compute(c_block - b_.transpose() * y_);
    if (!(z_.rcond() * kSingular > 1.0)) return false;
  }
  return true;
}

void BorderedFactor::solve(const Eigen::VectorXd& y, Eigen::VectorXd& x) {
  const auto size = static_cast<Eigen::Index>(old_of_.size());
  s_.setZero();
  for (Eigen::Index i = 0; i < size; ++i) {
    const int o = old_of_[static_cast<std::size_t>(i)];
    if (o >= 0) s_[o] = y[i];
  }
  reduced_solve();
  x.resize(size);
  if (!added_.empty()) {
    for (std::size_t a = 0; a < added_.size(); ++a) {
      xq_[static_cast<Eigen::Index>(a)] = y[added_[a]];
    }
    xq_.noalias() -= b_.transpose() * t_;
    solved_xq_ = z_.solve(xq_);
    t_.noalias() -= y_ * solved_xq_;
    for (std::size_t a = 0; a < added_.size(); ++a) {
      x[added_[a]] = solved_xq_[static_cast<Eigen::Index>(a)];
    }
  }
  for (Eigen::Index i = 0; i < size; ++i) {
    const int o = old_of_[static_cast<std::size_t>(i)];
    if (o >= 0) x[i] = t_[o];
  }
}

// t_ = F_KK^-1 s_ (s_ zero on the removed unknowns; t_ comes out zero on them, to round-off).
void BorderedFactor::reduced_solve() {
  ldlt_solve(*solver_, s_, t_, work_, values_);
  if (removed_.empty()) return;
  for (std::size_t c = 0; c < removed_.size(); ++c) {
    tau_[static_cast<Eigen::Index>(c)] = t_[removed_[c]];
  }
  solved_tau_ = h_.solve(tau_);
  t_.noalias() -= g_ * solved_tau_;
}

}  // namespace mpm
