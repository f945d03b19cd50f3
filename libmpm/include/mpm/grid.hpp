#pragma once
// The standard Cartesian grid (the A-grid) as flat arrays, and the per-particle stencil of
// tensor-product weights over it.

#include <vector>

#include "mpm/shape.hpp"
#include "mpm/types.hpp"

namespace mpm {

/// Ghost node layers the solver adds beyond each face of the scene's grid box, so the widest
/// kernel (B-spline, GIMP: 3 nodes) never leaves the grid and walls have nodes to mirror into.
inline constexpr int kGhostLayers = 2;

template <int D>
struct Grid {
  Vec<D> origin = Vec<D>::Zero();  ///< position of node (0,...,0)
  double h = 1.0;                  ///< node spacing
  double inv_h = 1.0;
  Index<D> nodes = Index<D>::Ones();   ///< nodes per axis
  Index<D> stride = Index<D>::Ones();  ///< linear index = sum_d i_d * stride_d; last axis fastest

  std::vector<double> mass;
  std::vector<Vec<D>> momentum;
  std::vector<Vec<D>> force;
  std::vector<Vec<D>> velocity;      ///< v_I^n = p_I / m_I (before the force update)
  std::vector<Vec<D>> velocity_new;  ///< v_I^{n+1} after forces and wall conditions

  void resize(const Vec<D>& grid_origin, double spacing, const Index<D>& node_count) {
    origin = grid_origin;
    h = spacing;
    inv_h = 1.0 / spacing;
    nodes = node_count;
    stride[D - 1] = 1;
    for (int d = D - 2; d >= 0; --d) stride[d] = stride[d + 1] * nodes[d + 1];
    const auto n = size();
    mass.assign(n, 0.0);
    momentum.assign(n, Vec<D>::Zero());
    force.assign(n, Vec<D>::Zero());
    velocity.assign(n, Vec<D>::Zero());
    velocity_new.assign(n, Vec<D>::Zero());
  }
  [[nodiscard]] std::size_t size() const { return static_cast<std::size_t>(nodes.prod()); }
  [[nodiscard]] int linear(const Index<D>& i) const { return i.dot(stride); }
  [[nodiscard]] Index<D> multi(int linear_index) const {
    Index<D> i;
    for (int d = 0; d < D; ++d) {
      i[d] = linear_index / stride[d];
      linear_index -= i[d] * stride[d];
    }
    return i;
  }
  [[nodiscard]] Vec<D> position(const Index<D>& i) const {
    return origin + h * i.template cast<double>();
  }
  void clear() {
    std::fill(mass.begin(), mass.end(), 0.0);
    std::fill(momentum.begin(), momentum.end(), Vec<D>::Zero());
    std::fill(force.begin(), force.end(), Vec<D>::Zero());
  }
};

/// Weights of one particle over its grid stencil (S^D nodes). Built once per particle per pass.
template <int D, class Shape>
struct Stencil {
  static constexpr int S = Shape::support;
  Index<D> base;
  int base_linear = 0;
  double w[D][S];
  double dw[D][S];  ///< already divided by h
  double dx[D][S];  ///< x_I - x_p per axis

  Stencil(const Grid<D>& g, const Vec<D>& x, double half_width) {
    for (int d = 0; d < D; ++d) {
      const double xg = (x[d] - g.origin[d]) * g.inv_h;
      Shape::weights(xg, half_width, base[d], w[d], dw[d]);
      for (int k = 0; k < S; ++k) {
        dw[d][k] *= g.inv_h;
        dx[d][k] = (base[d] + k - xg) * g.h;
      }
    }
    base_linear = g.linear(base);
  }

  /// f(node, N_I(x_p), grad N_I(x_p), x_I - x_p) for every node of the stencil.
  template <class F>
  void for_each(const Grid<D>& g, F&& f) const {
    if constexpr (D == 1) {
      for (int i = 0; i < S; ++i) f(base_linear + i, w[0][i], Vec<1>(dw[0][i]), Vec<1>(dx[0][i]));
    } else if constexpr (D == 2) {
      for (int i = 0; i < S; ++i) {
        for (int j = 0; j < S; ++j) {
          const int node = base_linear + i * g.stride[0] + j;
          f(node, w[0][i] * w[1][j], Vec<2>(dw[0][i] * w[1][j], w[0][i] * dw[1][j]),
            Vec<2>(dx[0][i], dx[1][j]));
        }
      }
    } else {
      for (int i = 0; i < S; ++i) {
        for (int j = 0; j < S; ++j) {
          const double wij = w[0][i] * w[1][j];
          const double dwi_j = dw[0][i] * w[1][j];
          const double wi_dj = w[0][i] * dw[1][j];
          const int row = base_linear + i * g.stride[0] + j * g.stride[1];
          for (int k = 0; k < S; ++k) {
            f(row + k, wij * w[2][k], Vec<3>(dwi_j * w[2][k], wi_dj * w[2][k], wij * dw[2][k]),
              Vec<3>(dx[0][i], dx[1][j], dx[2][k]));
          }
        }
      }
    }
  }
};

}  // namespace mpm
