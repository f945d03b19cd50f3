#pragma once
// The standard Cartesian grid (the A-grid) as flat arrays, and the per-particle stencil of
// tensor-product weights over it.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <vector>

#include "mpm/shape.hpp"
#include "mpm/types.hpp"

namespace mpm {

/// Ghost node layers the solver adds beyond each face of the scene's grid box, so the widest
/// kernel (B-spline, GIMP: 3 nodes) never leaves the grid and walls have nodes to mirror into.
inline constexpr int kGhostLayers = 2;

/// A node's velocities at the start of the step and after the forces: v = p / m and
/// v_new = v + dt f / m above the mass threshold, zero below it (both grids' update).
template <int D>
void node_velocities(double m, const Vec<D>& momentum, const Vec<D>& force, double dt,
                     double threshold, Vec<D>& velocity, Vec<D>& velocity_new) {
  if (m > threshold) {
    velocity = momentum / m;
    velocity_new = velocity + dt * force / m;
  } else {
    velocity.setZero();
    velocity_new.setZero();
  }
}

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
    for (int d = 0; d < D; ++d) {
      blocks[d] = (nodes[d] + kBlock - 1) / kBlock;
      halves[d] = (nodes[d] + 1) / 2;
    }
    block_active.assign(static_cast<std::size_t>(blocks.prod()), 0);
    half_marked.assign(static_cast<std::size_t>(halves.prod()), 0);
    active_blocks.clear();
    previous_blocks.clear();
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

  // Activity by blocks of kBlock^D nodes. Each step marks the blocks within reach of a particle
  // (the nodes within two of its cell: every kernel's stencil); clearing, the grid update and
  // the MUSL remap then run over those blocks only, and every node outside them holds zeros.
  // A debris flow covers a small part of its hillside's box: the rest costs nothing per step.
  // The particles mark half-blocks (2^D nodes: one store each); a block is active when a marked
  // half-block lies within reach: node i's particles reach nodes i-2..i+2, so the block of nodes
  // 4b..4b+3 is reached from the half-blocks 2b-1..2b+2.
  static constexpr int kBlock = 4;
  Index<D> blocks = Index<D>::Ones();      ///< blocks per axis
  Index<D> halves = Index<D>::Ones();      ///< half-blocks per axis
  std::vector<std::uint8_t> block_active;  ///< this step's flags
  std::vector<std::uint8_t> half_marked;   ///< this step's particles' half-blocks
  std::vector<int> active_blocks;          ///< this step's blocks, in index order
  std::vector<int> previous_blocks;        ///< the step before's (clear_previous() zeroes them)

  /// Linear index of the block with per-axis indices b (last axis fastest, as nodes).
  [[nodiscard]] int block_index(const Index<D>& b) const {
    int linear_block = 0;
    for (int d = 0; d < D; ++d) linear_block = linear_block * blocks[d] + b[d];
    return linear_block;
  }
  /// The block holding a node.
  [[nodiscard]] int block_of(int node) const {
    return block_index((multi(node).array() / kBlock).matrix());
  }
  /// Starts a step's marking: the last step's blocks become the previous ones.
  void begin_marking() {
    for (const int b : active_blocks) block_active[static_cast<std::size_t>(b)] = 0;
    std::swap(previous_blocks, active_blocks);
    active_blocks.clear();
    std::fill(half_marked.begin(), half_marked.end(), std::uint8_t{0});
  }
  /// Marks the half-block of the cell of x. Safe to call from several threads at once.
  void mark(const Vec<D>& x) {
    int linear_half = 0;
    for (int d = 0; d < D; ++d) {
      const int i = static_cast<int>(std::floor((x[d] - origin[d]) * inv_h));
      linear_half = linear_half * halves[d] + std::clamp(i, 0, nodes[d] - 1) / 2;
    }
    std::atomic_ref<std::uint8_t>(half_marked[static_cast<std::size_t>(linear_half)])
        .store(1, std::memory_order_relaxed);
  }
  /// Ends the marking: the blocks the marked half-blocks reach, listed in index order.
  void finish_marking() {
    Index<D> c = Index<D>::Zero();
    for (std::size_t k = 0; k < half_marked.size(); ++k) {
      if (half_marked[k] != 0) {
        Index<D> lo, hi;
        for (int d = 0; d < D; ++d) {
          lo[d] = c[d] >= 1 ? (c[d] - 1) / 2 : 0;
          hi[d] = std::min((c[d] + 1) / 2, blocks[d] - 1);
        }
        Index<D> b = lo;
        while (true) {
          block_active[static_cast<std::size_t>(block_index(b))] = 1;
          int d = D - 1;
          while (d >= 0 && b[d] == hi[d]) {
            b[d] = lo[d];
            --d;
          }
          if (d < 0) break;
          ++b[d];
        }
      }
      for (int d = D - 1; d >= 0 && ++c[d] == halves[d]; --d) c[d] = 0;
    }
    for (std::size_t b = 0; b < block_active.size(); ++b) {
      if (block_active[b] != 0) active_blocks.push_back(static_cast<int>(b));
    }
  }
  /// Calls f(first, count) for each run of nodes of `block` contiguous in memory (along the
  /// last axis).
  template <class F>
  void for_each_run(int block, F&& f) const {
    Index<D> b;
    for (int d = D - 1; d >= 0; --d) {
      b[d] = block % blocks[d];
      block /= blocks[d];
    }
    Index<D> lo, hi;
    for (int d = 0; d < D; ++d) {
      lo[d] = b[d] * kBlock;
      hi[d] = std::min(lo[d] + kBlock, nodes[d]);
    }
    const int count = hi[D - 1] - lo[D - 1];
    Index<D> i = lo;
    while (true) {
      f(linear(i), count);
      int d = D - 2;
      while (d >= 0 && i[d] + 1 == hi[d]) {
        i[d] = lo[d];
        --d;
      }
      if (d < 0) break;
      ++i[d];
    }
  }
  /// Calls f(node) for every node of `block`.
  template <class F>
  void for_each_node(int block, F&& f) const {
    for_each_run(block, [&](int first, int count) {
      for (int n = first; n < first + count; ++n) f(static_cast<std::size_t>(n));
    });
  }
  /// Zeroes what the last step left in its block previous_blocks[k] for the particles-to-grid
  /// transfer: mass, momentum and force, and the velocities if this step does not have the
  /// block (so that every node outside the active blocks is zero). After the marking; the
  /// blocks are disjoint, so they may be cleared in parallel.
  void clear_previous(std::size_t k) {
    const int b = previous_blocks[k];
    const bool stays = block_active[static_cast<std::size_t>(b)] != 0;
    for_each_run(b, [&](int first, int count) {
      std::fill_n(mass.begin() + first, count, 0.0);
      std::fill_n(momentum.begin() + first, count, Vec<D>::Zero());
      std::fill_n(force.begin() + first, count, Vec<D>::Zero());
      if (stays) return;
      std::fill_n(velocity.begin() + first, count, Vec<D>::Zero());
      std::fill_n(velocity_new.begin() + first, count, Vec<D>::Zero());
    });
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
