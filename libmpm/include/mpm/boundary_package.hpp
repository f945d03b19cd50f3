#pragma once
// The boundary package: everything the dual-grid step needs about one wall, built once by
// `mpm prep` (or on the fly by `mpm run`) and stored in HDF5 with an XDMF file for ParaView.
//
// HDF5 layout (version 1):
//   /          attrs format="mpm-boundary-package", version, source, source_digest
//   /grid      attrs dimension, origin_0..2, spacing, nodes_0..2, kernel ("linear"|"bspline2")
//   /layer     nodes (N x dim), cells (C x 2|4|6), cell_layer, cell_part, part_names (strings),
//              wall_facets, interface_facets, wall_facet_part, node_normals (N x dim),
//              node_on_wall, node_on_interface; attrs dimension, layers, thickness
//   /coupling/interface, /coupling/wall: multiplier_node, multiplier_integral, grid_rows,
//              grid_cols, grid_values (R^A as triplets), boundary_rows, boundary_cols,
//              boundary_values (R^alpha); attrs grid_row_count, grid_col_count,
//              boundary_row_count, boundary_col_count
//   /cell_flags  uint8 per standard-grid cell
//   /report    attrs of mpmgeom::LayerReport
//   /xdmf      visualisation copies (points padded to 3D, cells in VTK node order)

#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "mpm/shape.hpp"
#include "mpmgeom/boundary_grid.hpp"
#include "mpmgeom/coupling.hpp"
#include "mpmgeom/mesh_repair.hpp"
#include "mpmgeom/triangle_mesh.hpp"

namespace mpm {

/// The standard grid libmpm builds for a scene box (Solver<D>: two ghost layers beyond each
/// face), as libgeom needs it for the coupling matrices. box_min/box_max have `dimension`
/// entries. GIMP couples through the linear tent (its grid basis).
mpmgeom::GridSpec standard_grid_spec(int dimension, const Eigen::VectorXd& box_min,
                                     const Eigen::VectorXd& box_max, double spacing,
                                     ShapeKind shape);

struct BoundaryPackage {
  mpmgeom::BoundaryGrid layer;
  mpmgeom::GridSpec grid;
  mpmgeom::Coupling interface_coupling;  ///< on Phi (Blending)
  mpmgeom::Coupling wall_coupling;       ///< on Gamma (Enhanced)
  std::vector<std::uint8_t> cell_flags;  ///< per standard-grid cell: may a particle be in the layer
  mpmgeom::LayerReport report;
  mpmgeom::RepairReport repairs;  ///< what validation repaired in the mesh (not stored in HDF5)
  std::string source;             ///< the mesh file it was made from
  std::string source_digest;      ///< digest of the mesh bytes and every option (staleness check)
};

/// What `mpm prep` does to a surface mesh.
struct PrepOptions {
  mpmgeom::ImportOptions import;
  mpmgeom::RepairOptions repair;
  bool remesh = true;          ///< isotropic remeshing to the grid spacing first
  double remesh_factor = 1.0;  ///< target edge length = factor * h
  mpmgeom::LayerOptions layer;
};

/// Import, validate and repair, remesh, extrude the layer, integrate both coupling matrices and
/// flag the grid cells, for a 3D surface mesh and the given standard grid. Throws
/// mpmgeom::MeshError (bad mesh) or std::invalid_argument (bad option) with one-line messages.
BoundaryPackage prepare_boundary(const std::filesystem::path& mesh_file, const PrepOptions& options,
                                 const mpmgeom::GridSpec& grid);
/// The same for a mesh already imported from `mesh_file` with options.import (so a caller that
/// needed the mesh first does not read the file twice).
BoundaryPackage prepare_boundary(const mpmgeom::TriangleMesh& imported,
                                 const std::filesystem::path& mesh_file, const PrepOptions& options,
                                 const mpmgeom::GridSpec& grid);

/// Digest of a file's bytes and the options that shape the package (FNV-1a, 64 bit, hex).
std::string boundary_digest(const std::filesystem::path& mesh_file, const PrepOptions& options,
                            const mpmgeom::GridSpec& grid);

/// Writes the package (HDF5) and a ParaView index of the layer cells, Gamma and Phi (XDMF).
/// Written to temporary names and renamed, so an interrupted write leaves no half file.
void save_boundary_package(const BoundaryPackage& package, const std::filesystem::path& h5_path,
                           const std::filesystem::path& xmf_path);

/// Reads a package written by save_boundary_package. Throws std::runtime_error naming the file.
BoundaryPackage load_boundary_package(const std::filesystem::path& h5_path);

}  // namespace mpm
