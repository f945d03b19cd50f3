// The Blending method (DESIGN.md section 4): particles in a wall's layer belong to its boundary
// grid, all others to the standard grid; each grid gets mass, momentum and force from its own
// particles; wall conditions act on the boundary grid's Gamma nodes in the wall's own frame;
// continuity across Phi is imposed weakly with multipliers,
//
//   R^A^T v^A = R^alpha^T v^alpha,
//
// either one-way (as published: v^alpha prescribed for the bulk) or mortar (two-way saddle
// point, equal and opposite interface impulses), solved through the Schur complement on the
// multipliers with Eigen's sparse Cholesky.

#include <algorithm>
#include <array>
#include <atomic>
#include <cmath>
#include <limits>
#include <numeric>
#include <type_traits>
#include <unordered_map>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_invoke.h>

#include "alpha_stencil.hpp"
#include "mpm/solver.hpp"
#include "sparse_pattern.hpp"

namespace mpm {

namespace {

// The multiplier space of a Phi coupling, coarsened (DESIGN.md section 4: facets finer than h
// over-constrain the interface): multipliers are merged into groups whose basis is the sum of
// their P1 hats, which keeps the partition of unity over Phi (so momentum stays exact and
// uniform motion passes). Greedy over the multipliers in node order: an unassigned multiplier
// seeds a group, which takes the unassigned multipliers reachable from it along Phi's facet
// edges that lie within `radius` of it. It follows the surface (a thin wall's two faces, or two
// separate surfaces, never share a group unless a facet joins them) and the mesh alone (the same
// groups however the scene is turned). Returns the group of each multiplier; radius 0: one each.
template <int D>
std::vector<int> aggregate_multipliers(const DualWall<D>& w, const std::vector<int>& node,
                                       double radius) {
  const auto k = node.size();
  std::vector<int> group(k);
  if (!(radius > 0.0)) {
    for (std::size_t mu = 0; mu < k; ++mu) group[mu] = static_cast<int>(mu);
    return group;
  }
  std::vector<int> mu_of(w.position.size(), -1);
  for (std::size_t mu = 0; mu < k; ++mu)
    mu_of[static_cast<std::size_t>(node[mu])] = static_cast<int>(mu);
  // Phi's facet edges: the top nodes of a cell (its last D columns) that are multiplier nodes.
  std::vector<std::vector<int>> adjacent(k);
  const Eigen::Index top = w.layer->cells.cols() - (D == 1 ? 1 : D);
  for (Eigen::Index cell = 0; cell < w.layer->cells.rows(); ++cell) {
    for (Eigen::Index a = top; a < w.layer->cells.cols(); ++a) {
      const int ma = mu_of[static_cast<std::size_t>(w.layer->cells(cell, a))];
      if (ma < 0) continue;
      for (Eigen::Index b = a + 1; b < w.layer->cells.cols(); ++b) {
        const int mb = mu_of[static_cast<std::size_t>(w.layer->cells(cell, b))];
        if (mb < 0) continue;
        adjacent[static_cast<std::size_t>(ma)].push_back(mb);
        adjacent[static_cast<std::size_t>(mb)].push_back(ma);
      }
    }
  }
  // A multiplier at the radius (a polyline cut into segments of h, radius h) is in: the margin
  // keeps round-off from deciding it differently for a turned scene.
  const double reach = radius * (1.0 + 1e-9);
  std::fill(group.begin(), group.end(), -1);
  int groups = 0;
  std::vector<int> queue;
  for (std::size_t seed = 0; seed < k; ++seed) {
    if (group[seed] >= 0) continue;
    const Vec<D>& centre = w.position[static_cast<std::size_t>(node[seed])];
    group[seed] = groups;
    queue.assign(1, static_cast<int>(seed));
    for (std::size_t q = 0; q < queue.size(); ++q) {
      for (const int next : adjacent[static_cast<std::size_t>(queue[q])]) {
        const auto n = static_cast<std::size_t>(next);
        if (group[n] >= 0 ||
            (w.position[static_cast<std::size_t>(node[n])] - centre).norm() > reach) {
          continue;
        }
        group[n] = groups;
        queue.push_back(next);
      }
    }
    ++groups;
  }
  return group;
}

/// A package coupling's rows (standard-grid nodes in the package's lexicographic order, last
/// axis fastest: mpmgeom::GridSpec::linear_index) renumbered to the grid's blocked node index.
/// The scene reader has checked that the package was made for this grid (same nodes, origin).
template <int D>
Eigen::SparseMatrix<double> on_grid(const Grid<D>& grid, const Eigen::SparseMatrix<double>& m) {
  // Column by column (no row-major temporary: the rows are the grid's node slots).
  Eigen::SparseMatrix<double> out(static_cast<Eigen::Index>(grid.size()), m.cols());
  out.reserve(m.nonZeros());
  std::vector<std::pair<int, double>> column;
  for (int col = 0; col < m.outerSize(); ++col) {
    column.clear();
    for (Eigen::SparseMatrix<double>::InnerIterator it(m, col); it; ++it) {
      column.emplace_back(grid.linear(lattice_index<D>(it.row(), grid.nodes)), it.value());
    }
    std::sort(column.begin(), column.end());
    out.startVec(col);
    for (const auto& [row, value] : column) out.insertBack(row, col) = value;
  }
  out.finalize();
  return out;
}

// The concave corners and creases of a wall (walls.hpp, constrain_velocity_in_corner): for each
// Gamma node, the distinct unit normals of its wall facets, kept where two of them are more than
// a crease angle apart and the wall bends towards the material there (its neighbours along the
// wall lie, on average, on the material side of the plane through the node normal to it). At a
// convex corner or edge the node's own normal stays: material there can leave one facet
// without entering the other. None unless the wall asks for them ("corners": "facets").
template <int D>
void find_corners(DualWall<D>& w) {
  w.corner_first.assign(w.wall_nodes.size() + 1, 0);
  w.corner_normals.clear();
  w.corner_part.clear();
  if (!w.spec->corner_facets) return;
  if constexpr (D > 1) {
    const mpmgeom::BoundaryGrid& layer = *w.layer;
    std::vector<std::vector<int>> facets_at(w.wall_nodes.size());
    for (Eigen::Index f = 0; f < layer.wall_facets.rows(); ++f) {
      for (int k = 0; k < D; ++k) {
        facets_at[static_cast<std::size_t>(w.wall_index_of_node[layer.wall_facets(f, k)])]
            .push_back(static_cast<int>(f));
      }
    }
    const auto facet_normal = [&](int f) -> Vec<D> {
      const Vec<D> a = w.position[layer.wall_facets(f, 0)];
      const Vec<D> e = w.position[layer.wall_facets(f, 1)] - a;
      if constexpr (D == 2) {
        return Vec<D>(-e[1], e[0]).normalized();  // the left side, into the material
      } else {
        return e.cross(w.position[layer.wall_facets(f, 2)] - a).normalized();
      }
    };
    // A corner or crease: two facets more than ~25 degrees apart (libgeom's crease angle).
    // Below it the facets approximate a smooth wall, whose normal the node's own is (the shipped
    // hillside: 82 of 10,462 Gamma nodes are past it, all by more than 80 degrees, at the
    // barrier's foot and ends; the terrain's facets meet within 5 degrees).
    constexpr double kCornerCosine = 0.9;
    std::vector<Vec<D>> distinct;
    std::vector<int> parts;
    for (std::size_t i = 0; i < w.wall_nodes.size(); ++i) {
      const int node = w.wall_nodes[i];
      distinct.clear();
      parts.clear();
      double bend = 0.0;
      for (const int f : facets_at[i]) {
        const Vec<D> nf = facet_normal(f);
        // Facets in one plane (to round-off) give one constraint.
        const bool seen = std::any_of(distinct.begin(), distinct.end(),
                                      [&](const Vec<D>& m) { return m.dot(nf) > 1.0 - 1e-9; });
        if (!seen) {
          distinct.push_back(nf);
          parts.push_back(layer.wall_facet_part[f]);
        }
        for (int k = 0; k < D; ++k) {
          const int other = layer.wall_facets(f, k);
          if (other == node) continue;
          const Vec<D> d = w.position[other] - w.position[node];
          bend += w.wall_normal[i].dot(d) / d.norm();
        }
      }
      double spread = 1.0;  // the cosine of the widest angle between two of the facets
      for (const Vec<D>& a : distinct) {
        for (const Vec<D>& b : distinct) spread = std::min(spread, a.dot(b));
      }
      if (spread < kCornerCosine && distinct.size() <= kMaxCornerNormals && bend > 0.0) {
        w.corner_normals.insert(w.corner_normals.end(), distinct.begin(), distinct.end());
        w.corner_part.insert(w.corner_part.end(), parts.begin(), parts.end());
      }
      w.corner_first[i + 1] = static_cast<int>(w.corner_normals.size());
    }
  }
  w.corner_gap.assign(w.corner_normals.size(), std::numeric_limits<double>::infinity());
}

// Per entry of a lattice with `size` points per axis (last axis fastest), the distance to the
// nearest entry where `source` is set, as the largest of the axes' index differences (0 there,
// 255 at most: also where no entry is set). Two sweeps, each taking its neighbours' distance
// plus one from the half of the 3^D - 1 neighbours it has already passed (exact for this
// distance: Rosenfeld and Pfaltz 1966).
template <int D>
std::vector<std::uint8_t> chessboard_distance(const std::vector<std::uint8_t>& source,
                                              const Index<D>& size) {
  constexpr int kFar = 255;
  std::vector<std::uint8_t> distance(source.size());
  for (std::size_t i = 0; i < source.size(); ++i) distance[i] = source[i] != 0 ? 0 : kFar;
  // The neighbours' steps, those before an entry in the lattice's order (the first step that is
  // not zero is negative) and those after.
  std::vector<Index<D>> before, after;
  int codes = 1;
  for (int d = 0; d < D; ++d) codes *= 3;
  for (int code = 0; code < codes; ++code) {
    Index<D> step;
    for (int d = D - 1, c = code; d >= 0; --d, c /= 3) step[d] = c % 3 - 1;
    int first = 0;
    for (int d = 0; d < D && first == 0; ++d) first = step[d];
    if (first < 0) before.push_back(step);
    if (first > 0) after.push_back(step);
  }
  auto sweep = [&](const std::vector<Index<D>>& steps, long from, long to, long by) {
    for (long at = from; at != to; at += by) {
      auto& here = distance[static_cast<std::size_t>(at)];
      if (here == 0) continue;
      const Index<D> i = lattice_index<D>(at, size);
      int best = here;
      for (const Index<D>& step : steps) {
        const Index<D> j = i + step;
        if ((j.array() < 0).any() || (j.array() >= size.array()).any()) continue;
        best = std::min(best, distance[static_cast<std::size_t>(lattice_offset<D>(j, size))] + 1);
      }
      here = static_cast<std::uint8_t>(best);
    }
  };
  const auto n = static_cast<long>(source.size());
  sweep(before, 0, n, 1);
  sweep(after, n - 1, -1, -1);
  return distance;
}

// A wall's factorisations: the Phi coupling's S (Blending), Enhanced's K and contact system.
template <int D>
std::array<const SparseLdlt*, 3> solvers_of(const DualWall<D>& w) {
  return {w.schur.get(), w.enh.schur_solver.get(), w.enh.kkt_solver.get()};
}

// The seconds a wall's solvers have spent factorising (analysis and numeric).
template <int D>
double factorising_seconds(const DualWall<D>& w) {
  double seconds = 0.0;
  for (const SparseLdlt* s : solvers_of(w)) seconds += s->analysis_seconds() + s->numeric_seconds();
  return seconds;
}

// Adds the wall-clock time of its scope to `seconds`, less what the wall's solvers spent
// factorising meanwhile (they count that themselves).
template <int D>
class PartTimer {
 public:
  PartTimer(const DualWall<D>& w, double& seconds)
      : w_(w), seconds_(seconds), factorising_(factorising_seconds(w)) {}
  PartTimer(const PartTimer&) = delete;
  PartTimer& operator=(const PartTimer&) = delete;
  ~PartTimer() {
    const double elapsed =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
    seconds_ += elapsed - (factorising_seconds(w_) - factorising_);
  }

 private:
  const DualWall<D>& w_;
  double& seconds_;
  std::chrono::steady_clock::time_point start_ = std::chrono::steady_clock::now();
  double factorising_;
};

// The rows of columns `columns` of `r` not yet in `nodes`, appended once each (`mark`: 1 for
// those in `nodes`).
template <class Marks>
void add_support(const Eigen::SparseMatrix<double>& r, const std::vector<int>& columns, Marks& mark,
                 std::vector<int>& nodes) {
  for (const int col : columns) {
    for (Eigen::SparseMatrix<double>::InnerIterator it(r, col); it; ++it) {
      const auto node = static_cast<std::size_t>(it.row());
      if (mark[node] != 0) continue;
      mark[node] = 1;
      nodes.push_back(static_cast<int>(node));
    }
  }
}

// Per node of `nodes`, 1 if its mass is above `threshold` (and its mark cleared).
template <class Marks, class Masses>
void record_sides(const std::vector<int>& nodes, Marks& mark, const Masses& mass, double threshold,
                  std::vector<std::uint8_t>& above) {
  above.resize(nodes.size());
  for (std::size_t i = 0; i < nodes.size(); ++i) {
    const auto node = static_cast<std::size_t>(nodes[i]);
    mark[node] = 0;
    above[i] = mass[node] > threshold ? 1 : 0;
  }
}

// True if every node of `nodes` is on the side of `threshold` that `above` recorded.
template <class Masses>
bool same_sides(const std::vector<int>& nodes, const std::vector<std::uint8_t>& above,
                const Masses& mass, double threshold) {
  for (std::size_t i = 0; i < nodes.size(); ++i) {
    if ((mass[static_cast<std::size_t>(nodes[i])] > threshold) != (above[i] != 0)) return false;
  }
  return true;
}

// Records what the coupling in hand was assembled from (DualWall::support_recorded): the
// carried multipliers and each node of their supports once, with whether it carries mass
// above `threshold`.
template <int D, class Masses>
void record_support(DualWall<D>& w, const Masses& grid_mass, double threshold) {
  w.recorded_carried = w.carried_multipliers;
  w.support_grid_nodes.clear();
  w.support_layer_nodes.clear();
  add_support(w.grid_coupling, w.carried_multipliers, w.support_grid_mark, w.support_grid_nodes);
  add_support(w.boundary_coupling, w.carried_multipliers, w.support_layer_mark,
              w.support_layer_nodes);
  record_sides(w.support_grid_nodes, w.support_grid_mark, grid_mass, threshold,
               w.support_grid_above);
  record_sides(w.support_layer_nodes, w.support_layer_mark, w.mass, threshold,
               w.support_layer_above);
  w.support_recorded = true;
}

// True if every recorded support node is on the same side of `threshold` as when recorded.
template <int D, class Masses>
bool support_unchanged(const DualWall<D>& w, const Masses& grid_mass, double threshold) {
  return same_sides(w.support_grid_nodes, w.support_grid_above, grid_mass, threshold) &&
         same_sides(w.support_layer_nodes, w.support_layer_above, w.mass, threshold);
}

}  // namespace

template <int D>
std::vector<CouplingWork> Solver<D>::coupling_work() const {
  std::vector<CouplingWork> work;
  for (const DualWall<D>& w : dual_) {
    CouplingWork c;
    c.wall = w.spec->name;
    c.method = w.enhanced                                  ? "enhanced"
               : w.spec->method == CouplingMethod::one_way ? "one-way"
                                                           : "mortar";
    const mpmgeom::Coupling& surface =
        w.enhanced ? w.spec->package->wall_coupling : w.spec->package->interface_coupling;
    c.surface_nodes = surface.multiplier_node.size();
    c.multipliers = w.enhanced ? c.surface_nodes : w.multiplier_first.size() - 1;
    for (std::size_t i = 0; i < w.wall_nodes.size(); ++i) {
      if (!w.enhanced && w.corner_first[i + 1] > w.corner_first[i]) ++c.corner_nodes;
    }
    c.factorizations = w.factorizations + w.enh.factorizations;
    c.refinement_passes = w.refinements + w.enh.refinements;
    c.reshaped_steps = w.reshapes;
    c.kept_steps = w.kept_assemblies;
    c.active_set_passes = w.enh.active_set_passes;
    c.unsettled_steps = w.enh.unsettled_steps;
    c.kept_released = w.enh.kept_released;
    c.assembly_seconds = w.assembly_seconds;
    c.solve_seconds = w.solve_seconds;
    for (const SparseLdlt* s : solvers_of(w)) {
      c.analysis_seconds += s->analysis_seconds();
      c.factorization_seconds += s->numeric_seconds();
    }
    work.push_back(std::move(c));
  }
  return work;
}

template <int D>
std::vector<std::string> Solver<D>::wall_names() const {
  std::vector<std::string> names;
  for (const auto& wall : scene_.walls) names.push_back(wall.name);
  // The order of setup_dual_walls(): scene order, a dual wall per part when it has several.
  for (const DualWallSpec& spec : scene_.dual_walls) {
    const auto& parts = spec.package->layer.part_names;
    if (spec.method == CouplingMethod::sdf || parts.size() <= 1) {
      names.push_back(spec.name);
    } else {
      for (const auto& part : parts) names.push_back(spec.name + "_" + part);
    }
  }
  return names;
}

template <int D>
void Solver<D>::setup_dual_walls() {
  dual_.clear();
  sdf_.clear();
  for (const DualWallSpec& spec : scene_.dual_walls) {
    if (spec.method == CouplingMethod::sdf) {
      setup_sdf_wall(spec);
      continue;
    }
    DualWall<D> w;
    w.spec = &spec;
    w.layer = &spec.package->layer;
    w.locator = std::make_unique<mpmgeom::LayerLocator>(*w.layer);
    w.cell_filter = mpmgeom::LayerCellFilter(*w.layer, spec.package->grid);
    w.cell_nodes.assign(w.layer->cell_count(), {});
    for (std::size_t c = 0; c < w.cell_nodes.size(); ++c) {
      for (int k = 0; k < DualWall<D>::kCellNodes; ++k) {  // the scene's dimension (scene.cpp)
        w.cell_nodes[c][static_cast<std::size_t>(k)] =
            w.layer->cells(static_cast<Eigen::Index>(c), k);
      }
    }
    const auto n = static_cast<std::size_t>(w.layer->nodes.rows());
    w.position.resize(n);
    for (std::size_t i = 0; i < n; ++i) {
      w.position[i] = w.layer->nodes.row(static_cast<Eigen::Index>(i)).transpose();
    }
    w.mass.assign(n, 0.0);
    w.momentum.assign(n, Vec<D>::Zero());
    w.force.assign(n, Vec<D>::Zero());
    w.velocity.assign(n, Vec<D>::Zero());
    w.velocity_new.assign(n, Vec<D>::Zero());
    w.centroid.assign(n, Vec<D>::Zero());
    w.touch_gap.assign(n, std::numeric_limits<double>::infinity());
    // Each node's (cell, slot) pairs, cells in increasing order, and the cells' sort arrays.
    constexpr int slots = DualWall<D>::kCellNodes;
    const std::size_t cell_count = w.layer->cell_count();
    w.node_cell_first.assign(n + 1, 0);
    for (std::size_t c = 0; c < cell_count; ++c) {
      for (const int node : w.cell_nodes[c])
        ++w.node_cell_first[static_cast<std::size_t>(node) + 1];
    }
    std::partial_sum(w.node_cell_first.begin(), w.node_cell_first.end(), w.node_cell_first.begin());
    w.node_cells.resize(static_cast<std::size_t>(w.node_cell_first.back()));
    std::vector<int> cursor(w.node_cell_first.begin(), w.node_cell_first.end() - 1);
    for (std::size_t c = 0; c < cell_count; ++c) {
      for (int k = 0; k < slots; ++k) {
        const auto node = static_cast<std::size_t>(w.cell_nodes[c][static_cast<std::size_t>(k)]);
        w.node_cells[static_cast<std::size_t>(cursor[node]++)] = static_cast<int>(c) * slots + k;
      }
    }
    w.cell_first.assign(cell_count + 1, 0);
    w.cell_cursor.assign(cell_count, 0);
    w.node_reached.assign(n, 0);
    w.enhanced = spec.method == CouplingMethod::enhanced;
    if (w.enhanced) {
      w.momentum_new.assign(n, Vec<D>::Zero());
      w.enh.gamma_grid = on_grid(grid, spec.package->wall_coupling.grid);
      w.enh.a_row_of.assign_zero(grid.size());
      w.enh.alpha_col_of.assign(n, -1);
      // The cells ranked by their node lists (enhanced_assemble() groups particles by them).
      std::vector<int> by_nodes(cell_count);
      std::iota(by_nodes.begin(), by_nodes.end(), 0);
      std::sort(by_nodes.begin(), by_nodes.end(), [&](int a, int b) {
        const auto& x = w.cell_nodes[static_cast<std::size_t>(a)];
        const auto& y = w.cell_nodes[static_cast<std::size_t>(b)];
        return x != y ? x < y : a < b;
      });
      w.enh.cell_rank.assign(cell_count, 0);
      for (std::size_t r = 1; r < cell_count; ++r) {
        const auto a = static_cast<std::size_t>(by_nodes[r - 1]);
        const auto b = static_cast<std::size_t>(by_nodes[r]);
        w.enh.cell_rank[b] = w.enh.cell_rank[a] + (w.cell_nodes[a] != w.cell_nodes[b] ? 1 : 0);
      }
    } else {
      w.grid_row_of.assign_zero(grid.size());
      w.layer_row_of.assign(n, -1);
      w.support_grid_mark.assign_zero(grid.size());
      w.support_layer_mark.assign(n, 0);
    }

    // Gamma nodes and the part each reports to (from the last wall facet that holds it; a corner
    // node's facets each report to their own: layer_walls()).
    std::vector<int> part(n, 0);
    for (Eigen::Index f = 0; f < w.layer->wall_facets.rows(); ++f) {
      for (Eigen::Index k = 0; k < w.layer->wall_facets.cols(); ++k) {
        part[w.layer->wall_facets(f, k)] = w.layer->wall_facet_part[f];
      }
    }
    w.wall_index_of_node.assign(n, -1);
    for (std::size_t i = 0; i < n; ++i) {
      if (w.layer->node_on_wall[static_cast<Eigen::Index>(i)] == 0) continue;
      w.wall_index_of_node[i] = static_cast<int>(w.wall_nodes.size());
      w.wall_nodes.push_back(static_cast<int>(i));
      w.wall_normal.push_back(
          w.layer->node_normals.row(static_cast<Eigen::Index>(i)).transpose().normalized());
      w.wall_node_part.push_back(part[i]);
    }
    find_corners(w);
    w.impulse_offset = static_cast<int>(wall_impulse_.size());
    wall_impulse_.resize(
        wall_impulse_.size() + std::max<std::size_t>(1, w.layer->part_names.size()),
        Eigen::Vector3d::Zero());

    const mpmgeom::Coupling& c = spec.package->interface_coupling;
    const double radius = spec.multiplier_radius * scene_.spacing;
    const std::vector<int> group = aggregate_multipliers<D>(w, c.multiplier_node, radius);
    const int groups = group.empty() ? 0 : *std::max_element(group.begin(), group.end()) + 1;
    if (groups == static_cast<int>(group.size())) {  // one multiplier per Phi node
      w.grid_coupling = on_grid(grid, c.grid);
      w.boundary_coupling = c.boundary;
      w.multiplier_integral = c.multiplier_integral;
    } else {  // each group's columns summed
      std::vector<Eigen::Triplet<double>> entries;
      for (std::size_t mu = 0; mu < group.size(); ++mu) {
        entries.emplace_back(static_cast<int>(mu), group[mu], 1.0);
      }
      Eigen::SparseMatrix<double> P(static_cast<Eigen::Index>(group.size()), groups);
      P.setFromTriplets(entries.begin(), entries.end());
      w.grid_coupling = on_grid(grid, c.grid) * P;
      w.boundary_coupling = c.boundary * P;
      w.multiplier_integral = P.transpose() * c.multiplier_integral;
    }
    w.multiplier_first.assign(static_cast<std::size_t>(groups) + 1, 0);
    for (const int g : group) ++w.multiplier_first[static_cast<std::size_t>(g) + 1];
    for (int g = 0; g < groups; ++g) w.multiplier_first[g + 1] += w.multiplier_first[g];
    w.multiplier_nodes.resize(group.size());
    std::vector<int> fill(w.multiplier_first.begin(), w.multiplier_first.end() - 1);
    w.multiplier_of_node.assign(w.position.size(), -1);
    for (std::size_t mu = 0; mu < group.size(); ++mu) {
      w.multiplier_nodes[static_cast<std::size_t>(fill[group[mu]]++)] = c.multiplier_node[mu];
      w.multiplier_of_node[static_cast<std::size_t>(c.multiplier_node[mu])] = group[mu];
    }

    // The smallest cell extent (column height or wall edge) limits the stable step.
    double smallest = std::numeric_limits<double>::infinity();
    const int per_level = D == 1 ? 1 : D;
    for (Eigen::Index cell = 0; cell < w.layer->cells.rows(); ++cell) {
      for (int k = 0; k < per_level; ++k) {
        const Vec<D> a = w.position[w.layer->cells(cell, k)];
        const Vec<D> b = w.position[w.layer->cells(cell, k + per_level)];
        smallest = std::min(smallest, (b - a).norm());
        for (int j = k + 1; j < per_level; ++j) {
          smallest = std::min(smallest, (w.position[w.layer->cells(cell, j)] - a).norm());
        }
      }
    }
    w.min_cell_size = smallest;

    // Each cell's share of its wall facet for the touch test (layer_scatter): half the facet's
    // longest edge in 2D, 1/sqrt(3) of it in 3D (every point of a facet is that close to one of
    // its corners). Testing every particle in a node's support instead switched on nodes a cell
    // ahead of where a rolling disk touches, whose approach the rigid rotation extrapolates, and
    // the disk was braked (docs/verification.md). On facets longer than h the share grows by
    // the excess: their nodes interpolate over the whole facet, so contact anywhere on it
    // engages all of them.
    w.touch_window.assign(static_cast<std::size_t>(w.layer->cells.rows()), 0.0);
    for (Eigen::Index cell = 0; cell < w.layer->cells.rows(); ++cell) {
      double edge = 0.0;  // the longest edge between the cell's Gamma nodes
      for (Eigen::Index a = 0; a < w.layer->cells.cols(); ++a) {
        const int na = w.layer->cells(cell, a);
        if (w.wall_index_of_node[na] < 0) continue;
        for (Eigen::Index b = a + 1; b < w.layer->cells.cols(); ++b) {
          const int nb = w.layer->cells(cell, b);
          if (w.wall_index_of_node[nb] < 0) continue;
          edge = std::max(edge, (w.position[na] - w.position[nb]).norm());
        }
      }
      w.touch_window[static_cast<std::size_t>(cell)] =
          (D == 3 ? 1.0 / std::sqrt(3.0) : 0.5) * edge + std::max(0.0, edge - grid.h);
    }
    dual_.push_back(std::move(w));
  }

  // The cells whose particles' stencils reach a node a coupling may change (couple_beside()).
  // Node i is in the stencil of a particle in cell c when c - 1 <= i <= c + 2 along each axis
  // (linear kernel c, c + 1; quadratic B-spline and GIMP floor(x - 1/2) and the two after), so
  // a node marks cells i - 2 to i + 1. A Blending coupling writes the rows of its R^A; an
  // Enhanced one the rows of its R^A on Gamma and the stencil nodes of its layer particles,
  // which lie in the package's flagged cells c: nodes c - 1 to c + 2, so cells c - 3 to c + 3.
  coupled_cell_.clear();
  cell_clearance_.clear();
  chunk_travel_.clear();
  if (dual_.empty()) return;
  const Index<D> cells = grid.nodes - Index<D>::Ones();
  coupled_cell_.assign(static_cast<std::size_t>(cells.prod()), 0);
  // Marks the cells from `at` + below to `at` + above along each axis, `at` an entry of a
  // lattice of `size` points per axis (lattice_index()).
  auto mark = [&](long at, const Index<D>& size, int below, int above) {
    const Index<D> i = lattice_index<D>(at, size);
    const Index<D> lo = (i.array() + below).max(0).matrix();
    const Index<D> hi = (i.array() + above).min(cells.array() - 1).matrix();
    for_each_in_box(lo, hi, [&](const Index<D>& c) {
      coupled_cell_[static_cast<std::size_t>(lattice_offset<D>(c, cells))] = 1;
    });
  };
  for (const DualWall<D>& w : dual_) {
    const auto& package = *w.spec->package;
    const Eigen::SparseMatrix<double>& rows =
        w.enhanced ? package.wall_coupling.grid : package.interface_coupling.grid;
    std::vector<std::uint8_t> used(static_cast<std::size_t>(rows.rows()), 0);
    for (Eigen::Index col = 0; col < rows.outerSize(); ++col) {
      for (Eigen::SparseMatrix<double>::InnerIterator it(rows, col); it; ++it) {
        used[static_cast<std::size_t>(it.row())] = 1;
      }
    }
    for (std::size_t node = 0; node < used.size(); ++node) {
      if (used[node] != 0) mark(static_cast<long>(node), grid.nodes, -2, 1);
    }
    if (!w.enhanced) continue;
    for (std::size_t cell = 0; cell < package.cell_flags.size(); ++cell) {
      if (package.cell_flags[cell] != 0) mark(static_cast<long>(cell), cells, -3, 3);
    }
  }
  // How far each cell is from the cells whose particles locate_in_layers() must look at (a
  // layer's flagged cells, the coupled cells): particles far from them are skipped.
  std::vector<std::uint8_t> source = coupled_cell_;
  for (const DualWall<D>& w : dual_) {
    const auto& flags = w.spec->package->cell_flags;
    for (std::size_t cell = 0; cell < flags.size(); ++cell) source[cell] |= flags[cell];
  }
  cell_clearance_ = chessboard_distance<D>(source, cells);
}

// Ownership: a particle in a flagged standard-grid cell, within the bounds the layer's cells
// there have (DualWall::cell_filter), is looked up in the layer; found means the boundary grid
// owns it this step. Other particles never query Embree. The particles found
// are listed in index order with their cell and natural coordinates (per particle only the wall
// and the place in that list: most particles are in no layer).
template <int D>
void Solver<D>::locate_in_layers() {
  auto& P = particles;
  for (auto& w : dual_) w.layer_particles = 0;
  if (dual_.empty()) return;
  const Index<D> cells = grid.nodes - Index<D>::Ones();
  constexpr std::size_t kChunk = kLocateChunk;
  const std::size_t chunks = (P.size() + kChunk - 1) / kChunk;
  layer_hits_.resize(chunks);
  near_coupling_.resize(coupled_cell_.empty() ? 0 : P.size());
  if (chunk_travel_.size() != chunks || locate_limit_.size() != P.size()) {
    // The first step, or particles restored from a checkpoint: every one looked at.
    chunk_travel_.assign(chunks, 0.0);
    chunk_limit_.assign(chunks, 0.0);
    locate_limit_.assign(P.size(), 0.0);
  }
  if (!locate_skipping_) std::fill(locate_limit_.begin(), locate_limit_.end(), 0.0);
  std::atomic<bool> moved{false};  // a particle changed layer cell (or entered or left one)
  std::atomic<std::size_t> skipped{0};
  tbb::parallel_for(std::size_t{0}, chunks, [&](std::size_t chunk) {
    std::vector<LayerHit>& hits = layer_hits_[chunk];
    hits.clear();
    // A particle that has moved less than its clearance since it was last looked at is still
    // outside the flagged and coupled cells: in no layer (P.layer_wall -1, as then) and not near
    // a coupling (near_coupling_ 0, as then). The floor benchmark's block skips half its
    // particles so.
    const double travel = chunk_travel_[chunk];
    const std::size_t end = std::min(P.size(), (chunk + 1) * kChunk);
    if (locate_skipping_ && travel < chunk_limit_[chunk]) {
      skipped.fetch_add(end - chunk * kChunk, std::memory_order_relaxed);
      return;
    }
    double least = std::numeric_limits<double>::infinity();
    std::size_t passed = 0;
    for (std::size_t p = chunk * kChunk; p != end; ++p) {
      if (travel < locate_limit_[p]) {
        least = std::min(least, locate_limit_[p]);
        ++passed;
        continue;
      }
      // The hinted cell of the particle 32 places on asked for now (the cells' maps are read
      // in no order memory can guess: 0.1-0.3 ms of the floor's 1.9-3.0 ms on one thread).
      if (const std::size_t ahead = p + 32; ahead < end) {
        if (const int wall = P.layer_wall[ahead]; wall >= 0) {
          dual_[static_cast<std::size_t>(wall)].locator->prefetch(
              layer_cell_[static_cast<std::size_t>(P.layer_slot[ahead])]);
        }
      }
      // The layer cell of the step before (the list is rebuilt below, after this pass), tried
      // first: particles move a fraction of a cell per step.
      const int previous_wall = P.layer_wall[p];
      const int previous_cell =
          previous_wall >= 0 ? layer_cell_[static_cast<std::size_t>(P.layer_slot[p])] : -1;
      P.layer_wall[p] = -1;
      long cell = 0;
      Eigen::Vector3i ijk = Eigen::Vector3i::Zero();
      for (int d = 0; d < D; ++d) {
        ijk[d] = std::clamp(
            static_cast<int>(std::floor((P.position[p][d] - grid.origin[d]) * grid.inv_h)), 0,
            cells[d] - 1);
        cell = cell * cells[d] + ijk[d];
      }
      if (!coupled_cell_.empty()) near_coupling_[p] = coupled_cell_[static_cast<std::size_t>(cell)];
      // `far` cells from them is at least far - 1 cell widths away along an axis; half a cell
      // less, so that the rounding of the positions and of the cells' arithmetic cannot matter.
      const int far = cell_clearance_[static_cast<std::size_t>(cell)];
      locate_limit_[p] = travel + (far >= 2 ? (far - 1.5) * grid.h : 0.0);
      least = std::min(least, locate_limit_[p]);
      for (std::size_t wi = 0; wi < dual_.size(); ++wi) {
        // The flag first (a byte, as the filter's cells): most particles' cell has none.
        const auto& flags = dual_[wi].spec->package->cell_flags;
        if (flags.empty() || flags[static_cast<std::size_t>(cell)] == 0) continue;
        Eigen::Vector3d x = Eigen::Vector3d::Zero();
        x.head<D>() = P.position[p];
        if (!dual_[wi].cell_filter.may_hold(ijk, x)) continue;
        const auto found = dual_[wi].locator->locate(
            x, previous_wall == static_cast<int>(wi) ? previous_cell : -1);
        if (found.cell >= 0) {
          P.layer_wall[p] = static_cast<int>(wi);
          hits.push_back({static_cast<int>(p), found});
          if (previous_cell != found.cell) moved.store(true, std::memory_order_relaxed);
          break;
        }
      }
      if (P.layer_wall[p] != previous_wall) moved.store(true, std::memory_order_relaxed);
    }
    chunk_limit_[chunk] = least;
    skipped.fetch_add(passed, std::memory_order_relaxed);
  });
  locate_skipped_ += skipped.load();
  if (moved.load()) layer_sort_current_ = false;
  // The chunks' hits joined in chunk order (so the list stays in index order), each at its
  // place given by the counts of the chunks before it, in parallel; with each, the particle's
  // boundary-grid basis and the terms of its scatters that depend neither on the node nor on
  // what the step changes before them (layer_scatter(): its stress and body force are the
  // step's first; its centroid point is where its basis puts it).
  layer_chunk_first_.resize(layer_hits_.size() + 1);
  layer_chunk_first_[0] = 0;
  for (std::size_t chunk = 0; chunk < layer_hits_.size(); ++chunk) {
    layer_chunk_first_[chunk + 1] = layer_chunk_first_[chunk] + layer_hits_[chunk].size();
  }
  const std::size_t layer_count = layer_chunk_first_.back();
  layer_list_.resize(layer_count);
  layer_cell_.resize(layer_count);
  layer_stencil_.resize(layer_count);
  layer_gradient_.resize(layer_count);
  layer_terms_.resize(layer_count);
  const bool remaps = scene_.update == UpdateScheme::musl;
  tbb::parallel_for(std::size_t{0}, layer_hits_.size(), [&](std::size_t chunk) {
    const std::vector<LayerHit>& hits = layer_hits_[chunk];
    // A body's particles mostly share their initial volume: its root is taken once for each run
    // of equal volumes (the same value, bit for bit, as taken for each particle).
    double volume0 = std::numeric_limits<double>::quiet_NaN(), half = 0.0;
    for (std::size_t j = 0; j < hits.size(); ++j) {
      if (j + 8 < hits.size()) {
        // What this pass reads of the particle 8 hits on (a layer particle's arrays are read
        // in strides the hardware prefetcher does not follow).
        const auto q = static_cast<std::size_t>(hits[j + 8].particle);
        for (const auto* matrix : {P.deformation_gradient[q].data(), P.stress[q].data()}) {
          __builtin_prefetch(matrix);
          __builtin_prefetch(matrix + D * D - 1);
        }
        __builtin_prefetch(&P.volume0[q]);
        __builtin_prefetch(&P.mass[q]);
      }
      const std::size_t i = layer_chunk_first_[chunk] + j;
      const auto p = static_cast<std::size_t>(hits[j].particle);
      P.layer_slot[p] = static_cast<int>(i);
      layer_list_[i] = hits[j].particle;
      layer_cell_[i] = hits[j].at.cell;
      const DualWall<D>& w = dual_[P.layer_wall[p]];
      const AlphaStencil<D>& st = layer_stencil_[i] = alpha_stencil(w, hits[j].at);
      LayerTerms& t = layer_terms_[i];
      const double volume = P.volume0[p] * P.deformation_gradient[p].determinant();
      t.vs = -volume * P.stress[p];
      t.mb = P.mass[p] * body_acceleration_[P.body[p]];
      // Separable walls: the touch test of layer_walls() and enhanced_assemble(). A Gamma
      // node is in contact where a particle lying over it (within the node's share of the
      // facet, DualWall::touch_window, plus the particle's half-size) touches the wall: the
      // particle's near edge (half its initial size as a cube, widened by the touch
      // tolerance) reaches it.
      if (w.spec->contact.separable) {
        if (!(P.volume0[p] == volume0)) {
          volume0 = P.volume0[p];
          half = 0.5 * std::pow(volume0, 1.0 / D);
        }
        t.reach = (1.0 + w.spec->contact.touch_tolerance) * half;
        const double window = w.touch_window[static_cast<std::size_t>(layer_cell_[i])] + half;
        t.window_squared = window * window;
      }
      // The MUSL remap's nodal velocity is that of the particles at their centroid, which
      // layer_affine() fits at: the particle's point of the isoparametric map (Enhanced
      // keeps the standard grid's C_p and has no use for it; USL does not remap).
      if (remaps && !w.enhanced) {
        t.at.setZero();
        for (int k = 0; k < st.count; ++k) t.at += st.N[k] * w.position[st.node[k]];
      }
    }
  });
  for (const int p : layer_list_)
    ++dual_[P.layer_wall[static_cast<std::size_t>(p)]].layer_particles;
}

template <int D>
void Solver<D>::layer_scatter(bool with_force) {
  auto& P = particles;
  const bool apic = scene_.transfer == Transfer::apic;
  // Only the nodes the layer's particles reach hold anything: the arrays are cleared where the
  // last step's (or, for the remap, this step's) particles reached, not over the whole layer
  // (a hillside's layer is mostly empty).
  for (auto& w : dual_) {
    for (const int node : w.scatter_nodes) {
      const auto n = static_cast<std::size_t>(node);
      w.momentum[n].setZero();
      if (!with_force) continue;  // the centroids were cleared with the rest at the step's start
      w.mass[n] = 0.0;
      w.force[n].setZero();
      w.centroid[n].setZero();
      w.velocity[n].setZero();
      w.velocity_new[n].setZero();
      if (w.enhanced) w.momentum_new[n].setZero();
      w.touch_gap[n] = std::numeric_limits<double>::infinity();
      if (const int wi = w.wall_index_of_node[n]; wi >= 0) {
        const auto wu = static_cast<std::size_t>(wi);
        std::fill(w.corner_gap.begin() + w.corner_first[wu],
                  w.corner_gap.begin() + w.corner_first[wu + 1],
                  std::numeric_limits<double>::infinity());
      }
    }
  }
  if (dual_.empty()) return;
  if (with_force && !layer_sort_current_) {
    // The layer particles by cell, again when a particle changed cell (the remap has the same
    // stencils): a counting sort that keeps the layer list's order within a cell. A node's
    // (particle, slot) pairs are then those of the cells around it (DualWall::node_cells), and
    // the nodes reached are those of the occupied cells.
    layer_sort_current_ = true;
    for (auto& w : dual_) std::fill(w.cell_first.begin(), w.cell_first.end(), 0);
    for (std::size_t i = 0; i < layer_list_.size(); ++i) {
      DualWall<D>& w = dual_[P.layer_wall[static_cast<std::size_t>(layer_list_[i])]];
      ++w.cell_first[static_cast<std::size_t>(layer_cell_[i]) + 1];
    }
    for (auto& w : dual_) {
      std::partial_sum(w.cell_first.begin(), w.cell_first.end(), w.cell_first.begin());
      std::copy(w.cell_first.begin(), w.cell_first.end() - 1, w.cell_cursor.begin());
      w.cell_members.resize(static_cast<std::size_t>(w.cell_first.back()));
    }
    layer_place_.resize(layer_list_.size());
    for (std::size_t i = 0; i < layer_list_.size(); ++i) {
      DualWall<D>& w = dual_[P.layer_wall[static_cast<std::size_t>(layer_list_[i])]];
      const int place = w.cell_cursor[static_cast<std::size_t>(layer_cell_[i])]++;
      w.cell_members[static_cast<std::size_t>(place)] = static_cast<int>(i);
      layer_place_[i] = place;
    }
    for (auto& w : dual_) {
      // The occupied cells' nodes marked, then collected in node order by one pass over the
      // layer's nodes (0.02 ms a step on the floor benchmark; sorting the list took 0.41 ms).
      for (std::size_t c = 0; c + 1 < w.cell_first.size(); ++c) {
        if (w.cell_first[c + 1] == w.cell_first[c]) continue;
        for (const int node : w.cell_nodes[c]) w.node_reached[static_cast<std::size_t>(node)] = 1;
      }
      w.scatter_nodes.clear();
      for (std::size_t node = 0; node < w.node_reached.size(); ++node) {
        if (w.node_reached[node] == 0) continue;
        w.node_reached[node] = 0;
        w.scatter_nodes.push_back(static_cast<int>(node));
      }
      w.scatter_terms.resize(w.cell_members.size() * DualWall<D>::kCellNodes);
      if (w.spec->contact.separable) w.touch_terms.resize(w.scatter_terms.size());
    }
  }
  // Each pair's terms, particle by particle (a particle's data read once for its stencil), at
  // the particle's place in its wall's cell order among its slot's terms (DualWall::
  // scatter_terms: a node then sums, for each cell around it, one contiguous stretch).
  //
  // Enhanced: p^alpha_S = sum_p m_p N_S v_p without the APIC term, so that an affine particle
  // field gives v^alpha = 0 (the standard grid already reproduces it, docs/enhanced.md). The
  // MUSL remap (with_force false) leaves C_p out as well: C_p^{n+1} is the gradient of the
  // remapped field, and remapping with the old C_p would hand each particle its own C_p back,
  // so a particle alone in a boundary cell would keep straining at a fixed rate that its
  // stress never corrects (docs/verification.md, particle against a wall). Remapping only its
  // spin (the skew part) mended the rolling disk but fed back through the wall constraint: a
  // block on a one-cell incline blew up, and the debris scene threw a particle out at 27 m/s
  // (docs/verification.md, rolling cylinder).
  //
  // A separable wall's touch test (layer_walls(), enhanced_assemble()) of the pair (particle at
  // x, slot k at `node`) goes with its terms: the particle lies over the node's facet (within
  // the node's share of it plus the particle's half-size, LayerTerms::window_squared) and its near
  // edge (LayerTerms::reach) is `gap` off the wall there; +infinity where it lies beyond that or
  // the node is not on the wall. A node's touch gap is the least of its pairs' (the node pass); a
  // corner node's, per facet, are taken in the node pass.
  auto touch_term = [](DualWall<D>& w, const LayerTerms& t, const Vec<D>& x, int node, int k,
                       std::size_t place) {
    double gap = std::numeric_limits<double>::infinity();
    if (const int wi = w.flat_wall_index(static_cast<std::size_t>(node)); wi >= 0) {
      const Vec<D> d = x - w.position[static_cast<std::size_t>(node)];
      const Vec<D>& normal = w.wall_normal[static_cast<std::size_t>(wi)];
      const double along = d.dot(normal);
      if ((d - along * normal).squaredNorm() <= t.window_squared) gap = along - t.reach;
    }
    w.touch_terms[static_cast<std::size_t>(k) * w.cell_members.size() + place] = gap;
  };
  tbb::parallel_for(
      tbb::blocked_range<std::size_t>(0, layer_list_.size(), 256), [&](const auto& r) {
        for (std::size_t i = r.begin(); i != r.end(); ++i) {
          if (i + 8 < r.end()) {
            // What this pass reads of the particle 8 on (a layer's particles lie apart in the
            // particle arrays: the floor benchmark's in pairs 20 apart, which the hardware
            // prefetcher does not follow): the pass 0.66-0.72 -> 0.56-0.60 ms a step there.
            const auto q = static_cast<std::size_t>(layer_list_[i + 8]);
            __builtin_prefetch(&P.layer_wall[q]);
            __builtin_prefetch(&P.mass[q]);
            for (const double* x : {P.velocity[q].data(), P.position[q].data()}) {
              __builtin_prefetch(x);
              __builtin_prefetch(x + D - 1);
            }
            if (apic) {
              __builtin_prefetch(P.affine[q].data());
              __builtin_prefetch(P.affine[q].data() + D * D - 1);
            }
          }
          const auto p = static_cast<std::size_t>(layer_list_[i]);
          DualWall<D>& w = dual_[P.layer_wall[p]];
          const bool affine = apic && !w.enhanced && with_force;
          const bool centroids = !with_force && !w.enhanced;
          const bool touch = with_force && w.spec->contact.separable;
          const LayerTerms& t = layer_terms_[i];
          const AlphaStencil<D>& st = layer_stencil_[i];
          const double m = P.mass[p];
          const auto place = static_cast<std::size_t>(layer_place_[i]);
          for (int k = 0; k < st.count; ++k) {
            auto& terms = w.scatter_term(k, place);
            const double N = st.N[k];
            Vec<D> momentum;
            if (affine) {
              momentum =
                  N * m * (P.velocity[p] + P.affine[p] * (w.position[st.node[k]] - P.position[p]));
            } else {
              momentum = N * m * P.velocity[p];
            }
            for (int a = 0; a < D; ++a) terms[1 + a] = momentum[a];
            if (with_force) {
              terms[0] = N * m;
              const Vec<D> force = t.vs * st.dN[k] + N * t.mb;
              for (int a = 0; a < D; ++a) terms[1 + D + a] = force[a];
              if (touch) touch_term(w, t, P.position[p], st.node[k], k, place);
            } else if (centroids) {
              const Vec<D> centroid = N * m * t.at;
              for (int a = 0; a < D; ++a) terms[1 + D + a] = centroid[a];
            }
          }
        }
      });
  // Each node sums its particles' terms cell by cell around it (in DualWall::node_cells' order),
  // in the layer list's order within a cell, a cell's terms of one slot side by side; nodes in
  // parallel: no two tasks write the same node.
  for (auto& w : dual_) {
    const bool touch = with_force && w.spec->contact.separable;
    const bool centroids = !with_force && !w.enhanced;
    // f(place, slot, terms) for each (particle, slot) pair of `node`: the particle's place in
    // the cell order, the node's slot in the particle's cell, and the pair's terms.
    auto for_each_pair = [&](int node, auto&& f) {
      const auto n = static_cast<std::size_t>(node);
      for (int e = w.node_cell_first[n]; e < w.node_cell_first[n + 1]; ++e) {
        const int code = w.node_cells[static_cast<std::size_t>(e)];
        const auto c = static_cast<std::size_t>(code / DualWall<D>::kCellNodes);
        const int k = code % DualWall<D>::kCellNodes;
        for (int place = w.cell_first[c]; place < w.cell_first[c + 1]; ++place) {
          f(place, k, w.scatter_term(k, static_cast<std::size_t>(place)));
        }
      }
    };
    tbb::parallel_for(
        tbb::blocked_range<std::size_t>(0, w.scatter_nodes.size(), 256), [&](const auto& r) {
          for (std::size_t j = r.begin(); j != r.end(); ++j) {
            const int node = w.scatter_nodes[j];
            const auto n = static_cast<std::size_t>(node);
            // A node on a separable wall takes the least of its pairs' touch gaps (touch_term()),
            // a corner node its facets' below.
            const int wi = touch ? w.wall_index_of_node[n] : -1;
            const bool plain = touch && w.flat_wall_index(n) >= 0;
            double mass = 0.0, momentum[D] = {}, second[D] = {};  // force, or the centroid's
            double gap = w.touch_gap[n];
            for_each_pair(node, [&](int place, int k, const auto& terms) {
              // The remap sums only what it stores: the momentum, and for Blending the
              // centroid's terms (its pairs' mass terms are the force scatter's, left over).
              if (with_force) mass += terms[0];
              for (int a = 0; a < D; ++a) momentum[a] += terms[1 + a];
              if (with_force || centroids) {
                for (int a = 0; a < D; ++a) second[a] += terms[1 + D + a];
              }
              if (plain) {
                const std::size_t at = static_cast<std::size_t>(k) * w.cell_members.size() +
                                       static_cast<std::size_t>(place);
                gap = std::min(gap, w.touch_terms[at]);
              }
            });
            for (int a = 0; a < D; ++a) w.momentum[n][a] = momentum[a];
            if (centroids) {
              for (int a = 0; a < D; ++a) w.centroid[n][a] = second[a];
            }
            if (!with_force) continue;
            w.mass[n] = mass;
            for (int a = 0; a < D; ++a) w.force[n][a] = second[a];
            if (plain) w.touch_gap[n] = gap;
            if (wi < 0 || plain) continue;
            const auto wu = static_cast<std::size_t>(wi);
            const int c0 = w.corner_first[wu], c1 = w.corner_first[wu + 1];
            const Vec<D>& at_node = w.position[n];
            for_each_pair(node, [&](int place, int /*slot*/, const auto& /*terms*/) {
              const auto i =
                  static_cast<std::size_t>(w.cell_members[static_cast<std::size_t>(place)]);
              const auto p = static_cast<std::size_t>(layer_list_[i]);
              const LayerTerms& t = layer_terms_[i];
              const Vec<D> d = P.position[p] - at_node;
              // At a concave corner the particle may lie over any of the node's facets.
              for (int c = c0; c < c1; ++c) {
                const Vec<D>& normal = w.corner_normals[static_cast<std::size_t>(c)];
                const double along = d.dot(normal);
                if ((d - along * normal).squaredNorm() <= t.window_squared) {
                  const double facet_gap = along - t.reach;
                  w.touch_gap[n] = std::min(w.touch_gap[n], facet_gap);
                  w.corner_gap[c] = std::min(w.corner_gap[c], facet_gap);
                }
              }
            });
          }
        });
  }
}

template <int D>
void Solver<D>::layer_update(double dt) {
  for (auto& w : dual_) {
    // Nodes no particle reaches hold nothing (layer_scatter() cleared them): velocities zero.
    if (w.enhanced) {
      // The velocities come from the coupled solve (layer_couple); keep p + dt f for it.
      for (const int n : w.scatter_nodes) w.momentum_new[n] = w.momentum[n] + dt * w.force[n];
      continue;
    }
    for (const int n : w.scatter_nodes) {
      node_velocities<D>(w.mass[n], w.momentum[n], w.force[n], dt, mass_threshold_, w.velocity[n],
                         w.velocity_new[n]);
    }
  }
}

namespace {

// A boundary node the wall condition acts on: on Gamma, carrying mass, and (separable walls) in
// contact. layer_walls() constrains these; layer_affine() leaves them out of the C_p fit.
template <int D>
bool held_by_wall(const DualWall<D>& w, int node, double mass_threshold) {
  if (w.wall_index_of_node[node] < 0 || w.mass[node] <= mass_threshold) return false;
  // Separable: no contact until the material touches the wall at this node.
  return !(w.spec->contact.separable && w.touch_gap[node] > 0.0);
}

}  // namespace

// Wall conditions on Gamma in each node's own frame (normal into the material).
template <int D>
void Solver<D>::layer_walls(std::vector<Vec<D>> DualWall<D>::*velocity, bool record) {
  for (auto& w : dual_) {
    if (w.enhanced) continue;  // multiplier constraints in enhanced_solve()
    std::vector<Vec<D>>& v = w.*velocity;
    for (std::size_t i = 0; i < w.wall_nodes.size(); ++i) {
      const int n = w.wall_nodes[i];
      if (!held_by_wall(w, n, mass_threshold_)) continue;
      const int part = w.wall_node_part[i];
      const Vec<D> before = v[n];
      const int c0 = w.corner_first[i], c1 = w.corner_first[i + 1];
      // A separable corner holds the node against the facets its material touches (a foot
      // node lets the flow on the terrain slide on until it reaches the barrier).
      // Each facet takes its own part's condition (a barrier's foot: the terrain's friction and
      // the barrier's, weighted by how hard the node presses on each: corner_condition()).
      std::array<Vec<D>, kMaxCornerNormals> normals;
      std::array<int, kMaxCornerNormals> facet;
      std::array<const WallCondition*, kMaxCornerNormals> conditions;
      int count = 0;
      for (int c = c0; c < c1; ++c) {
        if (w.spec->contact.separable && w.corner_gap[c] > 0.0) continue;
        normals[count] = w.corner_normals[c];
        conditions[count] = &w.spec->condition(w.corner_part[c]);
        facet[count++] = c;
      }
      std::array<double, kMaxCornerNormals> lambda{};
      if (c1 == c0) {
        v[n] = std::visit(
            [&](const auto& condition) {
              return constrain_velocity<D>(condition, w.spec->contact.separable, w.wall_normal[i],
                                           before);
            },
            w.spec->condition(part));
      } else if constexpr (D > 1) {  // a 1D wall is a point: no corners
        v[n] =
            constrain_velocity_in_corner_of_parts<D>(conditions.data(), w.spec->contact.separable,
                                                     normals.data(), count, before, lambda.data());
      }
      if (!record) continue;
      const Vec<D> change = v[n] - before;
      if (c1 == c0) {
        wall_impulse_[w.impulse_offset + part] += pad3<D>(w.mass[n] * change);
        continue;
      }
      // A corner shares its force among its facets' parts (a barrier's foot on the terrain):
      // each takes its facet's normal push and friction in proportion to it.
      Vec<D> normal = Vec<D>::Zero();
      double total = 0.0;
      for (int c = 0; c < count; ++c) {
        normal += lambda[c] * normals[c];
        total += std::abs(lambda[c]);
      }
      const Vec<D> friction = change - normal;
      for (int c = 0; c < count; ++c) {
        const double share = total > 0.0 ? std::abs(lambda[c]) / total : 1.0 / count;
        wall_impulse_[w.impulse_offset + w.corner_part[facet[c]]] +=
            pad3<D>(w.mass[n] * (lambda[c] * normals[c] + share * friction));
      }
    }
  }
}

// Forms this step's Schur complement of the Phi coupling (layer_couple) and factorises it,
// analysing its pattern again only if it is new (keeping the ordering in hand if `order` says
// the multipliers are the factorised ones and it still fits, SparseLdlt::analyzePattern());
// keeps it as the matrix the factorisation is of (a checkpoint saves it). False, with the fault
// set, if it cannot be factorised.
template <int D>
bool Solver<D>::factorise_schur(DualWall<D>& w, bool mortar, SparseLdlt::Order order) {
  // S = B^T B with B = [M_A^-1/2 R^A; M_alpha^-1/2 R^alpha; shift^1/2 I] (the second block for
  // mortar only): sparse products of B form both terms and the shift.
  const Eigen::Index ng = w.grid_active.rows(), k = w.grid_active.cols();
  const Eigen::Index nl = mortar ? w.boundary_active.rows() : 0;
  // Each row's M^-1/2 once (a row is in many columns).
  const Eigen::VectorXd root_grid = w.inv_grid_mass.cwiseSqrt();
  const Eigen::VectorXd root_layer =
      mortar ? Eigen::VectorXd(w.inv_layer_mass.cwiseSqrt()) : Eigen::VectorXd();
  // B's compressed columns written in order (each column's rows increase: R^A's, R^alpha's
  // below them, the shift's last).
  Eigen::SparseMatrix<double> B(ng + nl + k, k);
  B.resizeNonZeros(w.grid_active.nonZeros() + (mortar ? w.boundary_active.nonZeros() : 0) + k);
  {
    int* outer = B.outerIndexPtr();
    int* inner = B.innerIndexPtr();
    double* value = B.valuePtr();
    const double root_shift = std::sqrt(w.schur_shift);
    int at = 0;
    outer[0] = 0;
    for (Eigen::Index c = 0; c < k; ++c) {
      for (Eigen::SparseMatrix<double>::InnerIterator it(w.grid_active, c); it; ++it) {
        inner[at] = static_cast<int>(it.row());
        value[at++] = it.value() * root_grid[it.row()];
      }
      if (mortar) {
        for (Eigen::SparseMatrix<double>::InnerIterator it(w.boundary_active, c); it; ++it) {
          inner[at] = static_cast<int>(ng + it.row());
          value[at++] = it.value() * root_layer[it.row()];
        }
      }
      inner[at] = static_cast<int>(ng + nl + c);
      value[at++] = root_shift;
      outer[c + 1] = at;
    }
  }
  // The factorisation reads S's lower triangle only, formed in two parts on the two cores: the
  // first `split` columns whole (B^T times those columns of B), the others from their rows at
  // or below `split` only (the product of the last columns of B with themselves), which leaves
  // out the upper block nobody reads. Each entry is the same sum in the same order as in Eigen's
  // whole product B^T B (bit for bit); the split, about 0.38 k, gives both parts about the same
  // work (k x split entries against (k - split)^2). The other core is otherwise idle here in a
  // flow whose layer is most of its work (the debris scene's coupling runs beside a short
  // gather).
  const Eigen::Index split = static_cast<Eigen::Index>(0.38 * static_cast<double>(k));
  const Eigen::Index rest = k - split;
  Eigen::SparseMatrix<double> left, right;
  tbb::parallel_invoke(
      [&] {
        const Eigen::SparseMatrix<double> bt = B.transpose();
        left = bt * B.leftCols(split);
      },
      [&] {
        const Eigen::SparseMatrix<double> bt = B.rightCols(rest).transpose();
        right = bt * B.rightCols(rest);
      });
  Eigen::SparseMatrix<double> S(k, k);
  S.resizeNonZeros(left.nonZeros() + right.nonZeros());
  {
    const auto offset = static_cast<int>(left.nonZeros());
    std::copy_n(left.outerIndexPtr(), split + 1, S.outerIndexPtr());
    std::transform(right.outerIndexPtr() + 1, right.outerIndexPtr() + rest + 1,
                   S.outerIndexPtr() + split + 1, [offset](int at) { return at + offset; });
    std::copy_n(left.innerIndexPtr(), left.nonZeros(), S.innerIndexPtr());
    std::transform(right.innerIndexPtr(), right.innerIndexPtr() + right.nonZeros(),
                   S.innerIndexPtr() + offset,
                   [split = static_cast<int>(split)](int row) { return row + split; });
    std::copy_n(left.valuePtr(), left.nonZeros(), S.valuePtr());
    std::copy_n(right.valuePtr(), right.nonZeros(), S.valuePtr() + offset);
  }
  bool refining = false;  // not reusable: layer_couple() decided to factorise
  if (!factorise_or_reuse(*w.schur, S, w.schur_base, w.pattern_hash, w.schur_factored, false,
                          refining, w.factorizations, order)) {
    fault_ = "dual wall \"" + w.spec->name + "\": the Phi coupling matrix does not factorise";
  }
  return w.schur_factored;
}

// Phi: R^A^T v^A = R^alpha^T v^alpha, componentwise. Only nodes above the coupling mass
// threshold take part. Only multipliers whose own boundary node carries mass and whose R^A
// column touches such a standard-grid node constrain anything; the
// kept rows of each column are rescaled to sum to the integral of S_mu again, which keeps the
// interface impulses equal and opposite (momentum exact) and leaves uniform motion untouched.
template <int D>
void Solver<D>::layer_couple(bool remapped) {
  for (auto& w : dual_) {
    if (w.layer_particles == 0) continue;  // nothing in the layer: the grids do not interact
    if (w.enhanced) {
      if (remapped) {
        const PartTimer<D> timer(w, w.solve_seconds);
        enhanced_solve(w, grid.velocity, w.momentum, w.velocity, true, false);
      } else {
        {
          const PartTimer<D> timer(w, w.assembly_seconds);
          enhanced_assemble(w);
        }
        const PartTimer<D> timer(w, w.solve_seconds);
        // The coupled v^n only for FLIP's increment (v^{n+1} - v^n): PIC and APIC gather v^{n+1},
        // and MUSL's remap solves the old velocities anew (as the Blending walls below).
        if (flip_increment()) {
          enhanced_solve(w, grid.velocity, w.momentum, w.velocity, false, false);
        }
        enhanced_solve(w, grid.velocity_new, w.momentum_new, w.velocity_new, true, true);
      }
      continue;
    }
    const bool mortar = w.spec->method == CouplingMethod::mortar;
    if (!remapped) {
      // Assemble the active coupling and its Schur complement once per step; the MUSL remap
      // reuses it (the masses do not change).
      const PartTimer<D> timer(w, w.assembly_seconds);
      // The multipliers one of whose Phi nodes carries mass, in increasing order (those nodes
      // are among the ones the layer's particles reach).
      std::vector<int>& carried = w.carried_multipliers;
      carried.clear();
      for (const int n : w.scatter_nodes) {
        const int mu = w.multiplier_of_node[static_cast<std::size_t>(n)];
        if (mu >= 0 && w.mass[n] > coupling_threshold_) carried.push_back(mu);
      }
      std::sort(carried.begin(), carried.end());
      carried.erase(std::unique(carried.begin(), carried.end()), carried.end());
      // The active coupling is fixed by which multipliers are carried and which nodes of their
      // supports carry mass above the threshold (the entries are R^A's and R^alpha's, rescaled
      // by sums over those nodes): where both are as when the coupling in hand was assembled
      // (a resting body: its layer's masses change, not which nodes hold them), the rows,
      // columns and entries would come out the same, and only the masses below are new.
      const bool unchanged = w.support_recorded && carried == w.recorded_carried &&
                             support_unchanged(w, grid.mass, coupling_threshold_);
      if (unchanged) {
        ++w.kept_assemblies;
      } else {
        w.support_recorded = false;
        for (const int node : w.layer_rows) w.layer_row_of[node] = -1;
        // The step before's rows and entries are kept aside (swapped, not copied) to be compared
        // with this step's below.
        std::swap(w.grid_rows, w.kept_grid_rows);
        std::swap(w.layer_rows, w.kept_layer_rows);
        std::swap(w.grid_entries, w.kept_grid_entries);
        std::swap(w.layer_entries, w.kept_layer_entries);
        w.active_multipliers.clear();
        w.grid_rows.clear();
        w.layer_rows.clear();
        auto compact = [](std::vector<int>& row_of, std::vector<int>& rows, int node) {
          int& row = row_of[static_cast<std::size_t>(node)];
          if (row < 0) {
            row = static_cast<int>(rows.size());
            rows.push_back(node);
          }
          return row;
        };
        std::vector<Eigen::Triplet<double>>& ga = w.grid_entries;
        std::vector<Eigen::Triplet<double>>& ba = w.layer_entries;
        ga.clear();
        ba.clear();
        for (const int mu : carried) {
          double grid_sum = 0.0, boundary_sum = 0.0;
          for (Eigen::SparseMatrix<double>::InnerIterator it(w.grid_coupling, mu); it; ++it) {
            if (grid.mass[it.row()] > coupling_threshold_) grid_sum += it.value();
          }
          for (Eigen::SparseMatrix<double>::InnerIterator it(w.boundary_coupling, mu); it; ++it) {
            if (w.mass[it.row()] > coupling_threshold_) boundary_sum += it.value();
          }
          if (grid_sum <= 1e-12 * w.multiplier_integral[mu] || boundary_sum <= 0.0) continue;
          const int col = static_cast<int>(w.active_multipliers.size());
          w.active_multipliers.push_back(mu);
          const double gs = w.multiplier_integral[mu] / grid_sum;
          const double bs = w.multiplier_integral[mu] / boundary_sum;
          for (Eigen::SparseMatrix<double>::InnerIterator it(w.grid_coupling, mu); it; ++it) {
            const int node = static_cast<int>(it.row());
            if (grid.mass[node] > coupling_threshold_) {
              ga.emplace_back(node_row(w.grid_row_of, w.grid_rows, node), col, gs * it.value());
            }
          }
          for (Eigen::SparseMatrix<double>::InnerIterator it(w.boundary_coupling, mu); it; ++it) {
            const int node = static_cast<int>(it.row());
            if (w.mass[node] > coupling_threshold_) {
              ba.emplace_back(compact(w.layer_row_of, w.layer_rows, node), col, bs * it.value());
            }
          }
        }
      }
      const auto k = static_cast<Eigen::Index>(w.active_multipliers.size());
      if (k == 0) continue;
      if (!unchanged) {
        // The same rows and entries as the step before's (the same nodes above the coupling
        // threshold: a resting body), which R^A and R^alpha hold already (the step before's were
        // assigned to them unless it had no multiplier, and then it had no entry either): only
        // the masses below change. The supports are then recorded, so that the next steps can
        // tell the same without assembling (`unchanged`).
        auto same = [](const std::vector<Eigen::Triplet<double>>& a,
                       const std::vector<Eigen::Triplet<double>>& b) {
          return std::ranges::equal(a, b, [](const auto& x, const auto& y) {
            return x.row() == y.row() && x.col() == y.col() && x.value() == y.value();
          });
        };
        const bool same_rows = w.grid_rows == w.kept_grid_rows && w.layer_rows == w.kept_layer_rows;
        if (!same_rows) ++w.reshapes;
        if (!(same_rows && same(w.grid_entries, w.kept_grid_entries) &&
              same(w.layer_entries, w.kept_layer_entries))) {
          w.transposes_current = false;
          assign_by_columns(w.grid_active, static_cast<Eigen::Index>(w.grid_rows.size()), k,
                            w.grid_entries, w.assembly_work);
          assign_by_columns(w.boundary_active, static_cast<Eigen::Index>(w.layer_rows.size()), k,
                            w.layer_entries, w.assembly_work);
        } else {
          record_support(w, grid.mass, coupling_threshold_);
        }
      }
      // S = R^A^T M_A^-1 R^A (+ R^alpha^T M_alpha^-1 R^alpha for mortar) + shift I; every kept
      // row is above the coupling threshold, so its mass is positive. More multipliers than the
      // active nodes can satisfy makes S singular (the inf-sup problem of DESIGN.md): a relative
      // 1e-10 diagonal shift keeps the factorisation defined and leaves well-posed systems
      // unchanged to round-off.
      w.inv_grid_mass.resize(static_cast<Eigen::Index>(w.grid_rows.size()));
      for (std::size_t r = 0; r < w.grid_rows.size(); ++r) {
        w.inv_grid_mass[static_cast<Eigen::Index>(r)] = 1.0 / grid.mass[w.grid_rows[r]];
      }
      w.inv_layer_mass.resize(mortar ? static_cast<Eigen::Index>(w.layer_rows.size()) : 0);
      for (Eigen::Index r = 0; r < w.inv_layer_mass.size(); ++r) {
        w.inv_layer_mass[r] = 1.0 / w.mass[w.layer_rows[static_cast<std::size_t>(r)]];
      }
      Eigen::VectorXd& diagonal = w.schur_diagonal;
      diagonal.setZero(k);
      add_weighted_column_squares(w.grid_active, w.inv_grid_mass, diagonal);
      if (mortar) add_weighted_column_squares(w.boundary_active, w.inv_layer_mass, diagonal);
      w.schur_shift = 1e-10 * diagonal.maxCoeff();
      // While the same multipliers are active, the factorisation in hand (an earlier step's S)
      // preconditions conjugate gradients on this step's, the products taken with the factors
      // R^A, M_A (S itself is not formed): layer particles move little per step, so S changes
      // little, and nodes that cross the coupling threshold (new rows of R^A, R^alpha, a new
      // pattern of S) change it by a term of low rank, which CG removes in a few passes (it
      // must be SPD: S always is). Other multipliers, or CG that runs out of passes, form and
      // factorise S. In a flow whose layer masses change fast (the debris scene: light nodes at
      // the front weigh 1/m in S) CG can fail time after time, each failure costing passes
      // before the factorisation it ends in: a failure right after another (against a fresh
      // factorisation) makes the next `refine_backoff` steps (1, 2, 4 ... 64, reset by a
      // success) factorise without trying.
      std::size_t structure = static_cast<std::size_t>(k);  // the active multipliers' hash
      for (const int mu : w.active_multipliers) {
        structure = structure * 1000003U + static_cast<std::size_t>(mu);
      }
      const bool waiting = w.refine_wait > 0;
      if (waiting) --w.refine_wait;
      const bool same =
          w.schur_factored && structure == w.factored_structure && w.schur->rows() == k;
      w.schur_refine = same && !waiting;
      if (!w.schur_refine) {
        w.factored_structure = structure;
        if (!factorise_schur(w, mortar,
                             same ? SparseLdlt::Order::kept : SparseLdlt::Order::fresh)) {
          continue;
        }
      }
    }
    if (w.active_multipliers.empty() || !w.schur_factored) continue;

    // Apply to the new velocities (and to the old ones, which FLIP differences against), or to
    // the remapped velocities of MUSL; all D components in one solve. The blocks are the wall's
    // scratch (sized once per active set).
    using Block = NodeBlock<D>;
    auto solve = [&](NodeField<Vec<D>>& va, std::vector<Vec<D>>& valpha, int kind) {
      const auto ng = static_cast<Eigen::Index>(w.grid_rows.size());
      const auto nl = static_cast<Eigen::Index>(w.layer_rows.size());
      const Eigen::Index k = w.grid_active.cols();
      Block& a = w.grid_block;
      Block& b = w.layer_block;
      a.resize(ng, D);
      b.resize(nl, D);
      w.gap.resize(k, D);
      w.lambda.resize(k, D);
      w.residual.resize(k, D);
      w.update.resize(k, D);
      if (!w.transposes_current) {
        transpose_into(w.grid_active, w.grid_active_t);
        transpose_into(w.boundary_active, w.boundary_active_t);
        w.transposes_current = true;
      }
      // The products with R^A and R^alpha on both cores, by rows of the result, each row's sum
      // over its entries in the order Eigen's products take them (the same values to the bit).
      // Rows r of (R^A x, R^alpha x), x a block of k rows, to out(r, which), which 0 for R^A
      // and 1 for R^alpha (rows of R^alpha only where `both`).
      auto by_rows = [&](const Block& x, bool both, auto&& out) {
        const Eigen::Index rows = ng + (both ? nl : 0);
        tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, rows, 512), [&](const auto& range) {
          for (Eigen::Index i = range.begin(); i != range.end(); ++i) {
            const bool grid_row = i < ng;
            const Eigen::Index r = grid_row ? i : i - ng;
            double sum[D] = {};
            for (Eigen::SparseMatrix<double>::InnerIterator it(
                     grid_row ? w.grid_active_t : w.boundary_active_t, r);
                 it; ++it) {
              for (int c = 0; c < D; ++c) sum[c] += it.value() * x(it.row(), c);
            }
            out(r, grid_row ? 0 : 1, sum);
          }
        });
      };
      // Columns j of (R^A^T u, R^alpha^T v) to out(j, sums of R^A, sums of R^alpha).
      auto by_columns = [&](const Block& u, const Block& v, bool both, auto&& out) {
        tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, k, 256), [&](const auto& range) {
          for (Eigen::Index j = range.begin(); j != range.end(); ++j) {
            double sum[D] = {}, more[D] = {};
            for (Eigen::SparseMatrix<double>::InnerIterator it(w.grid_active, j); it; ++it) {
              for (int c = 0; c < D; ++c) sum[c] += it.value() * u(it.row(), c);
            }
            if (both) {
              for (Eigen::SparseMatrix<double>::InnerIterator it(w.boundary_active, j); it; ++it) {
                for (int c = 0; c < D; ++c) more[c] += it.value() * v(it.row(), c);
              }
            }
            out(j, sum, more);
          }
        });
      };
      tbb::parallel_for(tbb::blocked_range<Eigen::Index>(0, ng + nl, 1024), [&](const auto& range) {
        for (Eigen::Index i = range.begin(); i != range.end(); ++i) {
          if (i < ng) {
            a.row(i) = va[w.grid_rows[i]].transpose();
          } else {
            b.row(i - ng) = valpha[w.layer_rows[i - ng]].transpose();
          }
        }
      });
      // gap = R^A^T v^A - R^alpha^T v^alpha; the larger term's size is the scale refine()
      // measures the constraint's residual against.
      by_columns(a, b, true, [&](Eigen::Index j, const double* grid_sum, const double* layer_sum) {
        for (int c = 0; c < D; ++c) {
          w.gap(j, c) = grid_sum[c];
          w.residual(j, c) = layer_sum[c];
        }
      });
      const double scale = std::max(w.gap.norm(), w.residual.norm());
      w.gap -= w.residual;
      // The grids agree at Phi already, to the coupling's tolerance of the interface terms
      // (material moving as a whole, or in a linear field both grids carry exactly): no
      // impulse, no solve.
      const double tolerance = scene_.coupling_tolerance;
      if (w.gap.norm() <= tolerance * scale) return;
      // The D components side by side: each entry of the factor is read once for all of them.
      // Against an earlier step's factor, which only preconditions CG, L's dropped copy
      // (SparseLdlt::dropped(): its entries that matter, in single precision); a factor of this
      // step's S solves in full.
      const LdltValues aged = w.schur->aged_values(LdltValues::single);
      auto factor_solve = [&](const Block& rhs, Block& x) {
        ldlt_solve(*w.schur, rhs, x, w.solve_work, w.schur_refine ? aged : LdltValues::full);
      };
      // A new factorisation's dropped copy preconditions well where it solves this step's S
      // nearly as well as all of L (check_dropped(), sparse_pattern.hpp); otherwise CG reads
      // all of L in single precision until the next factorisation.
      auto check = [&] {
        check_dropped(*w.schur, w.gap, w.lambda, w.update, w.solve_work, EuclideanNorm{});
      };
      if (w.schur_refine && aged == LdltValues::single) w.schur->round_to_single();
      // CG against an aged factorisation starts from the multipliers the last solve of this
      // kind found where they are for the same multipliers (a layer in steady contact: its
      // impulses change little from step to step), elsewhere from the factor's answer; CG that
      // fails from the last multipliers tries again from the factor's answer before S is
      // factorised (a flow's front changes its impulses faster than the factor ages: started
      // warm without the second try, the main job factorised 10,428 times against 9,383). The
      // mortar floor, 300 steps on two threads: solves 0.62 -> 0.53 s under MLS-MPM, 1.03 ->
      // 0.86 s under MUSL, 6 factorisations against 7; the main job 9,058 factorisations and
      // 59,666 passes against 9,383 and 44,837, its steps 244.8 -> 234.8 s (docs/performance.md,
      // 2026-12-07, late night). Where the solve of the kind before the last was for the same
      // multipliers too, the start is extrapolated along the two, 2 lambda_last -
      // lambda_earlier (impulses that change smoothly with time change by about as much from
      // one step to the next): the floor's CG passes over 300 steps 951 -> 712 under MLS-MPM
      // and 1,743 -> 1,378 under MUSL, the same factorisations (docs/performance.md,
      // 2026-12-08).
      const auto slot = static_cast<std::size_t>(kind);
      const bool warm = w.schur_refine && w.last_structure[slot] == w.factored_structure &&
                        w.last_lambda[slot].rows() == k;
      if (warm && w.earlier_structure[slot] == w.factored_structure &&
          w.earlier_lambda[slot].rows() == k) {
        w.lambda = 2.0 * w.last_lambda[slot] - w.earlier_lambda[slot];
      } else if (warm) {
        w.lambda = w.last_lambda[slot];
      } else {
        factor_solve(w.gap, w.lambda);
      }
      if (!w.schur_refine) check();
      if (w.schur_refine) {
        // CG preconditioned by the factorisation in hand (conjugate_refine(): to an error below
        // the coupling's tolerance of x, or a residual below it of the interface terms);
        // unconverged (the masses moved too far from the factorised step's), factorise this
        // step's S. The products run through a and b, free by now.
        // S x = R^A^T (M_A^-1 R^A x) (+ R^alpha^T (M_alpha^-1 R^alpha x)) + shift x.
        auto apply = [&](const Block& x, Block& y) {
          y.resize(k, D);  // (sized once: the caller's scratch)
          by_rows(x, mortar, [&](Eigen::Index r, int which, const double* sum) {
            for (int c = 0; c < D; ++c) {
              if (which == 0) {
                a(r, c) = sum[c] * w.inv_grid_mass[r];
              } else {
                b(r, c) = sum[c] * w.inv_layer_mass[r];
              }
            }
          });
          by_columns(a, b, mortar,
                     [&](Eigen::Index j, const double* grid_sum, const double* layer_sum) {
                       for (int c = 0; c < D; ++c) {
                         y(j, c) = (grid_sum[c] + layer_sum[c]) + w.schur_shift * x(j, c);
                       }
                     });
        };
        const auto cg = [&] {
          return conjugate_refine(w.gap, w.lambda, apply, factor_solve, w.refinements, w.residual,
                                  w.update, w.search, w.search_product, scale, tolerance);
        };
        bool converged = cg();  // sparse_pattern.hpp
        if (!converged && warm) {
          factor_solve(w.gap, w.lambda);
          converged = cg();
        }
        if (converged) {
          w.refine_backoff = 0;
        } else {
          w.refine_wait = w.refine_backoff;
          w.refine_backoff = std::clamp(2 * w.refine_backoff, 1, 64);
          if (!factorise_schur(w, mortar, SparseLdlt::Order::kept)) return;
          w.schur_refine = false;
          factor_solve(w.gap, w.lambda);
          check();
        }
      }
      std::swap(w.earlier_lambda[slot], w.last_lambda[slot]);  // (the buffers reused)
      w.earlier_structure[slot] = w.last_structure[slot];
      w.last_lambda[slot] = w.lambda;
      w.last_structure[slot] = w.factored_structure;
      // The impulses: v^A -= M_A^-1 R^A lambda, v^alpha += M_alpha^-1 R^alpha lambda (mortar).
      by_rows(w.lambda, mortar, [&](Eigen::Index r, int which, const double* sum) {
        const Vec<D> impulse = Eigen::Map<const Vec<D>>(sum);
        if (which == 0) {
          const int n = w.grid_rows[static_cast<std::size_t>(r)];
          va[n] -= impulse / grid.mass[n];
        } else {
          const int n = w.layer_rows[static_cast<std::size_t>(r)];
          valpha[n] += impulse / w.mass[n];
        }
      });
    };
    const PartTimer<D> timer(w, w.solve_seconds);
    if (remapped) {
      solve(grid.velocity, w.velocity, 2);
    } else {
      solve(grid.velocity_new, w.velocity_new, 0);
      // Only FLIP reads the old velocities again (v^{n+1} - v^n); PIC and APIC gather v^{n+1}.
      if (flip_increment()) {
        solve(grid.velocity, w.velocity, 1);
      }
    }
  }
}

namespace {

// C_p of a boundary-grid particle under MUSL and APIC (docs/verification.md, rolling cylinder).
// The remap leaves the old C_p out (layer_scatter: with it, a particle alone in a boundary cell
// got its own C_p back and kept straining at a rate its stress never corrected), so a node's
// remapped velocity is the velocity of its particles at their mass centroid, not at the node.
// In a one-cell layer the top nodes see particles from below only, and the gradient of the
// remapped field (C_p before) shrank a rotation up to 4 times there: the layer bled a rolling
// disk's spin every step (mortar 10.5% on the rolling cylinder). Here C_p is the least-squares
// affine fit of the remapped velocities at the centroids (weights N_i), which gives back an
// affine particle field exactly. Two guards:
// - Gamma nodes the wall holds are left out: their velocity is the wall's condition, not the
//   material's, and a friction-sheared block would start to spin on them (the 2D incline sweep:
//   |v_n| up to 1.2% of gT instead of 0.4%).
// - The fit is scaled down where its affine kinetic energy, m_p sum_i N_i |C_p (x_i - x_p)|^2,
//   exceeds the spread of v^{n+1} the particle was gathered from, m_p sum_i N_i |v_i - v_p|^2.
//   Summed over particles the transfer then holds at most the grid's kinetic energy: it cannot
//   create energy however the centroids lie.
// Where the free nodes' centroids do not span the space (a lone particle, a cell held along
// its whole wall side), the gradient of the remapped field, `gradient`, stays.
template <int D>
Mat<D> layer_affine(const DualWall<D>& w, const AlphaStencil<D>& st, const Mat<D>& gradient,
                    const Vec<D>& velocity, double mass_threshold) {
  std::array<double, 6> weight{};
  double total = 0.0;
  Vec<D> x_bar = Vec<D>::Zero(), v_bar = Vec<D>::Zero(), at = Vec<D>::Zero();
  for (int k = 0; k < st.count; ++k) {
    const int n = st.node[k];
    at += st.N[k] * w.position[n];
    if (w.mass[n] <= mass_threshold || held_by_wall(w, n, mass_threshold)) continue;
    weight[k] = st.N[k];
    total += weight[k];
    x_bar += weight[k] * w.centroid[n];
    v_bar += weight[k] * w.velocity[n];
  }
  if (!(total > 0.0)) return gradient;
  x_bar /= total;
  v_bar /= total;
  Mat<D> B = Mat<D>::Zero(), M = Mat<D>::Zero();
  double spread = 0.0;
  for (int k = 0; k < st.count; ++k) {
    if (weight[k] == 0.0) continue;
    const int n = st.node[k];
    const Vec<D> d = w.centroid[n] - x_bar;
    B += weight[k] * (w.velocity[n] - v_bar) * d.transpose();
    M += weight[k] * d * d.transpose();
    spread += weight[k] * (w.position[n] - at).squaredNorm();
  }
  // Centroids on a line (or a point) leave a direction unfitted: the smallest eigenvalue of
  // their second moment against the nodes' own (1e-3: centroids spanning ~3% of the cell).
  // lambda_min(M) > t exactly when M - t I is positive definite, which Sylvester's criterion
  // decides from its leading principal minors (no eigenvalues: the iterative solver was 3% of
  // the debris scene's time, and the closed form still took an acos and two cosines a particle).
  // A NaN fails every comparison, so it too keeps the gradient.
  Mat<D> shifted = M;
  shifted.diagonal().array() -= 1e-3 * spread / (total * D);
  bool spans = shifted(0, 0) > 0.0;
  if constexpr (D >= 2) {
    spans = spans && shifted.template topLeftCorner<2, 2>().determinant() > 0.0;
  }
  if constexpr (D == 3) spans = spans && shifted.determinant() > 0.0;
  if (!spans) return gradient;
  Mat<D> C = B * M.inverse();
  double affine = 0.0, available = 0.0;
  for (int k = 0; k < st.count; ++k) {
    const int n = st.node[k];
    affine += st.N[k] * (C * (w.position[n] - at)).squaredNorm();
    available += st.N[k] * (w.velocity_new[n] - velocity).squaredNorm();
  }
  if (affine > available) C *= std::sqrt(available / affine);
  return C;
}

}  // namespace

namespace {

// sum_k v_k grad N_k^T over a boundary-grid stencil, summed in plain scalars (Eigen 3-vector
// temporaries cost a store-forwarding stall per node: docs/performance.md).
template <int D>
Mat<D> stencil_gradient(const std::vector<Vec<D>>& v, const AlphaStencil<D>& st) {
  double sum[D][D] = {};
  for (int k = 0; k < st.count; ++k) {
    const double* vk = v[st.node[k]].data();
    for (int a = 0; a < D; ++a) {
      for (int b = 0; b < D; ++b) sum[a][b] += vk[a] * st.dN[k][b];
    }
  }
  Mat<D> L;
  for (int a = 0; a < D; ++a) {
    for (int b = 0; b < D; ++b) L(a, b) = sum[a][b];
  }
  return L;
}

}  // namespace

// Boundary-grid particles: new velocity (PIC/FLIP blend or APIC with C_p = grad v, exact for the
// linear alpha basis), displacement, and for USL the velocity gradient.
template <int D>
void Solver<D>::layer_gather(double dt) {
  auto& P = particles;
  if (dual_.empty()) return;
  const bool apic = scene_.transfer == Transfer::apic;
  const bool usl = scene_.update != UpdateScheme::musl;  // USL or MLS
  const double alpha = scene_.flip_blend;
  // Each particle reads the nodes and writes only itself: in parallel.
  auto gather_one = [&](std::size_t i) {
    const auto p = static_cast<std::size_t>(layer_list_[i]);
    const DualWall<D>& w = dual_[P.layer_wall[p]];
    const AlphaStencil<D>& st = layer_stencil_[i];
    // USL and MLS take a Blending layer particle's strain rate (and APIC's C_p) from v^{n+1}
    // here. A node at or below the coupling threshold is left out of the coupling, and its
    // v^{n+1} is a sliver of mass's own acceleration (of order |grad N| / N), not the
    // material's: such nodes are treated as moving with the particle, as gather() treats the
    // standard grid's nodes below the mass threshold (the value renormalised over the others, the
    // gradient sum (v_k - v_p) grad N_k over them). Without it a block sliding on an inclined
    // mortar wall diverged within 0.2 s at every angle (docs/blending.md, "Update scheme").
    // MUSL takes both from the remapped field (layer_gather_gradient()) and keeps every node.
    const bool skip_light = usl && !w.enhanced;
    double sum[D] = {}, change[D] = {}, grad_sum[D] = {}, moment[D][D] = {}, weight = 0.0;
    for (int k = 0; k < st.count; ++k) {
      if (skip_light && w.mass[st.node[k]] <= coupling_threshold_) continue;
      const double* v_new = w.velocity_new[st.node[k]].data();
      const double* v_old = w.velocity[st.node[k]].data();
      weight += st.N[k];
      for (int a = 0; a < D; ++a) {
        sum[a] += st.N[k] * v_new[a];
        change[a] += st.N[k] * (v_new[a] - v_old[a]);
      }
      if (!skip_light) continue;
      for (int a = 0; a < D; ++a) {
        grad_sum[a] += st.dN[k][a];
        for (int b = 0; b < D; ++b) moment[a][b] += v_new[a] * st.dN[k][b];
      }
    }
    Vec<D> value = Eigen::Map<const Vec<D>>(sum);
    Vec<D> increment = Eigen::Map<const Vec<D>>(change);
    Mat<D> L = Mat<D>::Zero();
    if (skip_light) {
      if (weight > 0.0) {
        value /= weight;
        increment /= weight;
        for (int a = 0; a < D; ++a) {
          for (int b = 0; b < D; ++b) L(a, b) = moment[a][b] - value[a] * grad_sum[b];
        }
      }
    } else if (usl) {
      L = stencil_gradient(w.velocity_new, st);
    }
    if (w.enhanced) {
      // The enhancement adds to what gather() took from the standard grid.
      if (apic) {
        // C_p stays the standard grid's: the enhancement is the wall's sharp layer, which the
        // standard grid's affine transfer cannot carry (its scatter leaves C_p out too).
        P.velocity[p] += value;
      } else {
        P.velocity[p] += alpha * increment + (1.0 - alpha) * value;
      }
      if (!P.displacement.empty()) P.displacement[p] += dt * value;
      if (usl) layer_gradient_[i] += L;  // the standard grid's is there (gather())
      return;
    }
    if (apic) {
      P.velocity[p] = value;
      if (usl) P.affine[p] = L;  // MUSL: from the remapped field, layer_gather_gradient()
    } else {
      P.velocity[p] = alpha * (P.velocity[p] + increment) + (1.0 - alpha) * value;
    }
    if (!P.displacement.empty()) P.displacement[p] = dt * value;
    if (usl) layer_gradient_[i] = L;
  };
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, layer_list_.size(), 256),
                    [&](const auto& r) {
                      for (std::size_t i = r.begin(); i != r.end(); ++i) gather_one(i);
                    });
}

template <int D>
void Solver<D>::layer_remap() {
  layer_scatter(false);
  for (auto& w : dual_) {
    if (w.enhanced) continue;              // solved with the standard grid in layer_couple(true)
    for (const int n : w.scatter_nodes) {  // the others hold nothing (layer_scatter())
      const bool filled = w.mass[n] > mass_threshold_;
      w.velocity[n] = filled ? Vec<D>(w.momentum[n] / w.mass[n]) : Vec<D>::Zero();
      w.centroid[n] = filled ? Vec<D>(w.centroid[n] / w.mass[n]) : w.position[n];
    }
  }
  layer_walls(&DualWall<D>::velocity, false);
}

template <int D>
void Solver<D>::layer_gather_gradient() {
  auto& P = particles;
  const bool apic = scene_.transfer == Transfer::apic;
  auto gather_one = [&](std::size_t i) {
    const auto p = static_cast<std::size_t>(layer_list_[i]);
    const DualWall<D>& w = dual_[P.layer_wall[p]];
    const AlphaStencil<D>& st = layer_stencil_[i];
    const Mat<D> L = stencil_gradient(w.velocity, st);
    if (w.enhanced) {
      layer_gradient_[i] += L;  // on top of the standard grid's (gather_velocity_gradient())
      return;
    }
    layer_gradient_[i] = L;
    if (apic) P.affine[p] = layer_affine(w, st, L, P.velocity[p], mass_threshold_);
  };
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, layer_list_.size(), 256),
                    [&](const auto& r) {
                      for (std::size_t i = r.begin(); i != r.end(); ++i) gather_one(i);
                    });
}

#define MPM_DUAL_GRID_MEMBERS(D)                                                   \
  template std::vector<std::string> Solver<D>::wall_names() const;                 \
  template void Solver<D>::setup_dual_walls();                                     \
  template void Solver<D>::locate_in_layers();                                     \
  template void Solver<D>::layer_scatter(bool);                                    \
  template void Solver<D>::layer_update(double);                                   \
  template void Solver<D>::layer_walls(std::vector<Vec<D>> DualWall<D>::*, bool);  \
  template void Solver<D>::layer_couple(bool);                                     \
  template std::vector<CouplingWork> Solver<D>::coupling_work() const;             \
  template bool Solver<D>::factorise_schur(DualWall<D>&, bool, SparseLdlt::Order); \
  template void Solver<D>::layer_gather(double);                                   \
  template void Solver<D>::layer_remap();                                          \
  template void Solver<D>::layer_gather_gradient();

MPM_DUAL_GRID_MEMBERS(1)
MPM_DUAL_GRID_MEMBERS(2)
MPM_DUAL_GRID_MEMBERS(3)

}  // namespace mpm
