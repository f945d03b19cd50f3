#pragma once
// State of one dual-grid wall inside the solver (the Blending method, DESIGN.md section 4): the
// boundary grid's nodal arrays, its Gamma nodes with their wall frames, and the multipliers that
// tie it to the standard grid on Phi.

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <memory>
#include <string>
#include <vector>

#include "mpm/boundary_package.hpp"
#include "mpm/scene.hpp"
#include "mpm/types.hpp"
#include "mpmgeom/locator.hpp"

namespace mpm {

template <int D>
struct DualWall {
  const DualWallSpec* spec = nullptr;
  const mpmgeom::BoundaryGrid* layer = nullptr;
  std::unique_ptr<mpmgeom::LayerLocator> locator;

  // Boundary-grid nodal arrays (same roles as in Grid<D>).
  std::vector<Vec<D>> position;
  std::vector<double> mass;
  std::vector<Vec<D>> momentum, force, velocity, velocity_new;

  // Gamma: nodes on the wall, their unit normal into the material, and the part they report to.
  std::vector<int> wall_nodes;
  std::vector<Vec<D>> wall_normal;
  std::vector<int> wall_node_part;
  int impulse_offset = 0;  ///< index of this wall's first part in the solver's wall impulses

  // Phi coupling: R^A (standard-grid nodes x multipliers) and R^alpha (boundary nodes x
  // multipliers), the integral of each multiplier basis, and the per-step workspace.
  Eigen::SparseMatrix<double> grid_coupling;
  Eigen::SparseMatrix<double> boundary_coupling;
  Eigen::VectorXd multiplier_integral;
  std::vector<int> multiplier_node;
  std::vector<int> active_multipliers;  ///< this step's multipliers that constrain something
  /// Kept rows (compacted: row k is node grid_rows[k] / layer_rows[k]) and rescaled columns, so
  /// the per-step work scales with the interface, not with the whole grid.
  Eigen::SparseMatrix<double> grid_active, boundary_active;
  std::vector<int> grid_rows, layer_rows;
  /// Factorised Schur complement on the active multipliers (held by pointer: Eigen's solvers
  /// cannot be moved).
  std::unique_ptr<Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>> schur =
      std::make_unique<Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>>>();
  std::size_t pattern_hash = 0;  ///< sparsity of the last factorised S: reuse its ordering
  double min_cell_size = 0.0;    ///< for the CFL limit
  std::size_t layer_particles = 0;
};

}  // namespace mpm
