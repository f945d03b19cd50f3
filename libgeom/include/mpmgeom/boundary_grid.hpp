// The boundary grid (the alpha grid of DESIGN.md): a thin layer of cells on the material side of
// a wall, with the wall face Gamma and the interface face Phi. Plain arrays only.
//
// Cells and natural coordinates (the alpha basis is linear in them):
//   1D segment : nodes (w, i): wall node, interface node.              xi = (zeta)
//   2D quad    : nodes (w0, w1, i0, i1): wall segment w0->w1, and the interface nodes above
//                w0 and w1.                                           xi = (s, zeta)
//   3D wedge   : nodes (w0, w1, w2, i0, i1, i2): wall triangle (counter-clockwise seen from the
//                material) and the interface nodes above each.        xi = (r, s, zeta)
// zeta runs from 0 on the wall side to 1 on the interface side of the cell. With K sub-layers
// the cells of one column are stacked: layer k's interface side is layer k+1's wall side, and
// only layer 0 touches Gamma, only layer K-1 touches Phi.
//
// Positive orientation: det(dx/dxi) > 0 in every 2D and 3D cell (wall facet counter-clockwise
// seen from the material, zeta going into the material). In 1D dx/dzeta = side * t / K, which is
// negative for side = -1; there the orientation is carried by node_normals and "positive
// Jacobian" means side * dx/dzeta > 0.
//
// Layout made by the extrusion functions, with P wall points and F wall facets:
//   node  k * P + v : level k (0 = on Gamma, K = on Phi) of the column above wall point v;
//                     nodes 0..P-1 are the wall points themselves.
//   cell  k * F + f : sub-layer k of the column over wall facet f.
//   wall_facets row f and interface_facets row f: bottom and top of column f.
#pragma once

#include <array>
#include <cstddef>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "mpmgeom/triangle_mesh.hpp"

namespace mpmgeom {

struct BoundaryGrid {
  int dimension = 3;
  int layers = 1;
  double thickness = 0.0;  ///< nominal layer thickness t (before any local shrinking)

  Eigen::MatrixXd nodes;       ///< #N x dimension
  Eigen::MatrixXi cells;       ///< #C x (2, 4, 6) node indices, order as above
  Eigen::VectorXi cell_layer;  ///< #C, 0 = touching the wall
  Eigen::VectorXi cell_part;   ///< #C, index into part_names
  std::vector<std::string> part_names;

  /// Gamma and Phi as facet lists (1D: #x1 points, 2D: #x2 segments, 3D: #x3 triangles), node
  /// indices into `nodes`, ordered so that the facet normal points into the layer (Gamma) and
  /// out of the layer towards the bulk (Phi): both point away from the wall, so a wall facet and
  /// the interface facet above it have the same winding. The normal of a triangle (a, b, c) is
  /// (b - a) x (c - a); that of a segment (a, b) is b - a turned by +90 degrees (its left side).
  /// A 1D facet is a single node; its normal is node_normals of that node.
  Eigen::MatrixXi wall_facets;
  Eigen::MatrixXi interface_facets;
  Eigen::VectorXi wall_facet_part;  ///< #wall facets, index into part_names
  /// Unit normal at each node, pointing from the wall into the material (the extrusion
  /// direction); for interface and inner nodes the direction of their column.
  Eigen::MatrixXd node_normals;       ///< #N x dimension
  Eigen::VectorXi node_on_wall;       ///< #N, 1 if the node is on Gamma
  Eigen::VectorXi node_on_interface;  ///< #N, 1 if the node is on Phi

  [[nodiscard]] std::size_t cell_count() const { return static_cast<std::size_t>(cells.rows()); }
  [[nodiscard]] int nodes_per_cell() const { return dimension == 1 ? 2 : dimension == 2 ? 4 : 6; }
};

/// Values and natural-coordinate derivatives of the alpha-grid basis of one cell at xi
/// (dimension entries used). dN(k, j) = dN_k / dxi_j.
struct AlphaBasis {
  std::array<double, 6> N{};
  Eigen::Matrix<double, 6, 3> dN = Eigen::Matrix<double, 6, 3>::Zero();
};
AlphaBasis alpha_basis(int dimension, const Eigen::Vector3d& xi);

/// A cell's isoparametric map in closed form, the node differences formed once:
/// x(xi) = a + sum_j u_j e_j + z (d + sum_j u_j f_j), u the coordinates along the wall (xi_0,
/// xi_1 in 3D; xi_0 in 2D; none in 1D) and z = xi_{dimension-1} across the layer. The map of
/// alpha_basis() over the cell's nodes (3D: a = X_0, e_j = X_{j+1} - X_0, d = Y_0 - X_0,
/// f_j = (Y_{j+1} - X_{j+1}) - d, X the nodes on the wall side, Y = X_{k+3} across), so a point
/// and its Jacobian cost a few multiply-adds (point location and each layer particle's basis
/// gradients, every step). f = 0 where the cell is affine (a layer over a plane).
struct CellMap {
  int dimension = 3;
  /// a, e_0, e_1, d, f_0, f_1 at 3i + axis (unused vectors and axes 0).
  std::array<double, 18> v{};

  /// r = x(xi) - p and J = dx/dxi (columns and rows beyond `dimension` 0).
  void evaluate(const double* xi, const double* p, double* r, double (*J)[3]) const {
    const int m = dimension - 1;
    const double z = xi[m];
    for (int i = 0; i < 3; ++i) {
      double x = v[i] - p[i], across = v[9 + i];
      for (int j = 0; j < m; ++j) {
        x += xi[j] * v[3 + 3 * j + i];
        across += xi[j] * v[12 + 3 * j + i];
        J[i][j] = v[3 + 3 * j + i] + z * v[12 + 3 * j + i];
      }
      r[i] = x + z * across;
      J[i][m] = across;
      for (int j = m + 1; j < 3; ++j) J[i][j] = 0.0;
    }
  }
};
CellMap cell_map(const BoundaryGrid& grid, std::size_t c);

/// Physical position of natural coordinates xi in cell c, and the Jacobian dx/dxi
/// (dimension x dimension, stored in the top-left block).
Eigen::Vector3d cell_point(const BoundaryGrid& grid, std::size_t c, const Eigen::Vector3d& xi);
Eigen::Matrix3d cell_jacobian(const BoundaryGrid& grid, std::size_t c, const Eigen::Vector3d& xi);

struct LayerOptions {
  double thickness = 0.0;    ///< t > 0, typically the grid spacing h
  int layers = 1;            ///< sub-layers K >= 1
  int normal_smoothing = 2;  ///< Laplacian smoothing passes on vertex normals
  /// Where the full thickness would fold the layer (a non-positive corner Jacobian), t is shrunk
  /// locally, never below this fraction of t; cells that still fold are an error.
  double min_thickness_fraction = 0.1;
  /// True if thickness is finite and > 0, layers >= 1, normal_smoothing >= 0 and
  /// min_thickness_fraction is in (0, 1]; otherwise false and *why (if given) says which.
  bool valid(std::string* why = nullptr) const;
};

/// What extrusion did, for `mpm prep` and the tests.
struct LayerReport {
  std::size_t cells = 0;
  std::size_t nodes = 0;
  std::size_t columns_shrunk = 0;  ///< wall vertices whose offset was shortened
  double max_shrink = 0.0;         ///< largest relative shortening, 0..1
  /// Smallest det(dx/dxi) over all cells (the true minimum over each cell, not only its
  /// corners), divided by the determinant of the straight cell over the same wall facet with the
  /// nominal sub-layer height t / K (2 * triangle area * t / K in 3D, segment length * t / K in
  /// 2D). 1 for a flat wall. On a curved wall it is below 1: at the wall det J is the nominal
  /// value times the cosine between vertex and facet normals (cos(pi/n) on a regular n-gon),
  /// on concave parts the cells narrow further away from the wall, and where an offset was
  /// shrunk it is roughly the fraction of t that remains. Always > 0.
  double min_jacobian = 0.0;
  double volume = 0.0;             ///< layer volume (3D), area (2D), length (1D), exact
  double wall_measure = 0.0;       ///< area (3D), length (2D) or 1 (1D) of Gamma
  double interface_measure = 0.0;  ///< same for Phi
  /// Points on creases and corners whose smoothed normal leaned towards one side and was
  /// replaced by the centre of the cone of their facets' normals (the bisector of a crease).
  std::size_t crease_normals = 0;
};

/// 3D: wedges extruded from the wall triangles along smoothed vertex normals into the side the
/// triangle normals point to (the material side).
///
/// Vertex normals are angle-weighted averages of the triangle normals, smoothed by
/// options.normal_smoothing Jacobi passes n <- normalise(n + mean of the one-ring's n). On
/// creases and corners (a normal more than ~25 degrees off one of its triangles) a normal that
/// leans towards one side is replaced by the centre of the cone of its triangles' normals (the
/// direction furthest inside all their material sides: the bisector of a crease).
///
/// Wall point v is offset by s_v * t along its normal. s_v is first capped so that the column
/// stops at 0.9 of the height where it would get closer to another part of the wall than to its
/// own triangles (the medial axis: across a concave crease or corner, or facing another wall
/// closer than 2 t, columns would otherwise cross without any cell folding), then lowered where
/// the layer would fold or pinch: a column (a wall triangle extruded over the whole thickness) in
/// which det J along a vertical edge drops to <= 0 (a fold) or below 5 % of its value at the wall
/// is lowered to the height zeta* where it reaches 10 % of that value, by scaling the offsets of
/// its three vertices by zeta* (never below options.min_thickness_fraction); around shrunk vertices
/// the offset is then capped to grow by at most its distance along the wall (Phi rises at <= 45
/// degrees, no deep notch); all columns are rechecked until none asks for more. A fold that
/// remains is an error, a pinch that remains is accepted. det J is checked over the whole of
/// each cell (exactly: it is quadratic in zeta, linear in (r, s)), not only at the corners.
///
/// The medial test follows the columns' vertical edges (the vertex rays), not their side faces.
///
/// Unreferenced vertices of wall.V get no node; the others keep their order (so wall node i is
/// wall.V row i for a mesh from load_mesh()). Parts come from wall.part (all 0 if empty, named
/// "wall" if wall.part_names is empty).
///
/// Throws std::invalid_argument for invalid options; MeshError ("boundary layer: ...") for an
/// empty mesh, bad indices, non-finite coordinates, degenerate triangles, vertices without a
/// normal (inconsistent orientation), or a fold or medial limit that min_thickness_fraction does
/// not allow to resolve ("cannot extrude the layer at triangle k near (x, y, z): ...").
BoundaryGrid extrude_layer(const TriangleMesh& wall, const LayerOptions& options,
                           LayerReport* report = nullptr);

/// 2D: quads extruded from a polyline (#P x 2 points) to its left (the material side when the
/// polyline runs with the material on its left); closed joins the last point to the first (do
/// not repeat the first point at the end). Point normals are the normalised sums of the unit
/// left normals of their segments (corner bisectors), smoothed, and offsets are limited and
/// shrunk as in extrude_layer (the bilinear map's det J is linear, so its corners decide).
/// Gamma and Phi are 2-node segments running in the polyline's direction. Throws MeshError for
/// fewer than 2 points (3 if closed), non-finite points, zero-length segments or a fold that
/// cannot be removed.
BoundaryGrid extrude_layer_2d(const Eigen::MatrixX2d& polyline, bool closed,
                              const LayerOptions& options, const std::string& part_name = "wall",
                              LayerReport* report = nullptr);

/// 1D: K segments from the wall point into the material (side = +1: material at x > wall,
/// -1: at x < wall). Node k sits at wall_point + side * k t / K; cell k is (node k, node k+1),
/// the node nearer the wall first, so dx/dzeta = side * t / K. Throws std::invalid_argument for
/// invalid options or a side other than +-1, MeshError for a non-finite wall point.
BoundaryGrid layer_1d(double wall_point, int side, const LayerOptions& options,
                      const std::string& part_name = "wall", LayerReport* report = nullptr);

}  // namespace mpmgeom
