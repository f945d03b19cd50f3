// Coupling matrices between the standard grid (A) and the boundary grid (alpha), integrated
// exactly over the interface Phi or the wall Gamma (DESIGN.md section 2):
//
//   R^A_{J mu}     = integral N^A_J S_mu       R^alpha_{S mu} = integral N^alpha_S S_mu
//
// The multiplier basis S_mu is piecewise linear on the facets, one function per facet node
// (hat functions of the facet mesh). N^A is piecewise polynomial per Cartesian cell, so each
// facet is split along the planes where N^A changes polynomial piece (grid planes; for the
// quadratic B-spline also the mid-planes) and each piece integrated with a Gauss rule exact for
// the product degree.
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <Eigen/SparseCore>

#include "mpmgeom/boundary_grid.hpp"

namespace mpmgeom {

/// The standard grid, as libmpm builds it (mpm::Grid): node (i,j,k) at origin + h (i,j,k),
/// linear index sum_d i_d stride_d with the last axis fastest.
struct GridSpec {
  enum class Kernel { linear, bspline2 };  ///< GIMP's grid basis is the linear tent
  int dimension = 3;
  Eigen::Vector3d origin = Eigen::Vector3d::Zero();
  double spacing = 1.0;
  Eigen::Vector3i nodes = Eigen::Vector3i::Ones();  ///< per axis (unused axes 1)
  Kernel kernel = Kernel::bspline2;
  /// Product of nodes[d] over the first `dimension` axes.
  [[nodiscard]] long node_count() const;
  /// sum_d i_d stride_d over the first `dimension` axes, stride[D-1] = 1 and
  /// stride[d] = stride[d+1] nodes[d+1] (mpm::Grid::linear). No range check.
  [[nodiscard]] long linear_index(const Eigen::Vector3i& i) const;
};

enum class CouplingSurface { interface, wall };  ///< Phi or Gamma

struct Coupling {
  /// Boundary-grid node carrying each multiplier (the facet nodes of the chosen surface), in
  /// increasing node order: multiplier mu sits at node multiplier_node[mu].
  std::vector<int> multiplier_node;
  /// R^A: #A-grid nodes (linear index, node_count() rows) x #multipliers. Column mu sums to
  /// integral S_mu (partition of unity of N^A).
  Eigen::SparseMatrix<double> grid;
  /// R^alpha: #boundary-grid nodes x #multipliers; nonzero only in the rows of facet nodes.
  Eigen::SparseMatrix<double> boundary;
  /// integral of S_mu over the surface, per multiplier.
  Eigen::VectorXd multiplier_integral;
};

/// R^A, R^alpha and integral S_mu over Phi (interface) or Gamma (wall). Exact up to rounding:
/// each facet is cut along the knot planes of the kernel (grid planes for the tent, mid-planes
/// for the B-spline); pieces are integrated with Dunavant's 16-point triangle rule (degree 8,
/// needed 4 / 7) in 3D, 4-point Gauss-Legendre (degree 7, needed 3 / 5) in 2D, and by point
/// evaluation in 1D. R^alpha is the P1 facet mass matrix (the alpha basis is linear on faces).
/// Throws std::invalid_argument if the surface leaves the grid: every facet node must lie where
/// the whole kernel support has nodes, grid coordinate (x - origin) / h in [0, n-1] per axis for
/// the tent and [1/2, n-3/2] for the B-spline; also on a dimension mismatch or a bad GridSpec.
Coupling couple(const BoundaryGrid& boundary, const GridSpec& grid, CouplingSurface surface);

/// Per A-grid cell (linear index over cells, nodes-1 per axis over the first `dimension` axes,
/// last axis fastest): 1 if the closed cell [i, i+1] h + origin (per axis) meets the bounding
/// box, grown by 1e-9 h, of the nodes of some layer cell. Since a layer cell lies inside its
/// nodes' bounding box, a particle whose A-cell floor((x - origin) / h) is unflagged is
/// certainly outside the layer and needs no layer query. The flag is conservative (a flagged
/// cell may hold no layer point) and does not include the kernel reach: it answers "can a
/// particle in this cell be in the layer", not "can it touch a node the layer touches".
/// Parts of the layer outside the grid are ignored.
std::vector<std::uint8_t> layer_cell_flags(const BoundaryGrid& boundary, const GridSpec& grid);

/// layer_cell_flags made finer, for the point location's skip: per flagged A-cell, the bounding
/// box of the layer cells that meet it and a slab {x : lo <= n . x <= hi} across them, n their
/// mean column direction (interface side minus wall side), lo and hi the least and greatest
/// n . x of their nodes (a layer cell lies in its nodes' convex hull). Both are grown by 1e-6 of
/// the cell's size plus the coordinates' float round-off, as LayerLocator pads its cells'
/// boxes, so a point outside either is in none of those layer cells: it needs no query. A
/// flat layer off the grid lines flags the A-cells it crosses, a thin layer a cell or two
/// thick; the particles of a flagged cell above or below it (half of them, for a layer one cell
/// thick) fall outside its slab. Memory in proportion to the flagged cells: an index per block
/// of 8 cells a side, one per cell of a block that holds a flagged cell, and the bounds.
class LayerCellFilter {
 public:
  LayerCellFilter() = default;  ///< holds no cell: may_hold() is false everywhere
  /// Throws std::invalid_argument as layer_cell_flags does.
  LayerCellFilter(const BoundaryGrid& boundary, const GridSpec& grid);
  /// `cell`: the A-cell floor((x - origin) / h) of `x` per axis, within the grid's cells; unused
  /// axes 0 in both. False means no layer cell holds x; true that one may.
  [[nodiscard]] bool may_hold(const Eigen::Vector3i& cell, const Eigen::Vector3d& x) const;
  /// Whether layer_cell_flags flags the cell (the same cells).
  [[nodiscard]] bool flagged(const Eigen::Vector3i& cell) const { return bounds_of(cell) >= 0; }
  [[nodiscard]] std::size_t flagged_cells() const { return bounds_.size(); }

 private:
  static constexpr int kBlockShift = 3;  ///< blocks of 8 cells a side
  struct Bounds {
    std::array<double, 3> lo{}, hi{};  ///< the box (used axes)
    std::array<double, 3> normal{};    ///< n, or 0 where the cells' directions cancel
    double slab_lo = 0.0, slab_hi = 0.0;
  };
  [[nodiscard]] int bounds_of(const Eigen::Vector3i& cell) const;
  int dimension_ = 0;
  Eigen::Vector3i blocks_ = Eigen::Vector3i::Zero();  ///< per axis (unused axes 1)
  std::vector<int> block_first_;  ///< per block: its first entry in cell_bounds_, or -1
  std::vector<int> cell_bounds_;  ///< per cell of a held block: index into bounds_, or -1
  std::vector<Bounds> bounds_;
};

}  // namespace mpmgeom
