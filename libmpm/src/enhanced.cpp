// The Enhanced velocity field method (DESIGN.md section 4, docs/enhanced.md): inside a wall's
// layer the velocity is the sum of the standard field and a boundary-grid enhancement,
//
//   v(x) = sum_I N^A_I(x) v^A_I + sum_S N^alpha_S(x) v^alpha_S,
//
// with v^alpha = 0 on Phi (the interface nodes are not unknowns) and outside the layer. Every
// particle uses the standard grid; particles in the layer also use the boundary grid. The mass
// matrix has the cross terms m^{A,alpha}_IS = sum_p m_p N^A_I N^alpha_S; its diagonal blocks are
// lumped (m^A_I = sum_p m_p N^A_I, m^alpha_S = sum_p m_p N^alpha_S), which keeps it positive
// definite (each particle's block is, by Cauchy-Schwarz, since sum_S N^alpha_S <= 1) and keeps
// the uniform mode's row sums, so momentum is exact. The wall acts through multipliers on Gamma,
//
//   R^A^T v^A + R^alpha^T v^alpha = 0     (normal component only for slip and friction),
//
// with separation and Coulomb friction decided by an active set. The standard grid is diagonal,
// so it is eliminated: what is left is a symmetric quasi-definite system in the enhancement and
// the multipliers only,
//
//   [ K     -W  ] [v^alpha]   [p^alpha - C^T M_A^-1 p^A]
//   [ -W^T  -S_A] [j      ] = [R^A^T M_A^-1 p^A        ]
//
//   K = M^alpha - C^T M_A^-1 C,  W = R^alpha - C^T M_A^-1 R^A,  S_A = R^A^T M_A^-1 R^A,
//
// factorised with Eigen's sparse LDL^T (quasi-definite: stable for any ordering); then
// v^A = M_A^-1 (p^A - C v^alpha + R^A j). Standard-grid nodes the layer's particles do not reach
// keep their diagonal update.

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>
#include <type_traits>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>
#include <tbb/task_arena.h>

#include "alpha_stencil.hpp"
#include "mpm/solver.hpp"
#include "sparse_pattern.hpp"

namespace mpm {
namespace {

using Sparse = Eigen::SparseMatrix<double>;

}  // namespace

// Per step (the masses and positions are fixed for the step): the near standard-grid rows, the
// alpha columns that carry an enhancement, the cross mass matrix, the multipliers in contact and
// the products the solves need.
template <int D>
void Solver<D>::enhanced_assemble(DualWall<D>& w) {
  auto& P = particles;
  EnhancedState<D>& e = w.enh;
  for (const int n : e.alpha_cols) e.alpha_col_of[n] = -1;
  e.a_rows.clear();
  e.alpha_cols.clear();
  const int wall_index = static_cast<int>(&w - dual_.data());
  auto row_of = [&](int node) { return node_row(e.a_row_of, e.a_rows, node); };

  // Candidate alpha columns: free nodes (not on Phi) with mass; candidates are numbered first
  // and renumbered after the dependence check.
  std::vector<int>& candidates = e.candidates;
  candidates.clear();
  for (const int node : w.scatter_nodes) {  // in increasing order; the others have no mass
    const auto n = static_cast<std::size_t>(node);
    if (w.layer->node_on_interface[static_cast<Eigen::Index>(n)] != 0) continue;
    if (w.mass[n] <= coupling_threshold_) continue;
    e.alpha_col_of[n] = static_cast<int>(candidates.size());
    candidates.push_back(static_cast<int>(n));
  }

  // Cross mass m^{A,alpha}_IS = sum_p m_p N^A_I N^alpha_S over the layer's particles, on
  // standard-grid nodes above the mass threshold. Particles whose stencils on both grids are the
  // same (the same first standard node, the same boundary cell: about 8 at a time in a layer of
  // 8 particles per cell) share their (I, S) pairs: their terms are summed per group first, the
  // groups side by side. The rows are then numbered in group order, and each candidate column
  // sums its groups' terms row by row in group order, the columns side by side: the matrix the
  // groups' terms as triplets in group order gave through assign_by_columns(), bit for bit, in
  // two thirds of the time on one thread (the triplets, S^D x the cell's nodes per group, and
  // their sort into columns were the costliest part of the assembly: docs/performance.md).
  constexpr int kCell = DualWall<D>::kCellNodes;
  static_assert(kCell <= 8, "a node's cell terms are bits of a byte");
  dispatch_shape(scene_.shape, [&](auto shape) {
    using Shape = decltype(shape);
    constexpr int kS = Stencil<D, Shape>::S;
    constexpr int kStencil = D == 1 ? kS : D == 2 ? kS * kS : kS * kS * kS;  // nodes
    static_assert(kStencil <= 32, "a cell node's stencil terms are bits of a 32-bit word");
    auto& order = e.cross_order;
    // The keys side by side; another wall's particles sort last and are cut off.
    order.resize(layer_list_.size());
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, layer_list_.size(), 512),
                      [&](const auto& r) {
                        for (std::size_t i = r.begin(); i != r.end(); ++i) {
                          const auto p = static_cast<std::size_t>(layer_list_[i]);
                          if (P.layer_wall[p] != wall_index) {
                            order[i] = {std::numeric_limits<int>::max(), 0, static_cast<int>(i)};
                            continue;
                          }
                          const Stencil<D, Shape> st(grid, P.position[p], P.half_width[p]);
                          int first = 0;
                          for (int d = 0; d < D; ++d) first += st.offset[d][0];
                          const auto cell = static_cast<std::size_t>(layer_cell_[i]);
                          order[i] = {first, e.cell_rank[cell], static_cast<int>(i)};
                        }
                      });
    std::sort(order.begin(), order.end());
    while (!order.empty() && order.back().first == std::numeric_limits<int>::max()) {
      order.pop_back();
    }
    auto& group_first = e.cross_group_first;
    group_first.clear();
    for (std::size_t t = 0; t < order.size(); ++t) {
      if (t == 0 || order[t].first != order[t - 1].first || order[t].cell != order[t - 1].cell) {
        group_first.push_back(static_cast<int>(t));
      }
    }
    const std::size_t groups = group_first.size();
    group_first.push_back(static_cast<int>(order.size()));

    e.cross_row.resize(groups * kStencil);
    e.cross_sum.resize(groups * kStencil * kCell);
    e.cross_mask.resize(groups * kCell);
    // Each group's terms, in its particles' order: node q's row holds its grid node for now.
    // The group's particles share their standard stencil's nodes (which of them carry mass is
    // read once per group) and their boundary cell's nodes (which of them are candidate columns
    // with N^alpha > 0 is read once per particle, not once per stencil node).
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, groups, 16), [&](const auto& r) {
      for (std::size_t g = r.begin(); g != r.end(); ++g) {
        int* node_at = &e.cross_row[g * kStencil];
        std::uint8_t used[kStencil] = {};   // node q's cell nodes with a term (bit k)
        double sum[kStencil * kCell] = {};  // node q's terms at q * kCell + k
        bool massive[kStencil];
        for (int t = group_first[g]; t < group_first[g + 1]; ++t) {
          const auto i = static_cast<std::size_t>(order[static_cast<std::size_t>(t)].place);
          const auto p = static_cast<std::size_t>(layer_list_[i]);
          const AlphaStencil<D>& as = layer_stencil_[i];
          const Stencil<D, Shape> st(grid, P.position[p], P.half_width[p]);
          if (t == group_first[g]) {
            int q = 0;
            st.for_each(grid, [&](int node, double, const Vec<D>&, const Vec<D>&) {
              node_at[q] = node;
              massive[q++] = grid.mass[node] > mass_threshold_;
            });
          }
          unsigned columns = 0;       // bit k: the cell's node k is a candidate with N^alpha > 0
          double weight[kCell] = {};  // N^alpha_k there, 0 elsewhere
          for (int k = 0; k < as.count; ++k) {
            if (e.alpha_col_of[as.node[k]] >= 0 && as.N[k] > 0.0) {
              columns |= 1U << k;
              weight[k] = as.N[k];
            }
          }
          if (columns == 0) continue;
          const double m = P.mass[p];
          int q = 0;
          // Every node's terms added, a whole row of kCell at a time (vectorised): where N^A or
          // N^alpha is 0 the term is +0, which leaves the sum as it is, bit for bit (the sums
          // start at +0 and their terms are not negative), and the terms of nodes without mass
          // are never read (their `used` stays 0).
          st.for_each(grid, [&](int, double N, const Vec<D>&, const Vec<D>&) {
            if (N > 0.0 && massive[q]) used[q] = static_cast<std::uint8_t>(used[q] | columns);
            const double mN = m * N;
            double* row = sum + q * kCell;
            for (int k = 0; k < kCell; ++k) row[k] += mN * weight[k];
            ++q;
          });
        }
        // Per cell node k, the stencil nodes q with a term (bit q) and their terms, side by
        // side for the columns' merge (which reads a cell node's terms of a group together).
        std::uint32_t* mask = &e.cross_mask[g * kCell];
        std::fill(mask, mask + kCell, std::uint32_t{0});
        for (int q = 0; q < kStencil; ++q) {
          for (int k = 0; k < kCell; ++k) {
            if ((used[q] & (1U << k)) == 0) continue;
            mask[k] |= std::uint32_t{1} << q;
            e.cross_sum[(g * kCell + static_cast<std::size_t>(k)) * kStencil +
                        static_cast<std::size_t>(q)] = sum[q * kCell + k];
          }
        }
      }
    });
    // Rows numbered in group order (node q of group g becomes a row if it has a term); each
    // column's (group, k) pairs listed in group order, and an upper bound on its entries.
    const std::size_t columns = candidates.size();
    // f(column, k) for each node k of group g's cell that some node of its stencil has a term with.
    auto for_each_column = [&](std::size_t g, auto&& f) {
      const std::size_t first = static_cast<std::size_t>(group_first[g]);
      const AlphaStencil<D>& cell = layer_stencil_[static_cast<std::size_t>(order[first].place)];
      for (int k = 0; k < cell.count; ++k) {
        if (e.cross_mask[g * kCell + static_cast<std::size_t>(k)] != 0) {
          f(static_cast<std::size_t>(e.alpha_col_of[cell.node[k]]), k);
        }
      }
    };
    auto& pair_first = e.cross_pair_first;
    auto& slab_first = e.cross_slab_first;
    pair_first.assign(columns + 1, 0);
    slab_first.assign(columns + 1, 0);
    for (std::size_t g = 0; g < groups; ++g) {
      std::uint32_t with_terms = 0;  // the stencil nodes with a term (bit q)
      for (int k = 0; k < kCell; ++k) {
        with_terms |= e.cross_mask[g * kCell + static_cast<std::size_t>(k)];
      }
      for (; with_terms != 0; with_terms &= with_terms - 1) {  // in increasing order
        const std::size_t at =
            g * kStencil + static_cast<std::size_t>(std::countr_zero(with_terms));
        e.cross_row[at] = row_of(e.cross_row[at]);
      }
      for_each_column(g, [&](std::size_t c, int k) {
        ++pair_first[c + 1];
        slab_first[c + 1] += std::popcount(e.cross_mask[g * kCell + static_cast<std::size_t>(k)]);
      });
    }
    std::partial_sum(pair_first.begin(), pair_first.end(), pair_first.begin());
    std::partial_sum(slab_first.begin(), slab_first.end(), slab_first.begin());
    auto& pairs = e.cross_pairs;
    pairs.resize(static_cast<std::size_t>(pair_first[columns]));
    auto& cursor = e.cross_count;  // the pairs' cursors here, then the columns' entry counts
    cursor.assign(pair_first.begin(), pair_first.end() - 1);
    for (std::size_t g = 0; g < groups; ++g) {
      for_each_column(g, [&](std::size_t c, int k) {
        pairs[static_cast<std::size_t>(cursor[c]++)] = static_cast<int>(g) * kCell + k;
      });
    }
    // Each column's entries: its groups' terms summed row by row in group order, the rows
    // sorted (a thread's dense accumulator over the rows, reset after each column).
    const std::size_t rows = e.a_rows.size();
    e.cross_slab_row.resize(static_cast<std::size_t>(slab_first[columns]));
    e.cross_slab_value.resize(static_cast<std::size_t>(slab_first[columns]));
    const auto slots = static_cast<std::size_t>(tbb::this_task_arena::max_concurrency());
    if (e.cross_column.size() < slots) e.cross_column.resize(slots);
    for (auto& acc : e.cross_column) {
      if (acc.sum.size() >= rows) continue;
      acc.sum.resize(rows);
      acc.held.resize(rows, 0);
      acc.rows.reserve(rows);
    }
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, columns, 16), [&](const auto& r) {
      auto& acc =
          e.cross_column[static_cast<std::size_t>(tbb::this_task_arena::current_thread_index())];
      for (std::size_t c = r.begin(); c != r.end(); ++c) {
        acc.rows.clear();
        for (int j = pair_first[c]; j < pair_first[c + 1]; ++j) {
          const auto g = static_cast<std::size_t>(pairs[static_cast<std::size_t>(j)] / kCell);
          const int k = pairs[static_cast<std::size_t>(j)] % kCell;
          const std::size_t gk = g * kCell + static_cast<std::size_t>(k);
          for (std::uint32_t q_bits = e.cross_mask[gk]; q_bits != 0; q_bits &= q_bits - 1) {
            const auto q = static_cast<std::size_t>(std::countr_zero(q_bits));
            const auto row = static_cast<std::size_t>(e.cross_row[g * kStencil + q]);
            const double value = e.cross_sum[gk * kStencil + q];
            if (acc.held[row] == 0) {
              acc.held[row] = 1;
              acc.sum[row] = value;
              acc.rows.push_back(static_cast<int>(row));
            } else {
              acc.sum[row] += value;
            }
          }
        }
        // Nearly sorted (rows are numbered in group order): an insertion sort.
        for (std::size_t a = 1; a < acc.rows.size(); ++a) {
          const int row = acc.rows[a];
          std::size_t b = a;
          for (; b > 0 && acc.rows[b - 1] > row; --b) acc.rows[b] = acc.rows[b - 1];
          acc.rows[b] = row;
        }
        auto at = static_cast<std::size_t>(slab_first[c]);
        for (const int row : acc.rows) {
          const auto ru = static_cast<std::size_t>(row);
          e.cross_slab_row[at] = row;
          e.cross_slab_value[at] = acc.sum[ru];
          acc.held[ru] = 0;
          ++at;
        }
        e.cross_count[c] = static_cast<int>(acc.rows.size());
      }
    });
  });
  // The columns' entries packed into the cross mass over every candidate column, from which K_SS
  // is read and the kept columns are taken.
  Sparse& cross_candidates = e.cross_candidates;
  {
    const std::size_t columns = candidates.size();
    reshape(cross_candidates, static_cast<Eigen::Index>(e.a_rows.size()),
            static_cast<Eigen::Index>(columns));
    int* outer = cross_candidates.outerIndexPtr();
    outer[0] = 0;
    for (std::size_t c = 0; c < columns; ++c) outer[c + 1] = outer[c] + e.cross_count[c];
    cross_candidates.resizeNonZeros(outer[columns]);
    int* inner = cross_candidates.innerIndexPtr();
    double* value = cross_candidates.valuePtr();
    for (std::size_t c = 0; c < columns; ++c) {
      const auto from = static_cast<std::size_t>(e.cross_slab_first[c]);
      const auto n = static_cast<std::size_t>(e.cross_count[c]);
      std::copy_n(e.cross_slab_row.begin() + static_cast<std::ptrdiff_t>(from), n,
                  inner + outer[c]);
      std::copy_n(e.cross_slab_value.begin() + static_cast<std::ptrdiff_t>(from), n,
                  value + outer[c]);
    }
  }
  // Near-linear dependence: K_SS = m^alpha_S - sum_I (C_IS)^2 / m^A_I is the effective mass of
  // the enhancement at S once the standard grid has taken what it can represent. A node whose
  // K_SS is a small fraction of m^alpha_S adds (almost) nothing the standard grid does not have,
  // and its tiny effective mass would take large accelerations: drop it (v^alpha_S = 0).
  std::vector<double>& diag = e.candidate_diagonal;
  diag.resize(candidates.size());
  for (std::size_t c = 0; c < candidates.size(); ++c) diag[c] = w.mass[candidates[c]];
  for (Eigen::Index c = 0; c < cross_candidates.outerSize(); ++c) {
    for (Sparse::InnerIterator it(cross_candidates, c); it; ++it) {
      diag[static_cast<std::size_t>(c)] -=
          it.value() * it.value() / grid.mass[e.a_rows[static_cast<std::size_t>(it.row())]];
    }
  }
  // Coverage: where every standard-grid node that the Gamma multipliers at S reach carries mass,
  // the standard field alone can take the wall's value there, and an enhancement at S is only a
  // second, redundant way to do it (a ghost direction the lumped mass gives inertia to; in the
  // 1D bar it makes the contact chatter). The enhancement is kept where the wall cuts into cells
  // whose far nodes are empty, which is what it is for.
  const mpmgeom::Coupling& gamma = w.spec->package->wall_coupling;
  std::vector<char>& covered = e.covered;
  covered.assign(candidates.size(), 0);
  for (std::size_t c = 0; c < candidates.size(); ++c) {
    if (scene_.drop_covered_enhancement && w.layer->node_on_wall[candidates[c]] != 0) {
      covered[c] = 1;
    }
  }
  for (int mu = 0; mu < static_cast<int>(gamma.multiplier_node.size()); ++mu) {
    double active = 0.0;  // the whole column sums to integral S_mu (partition of unity)
    for (Sparse::InnerIterator it(e.gamma_grid, mu); it; ++it) {
      if (grid.mass[it.row()] > coupling_threshold_) active += it.value();
    }
    if (active >= (1.0 - 1e-9) * gamma.multiplier_integral[mu]) continue;
    for (Sparse::InnerIterator it(gamma.boundary, mu); it; ++it) {
      const int c = e.alpha_col_of[it.row()];
      if (c >= 0) covered[static_cast<std::size_t>(c)] = 0;
    }
  }
  std::vector<int>& renumber = e.renumber;
  renumber.assign(candidates.size(), -1);
  e.dropped_dependent = 0;
  e.dropped_covered = 0;
  e.min_mass_ratio = 1.0;
  for (std::size_t c = 0; c < candidates.size(); ++c) {
    const int n = candidates[c];
    const double ratio = diag[c] / w.mass[n];
    e.alpha_col_of[n] = -1;
    if (covered[c] != 0) {
      ++e.dropped_covered;
      continue;
    }
    if (ratio < scene_.dependence_tolerance) {
      ++e.dropped_dependent;
      continue;
    }
    e.min_mass_ratio = std::min(e.min_mass_ratio, ratio);
    renumber[c] = static_cast<int>(e.alpha_cols.size());
    e.alpha_col_of[n] = renumber[c];
    e.alpha_cols.push_back(n);
  }

  // Multipliers in contact: those whose Gamma node carries boundary-grid mass (material in the
  // wall's own cells). Their R^A columns keep the nodes above the coupling threshold, rescaled
  // to sum to integral S_mu again (so the reported impulse is the material's momentum change).
  e.multipliers.clear();
  e.normal.clear();
  e.part.clear();
  std::vector<double>& integral = e.integral_list;
  integral.clear();
  auto& ga = e.grid_entries;
  auto& gb = e.alpha_entries;
  ga.clear();
  gb.clear();
  for (int mu = 0; mu < static_cast<int>(gamma.multiplier_node.size()); ++mu) {
    const int g = gamma.multiplier_node[mu];
    if (w.mass[g] <= coupling_threshold_ || w.wall_index_of_node[g] < 0) continue;
    // Separable: no multiplier until the material touches the wall at its node.
    if (w.spec->contact.separable && w.touch_gap[g] > 0.0) continue;
    double sum = 0.0;
    for (Sparse::InnerIterator it(e.gamma_grid, mu); it; ++it) {
      if (grid.mass[it.row()] > coupling_threshold_) sum += it.value();
    }
    if (sum <= 1e-12 * gamma.multiplier_integral[mu]) continue;
    const int col = static_cast<int>(e.multipliers.size());
    e.multipliers.push_back(mu);
    e.normal.push_back(w.wall_normal[w.wall_index_of_node[g]]);
    e.part.push_back(w.wall_node_part[w.wall_index_of_node[g]]);
    integral.push_back(gamma.multiplier_integral[mu]);
    const double scale = gamma.multiplier_integral[mu] / sum;
    for (Sparse::InnerIterator it(e.gamma_grid, mu); it; ++it) {
      const int node = static_cast<int>(it.row());
      if (grid.mass[node] > coupling_threshold_)
        ga.emplace_back(row_of(node), col, scale * it.value());
    }
    for (Sparse::InnerIterator it(gamma.boundary, mu); it; ++it) {
      const int c = e.alpha_col_of[it.row()];
      if (c >= 0) gb.emplace_back(c, col, it.value());
    }
  }
  e.integral.resize(static_cast<Eigen::Index>(integral.size()));
  std::copy(integral.begin(), integral.end(), e.integral.data());

  const auto na = static_cast<Eigen::Index>(e.a_rows.size());
  const auto ns = static_cast<Eigen::Index>(e.alpha_cols.size());
  const auto k = static_cast<Eigen::Index>(e.multipliers.size());
  e.inv_mass.resize(na);
  for (Eigen::Index r = 0; r < na; ++r) e.inv_mass[r] = 1.0 / grid.mass[e.a_rows[r]];
  e.alpha_mass.resize(ns);
  for (Eigen::Index c = 0; c < ns; ++c) e.alpha_mass[c] = w.mass[e.alpha_cols[c]];
  // The kept columns of the cross mass (rows the multipliers added carry none).
  {
    Eigen::Index kept = 0;
    for (std::size_t c = 0; c < candidates.size(); ++c) {
      if (renumber[c] < 0) continue;
      const auto col = static_cast<Eigen::Index>(c);
      kept += cross_candidates.outerIndexPtr()[col + 1] - cross_candidates.outerIndexPtr()[col];
    }
    reshape(e.cross, na, ns);
    e.cross.resizeNonZeros(kept);
    int* outer = e.cross.outerIndexPtr();
    int next = 0;
    for (std::size_t c = 0; c < candidates.size(); ++c) {
      if (renumber[c] < 0) continue;
      outer[renumber[c]] = next;
      for (Sparse::InnerIterator it(cross_candidates, static_cast<Eigen::Index>(c)); it; ++it) {
        e.cross.innerIndexPtr()[next] = static_cast<int>(it.row());
        e.cross.valuePtr()[next] = it.value();
        ++next;
      }
    }
    outer[ns] = next;
  }
  // R^A, R^alpha and M_A^-1 C (the cross mass's pattern, rows scaled), side by side on the two
  // cores (each with its own scratch). The products K, W and S_A are formed only when a matrix
  // is factorised (form_products() in enhanced_solve()): refinement applies them through these
  // factors.
  Sparse& minv_c = e.minv_cross;
  tbb::parallel_invoke([&] { assign_by_columns(e.grid_r, na, k, ga, e.assembly_work[0]); },
                       [&] {
                         assign_by_columns(e.alpha_r, ns, k, gb, e.assembly_work[1]);
                         copy_into(e.cross, minv_c);
                         for (Eigen::Index c = 0; c < minv_c.outerSize(); ++c) {
                           for (Sparse::InnerIterator it(minv_c, c); it; ++it) {
                             it.valueRef() *= e.inv_mass[it.row()];
                           }
                         }
                       });
  e.products_formed = false;
  e.schur_ready = false;
  e.kkt_ready = false;  // new masses: the contact system is solved anew
  e.kkt_formed = false;
  // S_A plus a relative 1e-10 shift on the held rows: redundant multipliers (more than the
  // active nodes can satisfy, the inf-sup problem of DESIGN.md) keep the system quasi-definite.
  // (S_A's diagonal from R^A and the masses: S_A itself is formed only to factorise.)
  e.grid_rr_diagonal.setZero(k);
  add_weighted_column_squares(e.grid_r, e.inv_mass, e.grid_rr_diagonal);
  e.kkt_shift = k > 0 ? 1e-10 * e.grid_rr_diagonal.maxCoeff() : 0.0;
}

// One velocity solve: from the standard-grid velocities `va` (p^A = m^A va on the near rows,
// box walls already applied) and the boundary-grid momenta, the coupled velocities, with the
// wall's multipliers when `constrained`. Impulses go to the wall's parts when `record`.
template <int D>
void Solver<D>::enhanced_solve(DualWall<D>& w, NodeField<Vec<D>>& va,
                               const std::vector<Vec<D>>& alpha_momentum,
                               std::vector<Vec<D>>& valpha, bool constrained, bool record) {
  EnhancedState<D>& e = w.enh;
  // The step's own solves keep their solutions for the next step's start (solve()).
  const bool extrapolate = record && constrained;
  using Block = typename EnhancedState<D>::Block;
  const auto na = static_cast<Eigen::Index>(e.a_rows.size());
  const auto ns = static_cast<Eigen::Index>(e.alpha_cols.size());
  // Unconstrained solves keep every multiplier off.
  const auto k = static_cast<Eigen::Index>(e.multipliers.size());

  // The blocks and lists are the state's scratch (sized once per active set).
  Block& pa = e.pa;
  Block& ps = e.ps;
  pa.resize(na, D);
  ps.resize(ns, D);
  for (Eigen::Index r = 0; r < na; ++r) {
    pa.row(r) = grid.mass[e.a_rows[r]] * va[e.a_rows[r]].transpose();
  }
  for (Eigen::Index c = 0; c < ns; ++c) ps.row(c) = alpha_momentum[e.alpha_cols[c]].transpose();

  Block& vs = e.vs;
  Block& vna = e.vna;
  Block& impulse = e.impulse;
  Block& load = e.load;
  vs.setZero(ns, D);
  vna.resize(na, D);
  impulse.setZero(k, D);
  load.setZero(k, D);
  std::vector<Contact>& state = e.contact;
  state.assign(static_cast<std::size_t>(k), Contact::off);
  const WallContact& contact = w.spec->contact;
  // Each multiplier takes the condition of its part: its friction coefficient (0: slip) and the
  // state it starts in when it comes into contact (stick for sticky and frictional walls).
  std::vector<double>& mu_of = e.friction;
  std::vector<Contact>& on_of = e.on_contact;
  mu_of.assign(static_cast<std::size_t>(k), 0.0);
  on_of.assign(static_cast<std::size_t>(k), Contact::normal);
  for (std::size_t i = 0; i < static_cast<std::size_t>(k); ++i) {
    const WallCondition& condition = w.spec->condition(e.part[i]);
    const bool sticky = std::holds_alternative<Sticky>(condition);
    if (const auto* f = std::get_if<Friction>(&condition)) mu_of[i] = f->mu;
    if (sticky || mu_of[i] > 0.0) on_of[i] = Contact::stick;
  }

  // K = M^alpha - C^T M_A^-1 C, W = R^alpha - (M_A^-1 C)^T R^A and S_A = R^A^T M_A^-1 R^A in
  // the state's own storage, once per step and only for a matrix to be factorised (formed or
  // reused: the patterns are compared): refinement applies them through C, R^A and R^alpha
  // (apply_kkt), which hold fewer entries (the floor benchmark: 156 k against 378 k). The three
  // are independent, so they are formed side by side on the two cores.
  auto form_products = [&]() {
    if (e.products_formed) return;
    tbb::parallel_invoke(
        [&] {
          product_into(nullptr, &e.alpha_mass, e.cross, nullptr, e.minv_cross, e.schur,
                       e.product_work[0]);
        },
        [&] {
          product_into(&e.alpha_r, nullptr, e.minv_cross, nullptr, e.grid_r, e.coupled_r,
                       e.product_work[1]);
        },
        [&] {
          product_into(nullptr, nullptr, e.grid_r, &e.inv_mass, e.grid_r, e.grid_rr,
                       e.product_work[2]);
        });
    e.products_formed = true;
  };

  // The contact matrix of the held rows e.rows (for the current contact states),
  //
  //   [ K (x) I_D   -W_rows    ]
  //   [ -W_rows^T   -S_A,rows - shift I ],
  //
  // whose unknowns are v^alpha (node-major, D per node) and one impulse per held row: formed
  // into e.kkt_matrix to be factorised, or applied by blocks for refinement (apply_kkt).
  auto form_kkt = [&]() {
    const auto& rows = e.rows;
    const Eigen::Index nv = ns * D, nc = static_cast<Eigen::Index>(rows.size());
    form_products();
    // The held rows of multiplier i are row_first[i] .. row_first[i + 1] - 1 (rows are listed
    // by multiplier).
    std::vector<int>& row_first = e.row_first;
    row_first.assign(static_cast<std::size_t>(k) + 1, 0);
    for (const auto& row : rows) ++row_first[static_cast<std::size_t>(row.first) + 1];
    for (Eigen::Index i = 0; i < k; ++i) row_first[i + 1] += row_first[i];
    auto& t = e.kkt_entries;
    t.clear();
    for (Eigen::Index c = 0; c < e.schur.outerSize(); ++c) {
      for (Sparse::InnerIterator it(e.schur, c); it; ++it) {
        for (int d = 0; d < D; ++d) t.emplace_back(it.row() * D + d, c * D + d, it.value());
      }
    }
    for (Eigen::Index i = 0; i < e.coupled_r.outerSize(); ++i) {
      for (Sparse::InnerIterator it(e.coupled_r, i); it; ++it) {
        for (int c = row_first[i]; c < row_first[i + 1]; ++c) {
          const Vec<D>& dir = rows[c].second;
          for (int d = 0; d < D; ++d) {
            if (dir[d] == 0.0) continue;
            t.emplace_back(it.row() * D + d, nv + c, -it.value() * dir[d]);
            t.emplace_back(nv + c, it.row() * D + d, -it.value() * dir[d]);
          }
        }
      }
    }
    for (Eigen::Index i = 0; i < e.grid_rr.outerSize(); ++i) {
      for (Sparse::InnerIterator it(e.grid_rr, i); it; ++it) {
        for (int c = row_first[i]; c < row_first[i + 1]; ++c) {
          for (int c2 = row_first[it.row()]; c2 < row_first[it.row() + 1]; ++c2) {
            const double dd = rows[c].second.dot(rows[c2].second);
            if (dd != 0.0) t.emplace_back(nv + c2, nv + c, -it.value() * dd);
          }
        }
      }
    }
    for (Eigen::Index c = 0; c < nc; ++c) t.emplace_back(nv + c, nv + c, -e.kkt_shift);
    assign_by_columns(e.kkt_matrix, nv + nc, nv + nc, t, e.assembly_work[0]);
    e.kkt_formed = true;
  };
  // y = the contact matrix times x, by blocks: with V the v^alpha part as ns x D and J the
  // held rows' impulses summed per multiplier (k x D),
  //   y_v = K V - W J,   y_c = -n_c . (W^T V + S_A J)_i(c) - shift x_c,
  // through the factors of K, W and S_A: with U = M_A^-1 (C V - R^A J),
  //   K V - W J = M^alpha V - R^alpha J - C^T U,   W^T V + S_A J = R^alpha^T V - R^A^T U.
  // The same matrix as the formed one's, its products summed in another order (round-off apart).
  auto apply_kkt = [&](const Eigen::VectorXd& x, Eigen::VectorXd& y) {
    const auto& rows = e.rows;
    const Eigen::Index nv = ns * D, nc = static_cast<Eigen::Index>(rows.size());
    Block& v = e.apply_v;
    Block& yv = e.apply_y;
    Block& j = e.apply_j;
    Block& t = e.apply_t;
    Block& u = e.apply_u;
    Block& rj = e.apply_rj;
    v.resize(ns, D);
    for (Eigen::Index c = 0; c < ns; ++c) {
      for (int d = 0; d < D; ++d) v(c, d) = x[c * D + d];
    }
    j.setZero(k, D);
    for (Eigen::Index c = 0; c < nc; ++c)
      j.row(rows[c].first) += x[nv + c] * rows[c].second.transpose();
    // Each pair reads only what is formed before it: one on each core.
    tbb::parallel_invoke([&] { u.noalias() = e.cross * v; }, [&] { rj.noalias() = e.grid_r * j; });
    u -= rj;
    u = e.inv_mass.asDiagonal() * u;
    tbb::parallel_invoke(
        [&] {
          yv = e.alpha_mass.asDiagonal() * v;
          yv.noalias() -= e.alpha_r * j;
          yv.noalias() -= e.cross.transpose() * u;
        },
        [&] {
          t.noalias() = e.alpha_r.transpose() * v;
          t.noalias() -= e.grid_r.transpose() * u;
        });
    y.resize(nv + nc);
    for (Eigen::Index c = 0; c < ns; ++c) {
      for (int d = 0; d < D; ++d) y[c * D + d] = yv(c, d);
    }
    for (Eigen::Index c = 0; c < nc; ++c) {
      y[nv + c] = -rows[c].second.dot(t.row(rows[c].first).transpose()) - e.kkt_shift * x[nv + c];
    }
  };

  // Solve for the current contact states (and friction loads); returns false if the system
  // could not be factorised.
  auto solve = [&]() {
    Block& pa_l = e.pa_load;
    Block& ps_l = e.ps_load;
    Block& minv_pa = e.minv_pa;
    Block& rhs_alpha = e.rhs_alpha;
    pa_l = pa;
    pa_l.noalias() += e.grid_r * load;
    ps_l = ps;
    ps_l.noalias() += e.alpha_r * load;
    minv_pa = e.inv_mass.asDiagonal() * pa_l;
    rhs_alpha = ps_l;
    rhs_alpha.noalias() -= e.cross.transpose() * minv_pa;
    // Constraint rows: one per direction that is held.
    auto& rows = e.rows;
    rows.clear();
    for (Eigen::Index i = 0; i < k; ++i) {
      const auto s = state[static_cast<std::size_t>(i)];
      if (s == Contact::stick) {
        for (int d = 0; d < D; ++d) rows.emplace_back(static_cast<int>(i), Vec<D>::Unit(d));
      } else if (s == Contact::normal || s == Contact::slip) {
        rows.emplace_back(static_cast<int>(i), e.normal[static_cast<std::size_t>(i)]);
      }
    }
    impulse.setZero();
    if (rows.empty()) {
      // K alone (no wall contact): its factorisation in hand is reused while K's pattern holds.
      if (ns > 0 && !e.schur_ready) {
        form_products();
        if (!factorise_or_reuse(*e.schur_solver, e.schur, e.schur_base, e.schur_pattern,
                                e.schur_factored, true, e.schur_refine, e.factorizations)) {
          fault_ = "dual wall \"" + w.spec->name +
                   "\": the enhanced mass matrix is singular (raise scheme.dependence_tolerance)";
          return false;
        }
        e.schur_ready = true;
      }
      if (ns > 0 && !refined_solve(*e.schur_solver, e.schur, e.schur_base, e.schur_pattern,
                                   e.schur_refine, rhs_alpha, vs, e.refinements, e.factorizations,
                                   e.schur_work, scene_.coupling_tolerance)) {
        return false;
      }
    } else {
      const Eigen::Index nv = ns * D, nc = static_cast<Eigen::Index>(rows.size());
      // The matrix depends only on this step's masses and on which directions are held: a
      // solve with the same rows (the MUSL remap, or an active-set pass that only moved
      // friction loads) reuses the factorisation. Rows by wall multiplier (not by this step's
      // numbering), so that equal signatures are the same directions of the same multipliers.
      std::vector<int>& signature = e.signature;
      signature.resize(rows.size());
      for (std::size_t c = 0; c < rows.size(); ++c) {
        signature[c] = 4 * e.multipliers[static_cast<std::size_t>(rows[c].first)] +
                       static_cast<int>(state[rows[c].first]);
      }
      // The factorisation in hand bordered for this step's unknowns (BorderedFactor): its
      // velocities matched to these by node, its rows by signature (a stuck multiplier's D rows
      // in their order), at most kBorderedRows of them gone or new (each costs a solve with the
      // factorisation to set up, again in each step the rows differ: the floor benchmark's
      // factorisation costs about a hundred), and at most kBorderedBudget summed over the
      // borderings of one factorisation (rows that came or went for good are bordered again each
      // step until it factorises).
      const auto prepare_bordered = [&]() {
        constexpr std::size_t kBorderedRows = 64, kBorderedBudget = 128;
        if (e.bordered_factor != e.kkt_solver->factorizations()) {
          e.bordered_factor = e.kkt_solver->factorizations();
          e.bordered_rows = 0;
        }
        const std::vector<int>& factored = e.kkt_signature;
        // (A checkpoint written before the factorisation's nodes were saved leaves them
        // unknown: no bordering until the next factorisation.)
        if (static_cast<Eigen::Index>(e.kkt_alpha_cols.size() * D + factored.size()) !=
            e.kkt_solver->rows()) {
          return false;
        }
        auto key_of = [](const std::vector<int>& rows_signature, std::size_t c, int& run) {
          run = c > 0 && rows_signature[c - 1] == rows_signature[c] ? run + 1 : 0;
          return static_cast<std::int64_t>(rows_signature[c]) * 4 + run;
        };
        auto& old_of = e.bordered_old_of;
        old_of.resize(static_cast<std::size_t>(nv + nc));
        std::size_t added = 0;
        // v^alpha's unknowns by node (both lists of nodes increase).
        const std::vector<int>& factored_nodes = e.kkt_alpha_cols;
        for (Eigen::Index c = 0; c < ns; ++c) {
          const int node = e.alpha_cols[static_cast<std::size_t>(c)];
          const auto at = std::lower_bound(factored_nodes.begin(), factored_nodes.end(), node);
          const bool found = at != factored_nodes.end() && *at == node;
          const auto old_column = static_cast<int>(at - factored_nodes.begin());
          for (int d = 0; d < D; ++d) {
            old_of[static_cast<std::size_t>(c * D + d)] = found ? old_column * D + d : -1;
          }
          if (!found) added += D;
        }
        const auto factored_nv = static_cast<int>(factored_nodes.size()) * D;
        auto& keys = e.bordered_keys;
        keys.clear();
        int run = 0;
        for (std::size_t c = 0; c < factored.size(); ++c) {
          keys.emplace_back(key_of(factored, c, run), factored_nv + static_cast<int>(c));
        }
        std::sort(keys.begin(), keys.end());
        run = 0;
        for (std::size_t c = 0; c < signature.size(); ++c) {
          const std::pair<std::int64_t, int> key{key_of(signature, c, run), -1};
          const auto at = std::lower_bound(keys.begin(), keys.end(), key);
          const bool found = at != keys.end() && at->first == key.first;
          old_of[static_cast<std::size_t>(nv) + c] = found ? at->second : -1;
          if (!found) ++added;
        }
        const std::size_t removed = static_cast<std::size_t>(e.kkt_solver->rows()) -
                                    (static_cast<std::size_t>(nv + nc) - added);
        if (added + removed > kBorderedRows ||
            e.bordered_rows + added + removed > kBorderedBudget) {
          return false;
        }
        e.bordered_rows += added + removed;
        Eigen::VectorXd& unit = e.bordered_unit;
        unit.setZero(nv + nc);
        const auto column = [&](int j, Eigen::VectorXd& out) {
          unit[j] = 1.0;
          apply_kkt(unit, out);
          unit[j] = 0.0;
        };
        return e.bordered.prepare(*e.kkt_solver, e.kkt_solver->aged_values(LdltValues::full),
                                  old_of, column);
      };
      // Forms this step's matrix (if it is not) and factorises it unless its pattern and rows
      // are the factorised one's (`reusable`): the factorisation in hand is for these unknowns
      // from then on.
      const auto factorise = [&](bool reusable) {
        if (!e.kkt_formed) form_kkt();
        e.kkt_bordered = false;
        if (!factorise_or_reuse(*e.kkt_solver, e.kkt_matrix, e.kkt_base, e.kkt_pattern,
                                e.kkt_factored, reusable, e.kkt_refine, e.factorizations)) {
          return false;
        }
        e.kkt_alpha_cols = e.alpha_cols;
        e.kkt_signature = signature;
        return true;
      };
      if (!e.kkt_ready || signature != e.prepared_signature) {
        // The same unknowns as the factorisation in hand (the same held directions and the same
        // enhancement nodes: contact that has not changed since an earlier step): the masses
        // moved a little, so that factorisation is a close preconditioner and a few refinement
        // passes solve the new matrix (to 1e-10: refine()), which they apply by blocks: the
        // matrix is not formed. Its pattern may differ from the factorised one's (the cross mass
        // gains and loses (I, S) pairs as particles cross cells, nearly every step on the floor
        // benchmark); refinement that fails factorises this step's matrix. With a few held rows
        // or enhancement nodes more or fewer (multipliers coming into contact or leaving it,
        // nodes crossing the mass threshold), the factorisation bordered for them
        // (BorderedFactor) preconditions as well. Otherwise the matrix is formed, and
        // factorised unless its pattern is the factorised one's.
        const bool same_rows = signature == e.kkt_signature;
        const bool same_columns = e.alpha_cols == e.kkt_alpha_cols;
        e.kkt_formed = false;
        e.kkt_bordered = false;
        if (e.kkt_factored && same_rows && same_columns) {
          e.kkt_refine = true;
        } else if (e.kkt_factored && prepare_bordered()) {
          e.kkt_refine = true;
          e.kkt_bordered = true;
        } else if (!factorise(same_rows)) {
          return false;
        }
        e.kkt_ready = true;
        e.prepared_signature = signature;
      }
      Eigen::VectorXd& rhs = e.rhs;
      rhs.resize(nv + nc);
      for (Eigen::Index c = 0; c < ns; ++c) {
        for (int d = 0; d < D; ++d) rhs[c * D + d] = rhs_alpha(c, d);
      }
      Block& rt_minv_pa = e.rt_minv_pa;
      rt_minv_pa.noalias() = e.grid_r.transpose() * minv_pa;
      for (Eigen::Index c = 0; c < nc; ++c) {
        rhs[nv + c] = rows[c].second.dot(rt_minv_pa.row(rows[c].first).transpose());
      }
      Eigen::VectorXd& x = e.solution;
      // Refinement applies the matrix by blocks; unconverged, the matrix is formed (if it was
      // not) and factorised.
      const auto formed = [&]() -> const Sparse& {
        if (!e.kkt_formed) form_kkt();
        e.kkt_alpha_cols = e.alpha_cols;
        return e.kkt_matrix;
      };
      // Refinement measures x's error as velocities: an impulse unknown counts as the velocity
      // it gives the standard grid's nodes (|M_A^-1 R^A n| times it), so that the tolerance is
      // one fraction of the velocities for both kinds of unknown, whatever the node masses;
      // so does the check of a new factorisation's dropped copy (check_dropped()).
      Eigen::VectorXd& weight = e.impulse_weight;
      weight.resize(nc);
      for (Eigen::Index c = 0; c < weight.size(); ++c) {
        double sum = 0.0;
        for (Sparse::InnerIterator it(e.grid_r, rows[c].first); it; ++it) {
          const double v = it.value() * e.inv_mass[it.row()];
          sum += v * v;
        }
        weight[c] = rows[c].second.norm() * std::sqrt(sum);
      }
      // A row that reaches no standard-grid node (its impulse acts on the boundary grid alone)
      // takes the others' mean, so that no unknown goes unmeasured.
      const double mean = weight.size() > 0 ? weight.mean() : 0.0;
      for (Eigen::Index c = 0; c < weight.size(); ++c) {
        if (!(weight[c] > 0.0)) weight[c] = mean > 0.0 ? mean : 1.0;
      }
      const auto as_velocities = [&](const Eigen::VectorXd& y) {
        double sum = y.head(nv).squaredNorm();
        for (Eigen::Index c = 0; c < nc; ++c) {
          const double v = weight[c] * y[nv + c];
          sum += v * v;
        }
        return std::sqrt(sum);
      };
      if (e.kkt_bordered) {
        // Refinement against the bordered factorisation; unconverged, this step's matrix is
        // factorised and solved.
        const auto bordered_solve = [&](const Eigen::VectorXd& r, Eigen::VectorXd& out) {
          e.bordered.solve(r, out);
        };
        e.bordered.solve(rhs, x);
        if (!refine(rhs, x, apply_kkt, bordered_solve, e.refinements, e.kkt_work.residual,
                    e.kkt_work.update, 0.0, scene_.coupling_tolerance, as_velocities) &&
            !factorise(false)) {
          return false;
        }
      }
      // Against an aged factorisation, refinement starts from the last two solutions of the
      // step's own solve extrapolated, 2 x_0 - x_1, where both are for these unknowns (the
      // same held rows and enhancement nodes: contact that has not changed), not from the
      // factor's answer (refined_solve() tries that next where it does not converge, as the
      // Phi coupling's CG does). The floor over 300 steps on two threads: factorisations 22 ->
      // 20 (MLS-MPM) and 27 -> 24 (MUSL); the last solution alone as the start gave more (27
      // and 36: docs/performance.md, 2026-12-07, late night, and 2026-12-08).
      const Eigen::VectorXd* start = nullptr;
      auto& recent = e.recent_solution;
      if (extrapolate && e.kkt_refine && !e.kkt_bordered && e.recent_signature[0] == signature &&
          e.recent_signature[1] == signature && e.recent_columns[0] == e.alpha_cols &&
          e.recent_columns[1] == e.alpha_cols) {
        x = 2.0 * recent[0] - recent[1];  // (the same unknowns: the same sizes)
        start = &x;
      }
      if (!e.kkt_bordered &&
          !refined_solve(*e.kkt_solver, apply_kkt, formed, e.kkt_base, e.kkt_pattern, e.kkt_refine,
                         rhs, x, e.refinements, e.factorizations, e.kkt_work,
                         scene_.coupling_tolerance, as_velocities, start)) {
        return false;
      }
      if (extrapolate) {
        // (The buffers of the earlier one reused.)
        std::swap(recent[0], recent[1]);
        std::swap(e.recent_signature[0], e.recent_signature[1]);
        std::swap(e.recent_columns[0], e.recent_columns[1]);
        recent[0] = x;
        e.recent_signature[0] = signature;
        e.recent_columns[0] = e.alpha_cols;
      }
      for (Eigen::Index c = 0; c < ns; ++c) {
        for (int d = 0; d < D; ++d) vs(c, d) = x[c * D + d];
      }
      for (Eigen::Index c = 0; c < nc; ++c) {
        impulse.row(rows[c].first) += x[nv + c] * rows[c].second.transpose();
      }
    }
    // v^A = M_A^-1 (p^A - C v^alpha + R^A j), through pa_l.
    pa_l.noalias() -= e.cross * vs;
    pa_l.noalias() += e.grid_r * impulse;
    vna = e.inv_mass.asDiagonal() * pa_l;
    return true;
  };
  auto gaps = [&]() -> const Block& {
    e.gap.noalias() = e.grid_r.transpose() * vna;
    e.gap.noalias() += e.alpha_r.transpose() * vs;
    return e.gap;
  };

  bool ok = true;
  if (constrained && k > 0 && !record) {
    // The MUSL remap: the contact states the step's own solve settled on, so the strain rate
    // sees the same wall the forces did. Not its friction loads: the remapped velocities come
    // from particles that have already taken them, and a load is an impulse, not a constraint:
    // applied again, every sliding node would take its friction twice in the strain rate (a
    // block resting on a frictional incline slowly crushed itself, and gained energy, so).
    if (e.state.size() == static_cast<std::size_t>(k)) {
      for (Eigen::Index i = 0; i < k; ++i) state[i] = static_cast<Contact>(e.state[i]);
    }
    ok = solve();
  } else if (constrained && k > 0) {
    if (contact.separable) {
      // Start from the previous step's contact state where the multiplier was in contact then
      // (contact changes little from step to step, so the loop usually settles in one pass),
      // elsewhere from where the unconstrained field moves into the wall: that solve only when
      // some multiplier has no previous state (in steady contact none lacks one).
      const auto total = e.previous_state.size();
      auto known = [&](Eigen::Index i) {
        const auto mu = static_cast<std::size_t>(e.multipliers[static_cast<std::size_t>(i)]);
        return mu < total && e.previous_state[mu] != 0xFF;
      };
      bool all_known = true;
      for (Eigen::Index i = 0; i < k && all_known; ++i) all_known = known(i);
      if (!all_known) {
        ok = solve();
        gaps();
      }
      const Block& g = e.gap;
      for (Eigen::Index i = 0; i < k; ++i) {
        if (known(i)) {
          const auto mu = static_cast<std::size_t>(e.multipliers[static_cast<std::size_t>(i)]);
          const auto s = static_cast<Contact>(e.previous_state[mu]);
          state[static_cast<std::size_t>(i)] =
              s == Contact::off ? Contact::off : on_of[static_cast<std::size_t>(i)];
        } else if (g.row(i).dot(e.normal[static_cast<std::size_t>(i)].transpose()) < 0.0) {
          state[static_cast<std::size_t>(i)] = on_of[static_cast<std::size_t>(i)];
        }
      }
    } else {
      state = on_of;
    }
    // Active set: release multipliers that pull (separable), add those whose gap closes, and
    // switch between stick and Coulomb slip; a few passes settle it. A multiplier released twice
    // in a step stays released for the rest of it: on rough contact (the debris slope as an
    // Enhanced wall) one or two multipliers could alternate between pulling when held and
    // closing their gap when released, every pass a new factorisation, until the 30 passes ran
    // out (a quarter of the steps), and the step kept whichever state the last pass left.
    std::vector<unsigned char>& releases = e.releases;
    releases.assign(static_cast<std::size_t>(k), 0);
    bool settled = false;
    for (int iteration = 0; iteration < 30 && ok; ++iteration) {
      ++e.active_set_passes;
      ok = solve();
      if (!ok) break;
      const Block& g = gaps();
      bool changed = false;
      for (Eigen::Index i = 0; i < k; ++i) {
        const auto u = static_cast<std::size_t>(i);
        Vec<D> friction = load.row(i).transpose();
        bool kept = false;
        changed |= update_contact<D>(
            state[u], releases[u], friction, on_of[u], mu_of[u], contact.separable, e.normal[u],
            Vec<D>((impulse.row(i) + load.row(i)).transpose()), Vec<D>(g.row(i).transpose()), kept);
        load.row(i) = friction.transpose();
        if (kept) ++e.kept_released;
      }
      if (!changed) {
        settled = true;
        break;
      }
    }
    if (ok && !settled) ++e.unsettled_steps;
  } else {
    ok = solve();
  }
  if (!ok) {
    if (!fault_) {
      fault_ = "dual wall \"" + w.spec->name + "\": the enhanced contact system is singular";
    }
    return;
  }

  if (constrained && record) {
    e.previous_state.assign(w.spec->package->wall_coupling.multiplier_node.size(), 0xFF);
    for (Eigen::Index i = 0; i < k; ++i) {
      e.previous_state[static_cast<std::size_t>(e.multipliers[static_cast<std::size_t>(i)])] =
          static_cast<unsigned char>(state[static_cast<std::size_t>(i)]);
    }
    e.state.assign(static_cast<std::size_t>(k), 0);
    for (Eigen::Index i = 0; i < k; ++i) e.state[i] = static_cast<unsigned char>(state[i]);
  }
  for (Eigen::Index r = 0; r < na; ++r) va[e.a_rows[r]] = vna.row(r).transpose();
  for (Eigen::Index c = 0; c < ns; ++c) valpha[e.alpha_cols[c]] = vs.row(c).transpose();
  if (record) {
    for (Eigen::Index i = 0; i < k; ++i) {
      const Vec<D> j = (impulse.row(i) + load.row(i)).transpose();
      wall_impulse_[w.impulse_offset + e.part[static_cast<std::size_t>(i)]] +=
          pad3<D>(Vec<D>(e.integral[i] * j));
    }
  }
}

#define MPM_ENHANCED_MEMBERS(D)                                                                   \
  template void Solver<D>::enhanced_assemble(DualWall<D>&);                                       \
  template void Solver<D>::enhanced_solve(DualWall<D>&, NodeField<Vec<D>>&,                       \
                                          const std::vector<Vec<D>>&, std::vector<Vec<D>>&, bool, \
                                          bool);

MPM_ENHANCED_MEMBERS(1)
MPM_ENHANCED_MEMBERS(2)
MPM_ENHANCED_MEMBERS(3)

}  // namespace mpm
