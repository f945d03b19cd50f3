#pragma once
// The pattern of a Phi coupling's Schur complement on a flat wall, with values that make it well
// conditioned: shared by the sparse-solve tests and bench/bench_solve.cpp.

#include <cmath>
#include <cstddef>
#include <vector>

#include <Eigen/SparseCore>

namespace mpm::test {

/// The matrix of an m x m grid of unknowns, each coupled to those within `reach` spacings along
/// both axes (each multiplier of a flat Phi couples to its neighbours within a few spacings),
/// strictly diagonally dominant (off-diagonal row sums at most half the diagonal: condition
/// number below 3).
inline Eigen::SparseMatrix<double> grid_spd(int m, int reach = 2) {
  std::vector<Eigen::Triplet<double>> entries;
  const int n = m * m;
  std::vector<double> row_sum(static_cast<std::size_t>(n), 0.0);
  for (int i = 0; i < m; ++i) {
    for (int j = 0; j < m; ++j) {
      for (int di = -reach; di <= reach; ++di) {
        for (int dj = -reach; dj <= reach; ++dj) {
          const int k = i + di, l = j + dj;
          if ((di == 0 && dj == 0) || k < 0 || l < 0 || k >= m || l >= m) continue;
          const double v = -1.0 / (1.0 + di * di + dj * dj);
          entries.emplace_back(i * m + j, k * m + l, v);
          row_sum[static_cast<std::size_t>(i * m + j)] += std::abs(v);
        }
      }
    }
  }
  for (int r = 0; r < n; ++r) entries.emplace_back(r, r, 1.0 + 2.0 * row_sum[r]);
  Eigen::SparseMatrix<double> a(n, n);
  a.setFromTriplets(entries.begin(), entries.end());
  return a;
}

}  // namespace mpm::test
