// The alpha-grid basis: linear in the natural coordinates of a cell (boundary_grid.hpp).

#include "mpmgeom/boundary_grid.hpp"

namespace mpmgeom {

AlphaBasis alpha_basis(int dimension, const Eigen::Vector3d& xi) {
  AlphaBasis b;
  if (dimension == 1) {
    const double z = xi[0];
    b.N[0] = 1.0 - z;
    b.N[1] = z;
    b.dN(0, 0) = -1.0;
    b.dN(1, 0) = 1.0;
  } else if (dimension == 2) {
    const double s = xi[0], z = xi[1];
    const double along[2] = {1.0 - s, s}, d_along[2] = {-1.0, 1.0};
    const double across[2] = {1.0 - z, z}, d_across[2] = {-1.0, 1.0};
    for (int level = 0; level < 2; ++level) {
      for (int k = 0; k < 2; ++k) {
        const int n = 2 * level + k;
        b.N[n] = along[k] * across[level];
        b.dN(n, 0) = d_along[k] * across[level];
        b.dN(n, 1) = along[k] * d_across[level];
      }
    }
  } else {
    const double r = xi[0], s = xi[1], z = xi[2];
    const double lambda[3] = {1.0 - r - s, r, s};
    const double d_r[3] = {-1.0, 1.0, 0.0}, d_s[3] = {-1.0, 0.0, 1.0};
    const double across[2] = {1.0 - z, z}, d_across[2] = {-1.0, 1.0};
    for (int level = 0; level < 2; ++level) {
      for (int k = 0; k < 3; ++k) {
        const int n = 3 * level + k;
        b.N[n] = lambda[k] * across[level];
        b.dN(n, 0) = d_r[k] * across[level];
        b.dN(n, 1) = d_s[k] * across[level];
        b.dN(n, 2) = lambda[k] * d_across[level];
      }
    }
  }
  return b;
}

CellMap cell_map(const BoundaryGrid& grid, std::size_t c) {
  CellMap map;
  const int dim = grid.dimension;
  const int m = dim - 1;  // coordinates along the wall; nodes 0..m on the wall side
  map.dimension = dim;
  const auto row = static_cast<Eigen::Index>(c);
  auto node = [&](int k, int i) { return grid.nodes(grid.cells(row, k), i); };
  for (int i = 0; i < dim; ++i) {
    const double x0 = node(0, i);
    const double d = node(m + 1, i) - x0;  // the node across from node 0
    map.v[static_cast<std::size_t>(i)] = x0;
    map.v[static_cast<std::size_t>(9 + i)] = d;
    for (int j = 0; j < m; ++j) {
      map.v[static_cast<std::size_t>(3 + 3 * j + i)] = node(j + 1, i) - x0;
      map.v[static_cast<std::size_t>(12 + 3 * j + i)] = (node(m + 2 + j, i) - node(j + 1, i)) - d;
    }
  }
  return map;
}

Eigen::Vector3d cell_point(const BoundaryGrid& grid, std::size_t c, const Eigen::Vector3d& xi) {
  const int dim = grid.dimension;
  const AlphaBasis b = alpha_basis(dim, xi);
  Eigen::Vector3d x = Eigen::Vector3d::Zero();
  for (int k = 0; k < grid.nodes_per_cell(); ++k) {
    x.head(dim) += b.N[k] * grid.nodes.row(grid.cells(static_cast<Eigen::Index>(c), k)).transpose();
  }
  return x;
}

Eigen::Matrix3d cell_jacobian(const BoundaryGrid& grid, std::size_t c, const Eigen::Vector3d& xi) {
  const int dim = grid.dimension;
  const AlphaBasis b = alpha_basis(dim, xi);
  Eigen::Matrix3d J = Eigen::Matrix3d::Zero();
  for (int k = 0; k < grid.nodes_per_cell(); ++k) {
    const auto x = grid.nodes.row(grid.cells(static_cast<Eigen::Index>(c), k));
    for (int i = 0; i < dim; ++i) {
      for (int j = 0; j < dim; ++j) J(i, j) += x(i) * b.dN(k, j);
    }
  }
  return J;
}

}  // namespace mpmgeom
