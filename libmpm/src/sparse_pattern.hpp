#pragma once
// The sparsity signature the dual-grid solvers use to decide when a fill-reducing ordering (a
// symbolic factorisation) must be recomputed.

#include <cstddef>

#include <Eigen/SparseCore>

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

}  // namespace mpm
